"""Plot helpers: each takes ``ax=None`` (or axes) and returns what it drew."""

from __future__ import annotations

import base64
import io
import re
import tempfile
import textwrap
from pathlib import Path

import numpy as np
from PIL import Image

from . import model as M
from .units import interval_text


def axes(ax=None):
    """``ax``, or new axes of a new figure when it is None (every helper here starts so)."""
    if ax is None:
        import matplotlib.pyplot as plt  # load time: matplotlib (about 0.5 s), only when drawing
        _, ax = plt.subplots()
    return ax



def _texts(fig):
    """The figure's visible, non-empty texts with a name for each: titles, axis labels, tick
    labels, legend entries, annotations, colour bar labels."""
    out = []
    for k, ax in enumerate(fig.axes):
        where = f"axes {k}"
        named = [(ax.title, "title"), (ax._left_title, "title"), (ax._right_title, "title"),
                 (ax.xaxis.label, "x label"), (ax.yaxis.label, "y label")]
        # tick labels that are drawn: those of ticks inside the axis's view
        for axis, kind, coord in ((ax.xaxis, "x tick", 0), (ax.yaxis, "y tick", 1)):
            lo, hi = sorted(axis.get_view_interval())
            span = (hi - lo) * 1e-9
            named += [(t, kind) for t in axis.get_ticklabels()
                      if lo - span <= t.get_position()[coord] <= hi + span]
        legend = ax.get_legend()
        if legend is not None and legend.get_visible():
            named += [(t, "legend") for t in legend.get_texts()]
            named.append((legend.get_title(), "legend title"))
        named += [(t, "text") for t in ax.texts]
        for t, kind in named:
            if t.get_visible() and t.get_text().strip():
                out.append((t, f"{where} {kind} {t.get_text().strip()[:40]!r}"))
    named = [(t, "figure text") for t in fig.texts]
    if getattr(fig, "_suptitle", None) is not None:
        named.append((fig._suptitle, "suptitle"))
    out += [(t, f"{kind} {t.get_text().strip()[:40]!r}") for t, kind in named
            if t.get_visible() and t.get_text().strip()]
    return out


def text_overlaps(fig, tolerance_px: float = 1.0) -> list[str]:
    """Pairs of texts of ``fig`` that overlap when it is drawn (each named: axes, kind, text),
    by more than ``tolerance_px`` in both directions: a title running into its neighbour's,
    a colour bar label into the next panel, tick labels into each other. Texts of one legend
    are not compared with each other (the legend lays them out)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = []
    for t, name in _texts(fig):
        try:
            bb = t.get_window_extent(renderer)
        except (RuntimeError, ValueError):  # a text that cannot be laid out: nothing to compare
            continue
        if bb.width > 0 and bb.height > 0:
            boxes.append((bb, name, t))
    found = []
    for i in range(len(boxes)):
        a, name_a, ta = boxes[i]
        for j in range(i + 1, len(boxes)):
            b, name_b, tb = boxes[j]
            same_legend = " legend" in name_a and " legend" in name_b and name_a.split(" legend")[0] == \
                name_b.split(" legend")[0]
            twin = ta.get_text() == tb.get_text() and all(abs(p - q) <= 1.0 for p, q in zip(a.extents, b.extents))
            if same_legend or twin:  # a twin axes' label drawn on top of its own copy: one text to read
                continue
            w = min(a.x1, b.x1) - max(a.x0, b.x0)
            h = min(a.y1, b.y1) - max(a.y0, b.y0)
            if w > tolerance_px and h > tolerance_px:
                found.append(f"{name_a} overlaps {name_b}")
    return found

def _data_under(ax, box, renderer) -> list[str]:
    """The data of ``ax`` (lines, markers, scatter points, error bars, patches; not images,
    which any box inside the axes covers) drawn under the display-space ``box``, by label."""
    from matplotlib.collections import LineCollection, PathCollection  # load time: matplotlib, only when drawing

    def name(artist):
        label = str(artist.get_label() or "")
        return label if label and not label.startswith("_") else type(artist).__name__

    hits = []
    for line in ax.get_lines():
        if not line.get_visible() or len(line.get_xydata()) == 0:
            continue
        path = line.get_transform().transform_path(line.get_path())
        verts = path.vertices[np.all(np.isfinite(path.vertices), axis=1)]
        if line.get_linestyle() in ("None", "", " ", "none"):   # markers only: the points themselves
            inside = box.count_contains(verts) > 0 if len(verts) else False
        else:
            inside = bool(len(verts)) and (box.count_contains(verts) > 0 or path.intersects_bbox(box, filled=False))
        if inside:
            hits.append(name(line))
    for coll in ax.collections:
        if not coll.get_visible():
            continue
        if isinstance(coll, PathCollection) and len(coll.get_offsets()):
            pts = coll.get_offset_transform().transform(np.asarray(coll.get_offsets(), float))
            if box.count_contains(pts[np.all(np.isfinite(pts), axis=1)]) > 0:
                hits.append(name(coll))
        elif isinstance(coll, LineCollection):
            tr = coll.get_transform()
            if any(tr.transform_path(p).intersects_bbox(box, filled=False) for p in coll.get_paths()):
                hits.append(name(coll))
    for patch in ax.patches:
        if patch.get_visible() and patch.get_window_extent(renderer).overlaps(box):
            hits.append(name(patch))
    return hits


def _legends(fig):
    out = [(ax.get_legend(), ax) for ax in fig.axes if ax.get_legend() is not None]
    return out + [(leg, None) for leg in fig.legends]


def legends_on_data(fig) -> list[str]:
    """Legends of ``fig`` drawn over data of any of its axes (each named: the axes, what it
    covers): a legend that hides what it explains."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    found = []
    for legend, _ in _legends(fig):
        if not legend.get_visible():
            continue
        box = legend.get_window_extent(renderer)
        for k, ax in enumerate(fig.axes):
            if ax.get_window_extent(renderer).overlaps(box):
                hits = _data_under(ax, box, renderer)
                if hits:
                    found.append(f"axes {k} legend covers {', '.join(sorted(set(hits))[:4])}")
    return found


