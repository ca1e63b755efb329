"""ipywidgets panels. Callbacks only call the same leglib functions the papermill run
calls; every slider has ``continuous_update=False``."""

from __future__ import annotations

import base64
import math

import numpy as np

from .. import plots
from ..design import statefeedback as SF
from ..design.points import STATUS_FAILED, commanded_height, identify_response
from ..errors import ArgumentError
from ..experiments.step import step_response
from ..thesis import foot_mass, virtual_leg
from ..units import dynamics_text, interval_text, shown, significant
from . import png

THESIS_TORQUE_LIMIT = 0.73  # N*m at a joint: the thesis's current limit through the 1:3 belt


class PanelFigure:
    """A panel's figure, made once and drawn again in place on every change, shown as a PNG
    in an ``ipywidgets.Output`` (the previous picture stays until the next is ready).

    A slider's callback clears and redraws only the *dynamic* axes; axes listed as
    ``static`` are drawn once (by the caller, before the first :meth:`show`) and kept as
    pixels, with ``overlays`` (artists on them, e.g. a marker) drawn on top each time. The
    layout is fixed at the first :meth:`show` (``tight_layout``), so no redraw computes it
    again, and the PNG is the figure's canvas (no tight bounding box to search).

    The dynamic axes' frames (background, ticks, tick labels, axis labels, titles: most of a
    redraw's time, their texts) are kept as pixels too while their limits, scales, titles
    and labels stay; a redraw then draws only the data (lines, markers, texts, legend) and
    the spines over them, in the order a full draw uses. So that a slider step rarely moves
    the axes, an autoscaled dynamic axis keeps its previous limits while the new data's
    autoscaled limits lie inside them and span at least ``keep`` of them; otherwise it
    takes the new limits.

    Parameters
    ----------
    out : the Output widget showing the figure
    ncols : axes side by side
    figsize : inches
    static : indices of the axes drawn once
    legend : ``(handles, width)``: one legend of the figure beside the axes, its entries
        ``handles`` (artists with labels), ``width`` the fraction of the figure kept for it
        at the right; drawn once with the static axes (the dynamic axes' own legends would
        be laid out and their texts rendered again on every redraw, a quarter of it)
    keep : the least fraction of an axis's previous span its new autoscaled limits must
        cover for the previous limits to stay (1.0: always the new limits)
    """

    def __init__(self, out, ncols: int, figsize, static=(), legend=None, keep: float = 0.6):
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # load time: matplotlib, only when drawing
        from matplotlib.figure import Figure  # load time: as matplotlib's canvas above

        if not 0.0 < keep <= 1.0:
            raise ArgumentError(f"PanelFigure: keep = {keep!r} must lie in (0, 1]")
        self.out = out
        self.fig = Figure(figsize=figsize)
        FigureCanvasAgg(self.fig)
        self.axes = list(np.atleast_1d(self.fig.subplots(1, ncols)))
        self.static = [self.axes[i] for i in static]
        self.dynamic = [ax for ax in self.axes if ax not in self.static]
        self.overlays: list = []
        self.keep = keep
        self.frames_drawn = 0   # how often the dynamic axes' frames were drawn (the rest: data only)
        self._background = None
        self._frame = None      # (key, pixels): the background with the dynamic axes' frames
        self._shown_limits = None
        self._right = 1.0
        if legend is not None:
            handles, width = legend
            self._right = 1.0 - width
            self.fig.legend(handles=handles, loc="upper left", bbox_to_anchor=(self._right, 0.97), fontsize=7,
                            borderaxespad=0.0)

    def clear(self) -> list:
        """Empty the dynamic axes for the callback to draw into (its lines, markers, texts
        and legend go; the axes with their ticks stay: ``cla()`` would make the ticks anew,
        most of a redraw's time); returns all the axes."""
        for ax in self.dynamic:
            for artist in [*ax.lines, *ax.collections, *ax.texts, *ax.patches, *ax.images]:
                artist.remove()
            if ax.get_legend() is not None:
                ax.get_legend().remove()
            ax.relim()
            ax.autoscale()
        return self.axes

    def _keep_limits(self) -> None:
        """An autoscaled dynamic axis keeps the limits last shown while its new limits lie
        inside them and span at least ``keep`` of them."""
        shown = self._shown_limits or [None] * len(self.dynamic)
        for ax, before in zip(self.dynamic, shown):
            for auto, get, put, k in ((ax.get_autoscalex_on(), ax.get_xlim, ax.set_xlim, 0),
                                      (ax.get_autoscaley_on(), ax.get_ylim, ax.set_ylim, 1)):
                if not auto or before is None:
                    continue
                lo, hi = get()
                was_lo, was_hi = before[k]
                if was_lo <= lo and hi <= was_hi and (hi - lo) >= self.keep * (was_hi - was_lo):
                    put(was_lo, was_hi)
        self._shown_limits = [(ax.get_xlim(), ax.get_ylim()) for ax in self.dynamic]

    @staticmethod
    def _frame_of(ax) -> list:
        """What of an axes the kept frame holds: its axis objects (ticks, tick labels, axis
        labels) and titles; the axes' background patch is drawn with them."""
        return [ax.xaxis, ax.yaxis, *(t for t in (ax.title, getattr(ax, "_left_title", None),
                                                  getattr(ax, "_right_title", None)) if t is not None)]

    def _frame_key(self) -> tuple:
        return tuple((ax.get_xlim(), ax.get_ylim(), ax.get_xscale(), ax.get_yscale(),
                      *(t.get_text() for t in self._frame_of(ax)[2:]), ax.get_xlabel(), ax.get_ylabel())
                     for ax in self.dynamic)

    def png(self) -> bytes:
        """The figure as PNG: the static axes from the first draw's pixels, the dynamic axes'
        frames from the last draw with the same limits and labels, and their data and the
        overlays drawn now."""
        canvas = self.fig.canvas
        if self._background is None:
            self.fig.tight_layout(rect=(0.0, 0.0, self._right, 1.0))
            hidden = self.dynamic + self.overlays
            for a in hidden:
                a.set_visible(False)
            canvas.draw()
            self._background = canvas.copy_from_bbox(self.fig.bbox)
            for a in hidden:
                a.set_visible(True)
        self._keep_limits()
        renderer = canvas.get_renderer()
        data = {}
        for ax in self.dynamic:
            ax.apply_aspect()
            kept = set(self._frame_of(ax)) | {ax.patch}
            data[ax] = sorted((a for a in ax.get_children() if a not in kept and a.get_visible()),
                              key=lambda a: a.get_zorder())
        key = self._frame_key()
        if self._frame is None or self._frame[0] != key:
            canvas.restore_region(self._background)
            for ax in self.dynamic:
                for a in data[ax]:
                    a.set_visible(False)
                ax.draw(renderer)
                for a in data[ax]:
                    a.set_visible(True)
            self._frame = (key, canvas.copy_from_bbox(self.fig.bbox))
            self.frames_drawn += 1
        canvas.restore_region(self._frame[1])
        for ax in self.dynamic:
            for a in data[ax]:
                a.draw(renderer)
        for artist in self.overlays:
            artist.draw(renderer)
        return png.encode(np.asarray(canvas.buffer_rgba()))

    def show(self) -> None:
        """The new picture in place of the old one: one update of the Output widget's
        ``outputs`` (as its ``append_display_data`` does), not a clear and a display inside
        ``with out:`` (four messages; about 25 ms more from release to picture in JupyterLab)."""
        data = base64.b64encode(self.png()).decode("ascii")
        self.out.outputs = ({"output_type": "display_data", "metadata": {},
                             "data": {"image/png": data, "text/plain": "<panel figure>"}},)


