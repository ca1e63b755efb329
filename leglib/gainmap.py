"""The map from ODrive cascade gains to second-order dynamics, and its inverse (thesis 6.4-6.5).

Pipeline (Listings 7.6-7.8, done properly):

1. every step response of a sweep is identified with :func:`leglib.identify.second_order`
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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.interpolate import make_interp_spline
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from . import dataio
from .identify import IdentificationError, second_order

STATUS_OK, STATUS_UNSTABLE, STATUS_FAILED, STATUS_MISSING = "ok", "unstable", "failed", "missing"
AGREEMENT = 0.10  # relative cubic-vs-linear disagreement beyond which a fine point is not trusted
MIN_R2_MAP = 0.90  # a step the second-order fit explains less of is "failed", not a map point
MAX_OVERSHOOT = 1.0  # a second-order step overshoots less than 100 % of its step
MIN_POS_GAIN = 0.1  # (turn/s)/turn: below it there is no position control to identify
MIN_VEL_GAIN = 1e-4  # N*m/(turn/s): below it the cascade commands (almost) no torque
TOLERANCE = 0.05  # relative distance in zeta and fn within which a target counts as achievable


class OutsideRegionError(ValueError):
    """A requested (zeta, fn) is outside the achievable region of a gain map.

    Attributes
    ----------
    target : (zeta, fn [Hz]) that was asked for
    nearest : :class:`Choice`, the nearest achievable point (its gains, zeta, fn)
    """

    def __init__(self, target, nearest, tolerance):
        self.target = tuple(float(x) for x in target)
        self.nearest = nearest
        self.tolerance = tolerance
        g = ", ".join(f"{x:.4g}" for x in nearest.gains)
        super().__init__(
            f"target (zeta {target[0]:.3g}, fn {target[1]:.3g} Hz) is outside the achievable region "
            f"(no achievable point within {tolerance:.0%} in zeta and fn); the nearest achievable point is "
            f"(zeta {nearest.zeta:.3g}, fn {nearest.fn:.3g} Hz) with gains (pos_gain, vel_gain, "
            f"vel_integrator_gain) = ({g})")


@dataclass
class PointResult:
    """One identified grid point."""

    gains: tuple
    status: str
    zeta: float = math.nan
    wn: float = math.nan
    r2: float = math.nan
    reason: str = ""
    fit: object = field(default=None, repr=False, compare=False)  # the SecondOrderFit, when one was made

    @property
    def fn(self) -> float:
        return self.wn / (2 * math.pi)


def step_shape_problem(t, y, fit, shape=None) -> str | None:
    """Why a fitted step response is not a second-order step, or None when it is one.

    Parameters
    ----------
    t : (N,) time [s]
    y : (N,) response (e.g. foot height [m])
    fit : :class:`leglib.identify.SecondOrderFit` of (t, y)
    shape : the response's :func:`leglib.fastfit.shape_numbers` row when already computed
        (for many responses at once); computed here otherwise

    The tests: the fit explains at least :data:`MIN_R2_MAP` of the response (R^2); the
    response overshoots its final value by less than :data:`MAX_OVERSHOOT` of the step (no
    second-order step overshoots 100 %); an overdamped fit's fast pole
    wn (zeta + sqrt(zeta^2 - 1)) is slower than the sampling's Nyquist rate pi/dt (a faster
    pole cannot be seen in the data, so its zeta would be a number the data does not hold).
    """
    if not fit.r2 >= MIN_R2_MAP:
        return (f"not a second-order step: the fit explains R^2 = {fit.r2:.2f} of it "
                f"(the map needs {MIN_R2_MAP})")
    if shape is None:
        from .fastfit import shape_numbers
        shape = shape_numbers([t], [y])[0]
    start, final, peak, spacing = (float(v) for v in shape)
    step = final - start
    if step != 0 and peak / abs(step) >= MAX_OVERSHOOT:
        return f"not a second-order step: it overshoots by {peak / abs(step):.0%} of its step"
    if fit.zeta > 1:
        fast = fit.wn * (fit.zeta + math.sqrt(fit.zeta ** 2 - 1))
        nyquist = math.pi / spacing
        if fast > nyquist:
            return (f"not a second-order step: the fit's fast pole ({fast:.3g} rad/s, zeta {fit.zeta:.3g}) "
                    f"lies beyond the sampling's Nyquist rate ({nyquist:.3g} rad/s)")
    return None


def identify_response(resp, method: str = "fit", fit=None, shape=None) -> PointResult:
    """Identify one :class:`leglib.odrive_io.StepResponse` (foot height ``y``).

    Returns a :class:`PointResult` with status "unstable" (the step was aborted), "failed"
    (no position control because pos_gain < :data:`MIN_POS_GAIN` or vel_gain <
    :data:`MIN_VEL_GAIN`; the data cannot be identified; or the response is not a
    second-order step, :func:`step_shape_problem`) or "ok" with zeta, wn [rad/s] and r2.
    A "failed" point never carries numbers; ``reason`` says why. ``fit``: the response's
    ``second_order`` result (or its IdentificationError) when already computed, e.g. by
    :func:`identify_many`'s batch; ``shape`` likewise its :func:`step_shape_problem` numbers.
    """
    g = tuple(float(x) for x in resp.gains)
    if not resp.completed:
        return PointResult(g, STATUS_UNSTABLE, reason=resp.abort_reason or "aborted")
    if not (g[0] >= MIN_POS_GAIN and g[1] >= MIN_VEL_GAIN):
        return PointResult(g, STATUS_FAILED, reason=(
            f"no position control to identify: pos_gain {g[0]:g} (needs >= {MIN_POS_GAIN:g}) or "
            f"vel_gain {g[1]:g} (needs >= {MIN_VEL_GAIN:g}) is (nearly) zero"))
    try:
        if isinstance(fit, IdentificationError):
            raise fit
        f = second_order(resp.t, resp.y, method=method) if fit is None else fit
    except IdentificationError as exc:
        return PointResult(g, STATUS_FAILED, reason=str(exc))
    problem = step_shape_problem(resp.t, resp.y, f, shape)
    if problem:
        return PointResult(g, STATUS_FAILED, r2=f.r2, reason=problem, fit=f)
    return PointResult(g, STATUS_OK, f.zeta, f.wn, f.r2, fit=f)


def identify_many(responses, method: str = "fit", workers: int | None = None) -> list[PointResult]:
    """Identify many :class:`leglib.odrive_io.StepResponse` objects.

    Parameters
    ----------
    responses : iterable of StepResponse (foot height ``y`` [m] against ``t`` [s])
    method : "fit" identifies every completed response in one compiled call
        (:func:`leglib.fastfit.identify_batch`, the same numbers as
        :func:`identify_response` one by one); other methods go one by one
    workers : accepted for compatibility and ignored: the compiled batch needs no
        process pool (400 responses take well under a second on one core)

    Returns
    -------
    list of PointResult, in the order of ``responses``
    """
    from .fastfit import identify_batch

    responses = list(responses)
    if method != "fit":
        return [identify_response(r, method) for r in responses]
    done = [r for r in responses if r.completed]
    fits, shapes = identify_batch([r.t for r in done], [r.y for r in done], shapes=True)
    fits, shapes = iter(fits), iter(shapes)
    # the same checks as one by one (gains, shape, fit quality), on the batch's numbers
    return [identify_response(r, method, fit=next(fits), shape=next(shapes)) if r.completed
            else identify_response(r, method) for r in responses]


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
    """Fine-grid points the map can deliver: gains (M, 3), zeta (M,), fn (M,) [Hz]."""

    gains: np.ndarray
    zeta: np.ndarray
    fn: np.ndarray


@dataclass
class Choice:
    """Answer of :meth:`GainMap.nearest`: gains (pos_gain, vel_gain, vel_integrator_gain),
    the map's zeta and fn [Hz] there, and ``distance``, the larger of the relative
    distances in zeta and in fn to the request (max(|log(zeta/zeta_req)|, |log(fn/fn_req)|))."""

    gains: tuple
    zeta: float
    fn: float
    distance: float

    def within(self, tolerance: float = TOLERANCE) -> bool:
        """True when the point is within ``tolerance`` (relative) of the request."""
        return self.distance <= math.log1p(tolerance) + 1e-12


class GainMap:
    """Gains -> (zeta, wn, fn) on a 3-D grid, with gap filling, interpolation and inverse.

    Attributes
    ----------
    axes : (pos_gain values, vel_gain values, vel_integrator_gain values), sorted
    zeta, wn : arrays of shape (len(pos), len(vel), len(vint)); NaN where not identified
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
        self.points = points
        cells = zip(*(np.searchsorted(ax, G[:, k]).tolist() for k, ax in enumerate(self.axes)))
        for i, p in zip(cells, points):
            self.status[i] = p.status
            if p.status == STATUS_OK:
                self.zeta[i], self.wn[i] = p.zeta, p.wn
        self._fine = None

    # -- construction --------------------------------------------------------------------
    @classmethod
    def from_responses(cls, responses, method: str = "fit", workers: int | None = None) -> "GainMap":
        """From :class:`leglib.odrive_io.StepResponse` objects (identified in parallel)."""
        return cls(identify_many(responses, method, workers))

    @classmethod
    def from_measurements(cls, paths_or_dir, leg="thesis", method: str = "fit", progress: bool = False,
                          strict: bool = True) -> "GainMap":
        """From measurement files (a directory, or a list of ``*_positions.csv`` and batch
        ``*_batch.csv`` files).

        ``leg`` (name or LegParams) gives the kinematics for the foot height. ``strict=False``
        skips unreadable files and warns naming them (:func:`leglib.dataio.read_measurements`).
        Two files with the same gains are an error naming both: a map cell holds one
        measurement.
        """
        from tqdm.auto import tqdm

        from .odrive_io import StepResponse
        from .params import load_leg

        leg = load_leg(leg) if isinstance(leg, (str, Path)) else leg
        measurements = dataio.read_measurements(paths_or_dir, strict=strict).measurements
        if not measurements:
            raise ValueError(f"no readable measurement files in {paths_or_dir}")
        seen = {}
        for m in measurements:
            if m.gains is None:
                raise dataio.MeasurementError(f"{m.where}: no gains in the file name or sidecar")
            key = tuple(np.round(np.asarray(m.gains, dtype=float), 6))
            if key in seen:
                raise dataio.MeasurementError(f"{seen[key]} and {m.where} both hold gains {m.gains}: "
                                              f"a map cell holds one measurement; move one away")
            seen[key] = m.where
        with tqdm(total=len(measurements), desc="identify", unit="file", disable=not progress) as bar:
            points = identify_many(StepResponse.from_measurements(measurements, leg), method)
            bar.update(len(points))
        return cls(points)

    # -- summary -------------------------------------------------------------------------
    @property
    def fn(self) -> np.ndarray:
        return self.wn / (2 * math.pi)

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
        cannot resolve the map there), or where the value is non-physical.
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
        self._fine = {"key": key, "axes": fine_axes, "zeta": z, "fn": w / (2 * math.pi), "valid": valid}
        return self._fine

    def achievable(self, **kw) -> Achievable:
        """Every valid fine-grid point: the (zeta, fn) region of the thesis's Fig. 6.12."""
        f = self.fine(**kw)
        v = f["valid"]
        if v.shape == tuple(len(a) for a in f["axes"]):   # the valid points' gains, axis by axis
            gains = np.column_stack([a[i] for a, i in zip(f["axes"], np.nonzero(v))])
        else:
            gains = np.stack(np.meshgrid(*f["axes"], indexing="ij"), axis=-1)[v]
        return Achievable(gains=gains, zeta=f["zeta"][v], fn=f["fn"][v])

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
                   distance=float(d))
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


