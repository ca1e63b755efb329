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
    with pytest.warns(setup.FigureLayoutWarning, match="figure crowded: 1 overlapping text"):
        setup.save_figure(fig, tmp_path, "crowded")
    fig2, ax = plt.subplots()
    ax.set_title("fine")
    setup.save_figure(fig2, tmp_path, "fine")
    metrics = setup.write_metrics(tmp_path / "m.json", x=1)
    import json
    recorded = json.loads(metrics.read_text())["figure_text_overlaps"]
    assert list(recorded) == ["crowded"] and len(recorded["crowded"]) == 1