def design_readout(d) -> str:
    """The text the pole-placement panel shows for a design (also used by tests): K, L and Nbar
    row by row to four significant digits, each with its units (K per state: N·m/rad on the
    angles, N·m·s/rad on the velocities; L per state row: 1/s, 1/s²; Nbar N·m/rad:
    :func:`leglib.design.statefeedback.gain_units`). Single spaces only, so the text a browser
    renders is this string exactly."""
    units = SF.gain_units()

    def flat(m):
        return " ".join(significant(v, 4) for v in np.asarray(m).ravel())

    k_units = ", ".join(units["K"][0])
    l_units = ", ".join(row[0] for row in units["L"])
    return (f"K = [{flat(d.K)}] ({k_units} by state); L = [{flat(d.L)}] ({l_units} by state row); "
            f"Nbar = [{flat(d.Nbar)}] ({units['Nbar'][0][0]})")


def panel_poles(center: float, spread: float, zeta: float = 1.0) -> np.ndarray:
    """The four closed-loop poles the pole panel's sliders ask for.

    Parameters
    ----------
    center : [1/s], negative: with ``zeta >= 1`` the first real pole (the thesis's -7);
        with ``zeta < 1`` minus the natural frequency wn of the first complex pair
    spread : [1/s], distance between successive real poles, or between the two pairs' wn
    zeta : damping ratio of the pairs; 1 or more gives four real poles (as the thesis)

    Returns
    -------
    (4,) poles: real, or two complex-conjugate pairs -zeta wn +- j wn sqrt(1 - zeta^2).
    """
    if zeta >= 1:
        return SF.spread_poles(center, 4, spread)
    out = []
    for wn in (abs(center), abs(center) + spread):
        wd = wn * math.sqrt(1 - zeta ** 2)
        out += [complex(-zeta * wn, wd), complex(-zeta * wn, -wd)]
    return np.array(out)


