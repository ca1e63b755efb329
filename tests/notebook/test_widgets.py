"""The ipywidgets panels in-process: moving a slider sets the readout to exactly what the
leglib functions compute for the new value (the browser test checks the same in JupyterLab)."""

import matplotlib

import leglib as lg
from leglib import model as M
from leglib.design.points import identify_response
from leglib.device.virtual.wire import forget, serial_for_seed
from leglib.errors import ArgumentError
from leglib.notebook import widgets

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402


def _readout_html(text):
    return f"<code class='leglib-readout'>{text}</code>"


def test_pole_panel_readout_follows_sliders(leg):
    sys = M.linearize(leg)
    panel = widgets.pole_placement_panel(sys, center=-7.0, spread=0.007, observer_factor=6.0)
    (s_center, _s_spread, s_obs), readout = panel.children[0].children, panel.children[1]
    assert readout.value == _readout_html(widgets.design_readout(widgets.pole_panel_design(sys, -7.0, 0.007, 6.0)))
    s_center.value = -12.5
    s_obs.value = 4.0
    d = widgets.pole_panel_design(sys, -12.5, 0.007, 4.0)
    expected = widgets.design_readout(d)
    assert readout.value == _readout_html(expected)
    # the readout's K is the gain that places the asked poles
    eig = np.sort(np.linalg.eigvals(sys.A - sys.B @ d.K).real)
    assert eig == pytest.approx(sorted([-12.5, -12.507, -12.514, -12.521]), rel=1e-6)
    assert "  " not in expected  # single spaces: the browser shows this string exactly


def test_gain_panel_readout_follows_sliders(leg, monkeypatch):
    """The slider runs a step with the new gains and shows exactly step_readout of it. (The
    step is the panel's own, recorded: a second connection to the same virtual device is
    not the same history, its leg having settled meanwhile, and the readout's last digit
    can tell.)"""
    steps = []

    def recorded(*args, **kwargs):
        steps.append(lg.step_response(*args, **kwargs))
        return steps[-1]
    monkeypatch.setattr(widgets, "step_response", recorded)
    # a fresh board (a virtual board lives for the process under its seed: another test's
    # session would have left it elsewhere)
    forget(serial_for_seed(55))
    dev = lg.connect("virtual", leg=leg, seed=55)
    lg.configure(dev)
    lg.calibrate(dev)
    with dev:
        panel = widgets.gain_step_panel(dev)
        (s_pos, _s_vel, _s_int), readout = panel.children[0].children, panel.children[1]
        s_pos.value = 40.0
        shown = readout.value
    assert [s.gains for s in steps] == [(50.0, 0.046, 0.001), (40.0, 0.046, 0.001)]
    assert panel.last_step is steps[-1]
    expected = widgets.step_readout(steps[-1], leg=dev.leg)
    assert expected.startswith("zeta = ") and shown == _readout_html(expected)
    assert "at the foot m = " in expected and "N/m" in expected   # eqs. 6.1/6.3


def test_pole_panel_complex_poles_nonlinear_preview_and_saturation(leg):
    sys = M.linearize(leg)
    panel = widgets.pole_placement_panel(sys, leg=leg, torque_limit=0.73)
    (s_center, _, _), readout = panel.children[0].children, panel.children[1]
    (s_zeta, t_poles), warning, _out = panel.children[2].children, panel.children[3], panel.children[4]
    assert warning.value == ""  # the thesis design stays far below the torque limit
    # a damping below one: two complex pairs, placed exactly
    s_zeta.value = 0.5
    d = widgets.pole_panel_design(sys, -7.0, 0.007, 6.0, zeta=0.5)
    assert readout.value == _readout_html(widgets.design_readout(d))
    wn = np.abs(d.poles)
    assert np.iscomplexobj(d.poles) and np.allclose(-d.poles.real / wn, 0.5)
    eig = np.linalg.eigvals(sys.A - sys.B @ d.K)
    assert np.sort_complex(eig) == pytest.approx(np.sort_complex(d.poles), rel=1e-6)
    # any valid set as text, complex allowed; an invalid one is explained
    t_poles.value = "-3+4j, -3-4j, -10, -11"
    d = widgets.pole_panel_design(sys, -7.0, 0.007, 6.0, poles="-3+4j, -3-4j, -10, -11")
    assert readout.value == _readout_html(widgets.design_readout(d))
    t_poles.value = "-3+4j, -10, -11, -12"
    assert readout.value.startswith("<b>cannot place:</b>")
    t_poles.value = ""
    # fast real poles: K asks for more than the torque limit, and the panel says so
    s_zeta.value = 1.0
    s_center.value = -30.0
    d = widgets.pole_panel_design(sys, -30.0, 0.007, 6.0)
    tau = widgets.demanded_torque(d, (0.0, np.radians(20.0)), np.linspace(0, 2, 401))
    assert np.abs(tau).max() > 0.73
    assert "torque limit" in warning.value and "saturate" in warning.value
    assert "preview failed" not in warning.value  # the nonlinear leg, limited, was simulated


