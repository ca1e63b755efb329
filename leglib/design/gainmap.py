"""The map from ODrive cascade gains to second-order dynamics, and its inverse (thesis 6.4-6.5).

Pipeline (Listings 7.6-7.8, done properly):

1. every step response of a sweep is identified with :func:`leglib.identify.step.second_order`
   on the foot height; aborted (unstable) points, responses that cannot be identified and
   responses the second-order model does not describe (R^2 under :data:`MIN_R2_MAP`, an
   overshoot of 100 % or more, an overdamped fit whose fast pole lies beyond the sampling's
   Nyquist rate, no position control because a gain is near zero) are kept and marked as
   such, never given numbers;
2. the results go on the 3-D grid (pos_gain x vel_gain x vel_integrator_gain);
3. gaps are filled by harmonic in-painting (of log zeta, log wn): missing cells solve the discrete Laplace
   equation with the measured cells fixed (a sparse scipy solve; the thesis used inpaintn,
   whose smoothing prior is the same Laplacian);
4. the filled fields are interpolated cubically on a finer grid (as interp3, but in log
   gains and of log zeta, log wn: a cascade's zeta and wn scale like powers of its gains,
   which linear coordinates follow badly near small vel_gain); points that
   lie in a grid cell whose corners are not all measured and identified (interpolation there
   would rest on filled-in values: not supported by a measurement), where cubic and linear
   interpolation disagree (the grid cannot resolve the map there), or that come out
   non-physical (zeta <= 0, fn <= 0) are dropped: what is left is the achievable region;
5. :meth:`GainMap.gains_for` answers a desired (zeta, fn) with the nearest achievable point
   in (log zeta, log fn) (a KD-tree; the thesis's dsearchn), and raises
   :class:`OutsideRegionError`, naming the nearest achievable point and its gains, when
   that point is further than a relative tolerance from the request.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.interpolate import make_interp_spline
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from .. import plots
from ..errors import MeasurementError, OutsideRegionError
from ..experiments.step import StepResponse
from ..files.sweepdir import read_measurements
from ..params import load_leg
from ..units import dynamics_text
from .points import (
    STATUS_MISSING,
    STATUS_OK,
    STATUS_UNSTABLE,
    PointResult,
    identify_many,
)

AGREEMENT = 0.10  # relative cubic-vs-linear disagreement beyond which a fine point is not trusted
TOLERANCE = 0.05  # relative distance in zeta and fn within which a target counts as achievable


def harmonic_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Fill the cells of ``values`` where ``known`` is False by solving the discrete Laplace
    equation (index space, Neumann edges) with the known cells fixed."""
    values = np.asarray(values, dtype=float)
    known = np.asarray(known, dtype=bool)
    if known.all():
        return values.copy()
    if not known.any():
        raise ValueError("harmonic_fill: no known cell to fill from")
    shape = values.shape
    n = values.size
    idx = np.arange(n).reshape(shape)
    rows, cols, data = [], [], []
    for axis in range(values.ndim):
        if shape[axis] < 2:
            continue
        a = np.moveaxis(idx, axis, 0)
        lo, hi = a[:-1].ravel(), a[1:].ravel()
        # graph Laplacian: each neighbour pair contributes to both cells
        rows += [lo, hi, lo, hi]
        cols += [lo, hi, hi, lo]
        data += [np.ones(lo.size), np.ones(lo.size), -np.ones(lo.size), -np.ones(lo.size)]
    Lap = sparse.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    k = known.ravel()
    u = ~k
    rhs = -Lap[u][:, k] @ values.ravel()[k]
    filled = values.ravel().copy()
    filled[u] = spsolve(Lap[u][:, u].tocsc(), rhs)
    return filled.reshape(shape)


@dataclass
class Achievable:
    """Fine-grid points the map can deliver: gains (M, 3), zeta (M,), fn (M,) [Hz], and
    their 90 % intervals ``zeta_interval``, ``fn_interval`` (M, 2) (:meth:`GainMap.fine`)."""

    gains: np.ndarray
    zeta: np.ndarray
    fn: np.ndarray
    zeta_interval: np.ndarray = None
    fn_interval: np.ndarray = None