def pole_panel_design(sys, center: float, spread: float, observer_factor: float, integral_poles=None,
                      zeta: float = 1.0, poles: str = ""):
    """The design the panel shows for its values: ``poles`` (any valid set as text, e.g.
    "-3+4j, -3-4j, -10, -11") when given, else :func:`panel_poles` of the sliders."""
    p = SF.parse_poles(poles) if poles.strip() else panel_poles(center, spread, zeta)
    return SF.place_poles(sys, p, observer_factor, integral_poles=integral_poles)


def demanded_torque(d, r, t) -> np.ndarray:
    """Joint torques (N, 2) [N*m, deviation from the operating point's] the linear closed
    loop of design ``d`` demands for a reference step ``r`` (2,) [rad]: u = Nbar r - K x."""
    import control  # load time: python-control (about 2 s), only for a design's linear system
    A, B = d.sys.A, d.sys.B
    sys_u = control.ss(A - B @ d.K, B @ d.Nbar, -d.K, d.Nbar)
    t = np.asarray(t, dtype=float)
    return control.forced_response(sys_u, t, np.tile(np.asarray(r, float)[:, None], t.size)).outputs.T


def saturation_warning(tau, limit: float) -> str:
    """A warning when torques ``tau`` (N, 2) [N*m] reach the limit [N*m], else ""."""
    peak = float(np.max(np.abs(tau))) if np.size(tau) else 0.0
    if peak < limit:
        return ""
    return (f"K asks for {peak:.2f} N m, more than the {limit:.2f} N m torque limit: the motors saturate, "
            f"and the leg follows the nonlinear (limited) curve, not the linear prediction")