def _twins(ax):
    """``ax`` and the axes drawn at its place (``twinx``)."""
    pos = ax.get_position().bounds
    return [a for a in ax.figure.axes if np.allclose(a.get_position().bounds, pos)]


def _has_right_neighbour(ax, renderer) -> bool:
    """Another axes (a panel, a colour bar) to the right of ``ax`` in its row."""
    me = ax.get_window_extent(renderer)
    twins = _twins(ax)
    for other in ax.figure.axes:
        if other in twins or not other.get_visible():
            continue
        b = other.get_window_extent(renderer)
        if b.x0 >= me.x1 - 1 and min(b.y1, me.y1) > max(b.y0, me.y0):
            return True
    return False


def keep_legends_off_data(fig) -> list[str]:
    """Move each axes legend that covers data (:func:`legends_on_data`) where it covers none:
    first matplotlib's "best" place inside the axes; if none is free, beside the axes on the
    right (past a twin axis's labels) when nothing stands there, else above the axes, the
    title raised over it. Returns what was moved, e.g. ["axes 0: beside the axes"]."""
    moved = []
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for k, ax in enumerate(fig.axes):
        legend = ax.get_legend()
        if legend is None or not legend.get_visible():
            continue

        def covers():
            fig.canvas.draw()
            box = legend.get_window_extent(renderer)
            return any(_data_under(a, box, renderer) for a in fig.axes if a.get_window_extent(renderer).overlaps(box))

        if not covers():
            continue
        legend.set_bbox_to_anchor(None)
        legend.set_loc("best")
        if not covers():
            moved.append(f"axes {k}: best place inside")
            continue
        if not _has_right_neighbour(ax, renderer):
            right = max(a.get_tightbbox(renderer).x1 for a in _twins(ax))
            me = ax.get_window_extent(renderer)
            legend.set_loc("upper left")
            legend.set_bbox_to_anchor(((right - me.x0) / me.width + 0.02, 1.0), transform=ax.transAxes)
            moved.append(f"axes {k}: beside the axes")
        else:
            legend.set_loc("lower center")
            legend.set_bbox_to_anchor((0.5, 1.01), transform=ax.transAxes)
            fig.canvas.draw()
            height = legend.get_window_extent(renderer).height * 72.0 / fig.dpi   # points
            if ax.get_title():
                ax.set_title(ax.get_title(), pad=height + 8.0, fontsize=ax.title.get_fontsize())
            moved.append(f"axes {k}: above the axes")
    return moved


def clipped_texts(fig, tolerance_px: float = 1.0) -> list[str]:
    """Texts of ``fig`` that run past the figure's edge when it is drawn at its own size (an
    animation's frames, a widget's picture: nothing there widens the canvas as a saved
    figure's tight bounding box does), each named."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    w, h = fig.canvas.get_width_height()
    found = []
    for t, name in _texts(fig):
        try:
            bb = t.get_window_extent(renderer)
        except (RuntimeError, ValueError):
            continue
        if bb.width > 0 and (bb.x0 < -tolerance_px or bb.y0 < -tolerance_px or bb.x1 > w + tolerance_px
                             or bb.y1 > h + tolerance_px):
            found.append(f"{name} runs past the figure's edge")
    return found


def fit_title(ax, title: str, fontsize: float | None = None):
    """Set ``title`` on ``ax`` so that it fits its figure drawn at its own size: wrapped onto
    two lines when it is wider than the figure, then smaller if it still is; the axes moved
    down when it runs past the top (a long title on an animation's small figure was cut at
    both ends)."""
    fig = ax.figure
    size = fontsize or ax.title.get_fontsize()
    text = title
    t = ax.set_title(text, fontsize=size)
    for _ in range(12):
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        bb = t.get_window_extent(renderer)
        w, h = fig.canvas.get_width_height()
        if bb.x0 < 0 or bb.x1 > w:          # too wide: wrap, then shrink
            if "\n" not in text and " " in title:
                words = title.split(" ")
                half = len(title) / 2
                cut = min(range(1, len(words)), key=lambda i: abs(len(" ".join(words[:i])) - half))
                text = " ".join(words[:cut]) + "\n" + " ".join(words[cut:])
            else:
                size *= 0.9
            t = ax.set_title(text, fontsize=size)
        elif bb.y1 > h:                       # past the top: the axes make room
            top = fig.subplotpars.top - (bb.y1 - h + 4) / h
            fig.subplots_adjust(top=top)
        else:
            break
    return t


def draw_leg(leg, q1, q2, ax=None, **style):
    """Draw the four links of the exact five-bar at (q1, q2) [rad]; returns the Line2D."""
    ax = axes(ax)
    phi3, phi4 = M.lower_link_angles(leg, q1, q2)
    p1 = leg.l1 * np.array([np.cos(q1), np.sin(q1)])
    p2 = leg.l2 * np.array([np.cos(q2), np.sin(q2)])
    foot = p1 + leg.l4 * np.array([np.cos(phi4), np.sin(phi4)])
    pts = np.array([p1, [0, 0], p2, foot, p1])
    (line,) = ax.plot(pts[:, 0], pts[:, 1], "o-", **{"color": "k", "lw": 2, **style})
    return line


def plot_workspace(leg, ax=None, n: int = 45):
    """Foot positions over the working range, coloured by q2 - q1, with the leg at q0."""
    ax = axes(ax)
    q1, q2 = M.workspace_grid(leg, n=n)
    x, y = M.foot_position(leg, q1, q2)
    sc = ax.scatter(x, y, c=np.degrees(q2 - q1), s=4, cmap="viridis")
    ax.figure.colorbar(sc, ax=ax, label="q2 - q1 [deg]")
    draw_leg(leg, *leg.q0, ax=ax, label="operating point")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Foot workspace (exact five-bar)")
    ax.legend(loc="upper right")
    return sc


def plot_model_difference(cmp: dict, axes=None):
    """Three maps from :func:`leglib.model.linear.compare_models`: inertia, gravity, foot height."""
    if axes is None:
        import matplotlib.pyplot as plt  # load time: matplotlib (about 0.5 s), only when drawing
        _, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ext = np.degrees([cmp["theta"].min(), cmp["theta"].max(), cmp["gap"].min(), cmp["gap"].max()])
    panels = [
        (cmp["D_rel"] * 100, "||D_a - D_b|| / ||D_b|| [%]", "[%]"),
        (cmp["G_diff"] * 1e3, "||g_a - g_b|| [mN m]", "[mN m]"),
        ((cmp["y_eq65"] - cmp["y_exact"]) * 1e3, "eq. 6.5 y minus exact foot y [mm]", "[mm]"),
    ]
    images = []
    for k, (ax, (data, title, unit)) in enumerate(zip(axes, panels)):
        im = ax.imshow(data, origin="lower", aspect="auto", extent=ext, cmap="magma")
        ax.figure.colorbar(im, ax=ax, label=unit)
        ax.set_title(title)
        ax.set_xlabel("theta = (q1 + q2)/2 [deg]")
        if k == 0:  # shared by the row: repeated, it ran into the colour bar label beside it
            ax.set_ylabel("q2 - q1 [deg]")
        images.append(im)
    return images


def plot_states(t, states: dict, ax=None, deg: bool = True, idx=(0, 2), names=("q1", "q2")):
    """Overlay several (N, 4) state trajectories' joint angles; ``states`` maps label->x."""
    ax = axes(ax)
    lines = []
    scale = 180 / np.pi if deg else 1.0
    styles = ["-", "--", ":", "-."]
    for k, (label, x) in enumerate(states.items()):
        for j, name in zip(idx, names):
            (ln,) = ax.plot(t, x[:, j] * scale, styles[k % 4], label=f"{name} {label}")
            lines.append(ln)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("angle [deg]" if deg else "angle [rad]")
    ax.legend()
    return lines


