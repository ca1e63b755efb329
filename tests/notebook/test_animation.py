"""plots.animate_leg: every frame shows the five-bar at the sampled angles, the foot where
model.foot_position puts it; exportable without ffmpeg and small enough to embed."""

import matplotlib

from leglib import model as M
from leglib import plots

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.animation import Animation  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:Animation was deleted without rendering")


def _motion(leg, n=700):
    t = np.arange(n) * 0.002
    # the leg opens and closes while it swings
    q1 = leg.q1 - 0.3 * (1 - np.cos(2 * np.pi * 1.3 * t)) + 0.2 * np.sin(2 * np.pi * 0.7 * t)
    q2 = leg.q2 + 0.3 * (1 - np.cos(2 * np.pi * 1.3 * t)) + 0.2 * np.sin(2 * np.pi * 0.7 * t)
    return q1, q2, t


def test_frames_match_foot_position(leg):
    q1, q2, t = _motion(leg)
    anim = plots.animate_leg(leg, q1, q2, t, max_frames=40)
    assert isinstance(anim, Animation)
    idx = anim.frame_index
    assert len(idx) == 40 and idx[0] == 0 and idx[-1] == len(t) - 1 and np.all(np.diff(idx) > 0)
    x, y = M.foot_position(leg, q1, q2)
    for k in range(len(idx)):
        anim.show_frame(k)
        lx, ly = anim.links.get_data()
        i = idx[k]
        # hip at the origin, upper joints at l1, l2 along q1, q2, foot from the model
        np.testing.assert_allclose([lx[1], ly[1]], [0, 0], atol=0)
        np.testing.assert_allclose([lx[0], ly[0]], [leg.l1 * np.cos(q1[i]), leg.l1 * np.sin(q1[i])], rtol=1e-12)
        np.testing.assert_allclose([lx[2], ly[2]], [leg.l2 * np.cos(q2[i]), leg.l2 * np.sin(q2[i])], rtol=1e-12)
        np.testing.assert_allclose([lx[3], ly[3]], [x[i], y[i]], rtol=0, atol=1e-12)
        # the lower links have their lengths: the loop closes at the foot
        assert np.hypot(lx[3] - lx[2], ly[3] - ly[2]) == pytest.approx(leg.l3, rel=1e-9)
        assert np.hypot(lx[3] - lx[0], ly[3] - ly[0]) == pytest.approx(leg.l4, rel=1e-9)
        tx, ty = anim.foot_trace.get_data()
        assert len(tx) == i + 1
        np.testing.assert_allclose(tx, x[: i + 1], atol=1e-12)
        np.testing.assert_allclose(ty, y[: i + 1], atol=1e-12)
    plt.close("all")


def test_short_runs_and_bad_input(leg):
    q1, q2, t = _motion(leg, n=5)
    anim = plots.animate_leg(leg, q1, q2, t, max_frames=60)
    assert list(anim.frame_index) == [0, 1, 2, 3, 4]
    anim.figure.canvas.draw()   # drawn, as a notebook does: else matplotlib warns when it goes
    with pytest.raises(ValueError, match="one length"):
        plots.animate_leg(leg, q1, q2[:3], t)
    with pytest.raises(ValueError, match="strictly increasing"):
        plots.animate_leg(leg, q1, q2, t[::-1])
    with pytest.raises(ValueError, match="finite"):
        plots.animate_leg(leg, q1 * np.nan, q2, t)
    with pytest.raises(ValueError, match="does not close at sample 0"):
        plots.animate_leg(leg, q1, q1 + np.pi, t)
    plt.close("all")


@pytest.mark.slow
def test_exports_without_ffmpeg(leg, tmp_path):
    q1, q2, t = _motion(leg)
    anim = plots.animate_leg(leg, q1, q2, t, max_frames=30, setpoint=(leg.q1, leg.q2), title="test")
    html = anim.to_jshtml()
    assert html.count("data:image/png;base64") == 30 or html.count("frames[") >= 30
    # embedded size stays small: well under a megabyte for 30 frames
    assert len(html) < 1_000_000, len(html)
    gif = plots.save_animation(anim, tmp_path / "leg.gif")
    from PIL import Image
    with Image.open(gif) as im:
        assert im.n_frames == 30
    shown = plots.show_animation(anim, tmp_path, "shown")
    assert "<script" in shown.data and shown.data.count("data:image/png;base64") == 30
    with Image.open(tmp_path / "shown.gif") as im:    # the same 30 frames, drawn once
        assert im.n_frames == 30 and im.size == Image.open(gif).size
        assert im.info["duration"] == Image.open(gif).info["duration"]
    assert not plt.fignum_exists(anim.figure.number)          # no still copy left open
    plt.close("all")