def pole_placement_panel(sys, center: float = -7.0, spread: float = 0.007, observer_factor: float = 6.0,
                         step_rad=(0.0, np.radians(20.0)), duration: float = 2.0, leg=None,
                         torque_limit: float = THESIS_TORQUE_LIMIT):
    """Sliders for the closed-loop poles and the observer factor.

    The poles: a centre and a spread (the thesis's -7 ... -7.021), and a damping ratio that
    turns them into two complex pairs (zeta < 1, :func:`panel_poles`); or any valid set
    typed as text (complex allowed), which takes precedence while not empty. The panel shows
    K, L and Nbar, the pole map, the predicted step of the linear closed loop and, with
    ``leg``, the nonlinear leg's step under the torque limit ``torque_limit`` [N*m]
    (:func:`leglib.design.statefeedback.simulate_closed_loop`), with the torques and a warning
    when K asks for more torque than the limit.

    Layout: children[0] the centre, spread and observer sliders; children[1] the readout;
    children[2] the damping slider and the pole text; children[3] the warning;
    children[4] the plots.
    """
    import ipywidgets as W  # load time: ipywidgets, only inside a notebook

    s_center = W.FloatSlider(value=center, min=-30.0, max=-1.0, step=0.5, description="pole centre",
                             continuous_update=False, readout_format=".1f")
    s_spread = W.FloatSlider(value=spread, min=0.001, max=2.0, step=0.001, description="spread",
                             continuous_update=False, readout_format=".3f")
    s_obs = W.FloatSlider(value=observer_factor, min=2.0, max=12.0, step=0.5, description="observer x",
                          continuous_update=False, readout_format=".1f")
    s_zeta = W.FloatSlider(value=1.0, min=0.1, max=1.0, step=0.05, description="pole zeta",
                           continuous_update=False, readout_format=".2f")
    t_poles = W.Text(value="", description="or poles", placeholder="e.g. -3+4j, -3-4j, -10, -11 (1/s)",
                     continuous_update=False, layout=W.Layout(width="420px"))
    readout = W.HTML()
    warning = W.HTML()
    out = W.Output()
    from matplotlib.lines import Line2D  # load time: matplotlib, only when drawing

    # one legend for both plots, drawn once: colour the joint, dashes the linear prediction
    legend = [Line2D([], [], color="b", ls="--", lw=1, label="joint 1, linear"),
              Line2D([], [], color="r", ls="--", lw=1, label="joint 2, linear"),
              Line2D([], [], color="b", ls="-", label="joint 1, nonlinear, limited"),
              Line2D([], [], color="r", ls="-", label="joint 2, nonlinear, limited"),
              Line2D([], [], color="k", ls=":", lw=0.8, label="q2 setpoint"),
              Line2D([], [], color="k", ls="-.", lw=0.8, label="torque limit")]
    view = PanelFigure(out, 3, (15, 3.8), legend=(legend, 0.12))
    t = np.linspace(0, duration, 401)

    def redraw(*_):
        try:
            d = pole_panel_design(sys, s_center.value, s_spread.value, s_obs.value, zeta=s_zeta.value,
                                  poles=t_poles.value)
        except ValueError as exc:
            readout.value = f"<b>cannot place:</b> {exc}"
            warning.value = ""
            return
        readout.value = f"<code class='leglib-readout'>{design_readout(d)}</code>"
        y = d.predicted_step(step_rad, t)
        tau_lin = demanded_torque(d, step_rad, t)
        res, why = None, ""
        if leg is not None:
            try:
                res = SF.simulate_closed_loop(leg, d, step=step_rad, duration=duration, torque_limit=torque_limit)
            except ValueError as exc:
                why = f"nonlinear preview failed: {exc}"
        text = saturation_warning(tau_lin, torque_limit)
        warning.value = "".join(f"<p style='color:#b00'><b>warning:</b> {m}</p>" for m in (text, why) if m)
        a1, a2, a3 = view.clear()
        plots.plot_pole_map(d, ax=a1)
        a1.set_title("poles [1/s]")
        a2.plot(t, np.degrees(y[:, 0]), "b--", lw=1)
        a2.plot(t, np.degrees(y[:, 1]), "r--", lw=1)
        a2.axhline(np.degrees(step_rad[1]), color="k", ls=":", lw=0.8)
        a3.plot(t, tau_lin[:, 0], "b--", lw=1)
        a3.plot(t, tau_lin[:, 1], "r--", lw=1)
        if res is not None:
            q0 = np.array(leg.q0)
            a2.plot(res.t, np.degrees(res.x[:, 0] - q0[0]), "b-")
            a2.plot(res.t, np.degrees(res.x[:, 2] - q0[1]), "r-")
            tau0 = np.array(res.meta["tau0"])
            a3.plot(res.t, res.tau[:, 0] - tau0[0], "b-")
            a3.plot(res.t, res.tau[:, 1] - tau0[1], "r-")
        for s in (1, -1):
            a3.axhline(s * torque_limit, color="k", lw=0.8, ls="-.")
        a2.set_xlabel("t [s]")
        a2.set_ylabel("joint angle deviation [deg]")
        a2.set_title("predicted step" + (" (linear and nonlinear)" if res is not None else " (linear)"))
        a3.set_xlabel("t [s]")
        a3.set_ylabel("joint torque deviation [N m]")
        a3.set_title("torques against the limit")
        view.show()

    for s in (s_center, s_spread, s_obs, s_zeta, t_poles):
        s.observe(redraw, names="value")
    redraw()
    return W.VBox([W.HBox([s_center, s_spread, s_obs]), readout, W.HBox([s_zeta, t_poles]), warning, out])