@dataclass
class Choice:
    """Answer of :meth:`GainMap.nearest`: gains (pos_gain, vel_gain, vel_integrator_gain),
    the map's zeta and fn [Hz] there with their 90 % intervals (``zeta_interval``,
    ``fn_interval``: the measured neighbours' intervals interpolated, widened by the
    interpolation's own doubt), and ``distance``, the larger of the relative distances in
    zeta and in fn to the request (max(|log(zeta/zeta_req)|, |log(fn/fn_req)|))."""

    gains: tuple
    zeta: float
    fn: float
    distance: float
    zeta_interval: tuple = (math.nan, math.nan)
    fn_interval: tuple = (math.nan, math.nan)

    def text(self) -> str:
        """"zeta 0.24 [0.17, 0.31], fn 5.0 [4.5, 5.6] Hz" (the map's prediction, to the digits
        its intervals support)."""
        return dynamics_text(self.zeta, self.fn, self.zeta_interval, self.fn_interval)

    def within(self, tolerance: float = TOLERANCE) -> bool:
        """True when the point is within ``tolerance`` (relative) of the request."""
        return self.distance <= math.log1p(tolerance) + 1e-12


class GainMap:
    """Gains -> (zeta, wn, fn) on a 3-D grid, with gap filling, interpolation and inverse.

    Attributes
    ----------
    axes : (pos_gain values, vel_gain values, vel_integrator_gain values), sorted
    zeta, wn : arrays of shape (len(pos), len(vel), len(vint)); NaN where not identified
    zeta_interval, fn_interval : same shape + (2,): each identified point's 90 % interval
        (low, high) of zeta and of fn [Hz]; NaN where not identified
    status : same shape, one of "ok", "unstable", "failed", "missing"
    """

    def __init__(self, points: list[PointResult], decimals: int = 6):
        if not points:
            raise ValueError("GainMap needs at least one identified point")
        G = np.round(np.array([p.gains for p in points], dtype=float), decimals)
        self.axes = tuple(np.unique(G[:, i]) for i in range(3))
        shape = tuple(len(a) for a in self.axes)
        self.zeta = np.full(shape, np.nan)
        self.wn = np.full(shape, np.nan)
        self.status = np.full(shape, STATUS_MISSING, dtype=object)
        self.zeta_interval = np.full(shape + (2,), np.nan)
        self.fn_interval = np.full(shape + (2,), np.nan)
        self.points = points
        cells = zip(*(np.searchsorted(ax, G[:, k]).tolist() for k, ax in enumerate(self.axes)))
        for i, p in zip(cells, points):
            self.status[i] = p.status
            if p.status == STATUS_OK:
                self.zeta[i], self.wn[i] = p.zeta, p.wn
                self.zeta_interval[i], self.fn_interval[i] = p.zeta_interval, p.fn_interval
        self._fine = None

    # -- construction --------------------------------------------------------------------
    @classmethod
    def from_responses(cls, responses, leg, method: str = "fit", workers: int | None = None) -> "GainMap":
        """From :class:`leglib.experiments.step.StepResponse` objects of the leg ``leg``
        (LegParams or a parameter-set name: the commanded foot heights), identified in one
        compiled batch (:func:`leglib.design.points.identify_many`)."""
        leg = load_leg(leg) if isinstance(leg, (str, Path)) else leg
        return cls(identify_many(responses, leg, method, workers))

    @classmethod
    def from_measurements(cls, paths_or_dir, leg="thesis", method: str = "fit", progress: bool = False,
                          strict: bool = True) -> "GainMap":
        """From measurement files (a directory, or a list of ``*_positions.csv`` and batch
        ``*_batch.csv`` files).

        ``leg`` (name or LegParams) gives the kinematics for the foot height. ``strict=False``
        skips unreadable files and warns naming them (:func:`leglib.files.sweepdir.read_measurements`).
        Two files with the same gains are an error naming both: a map cell holds one
        measurement.
        """
        leg = load_leg(leg) if isinstance(leg, (str, Path)) else leg
        measurements = read_measurements(paths_or_dir, strict=strict).measurements
        if not measurements:
            raise ValueError(f"no readable measurement files in {paths_or_dir}")
        seen = {}
        for m in measurements:
            if m.gains is None:
                raise MeasurementError(f"{m.where}: no gains in the file name or sidecar")
            key = tuple(np.round(np.asarray(m.gains, dtype=float), 6))
            if key in seen:
                raise MeasurementError(f"{seen[key]} and {m.where} both hold gains {m.gains}: "
                                              f"a map cell holds one measurement; move one away")
            seen[key] = m.where
        with tqdm(total=len(measurements), desc="identify", unit="file", disable=not progress) as bar:
            points = identify_many(StepResponse.from_measurements(measurements, leg), leg, method)
            bar.update(len(points))
        return cls(points)

    # -- summary -------------------------------------------------------------------------
    @property
    def fn(self) -> np.ndarray:
        return self.wn / (2 * math.pi)

    def _repr_markdown_(self) -> str:
        c = self.counts()
        lines = [f"**Gain map** over {' x '.join(str(len(a)) for a in self.axes)} gains "
                 f"({', '.join(f'{k} {v}' for k, v in sorted(c.items()))})", "",
                 "| gain | from | to | values |", "|---|---|---|---|"]
        for name, a in zip(GAIN_NAMES, self.axes):
            lines.append(f"| {name} | {a[0]:.4g} | {a[-1]:.4g} | {len(a)} |")
        try:
            ach = self.achievable()
            if ach.zeta.size:
                lines += ["", f"Achievable: ζ {ach.zeta.min():.3f} to {ach.zeta.max():.3f}, fn {ach.fn.min():.2f} "
                              f"to {ach.fn.max():.2f} Hz ({ach.zeta.size} fine-grid points)."]
        except ValueError as exc:   # too few identified points for a region
            lines += ["", f"No achievable region: {exc}"]
        return "\n".join(lines)

    def plot(self, ax=None, targets=None):
        """The achievable (zeta, fn) region, the measured points and ``targets``
        (:func:`leglib.plots.plot_gain_region`)."""
        return plots.plot_gain_region(self, ax=ax, targets=targets)

    def counts(self) -> dict:
        """{status: number of grid points} (plain ``str`` and ``int``)."""
        vals, n = np.unique(self.status.astype(str), return_counts=True)
        return {str(v): int(k) for v, k in zip(vals, n)}

    # -- filling and interpolation ------------------------------------------------------------
    def filled(self) -> tuple[np.ndarray, np.ndarray]:
        """(zeta, wn) with every non-"ok" cell filled harmonically (in log) from the "ok" ones."""
        known = self.status == STATUS_OK
        return (np.exp(harmonic_fill(np.log(self.zeta), known)),
                np.exp(harmonic_fill(np.log(self.wn), known)))

    def fine(self, points_per_axis=(31, 46, 40)) -> dict:
        """Cubic interpolation of the filled map on a finer regular grid (as interp3).

        Returns dict with the fine axes, ``zeta``, ``fn`` and a ``valid`` mask: False where
        the grid cell holding the point has a corner that is not "ok" (unstable, failed or
        missing: the value there would rest on filled-in numbers, not on measurements),
        where cubic and linear interpolation disagree by more than AGREEMENT (the grid
        cannot resolve the map there), or where the value is non-physical; and
        ``zeta_interval``, ``fn_interval`` (shape + (2,)): 90 % intervals, the identified
        points' relative half-widths below and above (in log) interpolated linearly like the
        values, each widened by the disagreement of cubic and linear interpolation there
        (added in quadrature, in log).
        """
        key = tuple(points_per_axis)
        if self._fine is not None and self._fine["key"] == key:
            return self._fine
        zeta, wn = self.filled()
        stable = (self.status != STATUS_UNSTABLE).astype(float)
        axes = self.axes
        fine_axes = [np.geomspace(a[0], a[-1], n) if len(a) > 1 else a.copy() for a, n in zip(axes, points_per_axis)]
        active = [i for i, a in enumerate(axes) if len(a) > 1]
        # log coordinates: zeta and wn of a cascade scale like powers of the gains
        sub_axes = [np.log(axes[i]) for i in active]

        # the fine grid is a tensor product, and so are scipy's RegularGridInterpolator's
        # cubic (not-a-knot splines per axis) and linear interpolants: one small matrix per
        # axis gives the same values (tests/test_gainmap.py) in a fraction of the time
        cubic_ok = all(len(a) >= 4 for a in sub_axes)
        sub_fine = [np.log(fine_axes[i]) for i in active]
        mats = {m: [_axis_matrix(a, x, m) for a, x in zip(sub_axes, sub_fine)]
                for m in (("cubic", "linear") if cubic_ok else ("linear",))}

        def interp(field, method):
            f = field.reshape([len(a) for a in sub_axes])
            return _tensor_interp(f, mats[method if cubic_ok else "linear"])

        full = tuple(len(a) for a in fine_axes)   # an axis of one gain stays, of length 1
        z = np.exp(interp(np.log(zeta), "cubic")).reshape(full)
        w = np.exp(interp(np.log(wn), "cubic")).reshape(full)
        stab = interp(stable, "linear").reshape(full)
        # supported: every corner of the enclosing grid cell measured and identified
        ok = (self.status == STATUS_OK).reshape([len(a) for a in sub_axes])
        corner_ok = np.ones(full, dtype=bool)
        lower = []   # per active axis the cell below each fine point, along that axis
        for k, (a, x) in enumerate(zip(sub_axes, sub_fine)):
            i = np.clip(np.searchsorted(a, x, side="right") - 1, 0, max(len(a) - 2, 0))
            lower.append(i.reshape([len(x) if j == active[k] else 1 for j in range(len(full))]))
        for corner in np.ndindex(*(2,) * len(sub_axes)):
            idx = tuple(np.minimum(lo + c, len(a) - 1) for lo, c, a in zip(lower, corner, sub_axes))
            corner_ok &= ok[idx]
        # where cubic and linear interpolation disagree, the grid is too coarse to tell
        zl = np.exp(interp(np.log(zeta), "linear")).reshape(full)
        wl = np.exp(interp(np.log(wn), "linear")).reshape(full)
        trusted = (np.abs(z - zl) <= AGREEMENT * np.abs(zl)) & (np.abs(w - wl) <= AGREEMENT * np.abs(wl))
        valid = (stab > 1 - 1e-9) & corner_ok & trusted & (z > 0) & (w > 0) & np.isfinite(z) & np.isfinite(w)
        fn = w / (2 * math.pi)
        known = self.status == STATUS_OK
        bounds = {}
        for name, value, iv, lin in (("zeta", z, self.zeta_interval, zl), ("fn", fn, self.fn_interval,
                                                                          wl / (2 * math.pi))):
            est = self.zeta if name == "zeta" else self.fn
            extra = np.log(value / lin) ** 2        # the interpolation's own doubt, in log
            sides = []
            for k in (0, 1):
                # log of value / low and of high / value; a low end clipped at zero counts as
                # a factor of 10 (the interval reaches far down: more would only let one
                # ill-defined neighbour swamp the interpolation)
                with np.errstate(divide="ignore", invalid="ignore"):
                    r = np.abs(np.log(np.where(known, np.maximum(iv[..., k], est * 0.1), 1.0) / est))
                r = np.where(known & np.isfinite(r), r, 0.0)
                filled = harmonic_fill(r, known) if known.any() else r
                sides.append(np.sqrt(np.maximum(interp(filled, "linear").reshape(full), 0.0) ** 2 + extra))
            bounds[name] = np.stack([value * np.exp(-sides[0]), value * np.exp(sides[1])], axis=-1)
        self._fine = {"key": key, "axes": fine_axes, "zeta": z, "fn": fn, "valid": valid,
                      "zeta_interval": bounds["zeta"], "fn_interval": bounds["fn"]}
        return self._fine

    def achievable(self, **kw) -> Achievable:
        """Every valid fine-grid point: the (zeta, fn) region of the thesis's Fig. 6.12."""
        f = self.fine(**kw)
        v = f["valid"]
        if v.shape == tuple(len(a) for a in f["axes"]):   # the valid points' gains, axis by axis
            gains = np.column_stack([a[i] for a, i in zip(f["axes"], np.nonzero(v))])
        else:
            gains = np.stack(np.meshgrid(*f["axes"], indexing="ij"), axis=-1)[v]
        return Achievable(gains=gains, zeta=f["zeta"][v], fn=f["fn"][v], zeta_interval=f["zeta_interval"][v],
                          fn_interval=f["fn_interval"][v])

    # -- inverse -------------------------------------------------------------------------
    def _tree(self):
        if getattr(self, "_kd", None) is None or self._kd[0] is not self._fine:
            a = self.achievable()
            if a.zeta.size == 0:
                raise ValueError("the map has no achievable point (all unstable or failed?)")
            # log coordinates: a distance there is a relative error in zeta and in fn
            self._kd = (self._fine, cKDTree(np.column_stack([np.log(a.zeta), np.log(a.fn)])), a)
        return self._kd[1:]

    def nearest(self, zeta: float, fn: float, tolerance: float | None = None) -> Choice:
        """The achievable point nearest to (zeta, fn [Hz]).

        Parameters
        ----------
        zeta, fn : the requested damping ratio and natural frequency [Hz], positive
        tolerance : when given, raise :class:`OutsideRegionError` unless the nearest point
            is within this relative distance in both zeta and fn

        Returns
        -------
        Choice: gains, the map's (zeta, fn) there and the relative distance (the larger of
        the two relative errors, in log). Nearness is measured in (log zeta, log fn), the
        larger of the two relative errors (Chebyshev), so the answer is the point whose
        worse relative error is smallest.
        """
        if not (np.isfinite(zeta) and np.isfinite(fn) and zeta > 0 and fn > 0):
            raise ValueError(f"desired zeta and fn must be positive, got zeta={zeta}, fn={fn}")
        tree, a = self._tree()
        d, i = tree.query(np.log([zeta, fn]), p=np.inf)
        c = Choice(gains=tuple(float(x) for x in a.gains[i]), zeta=float(a.zeta[i]), fn=float(a.fn[i]),
                   distance=float(d), zeta_interval=tuple(map(float, a.zeta_interval[i])),
                   fn_interval=tuple(map(float, a.fn_interval[i])))
        if tolerance is not None and not c.within(tolerance):
            raise OutsideRegionError((zeta, fn), c, tolerance)
        return c

    def gains_for(self, zeta: float, fn: float, tolerance: float = TOLERANCE) -> tuple[float, float, float]:
        """(pos_gain, vel_gain, vel_integrator_gain) for a desired damping ratio and natural
        frequency fn [Hz].

        Raises
        ------
        OutsideRegionError
            when no achievable point is within ``tolerance`` (relative, in zeta and in fn)
            of the request; the message names the nearest achievable point and its gains
            (also in the exception's ``nearest``).
        """
        return self.nearest(zeta, fn, tolerance=tolerance).gains

    def predict(self, gains) -> tuple[float, float]:
        """(zeta, fn) the interpolated map gives at ``gains`` (cubic on the filled map)."""
        zeta, wn = self.filled()
        active = [i for i, a in enumerate(self.axes) if len(a) > 1]
        g = np.asarray(gains, dtype=float)
        for i in active:
            lo, hi = self.axes[i][0], self.axes[i][-1]
            if not lo <= g[i] <= hi:
                raise ValueError(f"{GAIN_NAMES[i]} = {g[i]:g} is outside the map's grid [{lo:g}, {hi:g}]")
        sub = [np.log(self.axes[i]) for i in active]
        shape = [len(a) for a in sub]
        method = "cubic" if all(n >= 4 for n in shape) else "linear"
        # the interpolant of fine(): exact per-axis splines in log gains
        mats = [_axis_matrix(a, np.log(g[[i]]), method) for a, i in zip(sub, active)]
        z = np.exp(_tensor_interp(np.log(zeta).reshape(shape), mats)).item()
        w = np.exp(_tensor_interp(np.log(wn).reshape(shape), mats)).item()
        return float(z), float(w / (2 * math.pi))
