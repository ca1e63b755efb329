"""The ipywidgets panels in-process: moving a slider sets the readout to exactly what the
leglib functions compute for the new value (the browser test checks the same in JupyterLab)."""

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from leglib import model as M, odrive_io as io, widgets  # noqa: E402


def _readout_html(text):
    return f"<code class='leglib-readout'>{text}</code>"


def test_pole_panel_readout_follows_sliders(leg):
    sys = M.linearize(leg)
    panel = widgets.pole_placement_panel(sys, center=-7.0, spread=0.007, observer_factor=6.0)
    (s_center, s_spread, s_obs), readout = panel.children[0].children, panel.children[1]
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


def test_gain_panel_readout_follows_sliders(leg):
    def device():
        dev = io.connect("virtual", leg=leg, seed=5)
        io.apply_configuration(dev)
        io.calibrate(dev)
        return dev

    with device() as dev:
        panel = widgets.gain_step_panel(dev)
        (s_pos, s_vel, s_int), readout = panel.children[0].children, panel.children[1]
        s_pos.value = 40.0
        shown = readout.value
    with device() as ref:  # the same device history, replayed without the panel
        io.step_response(ref, 50.0, 0.046, 0.001)
        expected = widgets.step_readout(io.step_response(ref, 40.0, 0.046, 0.001))
    assert expected.startswith("zeta = ") and shown == _readout_html(expected)