def step_readout(resp, identified=None, leg=None) -> str:
    """The text the gain panel shows for one step response (also used by tests);
    ``identified``: the response's :func:`leglib.design.points.identify_response`, when the
    caller already has it (``leg``, the leg's LegParams, is needed otherwise).
    "zeta = 0.371 [0.365, 0.378], fn = 6.98 [6.90, 7.05] Hz (90 % intervals), R^2 = ..." for
    a second-order step, followed, with the nominal ``leg``, by the equivalent
    spring-damper-mass at the foot of eqs. 6.1/6.3 (:func:`leglib.thesis.virtual_leg` with
    :func:`leglib.thesis.foot_mass`), b and k with the ranges the intervals give them;
    "not a second-order step: <why>" or "unstable: <why>" otherwise, never numbers."""
    if identified is None and leg is None:
        raise ArgumentError("step_readout: give the response's identification or the leg (its commanded foot "
                            "height)")
    p = identify_response(resp, leg) if identified is None else identified
    if p.status == STATUS_FAILED:
        why = p.reason.removeprefix("not a second-order step: ")
        return f"not a second-order step: {why}"
    if p.status != "ok":
        return f"{p.status}: {p.reason}"
    # each number to the digits its interval supports; b and k below from the numbers shown
    zeta, fn = shown(p.zeta, p.zeta_interval), shown(p.fn, p.fn_interval)
    (zl, zh), (fl, fh) = p.zeta_interval, p.fn_interval
    text = f"{dynamics_text(p.zeta, p.fn, p.zeta_interval, p.fn_interval, sep='=')} (90 % intervals), R^2 = {p.r2:.3f}"
    if leg is not None:
        # of the (zeta, fn) shown, so the line is a function of what the reader sees; b and k
        # grow with zeta and fn, so the intervals' ends bound them
        mass = foot_mass(leg)
        v = virtual_leg(zeta, fn, mass)
        lo = virtual_leg(max(zl, 1e-9), max(fl, 1e-9), mass)
        hi = virtual_leg(zh, fh, mass)
        text += (f"; at the foot m = {v.m:.3f} kg, b = {interval_text(v.b, (lo.b, hi.b), 'N*s/m')}, "
                 f"k = {interval_text(v.k, (lo.k, hi.k), 'N/m')}")
    return text


def foot_setpoint(leg, resp) -> float:
    """Foot height [m] the commanded step of ``resp`` asks for
    (:func:`leglib.design.points.commanded_height`)."""
    return commanded_height(resp, leg)