def test_gain_panel_shows_fit_and_refuses_non_second_order_steps(leg):
    with lg.connect("virtual", leg=leg, seed=5) as dev:
        lg.configure(dev)
        lg.calibrate(dev)
        panel = widgets.gain_step_panel(dev)
        (s_pos, s_vel, s_int), readout = panel.children[0].children, panel.children[1]
        assert "R^2 = " in readout.value
        # vel_gain at its minimum: the leg barely damps, the response is no second-order step
        s_vel.value = s_vel.min
        s_int.value = 0.0
        s_pos.value = 30.0
        shown = readout.value
        r = lg.step_response(dev, 30.0, s_vel.min, 0.0)
    p = identify_response(r, dev.leg)
    assert p.status != "ok" and "zeta" not in shown, shown
    assert ("not a second-order step" in shown) == (p.status == "failed")


def _pixels(png: bytes) -> np.ndarray:
    import io

    from PIL import Image
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))


def test_a_panel_figure_redraws_what_changed_and_keeps_the_rest():
    """PanelFigure: the static axes' pixels are those of the first draw on every update;
    the dynamic axes show the new data exactly as a full draw of the same figure does; an
    overlay moved leaves no trace where it was."""
    import ipywidgets as W
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    view = widgets.PanelFigure(W.Output(), 2, (8, 3), static=(1,))
    view.axes[1].plot([0, 1], [0, 1], "k-")
    view.axes[1].set_xlim(0, 1)
    view.axes[1].set_ylim(0, 1)
    marker = view.axes[1].scatter([0.2], [0.8], s=200, c="orange")
    view.overlays.append(marker)

    def draw(y):
        ax = view.clear()[0]
        ax.plot(np.linspace(0, 1, 50), y, "r-")
        ax.set_ylim(-2, 2)
        return _pixels(view.png())

    first = draw(np.sin(np.linspace(0, 6, 50)))
    marker.set_offsets([[0.8, 0.2]])
    second = draw(np.cos(np.linspace(0, 6, 50)))
    h, w = first.shape[:2]
    assert (h, w) == (round(3 * view.fig.dpi), round(8 * view.fig.dpi))
    # the same figure drawn from scratch, everything at once, gives the update's pixels
    FigureCanvasAgg(view.fig).draw()
    full = np.asarray(view.fig.canvas.buffer_rgba())
    assert np.array_equal(second, full)
    # the dynamic axes changed; where the marker was, the static background is back
    left = view.axes[0].get_window_extent()
    rows = slice(int(h - left.y1), int(h - left.y0))
    assert not np.array_equal(first[rows, : int(left.x1)], second[rows, : int(left.x1)])
    x, y = view.axes[1].transData.transform((0.2, 0.8))
    px = (int(h - y), int(x))
    assert tuple(first[px][:3]) != (255, 255, 255) and tuple(second[px][:3]) == (255, 255, 255)
    # the second update drew only the data over the kept frame (ticks, labels): one frame drawn
    assert view.frames_drawn == 1
    # new limits and a new title: the frame is drawn again, and the update is still the full draw
    ax = view.clear()[0]
    ax.plot([0, 2], [5, -5], "b-")
    ax.set_ylim(-6, 6)
    ax.set_title("moved")
    third = _pixels(view.png())
    assert view.frames_drawn == 2
    FigureCanvasAgg(view.fig).draw()
    assert np.array_equal(third, np.asarray(view.fig.canvas.buffer_rgba()))


def test_a_panel_figures_autoscaled_axes_keep_their_limits_while_the_data_fits():
    """An autoscaled dynamic axis keeps the limits shown while the new data's own limits
    lie inside them and span at least ``keep`` of them; data that outgrows them, or
    shrinks below ``keep``, gets its own limits."""
    import ipywidgets as W

    view = widgets.PanelFigure(W.Output(), 1, (4, 3), keep=0.6)

    def shown(y):
        ax = view.clear()[0]
        ax.plot([0.0, 1.0], y)
        view.png()
        return ax.get_ylim()

    first = shown([0.0, 10.0])
    assert shown([1.0, 9.0]) == first                       # inside, 80 % of the span: kept
    grown = shown([0.0, 12.0])
    assert grown != first and grown[1] > 12.0                # outgrown: its own limits
    small = shown([0.0, 3.0])
    assert small[1] < 4.0                                    # below 60 % of the span: its own
    with pytest.raises(ArgumentError, match="keep"):
        widgets.PanelFigure(W.Output(), 1, (4, 3), keep=0.0)


def test_the_pole_panels_picture_reads(leg, monkeypatch):
    """The panel's picture at the size it is shown: no texts over each other or past its
    edge, no legend on the curves (the torques' legend once hid the torque limit)."""
    from leglib import plots
    made = []
    real = widgets.PanelFigure.__init__

    def keep(self, *args, **kwargs):
        real(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(widgets.PanelFigure, "__init__", keep)
    widgets.pole_placement_panel(M.linearize(leg), center=-7.0, leg=leg, torque_limit=0.73)
    (view,) = made
    view.png()
    assert plots.text_overlaps(view.fig) == [] and plots.clipped_texts(view.fig) == []
    assert plots.legends_on_data(view.fig) == []
    # K, L, Nbar shown with their units
    assert "N·m/rad, N·m·s/rad, N·m/rad, N·m·s/rad by state" in widgets.design_readout(
        widgets.pole_panel_design(M.linearize(leg), -7.0, 0.007, 6.0))
