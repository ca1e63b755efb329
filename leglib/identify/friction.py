"""Friction identification (thesis 5.2): a single joint (:func:`fit_friction`) and the
whole five-bar from a torque run (:func:`fit_leg_friction`), with uncertainties.

Output-error least squares (bounds, a smooth Coulomb term whose width is fitted too,
several starts, the first from an equation-error regression), driven by the torque the
motors actually produced. A Stribeck variant is compared on AIC with a common effective
sample size and chosen only when its terms matter.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit
from scipy.optimize import least_squares

from .. import (
    _numba_gc,  # noqa: F401  (before any kernel compiles)
    _numba_inline,  # noqa: F401  (before any kernel compiles)
    checks,
)
from ..errors import IdentificationError
from ..model.dynamics import (
    bias_torque,
    friction_vector,
    mass_matrix,
    simulate_torque_table,
)
from ..units import interval_text, pretty
from .step import _r2


def effective_samples(resid) -> float:
    """Effective number of independent residuals, n (1 - rho) / (1 + rho) with rho the
    lag-1 autocorrelation (per column for 2-D input, summed): time-series residuals are
    far from independent, and AIC with the raw n overstates the evidence for extra terms."""
    r = np.asarray(resid, dtype=float)
    r = r[:, None] if r.ndim == 1 else r
    total = 0.0
    for col in r.T:
        c = col - col.mean()
        den = float(np.dot(c, c))
        rho = float(np.dot(c[1:], c[:-1]) / den) if den > 0 else 0.0
        rho = min(max(rho, 0.0), 0.999)
        total += col.size * (1 - rho) / (1 + rho)
    return max(total, 1.0)


def _aic(ssr: float, n: float, k: int) -> float:
    """Akaike's criterion for Gaussian residuals with ``n`` (effective) samples."""
    return n * math.log(max(ssr, 1e-300) / n) + 2 * k


def _covariance(res, n: int) -> np.ndarray:
    """Jacobian-based parameter covariance s^2 (J^T J)^-1 of a least_squares result."""
    J = res.jac
    dof = max(n - J.shape[1], 1)
    s2 = 2 * res.cost / dof
    try:
        return s2 * np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((J.shape[1], J.shape[1]), np.nan)


def derivative(t, x, order: int = 1, window: float | None = None) -> np.ndarray:
    """Robust derivative of a sampled signal: Savitzky-Golay on a uniform resampling.

    Parameters
    ----------
    t : (N,) times [s], increasing (need not be uniform)
    x : (N,) signal
    order : 1 or 2
    window : smoothing window [s] (default: 2 % of the record, at least 9 samples)
    """
    from scipy.signal import savgol_filter  # load time: scipy.signal, 0.6 s

    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    dt = float(np.median(np.diff(t)))
    tu = t[0] + dt * np.arange(int(round((t[-1] - t[0]) / dt)) + 1)
    xu = np.interp(tu, t, x)
    n = max(9, int(round((window or 0.02 * (t[-1] - t[0])) / dt)) | 1)
    n = min(n, (len(tu) - 1) | 1 if len(tu) % 2 == 0 else len(tu))
    d = savgol_filter(xu, n, 3, deriv=order, delta=dt)
    return np.interp(t, tu, d)


@njit(cache=True)
def _simulate_joint(t, torque, J, b, c_pos, c_neg, v0, eps, substeps=4):
    """Backward-Euler velocity of J dv/dt = tau - b v - c(v) tanh(v/eps), tau held between
    samples; c = c_pos for v > 0 and c_neg otherwise. Robust for stiff Coulomb terms."""
    v = np.empty(t.size)
    v[0] = v0
    x = v0
    for i in range(t.size - 1):
        h = (t[i + 1] - t[i]) / substeps
        for _ in range(substeps):
            y = x
            for _ in range(8):  # Newton on g(y) = J (y - x) / h - tau + b y + c tanh(y / eps)
                c = c_pos if y > 0 else c_neg
                th = math.tanh(y / eps)
                g = J * (y - x) / h - torque[i] + b * y + c * th
                dg = J / h + b + c * (1 - th * th) / eps
                step = g / dg
                y -= step
                if abs(step) < 1e-12:
                    break
            x = y
        v[i + 1] = x
    return v


