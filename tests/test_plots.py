"""Figures that read on their own: leglib.plots.text_overlaps finds texts drawn over each
other, and save_figure reports them (a warning, the notebook's metrics)."""

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from leglib import plots  # noqa: E402
from leglib.notebook import setup  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def test_titles_that_run_into_each_other_are_found_and_named():
    fig, (a, b) = plt.subplots(1, 2, figsize=(4, 2))
    a.set_title("a long title that runs into the next panel's")
    b.set_title("second title")
    found = plots.text_overlaps(fig)
    assert len(found) == 1
    assert "axes 0 title 'a long title" in found[0] and "axes 1 title 'second title'" in found[0]
    b.set_title("")
    a.set_title("short")
    assert plots.text_overlaps(fig) == []


def test_what_is_not_drawn_or_drawn_twice_is_not_an_overlap():
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.plot(np.linspace(0.002, 0.18, 10), np.linspace(-251, -190, 10))
    ax.set_xlim(0.002, 0.18)   # matplotlib keeps tick labels at 0.00 and 0.20 outside the view
    twin = ax.twinx()          # a twin's x tick labels sit exactly on the axes' own
    twin.plot([0.002, 0.18], [0, 1])
    ax.legend(["one", "two", "three"])
    assert plots.text_overlaps(fig) == []


def test_save_figure_warns_and_records_overlaps(tmp_path, monkeypatch):
    monkeypatch.setattr(setup, "FIGURE_OVERLAPS", {})
    fig, (a, b) = plt.subplots(1, 2, figsize=(4, 2))
    a.set_title("a long title that runs into the next panel's")
    b.set_title("second title")
    with pytest.warns(setup.FigureLayoutWarning, match=r"figure crowded: 1 overlapping text\(s\) or legend\(s\) on data"):
        setup.save_figure(fig, tmp_path, "crowded")
    fig2, ax = plt.subplots()
    ax.set_title("fine")
    setup.save_figure(fig2, tmp_path, "fine")
    metrics = setup.write_metrics(tmp_path / "m.json", x=1)
    import json
    recorded = json.loads(metrics.read_text())["figure_text_overlaps"]
    assert list(recorded) == ["crowded"] and len(recorded["crowded"]) == 1


def test_a_legend_on_data_is_found_and_moved_off_it():
    """legends_on_data names what a legend hides; keep_legends_off_data moves it to a free
    place inside, else beside the axes (past a twin axis's labels), else above them with the
    title raised; a legend beside the axes or on empty space is left where it is."""
    t = np.linspace(0, 8, 400)
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.plot(t, np.sin(t), label="q1")
    ax.plot(t, np.cos(t), label="q2")
    ax.fill_between(t, -1.2, 1.2, alpha=0.0)     # nothing drawn: not data a legend can hide
    twin = ax.twinx()
    twin.plot(t, 0.05 * np.sin(2 * t), "k:", label="tau")
    twin.set_ylabel("joint torque [N m]")
    ax.legend(loc="upper right")
    assert plots.legends_on_data(fig)[0].startswith("axes 0 legend covers")
    moved = plots.keep_legends_off_data(fig)
    assert moved == ["axes 0: beside the axes"]
    assert plots.legends_on_data(fig) == [] and plots.text_overlaps(fig) == []
    # past the twin axis's label
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    assert ax.get_legend().get_window_extent(r).x0 > twin.yaxis.label.get_window_extent(r).x1
    # with a panel to the right: above the axes, the title over it
    fig2, (a, b) = plt.subplots(1, 2, figsize=(8, 3))
    for k in range(6):
        a.plot(t, np.sin(t + k), label=f"line {k}")
    b.plot(t, t)
    a.set_title("six lines")
    a.legend(loc="center")
    assert plots.keep_legends_off_data(fig2) == ["axes 0: above the axes"]
    assert plots.legends_on_data(fig2) == [] and plots.text_overlaps(fig2) == []
    # a legend where the data leave room is left alone
    fig3, c = plt.subplots()
    c.plot([0, 1], [0, 0.2], label="low")
    c.set_ylim(0, 1)
    c.legend(loc="upper right")
    assert plots.legends_on_data(fig3) == [] and plots.keep_legends_off_data(fig3) == []


@pytest.mark.filterwarnings("ignore:Animation was deleted without rendering")   # only its layout is checked
def test_clipped_text_and_a_title_fit_to_the_figure():
    """An animation's small fixed-size figure cut its long title at both ends; fit_title
    wraps (and shrinks) it until it fits."""
    fig, ax = plt.subplots(figsize=(3.6, 4.4), dpi=72)
    ax.set_title("measured step, map's gains for the thesis target")
    assert plots.clipped_texts(fig) and "runs past the figure's edge" in plots.clipped_texts(fig)[0]
    plots.fit_title(ax, "measured step, map's gains for the thesis target")
    assert plots.clipped_texts(fig) == [] and "\n" in ax.get_title()
    assert ax.title.get_fontsize() >= 10          # wrapped and given room, not shrunk to a whisper
    # the leg's animation uses it
    from leglib.params import load_leg
    leg = load_leg("thesis")
    t = np.linspace(0, 1, 50)
    anim = plots.animate_leg(leg, np.full(50, leg.q1), leg.q2 + 0.1 * t, t, max_frames=5,
                             title="measured step, map's gains for the thesis target")
    assert plots.clipped_texts(anim.figure) == [] and plots.text_overlaps(anim.figure) == []


def test_map_slices_name_every_empty_cell_and_keep_their_tick_labels_apart():
    """Each empty cell drawn by why with its count in the legend; panels share the vertical
    axis (no tick labels running into the previous panel); cells centred on their gains."""
    class Map:
        axes = (np.array([20.0, 30.0]), np.linspace(0.002, 0.18, 5), np.linspace(0.002, 0.08, 4))
        status = np.full((2, 5, 4), "ok", dtype=object)
        zeta = np.random.default_rng(0).uniform(0.2, 1.2, (2, 5, 4))
    gm = Map()
    gm.status[:, 0, :] = "unstable"
    gm.status[0, 0, 0] = "failed"
    gm.status[1, 4, 3] = "missing"
    gm.zeta[gm.status != "ok"] = np.nan
    gm.fn = gm.zeta * 5
    plots.plot_map_slices(gm, "zeta")
    fig = plt.gcf()
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == ["unstable (the step aborted) (7)", "failed (not a second-order step) (1)", "not measured (1)"]
    assert plots.text_overlaps(fig) == [] and plots.legends_on_data(fig) == []
    a, b = fig.axes[:2]
    assert not any(t.get_visible() and t.get_text() for t in b.get_yticklabels())   # shared: only the first
    mesh = a.collections[0]
    x_edges = mesh.get_coordinates()[0, :, 0]
    assert x_edges[0] < 0.002 < x_edges[1]                                             # centred on the gain