# ---------------------------------------------------------------------------------------
# the model-based inverse: a handful of experiments instead of a full sweep
# ---------------------------------------------------------------------------------------

def twin_step_responses(twin, gains, step=0.4, duration=1.5, sample_period=0.002):
    """Listing 7.4's steps on a :class:`leglib.twin.Twin` for each gain triple (one batch),
    as :class:`leglib.odrive_io.StepResponse` with the foot height of the twin's nominal
    leg; the configuration's step velocity limit, an abort at twice the step."""
    from .model import foot_position
    from .odrive_io import StepResponse
    g = np.atleast_2d(np.asarray(gains, float))
    out = twin.step_batch(g, step_turns=step, duration=duration, sample_period=sample_period,
                          vel_limit=twin.config.step_vel_limit, abort_error_turns=2 * abs(step))
    ax = twin.axes
    res = []
    for i in range(len(g)):
        q1 = ax.counts_to_joint(out["counts"][i, :, ax.axis_of_joint[0]], 0)
        q2 = ax.counts_to_joint(out["counts"][i, :, ax.axis_of_joint[1]], 1)
        _, y = foot_position(twin.nominal_leg, q1, q2)
        res.append(StepResponse(t=out["t"], q1=q1, q2=q2, y=y, gains=tuple(g[i]), step=step,
                                completed=bool(out["abort_tick"][i] < 0)))
    return res