GAIN_NAMES = ("pos_gain", "vel_gain", "vel_integrator_gain")


def _axis_matrix(x: np.ndarray, xi: np.ndarray, method: str) -> np.ndarray:
    """(len(xi), len(x)) weights W: ``W @ f`` is the 1-D interpolant of samples ``f`` at
    ``x`` evaluated at ``xi`` -- a not-a-knot cubic spline (``method="cubic"``, as
    RegularGridInterpolator's) or piecewise linear."""
    n = len(x)
    if method == "cubic":
        return make_interp_spline(x, np.eye(n), k=3)(xi)
    j = np.clip(np.searchsorted(x, xi, side="right") - 1, 0, n - 2)
    t = (xi - x[j]) / (x[j + 1] - x[j])
    w = np.zeros((len(xi), n))
    rows = np.arange(len(xi))
    w[rows, j] = 1.0 - t
    w[rows, j + 1] = t
    return w


def _tensor_interp(field: np.ndarray, mats) -> np.ndarray:
    """A tensor-product interpolant on a product grid: ``mats[k]`` applied along axis k."""
    out = field
    for k, w in enumerate(mats):
        out = np.moveaxis(np.tensordot(w, out, axes=([1], [k])), 0, k)
    return out


def spread_targets(achievable: Achievable, count: int = 10, margin: float = 0.1, seed: int = 0) -> np.ndarray:
    """``count`` (zeta, fn) targets spread over the achievable region (farthest-point
    sampling in normalized coordinates, away from the region's edges by ``margin``)."""
    pts = np.column_stack([achievable.zeta, achievable.fn])
    lo, hi = np.quantile(pts, margin, axis=0), np.quantile(pts, 1 - margin, axis=0)
    inside = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    scale = np.ptp(inside, axis=0)
    scale[scale == 0] = 1.0
    norm = inside / scale
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(len(norm)))]
    dist = np.linalg.norm(norm - norm[chosen[0]], axis=1)
    while len(chosen) < min(count, len(norm)):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(norm - norm[nxt], axis=1))
    return inside[chosen]
