"""The live view: what an experiment's callback hands it is buffered exactly, drawn while
the experiment runs, and the callback never blocks (bounded queue, no drawing in it)."""

import threading
import time
import types

import numpy as np
import pytest

from leglib import plots
from leglib.notebook import liveview
from leglib.notebook.liveview import LiveView


def _run(leg, n=750, period=0.002):
    """A recorded step-like run: t, q1, q2 [rad], iq (n, 2) [A]."""
    t = np.arange(n) * period
    e = 1 - np.exp(-6 * t) * np.cos(25 * t)
    return types.SimpleNamespace(t=t, q1=leg.q1 - 0.3 * e, q2=leg.q2 + 0.3 * e,
                                 iq=np.column_stack([3 * np.exp(-4 * t), -2.5 * np.exp(-4 * t)]))


def _fake_experiment(run, on_sample, setpoint, out):
    """A paced polling loop at the run's own period (500 Hz) in its own thread, as an
    experiment with ``on_sample`` calls it."""
    out.update(liveview.replay(run, on_sample, setpoint=setpoint))


@pytest.mark.slow
@pytest.mark.parametrize("renderer", ["process", "thread"])
def test_samples_at_500_hz_are_buffered_exactly_and_drawn_while_running(leg, renderer):
    run = _run(leg)
    sp = (leg.q1 - 0.3, leg.q2 + 0.3)
    view = LiveView(leg=leg, rate_hz=10, renderer=renderer).start()
    pngs = [view.last_png]
    stats = {}
    exp = threading.Thread(target=_fake_experiment, args=(run, view.on_sample, sp, stats))
    exp.start()
    while exp.is_alive():                      # the picture changes while the experiment runs
        if view.last_png is not pngs[-1]:
            pngs.append(view.last_png)
        time.sleep(0.02)
    exp.join()
    final = view.stop()
    assert len(pngs) >= 3, f"only {len(pngs) - 1} redraws seen during a 1.5 s run"
    assert all(p.startswith(b"\x89PNG") for p in pngs)
    assert final["received"] == len(run.t) and final["dropped"] == 0 and final["errors"] == 0
    assert final["redraws"] >= 3 and final["redraw_rate_hz"] <= 10 * 1.2
    d = view.data()
    np.testing.assert_array_equal(d["t"], run.t)
    np.testing.assert_array_equal(d["q1"], run.q1)
    np.testing.assert_array_equal(d["q2"], run.q2)
    np.testing.assert_array_equal(d["iq"], run.iq)
    np.testing.assert_array_equal(d["setpoint"], np.tile(sp, (len(run.t), 1)))
    # the loop kept its pace: the median interval is the requested period
    assert stats["achieved_period_s"] == pytest.approx(0.002, rel=0.05)
    assert view._proc is None                  # the renderer process ended with stop()


def test_drawn_lines_are_the_buffered_samples(leg):
    run = _run(leg, n=300)
    view = LiveView(leg=leg, renderer="thread")
    for i in range(len(run.t)):
        view.on_sample({"t": run.t[i], "q1": run.q1[i], "q2": run.q2[i], "iq": tuple(run.iq[i]), "setpoint": None})
    assert view.redraw()
    lines = view._plot._lines
    np.testing.assert_allclose(lines["q1"].get_ydata(), np.degrees(run.q1), rtol=1e-12)
    np.testing.assert_allclose(lines["iq2"].get_ydata(), run.iq[:, 1], rtol=0)
    assert np.all(np.isnan(lines["sp1"].get_ydata()))        # no setpoint: nothing drawn
    np.testing.assert_allclose(np.column_stack(lines["leg"].get_data()),
                               plots.leg_points(leg, run.q1[-1], run.q2[-1]), rtol=1e-12)
    assert not view.redraw()                                  # nothing new: no redraw
    view.stop()


def test_callback_never_blocks_and_the_queue_is_bounded():
    view = LiveView(queue_size=100, renderer="thread")       # not started: nobody drains
    t0 = time.perf_counter()
    for i in range(20_000):
        view.on_sample({"t": i * 0.002, "q1": 4.6, "q2": 4.8, "iq": (0.0, 0.0), "setpoint": None})
    elapsed = time.perf_counter() - t0
    assert elapsed < 2.0                                      # 20,000 calls, no waiting on anything
    s = view.stats
    assert s["received"] == 20_000 and s["queued"] == 100 and s["dropped"] == 19_900
    d = view.data()
    np.testing.assert_array_equal(d["t"], np.arange(19_900, 20_000) * 0.002)
    # the callback holds no lock the drawing side takes: it runs while the view is locked
    with view._lock:
        done = threading.Event()
        threading.Thread(target=lambda: (view.on_sample({"t": 99.0, "q1": 1, "q2": 2}), done.set())).start()
        assert done.wait(1.0)


def test_bad_samples_are_reported_new_runs_restart_and_long_runs_thin_out():
    view = LiveView(max_points=100, renderer="thread")
    view.on_sample({"t": 0.0, "q1": 1.0})                     # no q2
    view.on_sample({"t": 0.0, "q1": 1.0, "q2": 2.0, "iq": None, "setpoint": None})
    view.on_sample({"t": 0.002, "q1": 1.0, "q2": "x"})
    d = view.data()
    assert len(d["t"]) == 1 and np.all(np.isnan(d["iq"]))
    assert len(view.errors) == 2 and "'q2'" in view.errors[0] and "sample 1 ignored" in view.errors[0]
    for i in range(1000):                                     # a new run (time went back), 10x the buffer
        view.on_sample({"t": i * 0.001, "q1": i, "q2": -i})
    d = view.data()
    assert 50 <= len(d["t"]) <= 100
    assert d["t"][0] == 0.0 and d["t"][-1] >= 0.9
    steps = np.round(np.diff(d["t"]) * 1000).astype(int)
    assert set(steps) == {16}                                 # thinned evenly (stride 16 after 4 halvings)
    np.testing.assert_array_equal(d["q1"], np.round(d["t"] * 1000))   # never mixed up
    view.on_sample({"t": 5.0, "q1": 1, "q2": 2})
    view.clear()
    assert len(view.data()["t"]) == 0 and view.stats["dropped"] == 0 and view.stats["queued"] == 0


def test_supports_and_arguments():
    def experiment(odrv, pos_gain, on_sample=None):
        pass

    assert liveview.supports(experiment) and not liveview.supports(lambda odrv: None)
    assert not liveview.supports(42)
    with pytest.raises(ValueError, match="rate_hz"):
        LiveView(rate_hz=0)
    with pytest.raises(ValueError, match="renderer"):
        LiveView(renderer="gpu")


def test_widget_shows_the_drawing(leg):
    view = LiveView(renderer="thread")
    box = view.widgets()
    view.on_sample({"t": 0.0, "q1": leg.q1, "q2": leg.q2, "iq": (0.1, 0.2), "setpoint": (leg.q1, leg.q2)})
    view.redraw()
    assert view.image.value == view.last_png and "leglib-liveview" in view.image._dom_classes
    assert "1 samples" in view.status.value and box.children[0] is view.image
    view.stop()
