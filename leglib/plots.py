"""Plot helpers: each takes ``ax=None`` (or axes) and returns what it drew."""

from __future__ import annotations

import numpy as np

from . import model as M


def _ax(ax):
    if ax is None:
        import matplotlib.pyplot as plt
        _, ax = plt.subplots()
    return ax


def draw_leg(leg, q1, q2, ax=None, **style):
    """Draw the four links of the exact five-bar at (q1, q2) [rad]; returns the Line2D."""
    ax = _ax(ax)
    phi3, phi4 = M.lower_link_angles(leg, q1, q2)
    p1 = leg.l1 * np.array([np.cos(q1), np.sin(q1)])
    p2 = leg.l2 * np.array([np.cos(q2), np.sin(q2)])
    foot = p1 + leg.l4 * np.array([np.cos(phi4), np.sin(phi4)])
    pts = np.array([p1, [0, 0], p2, foot, p1])
    (line,) = ax.plot(pts[:, 0], pts[:, 1], "o-", **{"color": "k", "lw": 2, **style})
    return line


def plot_workspace(leg, ax=None, n: int = 45):
    """Foot positions over the working range, coloured by q2 - q1, with the leg at q0."""
    ax = _ax(ax)
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
    """Three maps from :func:`leglib.model.compare_models`: inertia, gravity, foot height."""
    if axes is None:
        import matplotlib.pyplot as plt
        _, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    ext = np.degrees([cmp["theta"].min(), cmp["theta"].max(), cmp["gap"].min(), cmp["gap"].max()])
    panels = [
        (cmp["D_rel"] * 100, "||D_a - D_b|| / ||D_b|| [%]"),
        (cmp["G_diff"] * 1e3, "||g_a - g_b|| [mN m]"),
        ((cmp["y_eq65"] - cmp["y_exact"]) * 1e3, "eq. 6.5 y minus exact foot y [mm]"),
    ]
    images = []
    for ax, (data, title) in zip(axes, panels):
        im = ax.imshow(data, origin="lower", aspect="auto", extent=ext, cmap="magma")
        ax.figure.colorbar(im, ax=ax)
        ax.set_title(title)
        ax.set_xlabel("theta = (q1 + q2)/2 [deg]")
        ax.set_ylabel("q2 - q1 [deg]")
        images.append(im)
    return images


def plot_states(t, states: dict, ax=None, deg: bool = True, idx=(0, 2), names=("q1", "q2")):
    """Overlay several (N, 4) state trajectories' joint angles; ``states`` maps label->x."""
    ax = _ax(ax)
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