def plot_torque_run(run, ax=None):
    """Joint angles of a torque run (left axis) and the commanded torques (right axis)."""
    ax = axes(ax)
    l1 = ax.plot(run.t, np.degrees(run.q1), label="q1")
    l2 = ax.plot(run.t, np.degrees(run.q2), label="q2")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("joint angle [deg]")
    ax2 = ax.twinx()
    tt = run.period * np.arange(len(run.table))
    l3 = ax2.plot(tt, run.table[:, 0], "k:", lw=0.8, label="tau1")
    l4 = ax2.plot(tt, run.table[:, 1], "k--", lw=0.8, label="tau2")
    ax2.set_ylabel("joint torque [N m]")
    lines = l1 + l2 + l3 + l4
    # the angles and torques fill the axes: where no place inside is free, keep_legends_off_data
    # (save_figure) puts the legend beside them, past the torque axis
    ax.legend(lines, [ln.get_label() for ln in lines], fontsize=8)
    return lines


def plot_measured_vs_simulated(t, measured, simulated: dict, ax=None, label="q2"):
    """A measured angle [rad] against simulated ones (dict label -> array) in degrees."""
    ax = axes(ax)
    lines = ax.plot(t, np.degrees(measured), "r-", lw=2, label=f"{label} experiment")
    for style, (name, sim) in zip(["b--", "g-.", "m:"], simulated.items()):
        lines += ax.plot(t, np.degrees(sim), style, label=f"{label} {name}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("angle [deg]")
    ax.legend(fontsize=8)
    return lines


def plot_step_identification(t, y, fit, ax=None):
    """A step response with its second-order fit; the fit's 90 % intervals of zeta and fn in
    the legend when it has them (``fit.intervals``)."""
    ax = axes(ax)
    lines = ax.plot(t, y * 1e3, "r-", label="measured")
    iv = getattr(fit, "intervals", None)
    if iv is not None:
        label = (f"{fit.method}: zeta={iv.text('zeta', fit.zeta)}, fn={iv.text('fn', fit.fn)} Hz "
                 f"(90 %), R^2={fit.r2:.3f}")
    else:
        label = f"{fit.method}: zeta={fit.zeta:.3f}, fn={fit.fn:.2f} Hz, fd={fit.fd:.2f} Hz, R^2={fit.r2:.3f}"
    lines += ax.plot(t, fit.response(np.asarray(t, float) - t[0]) * 1e3, "b--", label=label)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("foot height y [mm]")
    ax.set_title("Step response and its second-order fit")
    ax.legend(fontsize=8)
    return lines


def plot_pole_map(d, ax=None):
    """Closed-loop and observer poles of a :class:`leglib.design.statefeedback.StateFeedback`, with the
    open-loop poles of its model."""
    ax = axes(ax)
    ol = np.linalg.eigvals(d.sys.A)
    arts = [ax.plot(ol.real, ol.imag, "kx", ms=9, label="open loop")[0],
            ax.plot(np.real(d.poles), np.imag(d.poles), "bo", label="controller")[0],
            ax.plot(np.real(d.observer_poles), np.imag(d.observer_poles), "r^", label="observer")[0]]
    if d.integral_poles is not None:
        arts.append(ax.plot(np.real(d.integral_poles), np.imag(d.integral_poles), "gs", label="integrators")[0])
    ax.axvline(0, color="0.6", lw=0.8)
    ax.axhline(0, color="0.6", lw=0.8)
    ax.set_xlabel("Re [1/s]")
    ax.set_ylabel("Im [1/s]")
    ax.set_title("Poles")
    ax.legend(fontsize=8)
    return arts


def plot_step_comparison(series: dict, target_deg: float, ax=None, joint: str = "q2"):
    """Joint-angle responses (dict label -> (t, q [rad])) against the setpoint."""
    ax = axes(ax)
    lines = []
    for style, (label, (t, q)) in zip(["r-", "b--", "g-.", "m:", "c-"], series.items()):
        lines += ax.plot(t, np.degrees(q), style, label=label)
    lines.append(ax.axhline(target_deg, color="k", lw=0.8, ls=":", label="setpoint"))
    ax.set_xlabel("t [s]")
    ax.set_ylabel(f"{joint} [deg]")
    ax.legend(fontsize=8)
    return lines


def plot_gain_region(gm, ax=None, targets=None, marker=None, numbered: bool = True):
    """The achievable (zeta, fn) region of a :class:`leglib.design.gainmap.GainMap` (the thesis's
    Fig. 6.12), measured grid points on top; optional targets ((M, 2) zeta, fn [Hz]),
    numbered 1..M in order (to match a table's rows) when ``numbered``, and a highlighted
    point ``marker`` (zeta, fn)."""
    ax = axes(ax)
    a = gm.achievable()
    arts = [ax.scatter(a.zeta, a.fn, s=2, c="0.75", label="achievable (interpolated between identified points)")]
    ok = gm.status == "ok"
    z, f = gm.zeta[ok], gm.fn[ok]
    zi, fi = gm.zeta_interval[ok], gm.fn_interval[ok]
    arts.append(ax.errorbar(z, f, xerr=np.abs(zi.T - z), yerr=np.abs(fi.T - f), fmt="none", ecolor="b", alpha=0.25,
                            lw=0.6))
    hi = float(np.nanmax(a.zeta)) * 1.05 if a.zeta.size else 2.0
    # the frequency axis spans the points, not their intervals: a wide interval (an
    # approximate second-order response) runs off the axes rather than squeezing every point
    top = float(np.nanmax(np.concatenate([f, a.fn, [1.0]]))) * 1.1
    cut = int(np.sum(fi[:, 1] > top)) if len(fi) else 0
    arts.append(ax.scatter(z, f, s=14, c="b", label="measured grid points (identified, 90 % intervals"
                           + (f"; {cut} run past the top)" if cut else ")")))
    if targets is not None and len(targets):
        t = np.atleast_2d(np.asarray(targets, dtype=float))
        arts.append(ax.scatter(t[:, 0], t[:, 1], s=60, marker="x", c="r", label="targets"))
        if numbered:
            for k, (z, f) in enumerate(t, start=1):
                ax.annotate(str(k), (z, f), textcoords="offset points", xytext=(5, 4), fontsize=8, color="r")
        hi = max(hi, float(np.max(t[:, 0])) * 1.05)
        top = max(top, float(np.max(t[:, 1])) * 1.1)
    if marker is not None:
        arts.append(ax.scatter([marker[0]], [marker[1]], s=120, marker="*", c="orange", label="this step"))
        hi = max(hi, float(marker[0]) * 1.05)
        top = max(top, float(marker[1]) * 1.1)
    ax.set_xlabel("damping ratio zeta [-]")
    ax.set_ylabel("natural frequency fn [Hz]")
    ax.set_title("Achievable (zeta, fn) of the foot's step")
    ax.set_xlim(0, min(hi, 3.0))
    ax.set_ylim(0, top)
    region_legend(ax)
    return arts


def region_legend(ax):
    """The legend of a region plot, beside the axes: inside it sat on the targets' numbers."""
    return ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)