@dataclass
class LegPlantModel:
    """The leg as the cascade sees it, from a handful of step responses: the nominal
    five-bar's geometry with a fitted inertia scale, a payload on the foot [kg] and joint
    friction (viscous, Coulomb; the same on both joints), simulated through the same
    compiled cascade as the twin, without noise or quantization. ``params`` holds the fitted values, ``experiments`` how many step
    responses it took, ``rms_turns`` the fit's motor-position residual."""

    params: dict
    template: object
    config: object
    step: float
    duration: float
    sample_period: float
    rms_turns: float
    experiments: int

    def twin(self):
        from .twin import Twin
        p = self.params
        plant = self.template.replace(inertia_scale=p["inertia_scale"], mass_scale=1.0,
                                      viscous1=p["viscous"], viscous2=p["viscous"], coulomb1=p["coulomb"],
                                      coulomb2=p["coulomb"], stribeck1=0.0, stribeck2=0.0,
                                      payload_mass=p["payload_mass"])
        # exact positions: finite differences of the fit must see small parameter changes
        return Twin(plant, self.config, noise=False, quantize=False)

    def responses(self, gains):
        """Simulated :class:`leglib.odrive_io.StepResponse` for each gain triple (batch)."""
        return twin_step_responses(self.twin(), gains, self.step, self.duration, self.sample_period)

    def predict(self, gains) -> tuple[float, float]:
        """(zeta, fn [Hz]) the model predicts for one gain triple (NaN if unstable or not a
        second-order step)."""
        r = self.responses([gains])[0]
        if not r.completed:
            return math.nan, math.nan
        try:
            f = second_order(r.t, r.y)
        except IdentificationError:
            return math.nan, math.nan
        return f.zeta, f.fn

    def gains_for(self, zeta: float, fn: float, vel_integrator_gain: float = 0.01, start=None):
        """Gains giving (zeta, fn [Hz]) on the model: Kp, Kv solved (log space, bounded by
        the configuration) from the analytic PD start; returns (gains, predicted (zeta, fn))."""
        from scipy.optimize import least_squares
        cfg = self.config
        lo = np.log([1.0, 1e-3])
        hi = np.log([cfg.max_pos_gain, cfg.max_vel_gain])
        if start is None:
            # PD on the model leg's opening-mode inertia at rest, seen at the motor:
            # wn^2 = Kv Kp / J, 2 zeta wn J = Kv
            from .cascade import motor_side_inertia
            from .model import mass_matrix
            tw = self.twin()
            D = mass_matrix(tw.leg, *tw.leg.q0)
            J = motor_side_inertia(D[0, 0] - D[0, 1], tw.axes.gear_ratio)
            wn = 2 * math.pi * fn
            kv = 2 * zeta * wn * J
            start = (wn ** 2 * J / kv, kv)
        starts = [np.log(start)] + [np.log(start) + d for d in ([0.0, -0.4], [0.0, 0.4])]

        def resid(x):
            z, f = self.predict((math.exp(x[0]), math.exp(x[1]), vel_integrator_gain))
            if not np.isfinite(z):
                return np.array([2.0, 2.0])
            return np.array([z / zeta - 1, f / fn - 1])

        best = None
        for x0 in starts:  # a second start only when the first does not reach the target
            res = least_squares(resid, np.clip(x0, lo + 1e-6, hi - 1e-6), bounds=(lo, hi), diff_step=1e-3,
                                max_nfev=60)
            if best is None or res.cost < best.cost:
                best = res
            if np.max(np.abs(best.fun)) < 0.005:
                break
        gains = (math.exp(best.x[0]), math.exp(best.x[1]), vel_integrator_gain)
        return gains, self.predict(gains)