def gain_step_panel(odrv, gm=None, pos_gain: float = 50.0, vel_gain: float = 0.046,
                    vel_integrator_gain: float = 0.001):
    """Sliders for pos_gain, vel_gain and vel_integrator_gain: each change runs one step
    (:func:`leglib.experiments.step.step_response`) and shows the response with its fitted
    second-order step, the setpoint and R^2 (or "not a second-order step"), the readout
    (:func:`step_readout`), and its place on the map's achievable region. The panel's
    ``last_step`` is the :class:`~leglib.experiments.step.StepResponse` it shows."""
    import ipywidgets as W  # load time: ipywidgets, only inside a notebook

    cfg = odrv.config
    s_pos = W.FloatSlider(value=pos_gain, min=1.0, max=min(cfg.max_pos_gain, 100.0), step=1.0,
                          description="pos_gain", continuous_update=False, readout_format=".0f")
    s_vel = W.FloatSlider(value=vel_gain, min=0.002, max=min(cfg.max_vel_gain, 0.3), step=0.002,
                          description="vel_gain", continuous_update=False, readout_format=".3f")
    s_int = W.FloatSlider(value=vel_integrator_gain, min=0.0, max=0.2, step=0.001,
                          description="vel_int_gain", continuous_update=False, readout_format=".3f")
    readout = W.HTML()
    out = W.Output()
    leg = odrv.leg   # the commanded foot height of each step, and eqs. 6.1/6.3 at the foot
    # the map's region is drawn once and kept as pixels; each step moves only its marker
    view = PanelFigure(out, 2, (12.5, 3.8), static=(1,) if gm is not None else ())
    a2 = view.axes[1]
    if gm is not None:
        plots.plot_gain_region(gm, ax=a2)
        here = a2.scatter(np.empty(0), np.empty(0), s=120, marker="*", c="orange", label="this step")
        plots.region_legend(a2)
        view.overlays.append(here)

    def redraw(*_):
        resp = step_response(odrv, s_pos.value, s_vel.value, s_int.value)
        panel.last_step = resp
        p = identify_response(resp, leg)
        text = step_readout(resp, p, leg=leg)
        readout.value = f"<code class='leglib-readout'>{text}</code>"
        a1 = view.clear()[0]
        a1.plot(resp.t, resp.y * 1e3, "r-", label="measured")
        fit = p.fit  # None when unstable or not identifiable at all
        if fit is not None:
            style = "b--" if p.status == "ok" else "0.5"
            a1.plot(resp.t, fit.response(resp.t) * 1e3, style, lw=1.2,
                    label=f"second-order fit, R^2 = {fit.r2:.3f}" + ("" if p.status == "ok" else " (rejected)"))
        if leg is not None:
            a1.axhline(foot_setpoint(leg, resp) * 1e3, color="k", ls=":", lw=0.8, label="setpoint")
        if p.status != "ok":
            a1.text(0.5, 0.5, "not a second-order step" if p.status == "failed" else p.status,
                    transform=a1.transAxes, ha="center", color="#b00", fontsize=12,
                    bbox={"fc": "w", "ec": "#b00"})
        a1.set_xlabel("t [s]")
        a1.set_ylabel("foot height y [mm]")
        a1.set_title(f"step with gains ({s_pos.value:g}, {s_vel.value:g}, {s_int.value:g})")
        a1.legend(fontsize=8)
        if gm is not None:
            here.set_offsets(np.array([[p.zeta, p.fn]]) if p.status == "ok" else np.empty((0, 2)))
        view.show()

    panel = W.VBox([W.HBox([s_pos, s_vel, s_int]), readout, out])
    panel.last_step = None   # the StepResponse the readout and the figure show
    for s in (s_pos, s_vel, s_int):
        s.observe(redraw, names="value")
    redraw()
    return panel