#: how a map slice draws a grid point without a value, and what the legend calls it
EMPTY_CELLS = {"unstable": ({"facecolor": "0.35", "hatch": None}, "unstable (the step aborted)"),
               "failed": ({"facecolor": "#f6d2d2", "hatch": "xx", "edgecolor": "#b00"},
                          "failed (not a second-order step)"),
               "missing": ({"facecolor": "white", "hatch": "..", "edgecolor": "0.6"}, "not measured")}


def _edges(values) -> np.ndarray:
    """Cell edges around grid values (midpoints; the ends half a step out), so each cell is
    centred on its value."""
    v = np.asarray(values, float)
    if v.size == 1:
        return np.array([v[0] * 0.9, v[0] * 1.1]) if v[0] else np.array([-0.5, 0.5])
    mid = (v[1:] + v[:-1]) / 2
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])


def plot_map_slices(gm, field: str = "zeta", axes=None):
    """One panel per pos_gain: ``field`` ("zeta" or "fn" [Hz]) over vel_gain x
    vel_integrator_gain, each cell centred on its grid point. Cells without a value are drawn
    by why (:data:`EMPTY_CELLS`: unstable, failed, not measured) and named in the legend with
    their counts; the colour scale spans the 2nd to 98th percentile, an arrow on the colour
    bar marking values beyond it. The panels share their vertical axis (tick labels only on
    the first)."""
    import matplotlib.pyplot as plt  # load time: matplotlib (about 0.5 s), only when drawing
    from matplotlib.patches import Patch  # load time: matplotlib, only when drawing

    data = gm.zeta if field == "zeta" else gm.fn
    n = len(gm.axes[0])
    if axes is None:
        fig, axes = plt.subplots(1, n, figsize=(3.6 * n + 1.2, 3.6), squeeze=False, sharey=True,
                                 layout="constrained")
        axes = axes[0]
    fig = axes[0].figure
    vmin, vmax = np.nanpercentile(data, [2, 98]) if np.isfinite(data).any() else (0.0, 1.0)
    xe, ye = _edges(gm.axes[1]), _edges(gm.axes[2])
    status = np.asarray(gm.status).astype(str)
    images, counts = [], {k: 0 for k in EMPTY_CELLS}
    for k, ax in enumerate(axes):
        images.append(ax.pcolormesh(xe, ye, data[k].T, vmin=vmin, vmax=vmax, cmap="viridis"))
        for kind, (style, _) in EMPTY_CELLS.items():
            for i, j in zip(*np.nonzero(status[k] == kind)):
                counts[kind] += 1
                ax.add_patch(plt.Rectangle((xe[i], ye[j]), xe[i + 1] - xe[i], ye[j + 1] - ye[j], lw=0.0,
                                           **style))
        ax.set_title(f"pos_gain = {gm.axes[0][k]:g} (turn/s)/turn", fontsize=9)
        ax.set_xlabel("vel_gain [N m/(turn/s)]")
        ax.tick_params(axis="x", labelsize=8)
        if k == 0:  # shared by the row; repeated labels would overlap the neighbour
            ax.set_ylabel("vel_integrator_gain [N m/turn]")
    extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[
        (bool(np.nanmin(data) < vmin), bool(np.nanmax(data) > vmax))] if np.isfinite(data).any() else "neither"
    fig.colorbar(images[-1], ax=list(axes), extend=extend,
                 label=("zeta [-]" if field == "zeta" else "fn [Hz]") + (" (arrows: beyond the scale)"
                                                                          if extend != "neither" else ""))
    handles = [Patch(label=f"{label} ({counts[kind]})", **{k: v for k, v in style.items() if v is not None})
               for kind, (style, label) in EMPTY_CELLS.items() if counts[kind]]
    if handles:   # above the panels: every empty cell is said
        from matplotlib.layout_engine import ConstrainedLayoutEngine  # load time: matplotlib, only when drawing
        outside = isinstance(fig.get_layout_engine(), ConstrainedLayoutEngine)
        fig.legend(handles=handles, ncol=len(handles), fontsize=8, frameon=False,
                   **({"loc": "outside upper center"} if outside else
                      {"loc": "lower center", "bbox_to_anchor": (0.5, 1.0)}))
    return images