def fit_leg_plant(responses, config, template="default") -> LegPlantModel:
    """Fit :class:`LegPlantModel` to measured step responses (least squares on both axes'
    motor positions). ``template`` supplies the structure (base leg, stops); its friction,
    inertia and mass values are not used. Unstable responses are skipped."""
    from scipy.optimize import least_squares

    from .drive import AxisMap
    from .params import load_plant
    template = load_plant(template) if isinstance(template, str) else template
    done = [r for r in responses if r.completed]
    if len(done) < 2:
        raise ValueError(f"need at least two completed step responses, got {len(done)}")
    r0 = done[0]
    dt = float(r0.t[1] - r0.t[0])
    model = LegPlantModel(params={}, template=template, config=config, step=float(r0.step),
                          duration=float(len(r0.t) * dt), sample_period=dt, rms_turns=math.nan,
                          experiments=len(responses))
    ax = AxisMap.from_leg(template.base_leg())
    meas = np.concatenate([np.concatenate([ax.motor_turns(r.q1, 0), ax.motor_turns(r.q2, 1)]) for r in done])
    gains = np.array([r.gains for r in done])
    names = ("inertia_scale", "payload_mass", "viscous", "coulomb")

    def resid(x):
        model.params = dict(zip(names, np.exp(x)))
        sims = model.responses(gains)
        n = min(len(s.t) for s in sims)
        sim = np.concatenate([np.concatenate([ax.motor_turns(s.q1, 0), ax.motor_turns(s.q2, 1)]) for s in sims])
        return sim - meas if sim.size == meas.size and n == len(r0.t) else np.full(meas.size, 1.0)

    x0 = np.log([1.0, 0.05, 0.003, 0.01])
    res = least_squares(resid, x0, bounds=(np.log([0.2, 1e-4, 1e-5, 1e-5]), np.log([5.0, 5.0, 0.2, 0.3])),
                        diff_step=1e-3)
    model.params = dict(zip(names, map(float, np.exp(res.x))))
    model.rms_turns = float(np.sqrt(np.mean(res.fun ** 2)))
    return model


def fitting_gains(count: int = 5, pos_range=(25.0, 50.0), vel_range=(0.03, 0.15),
                  vel_integrator_gain: float = 0.01) -> np.ndarray:
    """``count`` gain triples for fitting :class:`LegPlantModel`: pos_gain and vel_gain
    spread over moderate, stable ranges in different orders (so damping and stiffness vary
    independently across the experiments), a small fixed integrator gain."""
    pos = np.linspace(*pos_range, count)
    vel = np.roll(np.linspace(*vel_range, count)[::-1], 1)
    return np.column_stack([pos, vel, np.full(count, vel_integrator_gain)])


# ---------------------------------------------------------------------------------------
# prescribed dynamics on any leg in a handful of experiments (leglib.autotune)
# ---------------------------------------------------------------------------------------

from .autotune import Design, design  # noqa: E402,F401  (gainmap.design is the documented entry point)