@dataclass
class FrictionFit:
    """Single-joint friction and inertia: J dv/dt = tau - viscous v - coulomb(v) tanh(v/eps).

    Attributes
    ----------
    coulomb_pos, coulomb_neg : Coulomb friction [N*m] for positive and negative velocity;
        NaN for a direction the data never excited (``identified_pos`` / ``identified_neg``
        False): the data say nothing about it, so no number is given
    viscous : [N*m*s/rad]
    inertia : [kg*m^2]
    v0 : initial velocity [rad/s]; eps : Coulomb smoothing velocity [rad/s]
    stderr : standard errors by name (NaN for a direction not identified)
    r2, rms : of the velocity fit (rms in rad/s); aic; n : samples
    identified_pos, identified_neg : whether each direction's Coulomb value is identified:
        the direction was excited (moved faster than a few eps for at least
        :data:`MIN_DIRECTION_SAMPLES` samples) and the data separate it (see
        ``not_identifiable``)
    not_identifiable : {parameter: why the data cannot give it, and the experiment that
        would}: a direction never excited, one torque level while moving one way with the
        inertia fitted (Coulomb + viscous x plateau velocity is one equation, the rise one
        more for three unknowns), a value fitted onto its bound. A Coulomb value listed here
        is NaN; a viscous or inertia value listed here is kept only for :meth:`simulate`
    intervals : {parameter: (low, high)}, 90 % intervals from the standard errors (clipped
        at 0); NaN for a parameter that is not identifiable
    """

    coulomb_pos: float
    coulomb_neg: float
    viscous: float
    inertia: float
    v0: float
    eps: float
    stderr: dict
    r2: float
    rms: float
    aic: float
    n: int
    identified_pos: bool = True
    identified_neg: bool = True
    not_identifiable: dict = field(default_factory=dict)
    intervals: dict = field(default_factory=dict)

    #: the unit of each reported value
    UNITS = {"coulomb_pos": "N*m", "coulomb_neg": "N*m", "coulomb": "N*m", "viscous": "N*m*s/rad",
             "inertia": "kg*m^2"}

    def table(self) -> str:
        """Markdown: each parameter with its 90 % interval, or why the data cannot give it."""
        rows = ["| parameter | value [90 % interval] |", "|---|---|"]
        for name, unit in self.UNITS.items():
            why = self.not_identifiable.get(name)
            if why:
                rows.append(f"| {name} [{pretty(unit)}] | not identifiable: {why} |")
                continue
            rows.append(f"| {name} [{pretty(unit)}] | {interval_text(getattr(self, name), self.intervals.get(name))} |")
        return "\n".join(rows)

    def _repr_markdown_(self) -> str:
        return self.table()

    @property
    def coulomb(self) -> float:
        """Coulomb friction [N*m]: the mean of the identified directions (one direction's
        value when the data ran one way only; NaN when neither was excited)."""
        vals = [c for c, ok in ((self.coulomb_pos, self.identified_pos), (self.coulomb_neg, self.identified_neg))
                if ok]
        return float(np.mean(vals)) if vals else math.nan

    @property
    def directions(self) -> str:
        """Which directions the Coulomb values rest on: "both", "positive only",
        "negative only" or "none"."""
        return {(True, True): "both", (True, False): "positive only", (False, True): "negative only",
                (False, False): "none"}[(bool(self.identified_pos), bool(self.identified_neg))]

    def simulate(self, t, torque, v0: float | None = None) -> np.ndarray:
        """Velocity [rad/s] for torque samples [N*m] at times t [s] (held between samples).
        A direction that was not identified is simulated with the other direction's
        Coulomb value (an assumption, for simulation only)."""
        t = np.asarray(t, dtype=float)
        cp = self.coulomb_pos if self.identified_pos else self.coulomb_neg
        cn = self.coulomb_neg if self.identified_neg else self.coulomb_pos
        cp, cn = (0.0 if not np.isfinite(c) else c for c in (cp, cn))
        return _simulate_joint(t, np.asarray(torque, dtype=float), self.inertia, self.viscous,
                               cp, cn, self.v0 if v0 is None else v0, self.eps)
MIN_DIRECTION_SAMPLES = 20  # samples beyond 3 eps a direction needs to count as excited