def plot_thesis_peaks(t, reading, ax=None):
    """Listing 7.7's view of a step (the thesis's Fig. 6.10): smooth(-y) [m] with the peaks
    ``findpeaks`` found as red circles and the reading (thesis measure) in the legend.

    ``reading`` is a :class:`leglib.identify.listing77.ThesisReading` of ``t``.
    """
    ax = axes(ax)
    if reading.flagged:
        label = f"Listing 7.7: {reading.n_peaks} peak(s), zeta set to {reading.zeta:g}"
    elif getattr(reading, "intervals", None) is not None:
        label = (f"Listing 7.7: zeta = {interval_text(reading.zeta, reading.zeta_interval)}, 1/(t2 - t1) = "
                 f"{interval_text(reading.fd, reading.fd_interval)} Hz (90 % intervals)")
    else:   # a failure: the numbers it would give, no interval
        label = f"Listing 7.7: zeta = {reading.zeta:.3g}, 1/(t2 - t1) = {reading.fd:.3g} Hz (no reading)"
    arts = ax.plot(t, reading.smoothed, "b-", lw=1.5, label="smooth(-y)")
    arts += ax.plot(reading.peak_times, reading.peak_values, "ro", mfc="none", ms=8, mew=1.5,
                    label=f"findpeaks: {reading.n_peaks} peaks")
    if reading.n_peaks >= 2:
        arts += ax.plot(reading.peak_times[:2], reading.peak_values[:2], "r*", ms=12, label=label)
    problem = reading.problem
    if problem:
        # the failure is part of the legend (its own line, in red): a reading it marks is
        # not the listing's measurement of the oscillation
        arts += ax.plot([], [], " ", label="\n".join(_wrap("Listing 7.7 FAILS here: " + problem, 60)))
    ax.set_xlabel("t [s]")
    ax.set_ylabel("-y of Listing 7.7 [m]")
    legend = ax.legend(fontsize=8)
    if problem:
        legend.get_texts()[-1].set_color("#b00")
    return arts


def _wrap(text: str, width: int) -> list[str]:
    return textwrap.wrap(text, width)


#: the fixed axes of the true-measure panel (zeta, fn [Hz]): the region a cascade on this leg
#: reaches (the twin's thesis-grid map: zeta 0.2-1.3, fn 3-10 Hz) with room; points beyond are
#: counted on the figure rather than stretching it
TRUE_AXES = ((0.0, 2.0), (0.0, 15.0))


def plot_readings_map(rows, measure: str = "thesis", ax=None, targets=None):
    """Measured grid points of a sweep in one measure (rows of
    :func:`leglib.thesis.compare_readings`), on fixed axes; points beyond them are counted
    in the legend.

    ``measure="thesis"``: Listing 7.7's zeta against its 1/(t2 - t1) [Hz] with their 90 %
    intervals, on the thesis's
    Fig. 6.12 axes (0-1, 0-10 Hz), for the "ok" points whose reading is usable (the first two
    peaks are the oscillation's); a usable reading on which the listing still fails (more
    peaks than cycles) is drawn hollow, and the points it fails on outright (fewer than two
    peaks, a second peak of tail ripple) are counted. ``"true"``: the least-squares zeta
    against fn [Hz] of the "ok" points with their 90 % intervals, on :data:`TRUE_AXES`.
    ``targets``: dict label -> (zeta, f) drawn as crosses, in the same measure.
    """
    ax = axes(ax)
    okr = [r for r in rows if r["status"] == "ok"]
    arts = []
    if measure == "thesis":
        (x0, x1), (y0, y1) = (0.0, 1.0), (0.0, 10.0)
        use = [r for r in okr if r.get("thesis_usable", not r["thesis_flagged"])]
        clean = [r for r in use if not r.get("thesis_problem")]
        many = [r for r in use if r.get("thesis_problem")]
        for group, style in ((clean, {"c": "b"}), (many, {"facecolors": "none", "edgecolors": "tab:orange"})):
            if not group:
                continue
            x = np.array([r["thesis_zeta"] for r in group])
            y = np.array([r["thesis_f_hz"] for r in group])
            zi = np.array([r.get("thesis_zeta_interval", (np.nan, np.nan)) for r in group], float)
            fi = np.array([r.get("thesis_f_interval", (np.nan, np.nan)) for r in group], float)
            inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1) & np.all(np.isfinite(zi), axis=1) \
                & np.all(np.isfinite(fi), axis=1)
            if inside.any():   # each reading's 90 % intervals (listing77.ReadingIntervals)
                arts.append(ax.errorbar(x[inside], y[inside], xerr=np.abs(zi[inside].T - x[inside]),
                                        yerr=np.abs(fi[inside].T - y[inside]), fmt="none",
                                        ecolor=style.get("c", style.get("edgecolors")), alpha=0.35, lw=0.6))
            label = (f"Listing 7.7 readings ({len(group)}, 90 % intervals)" if group is clean else
                     f"Listing 7.7 fails: more peaks than cycles ({len(group)}; first two peaks the oscillation's, "
                     f"90 % intervals)")
            arts.append(ax.scatter(np.clip(x, x0, x1), np.clip(y, y0, y1), s=12, label=label, **style))
        failed = len(okr) - len(use)
        if failed:
            arts += ax.plot([], [], " ", label=f"{failed} points where Listing 7.7 fails outright (not drawn)")
        shown = use
        xs = np.array([r["thesis_zeta"] for r in shown])
        ys = np.array([r["thesis_f_hz"] for r in shown])
        ax.set_xlabel("zeta by Listing 7.7 [-]")
        ax.set_ylabel("1/(t2 - t1) by Listing 7.7 [Hz]")
    elif measure == "true":
        (x0, x1), (y0, y1) = TRUE_AXES
        shown = okr
        xs = np.array([r["zeta"] for r in shown])
        ys = np.array([r["fn"] for r in shown])
        inside = (xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)
        if inside.any():
            zi = np.array([r["zeta_interval"] for r in shown], float)[inside]
            fi = np.array([r["fn_interval"] for r in shown], float)[inside]
            arts.append(ax.errorbar(xs[inside], ys[inside], xerr=np.abs(zi.T - xs[inside]),
                                    yerr=np.abs(fi.T - ys[inside]), fmt="none", ecolor="b", alpha=0.25, lw=0.6))
        arts.append(ax.scatter(xs[inside], ys[inside], s=12, c="b",
                               label=f"measured grid points ({int(inside.sum())}, 90 % intervals)"))
        ax.set_xlabel("zeta, least squares [-]")
        ax.set_ylabel("fn, least squares [Hz]")
    else:
        raise ValueError(f"measure must be 'thesis' or 'true', got {measure!r}")
    beyond = int(np.sum((xs < x0) | (xs > x1) | (ys < y0) | (ys > y1))) if len(shown) else 0
    if beyond:
        where = "drawn at the edge" if measure == "thesis" else "not drawn"
        arts += ax.plot([], [], " ", label=f"{beyond} beyond the axes (zeta > {x1:g} or f > {y1:g} Hz; {where})")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    for (label, (z, f)), style in zip((targets or {}).items(), ["rx", "m+", "g^", "kd"]):
        arts += ax.plot([z], [f], style, ms=10, mew=2, label=label)
    ax.legend(fontsize=7)
    return arts


