"""ipywidgets panels. Callbacks only call the same leglib functions the papermill run
calls; every slider has ``continuous_update=False``."""

from __future__ import annotations

import numpy as np

from . import plots
from . import statefeedback as SF


def design_readout(d) -> str:
    """The text the pole-placement panel shows for a design (also used by tests). Single
    spaces only, so the text a browser renders is this string exactly."""
    K = " ".join(f"{v:.4f}" for v in d.K.ravel())
    L = " ".join(f"{v:.2f}" for v in d.L.ravel())
    Nbar = " ".join(f"{v:.4f}" for v in d.Nbar.ravel())
    return f"K = [{K}]; L = [{L}]; Nbar = [{Nbar}]"


def pole_panel_design(sys, center: float, spread: float, observer_factor: float, integral_poles=None):
    """The design the panel shows for its slider values."""
    return SF.design(sys, SF.spread_poles(center, 4, spread), observer_factor, integral_poles=integral_poles)


def pole_placement_panel(sys, center: float = -7.0, spread: float = 0.007, observer_factor: float = 6.0,
                         step_rad=(0.0, np.radians(20.0)), duration: float = 2.0):
    """Sliders for the closed-loop poles (a centre and a spread of four real poles, as the
    thesis's -7 ... -7.021) and the observer factor; they update the pole map, K and L, and
    the predicted step response of the linear closed loop."""
    import ipywidgets as W
    import matplotlib.pyplot as plt

    s_center = W.FloatSlider(value=center, min=-30.0, max=-1.0, step=0.5, description="pole centre",
                             continuous_update=False, readout_format=".1f")
    s_spread = W.FloatSlider(value=spread, min=0.001, max=2.0, step=0.001, description="spread",
                             continuous_update=False, readout_format=".3f")
    s_obs = W.FloatSlider(value=observer_factor, min=2.0, max=12.0, step=0.5, description="observer x",
                          continuous_update=False, readout_format=".1f")
    readout = W.HTML()
    out = W.Output()
    t = np.linspace(0, duration, 401)

    def redraw(*_):
        try:
            d = pole_panel_design(sys, s_center.value, s_spread.value, s_obs.value)
        except ValueError as exc:
            readout.value = f"<b>cannot place:</b> {exc}"
            return
        readout.value = f"<code class='leglib-readout'>{design_readout(d)}</code>"
        with out:
            out.clear_output(wait=True)
            fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.8))
            plots.plot_pole_map(d, ax=a1)
            y = d.predicted_step(step_rad, t)
            a2.plot(t, np.degrees(y[:, 0]), label="q1 deviation")
            a2.plot(t, np.degrees(y[:, 1]), label="q2 deviation")
            a2.set_xlabel("t [s]")
            a2.set_ylabel("deg")
            a2.set_title("predicted step (linear closed loop)")
            a2.legend(fontsize=8)
            plt.show()

    for s in (s_center, s_spread, s_obs):
        s.observe(redraw, names="value")
    redraw()
    return W.VBox([W.HBox([s_center, s_spread, s_obs]), readout, out])


def step_readout(resp, identified=None) -> str:
    """The text the gain panel shows for one step response (also used by tests);
    ``identified``: the response's :func:`leglib.gainmap.identify_response`, when the
    caller already has it."""
    from .gainmap import identify_response
    p = identify_response(resp) if identified is None else identified
    if p.status != "ok":
        return f"{p.status}: {p.reason}"
    return f"zeta = {p.zeta:.3f}, fn = {p.fn:.2f} Hz"


def gain_step_panel(odrv, gm=None, pos_gain: float = 50.0, vel_gain: float = 0.046,
                    vel_integrator_gain: float = 0.001):
    """Sliders for pos_gain, vel_gain and vel_integrator_gain: each change runs one step
    (:func:`leglib.odrive_io.step_response`), shows the response, its zeta / fn readout,
    and its place on the map's achievable region."""
    import ipywidgets as W
    import matplotlib.pyplot as plt

    from . import odrive_io as io
    from .gainmap import identify_response

    cfg = odrv.config
    s_pos = W.FloatSlider(value=pos_gain, min=1.0, max=min(cfg.max_pos_gain, 100.0), step=1.0,
                          description="pos_gain", continuous_update=False, readout_format=".0f")
    s_vel = W.FloatSlider(value=vel_gain, min=0.002, max=min(cfg.max_vel_gain, 0.3), step=0.002,
                          description="vel_gain", continuous_update=False, readout_format=".3f")
    s_int = W.FloatSlider(value=vel_integrator_gain, min=0.0, max=0.2, step=0.001,
                          description="vel_int_gain", continuous_update=False, readout_format=".3f")
    readout = W.HTML()
    out = W.Output()

    def redraw(*_):
        resp = io.step_response(odrv, s_pos.value, s_vel.value, s_int.value)
        p = identify_response(resp)
        readout.value = f"<code class='leglib-readout'>{step_readout(resp, p)}</code>"
        with out:
            out.clear_output(wait=True)
            fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.8))
            a1.plot(resp.t, resp.y * 1e3)
            a1.set_xlabel("t [s]")
            a1.set_ylabel("foot y [mm]")
            a1.set_title(f"gains ({s_pos.value:g}, {s_vel.value:g}, {s_int.value:g})")
            if gm is not None:
                plots.plot_gain_region(gm, ax=a2, marker=(p.zeta, p.fn) if p.status == "ok" else None)
            plt.show()

    for s in (s_pos, s_vel, s_int):
        s.observe(redraw, names="value")
    redraw()
    return W.VBox([W.HBox([s_pos, s_vel, s_int]), readout, out])