def fit_friction(t, torque, velocity=None, position=None, inertia: float | None = None,
                 eps: float | None = None, starts: int = 3) -> FrictionFit:
    """Fit Coulomb and viscous friction (and the inertia unless given) of one joint.

    Parameters
    ----------
    t : (N,) time [s], increasing
    torque : (N,) applied torque [N*m], held between samples
    velocity : (N,) joint velocity [rad/s], or
    position : (N,) joint angle [rad], differentiated robustly (Savitzky-Golay)
    inertia : [kg*m^2] if known (positive, finite); fitted otherwise
    eps : Coulomb smoothing velocity [rad/s] (positive, finite); fitted when not given
    starts : number of optimizer starts (equation-error estimate first), an integer in [1, 100]

    The series are arrays of finite real numbers: masked arrays with masked samples
    (masks are not honoured: drop those samples), complex values and strings are refused.

    Returns
    -------
    FrictionFit
        ``.coulomb``, ``.coulomb_pos``, ``.coulomb_neg`` [N*m], ``.viscous`` [N*m*s/rad],
        ``.inertia`` [kg*m^2], ``.stderr`` (their standard errors), ``.r2``, and which
        directions the data excited (``.identified_pos``, ``.identified_neg``).

    Raises
    ------
    IdentificationError
        Mismatched, short, non-increasing, non-finite, masked, complex or non-numeric data,
        neither or both of ``velocity`` and ``position``, or an invalid ``inertia``, ``eps``
        or ``starts`` (each named).

    Output-error least squares on the velocity, with bounds, a smooth Coulomb term with
    separate values per direction (asymmetric data is fine), several starts. Uncertainties
    from the Jacobian. A direction the joint never moved in (fewer than
    :data:`MIN_DIRECTION_SAMPLES` samples beyond 3 eps) is not identified: its Coulomb value
    is NaN, its flag False, and ``coulomb`` is the excited direction's value.
    """
    E = IdentificationError
    t = checks.real_array(t, "t", E)
    tau = checks.real_array(torque, "torque", E)
    if t.ndim != 1 or tau.shape != t.shape or t.size < 20:
        raise IdentificationError("t and torque must be 1-D of equal length (at least 20 samples)")
    if np.any(np.diff(t) <= 0):
        raise IdentificationError("time must increase strictly")
    if (velocity is None) == (position is None):
        raise IdentificationError("give exactly one of velocity [rad/s] or position [rad]")
    if inertia is not None:
        inertia = checks.number(inertia, "fit_friction: inertia [kg*m^2]", E, low=0.0, low_open=True)
    if eps is not None:
        eps = checks.number(eps, "fit_friction: eps [rad/s]", E, low=0.0, low_open=True)
    starts = checks.integer(starts, "fit_friction: starts", E, low=1, high=100)
    if velocity is None:
        x = checks.real_array(position, "position", E)
        if x.shape != t.shape:
            raise IdentificationError(f"position must match t: shape {x.shape}, t has {t.shape}")
        v = derivative(t, x)
    else:
        v = checks.real_array(velocity, "velocity", E)
        if v.shape != t.shape:
            raise IdentificationError(f"velocity must match t: shape {v.shape}, t has {t.shape}")
    vmax = float(np.max(np.abs(v)))
    if vmax <= 0:
        raise IdentificationError("the joint did not move: friction cannot be identified")
    fit_eps = eps is None
    eps0 = 0.01 * vmax if eps is None else eps
    # equation error: tau = J a + b v + c+ s+ + c- s-  (linear least squares)
    a = derivative(t, v)
    th = np.tanh(v / eps0)
    cols = [v, np.where(v > 0, th, 0.0), np.where(v <= 0, th, 0.0)]
    if inertia is None:
        cols.insert(0, a)
        rhs = tau
    else:
        rhs = tau - inertia * a
    X = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(X, rhs, rcond=None)
    if inertia is None:
        J0, b0, cp0, cn0 = coef
    else:
        J0, (b0, cp0, cn0) = inertia, coef
    J0 = max(J0, 1e-9)
    scale_v = max(vmax, 1e-9)

    def unpack(p):
        k = 0
        if inertia is None:
            J, k = p[0], 1
        else:
            J = inertia
        b, cp, cn, v0 = p[k:k + 4]
        e = p[k + 4] if fit_eps else eps0
        return J, b, cp, cn, v0, e

    def resid(p):
        J, b, cp, cn, v0, e = unpack(p)
        return (_simulate_joint(t, tau, J, b, cp, cn, v0, e) - v) / scale_v

    base = [max(b0, 0.0), max(cp0, 0.0), max(cn0, 0.0), v[0]]
    lo = [0.0, 0.0, 0.0, -10 * scale_v]
    hi = [np.inf, np.inf, np.inf, 10 * scale_v]
    if inertia is None:
        base.insert(0, J0)
        lo.insert(0, 1e-12)
        hi.insert(0, np.inf)
    if fit_eps:
        base.append(eps0)
        lo.append(1e-4 * scale_v)
        hi.append(0.2 * scale_v)
    rng = np.random.default_rng(0)
    best = None
    for k in range(starts):
        x0 = np.array(base, dtype=float)
        if k > 0:
            x0 *= np.exp(rng.normal(0, 0.5, x0.size))
            x0 += 1e-6
        x0 = np.clip(x0, lo, hi)
        res = least_squares(resid, x0, bounds=(lo, hi), x_scale=np.abs(x0) + 1e-6, method="trf")
        if best is None or res.cost < best.cost:
            best = res
    J, b, cp, cn, v0, eps = unpack(best.x)
    vhat = _simulate_joint(t, tau, J, b, cp, cn, v0, eps)
    cov = _covariance(best, t.size) * scale_v ** 2
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    names = ((["inertia"] if inertia is None else []) + ["viscous", "coulomb_pos", "coulomb_neg", "v0"]
             + (["eps"] if fit_eps else []))
    stderr = dict(zip(names, map(float, se)))
    if inertia is not None:
        stderr["inertia"] = 0.0
    i_p, i_n = names.index("coulomb_pos"), names.index("coulomb_neg")
    # a direction the joint never moved in (beyond the smoothing) holds no information on
    # its Coulomb value: it is reported as not identified, never averaged in
    need = min(MIN_DIRECTION_SAMPLES, max(3, t.size // 20))
    pos_ok = int(np.sum(v > 3 * eps)) >= need
    neg_ok = int(np.sum(v < -3 * eps)) >= need
    why = _single_joint_identifiability(t, tau, v, eps, need, inertia is None,
                                        {"coulomb_pos": cp, "coulomb_neg": cn, "viscous": b})
    pos_ok = pos_ok and "coulomb_pos" not in why
    neg_ok = neg_ok and "coulomb_neg" not in why
    if pos_ok and neg_ok:
        # the mean Coulomb's error from the two directions' (independent to first order)
        stderr["coulomb"] = float(0.5 * math.sqrt(max(cov[i_p, i_p] + cov[i_n, i_n] + 2 * cov[i_p, i_n], 0)))
    elif pos_ok or neg_ok:
        stderr["coulomb"] = stderr["coulomb_pos" if pos_ok else "coulomb_neg"]
    else:
        stderr["coulomb"] = math.nan
        if "coulomb_pos" in why and "coulomb_neg" in why:
            why["coulomb"] = "neither direction's Coulomb value is identified (above)"
    if not pos_ok:
        cp, stderr["coulomb_pos"] = math.nan, math.nan
    if not neg_ok:
        cn, stderr["coulomb_neg"] = math.nan, math.nan
    ssr = float(np.sum((vhat - v) ** 2))
    fit = FrictionFit(coulomb_pos=float(cp), coulomb_neg=float(cn), viscous=float(b), inertia=float(J),
                      v0=float(v0), eps=float(eps), stderr=stderr, r2=_r2(v, vhat),
                      rms=math.sqrt(ssr / t.size),
                      aic=_aic(ssr * effective_samples(vhat - v) / t.size, effective_samples(vhat - v), len(best.x)),
                      n=int(t.size), identified_pos=pos_ok, identified_neg=neg_ok, not_identifiable=why)
    fit.intervals = {name: (math.nan, math.nan) if name in why or not math.isfinite(getattr(fit, name))
                     else _interval90(getattr(fit, name), stderr.get(name, math.nan))
                     for name in ("coulomb_pos", "coulomb_neg", "coulomb", "viscous", "inertia")}
    return fit


#: two-sided 90 % normal quantile, for the friction values' intervals
Z90 = 1.6448536269514722
#: a joint's torque while it moves one way spans less than this part of the largest torque:
#: one torque level
ONE_LEVEL = 0.05


def _interval90(value: float, se: float, low: float = 0.0) -> tuple:
    """value -+ 1.645 se, its low end no lower than the parameter's own bound ``low`` (0 for a
    friction level; a signed parameter, an initial velocity or a cross damping, passes its
    fit's lower bound: clipping it at 0 once gave dq2_0 = -1.56 the interval [0, -1.56])."""
    if not (math.isfinite(value) and math.isfinite(se)):
        return (math.nan, math.nan)
    return (max(value - Z90 * se, low), value + Z90 * se)


def _single_joint_identifiability(t, tau, v, eps, need, inertia_fitted, values) -> dict:
    """{parameter: why the data cannot identify it, and what experiment would} for
    :func:`fit_friction`: a direction never excited, a direction driven at one torque level
    while the inertia is fitted, a value on its bound (0)."""
    why = {}
    scale = float(np.max(np.abs(tau))) or 1.0
    names = {1: ("coulomb_pos", "positive"), -1: ("coulomb_neg", "negative")}
    one_level = {}
    for sign, (name, word) in names.items():
        moving = sign * v > 3 * eps
        if int(np.sum(moving)) < need:
            why[name] = (f"the joint never moved in the {word} direction (fewer than {need} samples faster than "
                         f"3 eps = {3 * eps:.3g} rad/s): run a torque that drives it {word} too")
            continue
        level = tau[moving]
        if np.ptp(level) < ONE_LEVEL * scale:
            one_level[name] = float(np.median(level))
    if inertia_fitted and one_level:
        for name, level in one_level.items():
            word = names[1 if name == "coulomb_pos" else -1][1]
            why[name] = (f"one torque level ({level:.3g} N m) while moving {word}: the plateau fixes only "
                         f"Coulomb + viscous x velocity and the rise the inertia / viscous, three unknowns from two "
                         f"numbers; run at least two torque levels that way (e.g. {level:.3g} and {1.6 * level:.3g} N m), "
                         f"a sine of the torque, or give the inertia")
        excited = [n for n in ("coulomb_pos", "coulomb_neg") if n not in why or n in one_level]
        if all(n in one_level for n in excited):
            for name in ("viscous", "inertia"):
                why[name] = ("every direction the joint moved in was driven at one torque level: " +
                             why[excited[0]].split(": ", 1)[1])
    for name in ("coulomb_pos", "coulomb_neg", "viscous"):
        if name not in why and math.isfinite(values[name]) and values[name] <= 1e-6 * scale:
            why[name] = (f"fitted onto its bound 0 ({values[name]:.2g}): the data push it below what is physical, "
                         "so they do not hold its value; vary the torque (two levels or a sine) over the range where "
                         "it acts")
    return why
FRICTION_MODELS = ("coulomb_viscous", "stribeck")


@dataclass
class LegFrictionFit:
    """Friction of both joints identified on the exact five-bar model.

    ``params`` / ``stderr``: viscous1, viscous2 [N*m*s/rad], coulomb1, coulomb2 [N*m],
    inertia_scale, mass_scale [-] (relative to the nominal leg), dq1_0, dq2_0 [rad/s]
    (initial velocities), and for the variants c12, c21 [N*m*s/rad] (cross damping) or
    stribeck1, stribeck2 [N*m], v_stribeck [rad/s]. ``rms_deg`` (q1, q2), ``r2`` (q1, q2),
    ``aic`` (on ``n_eff``, the effective number of independent residuals, see
    :func:`effective_samples`), ``n`` residuals, ``ssr`` [rad^2]. Compare models with
    :func:`compare_friction_models`, which puts them on a common ``n_eff``. ``leg`` is the identified leg (scaled nominal leg with the
    fitted friction); ``friction`` the kernels' friction vector. ``converged`` is False when
    the optimizer stopped at its evaluation budget (``max_nfev``) rather than at a minimum:
    the numbers are then the best found, not an optimum, and should not be trusted as one.
    """

    model: str
    params: dict
    stderr: dict
    rms_deg: tuple
    r2: tuple
    aic: float
    n: int
    n_eff: float
    ssr: float
    leg: object
    friction: np.ndarray
    start: float
    v_smooth: float
    converged: bool = True
    #: {parameter: (low, high)} 90 % intervals from the standard errors; NaN for a parameter
    #: that is not identifiable
    intervals: dict = field(default_factory=dict)
    #: {parameter: why the data cannot give it}: a value fitted onto its bound
    not_identifiable: dict = field(default_factory=dict)

    #: the unit of each parameter (the scales are relative to the nominal leg)
    UNITS = {"viscous1": "N*m*s/rad", "viscous2": "N*m*s/rad", "coulomb1": "N*m", "coulomb2": "N*m",
             "inertia_scale": "-", "mass_scale": "-", "dq1_0": "rad/s", "dq2_0": "rad/s", "v_smooth": "rad/s",
             "c12": "N*m*s/rad", "c21": "N*m*s/rad", "stribeck1": "N*m", "stribeck2": "N*m",
             "v_stribeck": "rad/s"}

    def simulate(self, run) -> np.ndarray:
        """Simulated (q1, q2) [rad] at the run's sample times from ``start`` on: (M, 2)."""
        return simulate_run(run, self.leg, self.friction, self.start,
                            (self.params["dq1_0"], self.params["dq2_0"]))[1]

    def to_dict(self) -> dict:
        return {"model": self.model, "params": self.params, "stderr": self.stderr,
                "intervals": {k: list(v) for k, v in self.intervals.items()},
                "not_identifiable": dict(self.not_identifiable), "converged": self.converged,
                "rms_deg": list(self.rms_deg), "r2": list(self.r2), "aic": self.aic, "n": self.n,
                "n_eff": self.n_eff, "start_s": self.start, "v_smooth": self.v_smooth}


def friction_table(fits: dict) -> str:
    """Markdown: the parameters of one or more :class:`LegFrictionFit` (``{column title: fit}``)
    side by side, each with its unit and 90 % interval to the digits the interval supports,
    "not identifiable" with the reason where the run does not hold it, "—" where a fit has no
    such parameter; then each fit's RMS error (two significant digits), R² and AIC."""
    names = list(dict.fromkeys(k for f in fits.values() for k in f.params))

    def cell(f, k):
        if k not in f.params:
            return "—"
        if k in f.not_identifiable:
            return f"not identifiable: {f.not_identifiable[k]}"
        return interval_text(f.params[k], f.intervals.get(k))

    head = "| parameter | unit | " + " | ".join(f"{t} [90 % interval]" for t in fits) + " |"
    rows = [head, "|---|---|" + "---|" * len(fits)]
    rows += [f"| {k} | {pretty(LegFrictionFit.UNITS.get(k, '')) or '-'} | "
             + " | ".join(cell(f, k) for f in fits.values()) + " |" for k in names]
    rows.append("| RMS q1, q2 | deg | " + " | ".join(", ".join(f"{v:.2g}" for v in f.rms_deg) for f in fits.values())
                + " |")
    rows.append("| R² q1, q2 | - | " + " | ".join(", ".join(f"{v:.6f}" for v in f.r2) for f in fits.values()) + " |")
    rows.append("| AIC | - | " + " | ".join(f"{f.aic:.1f}" for f in fits.values()) + " |")
    return "\n".join(rows)


def compare_friction_models(fits: dict) -> dict:
    """AIC of several fits of the same data on a common effective sample size (the smallest
    of theirs: the most conservative). Returns {name: (aic, delta to the best)}; a delta
    above about 2 is evidence against that model."""
    n_eff = min(f.n_eff for f in fits.values())
    aic = {name: n_eff * math.log(f.ssr / f.n) + 2 * len(f.params) for name, f in fits.items()}
    best = min(aic.values())
    return {name: (a, a - best) for name, a in aic.items()}


class RunSimulator:
    """The leg simulated against one torque run from ``start`` on: the applied torque
    (:meth:`TorqueRun.applied_torque`) on a ``step`` grid and the read times are prepared
    once, so a fit can call :meth:`simulate` many times."""

    def __init__(self, run, start: float, step: float = 1.25e-4):
        self.run, self.start, self.step = run, start, step
        self.use = run.t >= start
        self.grid = start + step * np.arange(int(math.ceil((run.t[-1] - start) / step)) + 2)
        before = np.arange(0.0, start, step)  # the current loop's lag carries over the start
        self.tau = run.applied_torque(np.concatenate([before, self.grid]))[before.size:]
        # each joint at the moment it was read (they are read one after the other)
        t_read = getattr(run, "t_read", None)
        self.t_read = t_read[self.use] if t_read is not None else np.column_stack([run.t[self.use]] * 2)
        self.q_start = (float(np.interp(start, run.t, run.q1)), float(np.interp(start, run.t, run.q2)))
        self.measured = np.column_stack([run.q1[self.use], run.q2[self.use]])

    def simulate(self, leg, friction, dq0) -> np.ndarray:
        """Simulated (q1, q2) [rad] at the used samples' read times: (M, 2)."""
        x0 = (self.q_start[0], dq0[0], self.q_start[1], dq0[1])
        sim = simulate_torque_table(leg, x0, self.tau, self.step, substeps=1, friction=friction)
        return np.column_stack([np.interp(self.t_read[:, 0], self.grid, sim[:, 0]),
                                np.interp(self.t_read[:, 1], self.grid, sim[:, 2])])


def simulate_run(run, leg, friction, start, dq0):
    """The leg simulated from its measured state at ``start`` under the torque the motors
    applied during ``run``; returns (mask of the run's samples used, (M, 2) simulated q)."""
    sim = RunSimulator(run, start)
    return sim.use, sim.simulate(leg, friction, dq0)


def _leg_part(leg, inertia: bool):
    """The leg with only its inertias (inertia=True) or only its masses: D, Coriolis and
    gravity are linear in the two parts, which the equation-error start exploits."""
    if inertia:
        return leg.replace(m1=0.0, m2=0.0, m3=0.0, m4=0.0)
    return leg.replace(I1=0.0, I2=0.0, I3=0.0, I4=0.0, Jd1=0.0, Jd2=0.0)


def _equation_error_start(run, leg, start, v_smooth):
    use = run.t >= start
    t = run.t[use]
    q = np.column_stack([run.q1[use], run.q2[use]])
    dq = np.column_stack([derivative(t, q[:, j]) for j in (0, 1)])
    ddq = np.column_stack([derivative(t, q[:, j], order=2) for j in (0, 1)])
    Y = []
    for part in (_leg_part(leg, True), _leg_part(leg, False)):
        D = mass_matrix(part, q[:, 0], q[:, 1])
        b = bias_torque(part, q[:, 0], q[:, 1], dq[:, 0], dq[:, 1])
        Y.append(np.einsum("nij,nj->ni", D, ddq) + b)
    tau = run.tau[use]
    rows, rhs = [], []
    for j in (0, 1):
        cols = np.zeros((t.size, 6))
        cols[:, 0] = Y[0][:, j]
        cols[:, 1] = Y[1][:, j]
        cols[:, 2 + j] = dq[:, j]
        cols[:, 4 + j] = np.tanh(dq[:, j] / v_smooth)
        rows.append(cols)
        rhs.append(tau[:, j])
    coef, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
    s, m, b1, b2, c1, c2 = coef
    return {"inertia_scale": s, "mass_scale": m, "viscous1": b1, "viscous2": b2,
            "coulomb1": c1, "coulomb2": c2, "dq1_0": float(dq[0, 0]), "dq2_0": float(dq[0, 1])}


def fit_leg_friction(run, leg, model: str = "coulomb_viscous", cross: bool = False,
                     start: float = 0.8, starts: int = 3, max_nfev: int | None = None) -> LegFrictionFit:
    """Identify joint friction (and the leg's inertia and mass scale) from a torque run.

    Output-error least squares between the measured joint angles and the exact five-bar
    model simulated under the same torque table (the thesis: fminsearch on Simulink), with
    bounds, a smooth Coulomb term and several starts, the first from an equation-error
    linear regression on differentiated measurements.

    Parameters
    ----------
    run : :class:`leglib.experiments.torque.TorqueRun` with its ``table`` (e.g. from
        :func:`leglib.experiments.torque.friction_experiment`)
    leg : nominal LegParams (geometry, masses, inertias to scale)
    model : "coulomb_viscous" or "stribeck" (adds a Stribeck term per joint)
    cross : also fit the damping matrix's cross terms c12, c21
    start : fit from this time on [s] (after the fade-in, off the stops)
    starts : number of optimizer starts (the equation-error regression's first)
    max_nfev : evaluation budget of each start (default: scipy's, 100 per parameter); a fit
        stopped by it is marked ``converged=False``

    Returns
    -------
    LegFrictionFit
        The fitted parameters with their standard errors, the fit's residuals and whether
        it converged.

    Raises
    ------
    ValueError
        ``model`` is not one of :data:`FRICTION_MODELS`.
    IdentificationError
        The run has no torque table, too few samples after ``start``, or ``starts``,
        ``start``, ``max_nfev`` invalid (named).

    The Coulomb term is c tanh(v / v_smooth); its width v_smooth [rad/s] is fitted too (the
    residual tells it: assuming a width biases the viscous estimate). The simulation is
    driven by the torque the motors actually produced: each value held from the moment it
    was written, through the current loop's known bandwidth.
    """
    if model not in FRICTION_MODELS:
        raise ValueError(f"model must be one of {FRICTION_MODELS}, got {model!r}")
    if getattr(run, "table", None) is None:
        raise IdentificationError("the run has no torque table (play it with leglib.experiments.torque)")
    starts = checks.integer(starts, "fit_leg_friction: starts", IdentificationError, low=1, high=100)
    start = checks.number(start, "fit_leg_friction: start [s]", IdentificationError, low=0.0)
    if max_nfev is not None:
        max_nfev = checks.integer(max_nfev, "fit_leg_friction: max_nfev", IdentificationError, low=1)
    names = ["viscous1", "viscous2", "coulomb1", "coulomb2", "inertia_scale", "mass_scale", "dq1_0", "dq2_0",
             "v_smooth"]
    lo = [0, 0, 0, 0, 0.2, 0.2, -20, -20, 5e-4]
    hi = [2, 2, 2, 2, 5, 5, 20, 20, 0.05]
    if cross:
        names += ["c12", "c21"]
        lo += [-0.5, -0.5]
        hi += [0.5, 0.5]
    if model == "stribeck":
        names += ["stribeck1", "stribeck2", "v_stribeck"]
        lo += [0, 0, 0.005]
        hi += [2, 2, 5]
    lo, hi = np.array(lo, float), np.array(hi, float)
    v_smooth0 = 0.005
    sim = RunSimulator(run, start)
    qm = sim.measured

    def build(p):
        d = dict(zip(names, p))
        lg = leg.scaled(d["inertia_scale"], d["mass_scale"])
        F = [d["viscous1"], d.get("c12", 0.0), d.get("c21", 0.0), d["viscous2"], d["coulomb1"],
             d["coulomb2"], d["v_smooth"]]
        if model == "stribeck":
            F += [d["stribeck1"], d["stribeck2"], d["v_stribeck"]]
        return d, lg, np.array(F)

    def resid(p):
        d, lg, F = build(p)
        r = (sim.simulate(lg, F, (d["dq1_0"], d["dq2_0"])) - qm).ravel()
        return np.where(np.isfinite(r), r, 1.0)  # a run that left the valid region fits badly

    ee = _equation_error_start(run, leg, start, v_smooth0)
    ee["v_smooth"] = v_smooth0
    nominal = {"viscous1": leg.c11, "viscous2": leg.c22, "coulomb1": leg.coulomb1, "coulomb2": leg.coulomb2,
               "inertia_scale": 1.0, "mass_scale": 1.0, "dq1_0": ee["dq1_0"], "dq2_0": ee["dq2_0"],
               "v_smooth": v_smooth0}
    extra = {"c12": 0.0, "c21": 0.0, "stribeck1": 0.005, "stribeck2": 0.005, "v_stribeck": 0.1}
    candidates = [ee, nominal]
    rng = np.random.default_rng(1)
    while len(candidates) < max(starts, 2):
        candidates.append({k: v * math.exp(rng.normal(0, 0.4)) if k[:2] != "dq" else v for k, v in ee.items()})
    # the nominal start matters only when the equation-error start is poor: order by cost
    best = None
    for cand in candidates[:max(starts, 1)]:
        x0 = np.clip([cand.get(n, extra.get(n, 0.0)) for n in names], lo + 1e-9, hi - 1e-9)
        res = least_squares(resid, x0, bounds=(lo, hi), method="trf",
                            x_scale=np.maximum(np.abs(x0), 1e-3), diff_step=1e-6, max_nfev=max_nfev)
        if best is None or res.cost < best.cost:
            best = res
    d, lg, F = build(best.x)
    fitted_leg = lg.replace(c11=d["viscous1"], c12=d.get("c12", 0.0), c21=d.get("c21", 0.0),
                            c22=d["viscous2"], coulomb1=d["coulomb1"], coulomb2=d["coulomb2"])
    q = sim.simulate(lg, F, (d["dq1_0"], d["dq2_0"]))
    r = q - qm
    cov = _covariance(best, r.size)
    se = dict(zip(names, map(float, np.sqrt(np.clip(np.diag(cov), 0, None)))))
    ssr = float(np.sum(r ** 2))
    why = {}
    for k, (name, value) in enumerate(zip(names, best.x)):
        span = hi[k] - lo[k]
        for bound, word in ((lo[k], "lower"), (hi[k], "upper")):
            if abs(value - bound) <= 1e-6 * span and not name.startswith("dq"):
                why[name] = (f"fitted onto its {word} bound {bound:g}: the run does not hold its value (a fit that "
                             f"wants it past what the model allows); vary the torque more where it acts")
    intervals = {name: (math.nan, math.nan) if name in why else _interval90(float(d[name]), se[name], float(low))
                 for name, low in zip(names, lo)}
    return LegFrictionFit(model=model, params={k: float(v) for k, v in d.items()}, stderr=se,
                          intervals=intervals, not_identifiable=why,
                          rms_deg=tuple(float(np.degrees(np.sqrt(np.mean(r[:, j] ** 2)))) for j in (0, 1)),
                          r2=tuple(_r2(qm[:, j], q[:, j]) for j in (0, 1)),
                          aic=_aic(ssr * effective_samples(r) / r.size, effective_samples(r), len(names)),
                          n=int(r.size), n_eff=effective_samples(r), ssr=ssr, leg=fitted_leg, friction=F, start=start, v_smooth=d["v_smooth"],
                          converged=bool(best.status > 0))


def choose_friction_model(plain: LegFrictionFit, stribeck: LegFrictionFit, min_effect: float = 0.2):
    """Pick between a Coulomb + viscous fit and a Stribeck fit of the same data.

    The Stribeck model is chosen only when AIC (common effective n) favours it by more
    than 2 *and* its breakaway terms are material: at least ``min_effect`` of the Coulomb
    friction on some joint (real breakaway friction is typically 20-50 % above Coulomb), and
    its Stribeck velocity must be clearly wider than the Coulomb smoothing width. A
    trajectory fit's residuals carry process noise, and near zero speed a small Stribeck
    term mimics a different Coulomb smoothing width, so small extra terms can win on AIC
    alone. Returns (chosen fit, reason).
    """
    cmp = compare_friction_models({"plain": plain, "stribeck": stribeck})
    delta = cmp["plain"][1] - cmp["stribeck"][1]   # > 0: AIC favours Stribeck
    vs, vc = stribeck.params["v_stribeck"], stribeck.params["v_smooth"]
    if vs < 3 * vc:
        return plain, (f"the Stribeck term acts only within {vs:.3g} rad/s, about the Coulomb smoothing "
                       f"width {vc:.3g} rad/s: it reshapes the friction law at zero speed rather than "
                       f"adding breakaway friction; keep the simpler model")
    effect = max(stribeck.params["stribeck1"] / max(stribeck.params["coulomb1"], 1e-12),
                 stribeck.params["stribeck2"] / max(stribeck.params["coulomb2"], 1e-12))
    if delta > 2 and effect >= min_effect:
        return stribeck, f"AIC favours Stribeck by {delta:.1f} and its terms reach {effect:.0%} of Coulomb"
    if delta > 2:
        return plain, (f"AIC favours Stribeck by {delta:.1f}, but its terms are only {effect:.1%} of "
                       f"Coulomb friction: negligible, keep the simpler model")
    return plain, f"AIC does not favour the Stribeck terms (difference {delta:+.1f})"


def load_identified(path, leg):
    """The identified leg written by notebook 02 (``data/processed/friction_identified.json``):
    returns (LegParams with identified masses, inertias and friction; the kernels' friction
    vector with the identified Coulomb width)."""


    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no identified leg; run notebook 02_friction_fitting first "
                                f"(or design on the nominal leg)")
    try:
        doc = json.loads(p.read_text())
        values = {k: float(v) for k, v in doc["leg"].items()}
        v_smooth = float(doc["friction"]["v_smooth"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{p}: not an identified-leg file ({exc})") from None
    ident = leg.replace(**values)
    return ident, friction_vector(ident, v_smooth=v_smooth)