# ---------------------------------------------------------------------------------------
# the leg animated


# ---------------------------------------------------------------------------------------

def leg_points(leg, q1, q2) -> np.ndarray:
    """Joint positions of the exact five-bar, (..., 5, 2) [m]: upper joint 1, hip (origin),
    upper joint 2, foot, upper joint 1 again (the closed outline :func:`draw_leg` draws).

    ``q1``, ``q2`` [rad], scalars or arrays of one shape. The foot is the end of link 4
    hung from link 1, i.e. :func:`leglib.model.kinematics.foot_position`.
    """
    q1 = np.asarray(q1, dtype=float)
    q2 = np.asarray(q2, dtype=float)
    _, phi4 = M.lower_link_angles(leg, q1, q2)
    p1 = np.stack([leg.l1 * np.cos(q1), leg.l1 * np.sin(q1)], axis=-1)
    p2 = np.stack([leg.l2 * np.cos(q2), leg.l2 * np.sin(q2)], axis=-1)
    foot = p1 + np.stack([leg.l4 * np.cos(phi4), leg.l4 * np.sin(phi4)], axis=-1)
    return np.stack([p1, np.zeros_like(p1), p2, foot, p1], axis=-2)


def animate_leg(leg, q1, q2, t, ax=None, max_frames: int = 60, speed: float = 1.0, trace: bool = True,
                title: str | None = None, setpoint=None):
    """A matplotlib animation of the five-bar: links, joints and the foot's trace.

    Parameters
    ----------
    leg : :class:`leglib.params.LegParams` (link lengths of the exact five-bar)
    q1, q2 : (N,) joint angles [rad] of any measured or simulated run
    t : (N,) time [s], increasing
    ax : axes to draw in (a new 3.6 x 4.4 in figure at 72 dpi when None)
    max_frames : at most this many frames (evenly spaced samples, the last one included):
        keeps the embedded size of ``to_jshtml()`` small (about 10-20 kB per frame)
    speed : playback speed (1.0: real time)
    trace : draw the foot's path up to the current frame
    title : axes title
    setpoint : optional (q1, q2) [rad] drawn as a grey leg (the target pose)

    Returns
    -------
    matplotlib.animation.FuncAnimation
        with ``frame_index`` (F,) the sample index shown in each frame, ``links`` the
        Line2D of the leg, ``foot_trace`` the Line2D of the trace (or None), ``show_frame(k)``
        drawing frame k (what the animation calls). Show it with ``anim.to_jshtml()``
        (needs nothing) or ``to_html5_video()`` (needs ffmpeg); save a GIF with
        :func:`save_animation`.
    """
    from matplotlib import animation  # load time: matplotlib, only when drawing

    q1 = np.asarray(q1, dtype=float).ravel()
    q2 = np.asarray(q2, dtype=float).ravel()
    t = np.asarray(t, dtype=float).ravel()
    if not (q1.shape == q2.shape == t.shape) or t.size < 2:
        raise ValueError(f"q1, q2 and t must be 1-D of one length >= 2, got {q1.shape}, {q2.shape}, {t.shape}")
    if not (np.all(np.isfinite(q1)) and np.all(np.isfinite(q2)) and np.all(np.isfinite(t))):
        raise ValueError("q1, q2 and t must be finite")
    if np.any(np.diff(t) <= 0):
        raise ValueError("t must be strictly increasing")
    if max_frames < 2 or speed <= 0:
        raise ValueError(f"max_frames must be >= 2 and speed > 0, got {max_frames}, {speed}")
    if ax is None:
        import matplotlib.pyplot as plt  # load time: matplotlib (about 0.5 s), only when drawing
        _, ax = plt.subplots(figsize=(3.6, 4.4), dpi=72)
    fig = ax.figure
    idx = np.unique(np.round(np.linspace(0, t.size - 1, min(max_frames, t.size))).astype(int))
    pts = leg_points(leg, q1, q2)                         # (N, 5, 2)
    bad = ~np.all(np.isfinite(pts), axis=(1, 2))
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"the five-bar does not close at sample {i} (q1 = {q1[i]:.4f}, q2 = {q2[i]:.4f} rad)")
    foot = pts[:, 3, :]
    allp = pts.reshape(-1, 2)
    if setpoint is not None:
        sp = leg_points(leg, *setpoint)
        ax.plot(sp[:, 0], sp[:, 1], "o-", color="0.75", lw=1.5, label="setpoint")
        allp = np.vstack([allp, sp])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    pad = 0.08 * float(np.max(hi - lo)) + 0.005
    # at least 0.6 as wide as tall: a leg swinging little in x made an axes too narrow for
    # its own tick labels
    cx, half = (lo[0] + hi[0]) / 2, max((hi[0] - lo[0]) / 2, 0.3 * (hi[1] - lo[1]))
    ax.set_xlim(cx - half - pad, cx + half + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    from matplotlib.ticker import MaxNLocator  # load time: matplotlib, only when drawing
    ax.xaxis.set_major_locator(MaxNLocator(4))   # a narrow figure: more tick labels would touch
    if title:
        fit_title(ax, title)   # the figure is small: a long title wraps rather than being cut
    (links,) = ax.plot([], [], "o-", color="k", lw=2.5, ms=5)
    trace_line = ax.plot([], [], "-", color="tab:red", lw=1, label="foot")[0] if trace else None
    label = ax.text(0.02, 0.97, "", transform=ax.transAxes, va="top", fontsize=9)

    def show_frame(k):
        i = idx[k]
        links.set_data(pts[i, :, 0], pts[i, :, 1])
        label.set_text(f"t = {t[i] - t[0]:.3f} s")
        arts = [links, label]
        if trace_line is not None:
            trace_line.set_data(foot[: i + 1, 0], foot[: i + 1, 1])
            arts.append(trace_line)
        return arts

    interval = 1000.0 * float(np.median(np.diff(t[idx]))) / speed
    anim = animation.FuncAnimation(fig, show_frame, frames=len(idx), interval=max(interval, 1.0), blit=False)
    anim.frame_index = idx
    anim.figure = fig
    anim.links = links
    anim.foot_trace = trace_line
    anim.show_frame = show_frame
    return anim


def save_animation(anim, path, fps: float | None = None) -> "Path":
    """Write an animation as a GIF (matplotlib's PillowWriter: no ffmpeg needed).

    ``fps`` defaults to the animation's own rate (1000 / interval). Returns the path.
    """

    from matplotlib.animation import PillowWriter  # load time: matplotlib, only when drawing
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fps = fps if fps is not None else 1000.0 / anim._interval
    anim.save(str(path), writer=PillowWriter(fps=max(1, round(fps))))
    return path


# matplotlib's animation player (matplotlib/_animation_data.py): its Font Awesome 4 icons as
# characters of Basic Latin and Geometric Shapes (U+25A0-25FF), which common fonts cover (DejaVu
# Sans, matplotlib's own, included); the media-control symbols (U+23E9-23EF) often are not
PLAYER_ICONS = {"fa-minus": "\u2212", "fa-fast-backward": "\u25ae\u25c0\u25c0", "fa-step-backward": "\u25c0\u25ae",
                "fa-play fa-flip-horizontal": "\u25c0", "fa-pause": "\u25ae\u25ae", "fa-play": "\u25b6",
                "fa-step-forward": "\u25ae\u25b6", "fa-fast-forward": "\u25b6\u25b6\u25ae", "fa-plus": "+"}
_ICON = re.compile(r'<i class="fa (' + "|".join(sorted(map(re.escape, PLAYER_ICONS), key=len, reverse=True))
                   + r')"></i>')
_FONT_AWESOME = re.compile(r'<link rel="stylesheet"\s+href="https://[^"]*font-awesome[^"]*">\s*')


def player_html(html: str) -> str:
    """matplotlib's animation player without Font Awesome (loaded from a CDN, so blank buttons
    offline): its icons as Unicode characters."""
    html = _FONT_AWESOME.sub("", html)
    return _ICON.sub(lambda m: f'<span class="leglib-icon">{PLAYER_ICONS[m.group(1)]}</span>', html)


def show_animation(anim, figures_dir=None, name: str | None = None):
    """The animation as a self-contained HTML player (as ``anim.to_jshtml()``: PNG frames
    embedded, no ffmpeg needed) for a notebook's output; its figure is closed so the
    notebook does not show a still copy too. With ``figures_dir`` and ``name`` a GIF
    (``<figures_dir>/<name>.gif``) is written as well, from the same frames (each frame is
    drawn once).

    Returns
    -------
    IPython.display.HTML
    """

    import matplotlib.pyplot as plt  # load time: matplotlib (about 0.5 s), only when drawing
    from IPython.display import HTML  # load time: IPython, only inside a notebook
    from matplotlib.animation import HTMLWriter  # load time: matplotlib, only when drawing

    frames = []

    class Writer(HTMLWriter):
        def grab_frame(self, **savefig_kwargs):
            super().grab_frame(**savefig_kwargs)
            saved = getattr(self, "_saved_frames", None)   # the base64 PNGs it embeds
            if saved is not None and len(saved) > len(frames):
                frames.append(Image.open(io.BytesIO(base64.b64decode(saved[-1]))))

    fps = 1000.0 / anim._interval
    with tempfile.TemporaryDirectory() as tmp:
        page = Path(tmp) / "animation.html"
        anim.save(str(page), writer=Writer(fps=fps, embed_frames=True,
                                           default_mode="loop" if getattr(anim, "_repeat", False) else "once"))
        html = HTML(player_html(page.read_text()))  # buttons that need no CDN
    if figures_dir is not None and name:
        gif = Path(figures_dir) / f"{name}.gif"
        if frames:
            gif.parent.mkdir(parents=True, exist_ok=True)
            frames[0].save(gif, save_all=True, append_images=frames[1:], duration=int(1000 / max(1, round(fps))),
                           loop=0)
        else:   # a matplotlib whose HTML writer keeps its frames elsewhere: draw them again
            save_animation(anim, gif)
    plt.close(anim._fig)  # matplotlib's own reference: any Animation, not only animate_leg's
    return html


def plot_design_path(design, ax=None):
    """The experiments of one :func:`leglib.design.tuning.tune` in the (zeta, fn) plane: each
    experiment's measured point, numbered, the model's prediction for it, and the target
    with its tolerance box."""
    ax = axes(ax)
    zt, ft = design.target
    tol = design.tolerance
    from matplotlib.patches import Rectangle  # load time: matplotlib, only when drawing
    ax.add_patch(Rectangle((zt * (1 - tol), ft * (1 - tol)), 2 * tol * zt, 2 * tol * ft, color="tab:green",
                               alpha=0.25, label=f"target ± {tol:.0%}"))
    ax.plot([zt], [ft], "g+", ms=12)
    pts = np.array([e.measured for e in design.experiments], float)
    pred = np.array([e.predicted for e in design.experiments], float)
    iv = np.array([e.intervals for e in design.experiments], float)   # (K, 2 quantities, 2 ends)
    ax.errorbar(pts[:, 0], pts[:, 1], xerr=np.abs(iv[:, 0, :].T - pts[:, 0]), yerr=np.abs(iv[:, 1, :].T - pts[:, 1]),
                fmt="none", ecolor="tab:blue", alpha=0.5, lw=0.8)
    ax.plot(pts[:, 0], pts[:, 1], "o-", color="tab:blue", label="measured (90 % intervals)")
    ax.plot(pred[:, 0], pred[:, 1], "x", color="tab:orange", label="model's prediction")
    for i, (z, f) in enumerate(pts, 1):
        if np.isfinite(z):
            ax.annotate(str(i), (z, f), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("zeta [-]")
    ax.set_ylabel("fn [Hz]")
    ax.legend(fontsize=8)
    return ax


def plot_design_study(rows, ax=None, limits=(0.05, 0.10)):
    """|relative error| of zeta and fn of every design of
    :func:`leglib.evaluation.robustness.design_study`, grouped by plant and payload, with their
    90 % intervals as bars and the median and worst limits as lines."""
    ax = axes(ax)
    groups = list(dict.fromkeys(f"{r.plant}\n{r.payload:g} kg" for r in rows))
    failed_label = True
    for i, g in enumerate(groups):
        rs = [r for r in rows if f"{r.plant}\n{r.payload:g} kg" == g and r.design is not None]
        if not rs:   # the leg could not be prepared (its reason is in the table)
            ax.plot(i, 0.0, "x", color="tab:red", ms=9, label="not prepared (see table)" if failed_label else None)
            failed_label = False
            continue
        for k, dx, style, color, name in ((0, -0.12, "o", "tab:blue", "zeta"), (1, 0.12, "s", "tab:orange", "fn")):
            e = np.array([100 * abs(r.error[k]) for r in rs])
            # the 90 % interval of |measured / target - 1|
            iv = np.array([[100 * (b / r.target[k] - 1) for b in r.design.intervals[k]] for r in rs])
            lo = np.where((iv[:, 0] < 0) & (iv[:, 1] > 0), 0.0, np.min(np.abs(iv), axis=1))
            hi = np.max(np.abs(iv), axis=1)
            ax.errorbar(np.full(len(e), i + dx), e, yerr=[np.maximum(e - lo, 0), np.maximum(hi - e, 0)], fmt=style,
                        color=color, ms=5, capsize=2, label=f"{name} (90 % interval)" if i == 0 else None)
    for lim, style, name in zip(limits, ("--", ":"), ("median limit", "worst limit")):
        ax.axhline(100 * lim, color="k", ls=style, lw=1, label=f"{name} {lim:.0%}")
    ax.set_xticks(range(len(groups)), groups, fontsize=8)
    ax.set_ylabel("|measured / target - 1| [%]")
    ax.legend(fontsize=8)
    return ax


def plot_validation(validation, ax=None):
    """Relative errors of zeta and fn per target of a :class:`leglib.design.validation.Validation`
    (targets numbered as its table's rows), with their 90 % intervals as bars; a check that
    is no second-order step is marked at the top with a cross, a target outside the
    method's answers at the bottom."""
    ax = axes(ax)
    bounds = [abs(b) for r in validation.rows if not r.outside and r.identified for iv in r.error_interval
              for b in iv if np.isfinite(b)]
    top = 100 * max(bounds + [0.01]) * 1.3
    marked = {"failed": False, "outside": False, "ok": False}
    for k, r in enumerate(validation.rows, 1):
        if r.outside:
            ax.plot(k, -top, "v", color="gray", label=None if marked["outside"] else "outside the region")
            marked["outside"] = True
        elif not r.identified:
            ax.plot(k, top, "x", color="tab:red", ms=9, label=None if marked["failed"] else "not identifiable")
            marked["failed"] = True
        else:
            for dx, e, (lo, hi), style, name in ((-0.1, r.error[0], r.error_interval[0], "o", "zeta"),
                                                 (0.1, r.error[1], r.error_interval[1], "s", "fn")):
                color = "tab:blue" if name == "zeta" else "tab:orange"
                ax.errorbar(k + dx, 100 * e, yerr=[[100 * (e - lo)], [100 * (hi - e)]], fmt=style, color=color,
                            ms=5, capsize=2, label=None if marked["ok"] else f"{name} (90 % interval)")
            marked["ok"] = True
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_xticks(range(1, len(validation.rows) + 1))
    ax.set_xlabel("target")
    ax.set_ylabel("measured / target - 1 [%]")
    ax.set_title(f"{validation.method}: error per target")
    ax.legend(fontsize=8)
    return ax
