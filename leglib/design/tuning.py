"""Prescribed dynamics on any leg in a handful of experiments: :func:`design`.

The map (:class:`leglib.design.gainmap.GainMap`) needs a full sweep; the model-based inverse
(:func:`leglib.design.plantfit.fit_leg_plant`) assumes the leg has the twin's own structure. A real
leg has compliant belts, cogging, a nonlinear encoder and friction no model here holds, so
:func:`design` trusts a model only for *directions* and the device for *values*:

1. **Model.** One axis of the ODrive cascade, linearized (:func:`leglib.model.cascade.axis_closed_loop`:
   position P, velocity PI, first-order current loop, the encoder PLL) on a plant of two
   numbers, the inertia ``J`` and viscous damping ``b`` seen by the motor. Its step is
   mapped to the foot height through the nominal five-bar and identified with the same
   :func:`leglib.identify.step.second_order` as the measurements, so model and device are
   compared in one measure (zeta, fn of the foot height).
2. **Start.** ``J`` from the nominal leg's opening-mode inertia at rest (plus a payload
   guess when given), ``b = 0``; the model is inverted for the target: the first
   experiment's gains.
3. **Iterate.** After every experiment the model's ``J`` and ``b`` are refitted to the
   measured (zeta, fn) of the experiments so far (nearest to the target weighted most),
   the model's remaining error at the experiment nearest the target is carried as a bias
   ("the model is off by this much here"), and the model is inverted for the target
   corrected by that bias. Steps in log-gain space are limited, gains stay inside the
   configuration's bounds, and every experiment is :func:`leglib.experiments.step.step_response`
   with its safety checks. An unstable or unidentifiable step is kept, and the next gains
   go back halfway towards the best identified experiment.
4. **Stop** when an experiment's measured zeta and fn are both within ``tolerance`` of the
   target (that experiment is the final check), or after ``max_experiments``: the result
   then holds the best experiment and says that the target was not reached. The target
   counts as *reached* only when the final check's 90 % intervals of zeta and fn lie within
   the tolerance (:func:`leglib.design.validation.verdict`); where they are wider than the
   tolerance (the response's model error exceeds it) the result says so.

Units: pos_gain [(turn/s)/turn], vel_gain [N*m/(turn/s)], vel_integrator_gain [N*m/turn],
fn [Hz], J [N*m/(turn/s^2)], b [N*m/(turn/s)] at the motor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from .. import checks, plots
from ..device import bench
from ..device.session import as_device, check_gains
from ..errors import ArgumentError, IdentificationError
from ..experiments.step import step_response
from ..identify.step import second_order, standard_errors
from ..model.cascade import axis_closed_loop_matrices, motor_side_inertia
from ..model.drive import AxisMap
from ..model.dynamics import mass_matrix
from ..model.kinematics import foot_position
from ..units import interval_text
from .points import identify_response
from .validation import relative_intervals, verdict

#: default relative error in zeta and fn at which a design stops
TOLERANCE = 0.02
#: largest change of log(pos_gain) or log(vel_gain) between two experiments
MAX_LOG_STEP = 1.0


# ---------------------------------------------------------------------------------------
# the model: one linearized cascade axis, its step exactly discretized
# ---------------------------------------------------------------------------------------

def _expm(M: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring of a degree-12 Taylor series (||M|| / 2^s
    below 1/2: truncation error under 1e-16 relative); for the small matrices here it is
    several times cheaper than scipy.linalg.expm's general Pade path."""
    norm = float(np.max(np.sum(np.abs(M), axis=1)))
    s = max(0, int(math.ceil(math.log2(norm / 0.5)))) if norm > 0.5 else 0
    X = M / (2.0 ** s)
    n = M.shape[0]
    E = np.eye(n)
    term = np.eye(n)
    for k in range(1, 13):
        term = term @ X / k
        E = E + term
    for _ in range(s):
        E = E @ E
    return E


def lti_step(A: np.ndarray, B: np.ndarray, C: np.ndarray, n: int, dt: float, u: float = 1.0) -> np.ndarray:
    """Exact samples y[k] = C x(k dt), k = 0..n-1, of dx/dt = A x + B u from x(0) = 0 with a
    constant input ``u`` (zero-order hold is exact for a step). The affine recurrence
    x[k+1] = Phi x[k] + Gamma u is unrolled by doubling (log2 n matrix products), so it
    costs little more than one matrix exponential."""
    ns = A.shape[0]
    M = np.zeros((ns + 1, ns + 1))
    M[:ns, :ns] = A * dt
    M[:ns, ns] = B[:, 0] * dt
    E = _expm(M)
    phi, gam = E[:ns, :ns], E[:ns, ns] * u
    X = np.zeros((1, ns))            # x[0] = 0
    P = phi.copy()                   # Phi^m for the current block length m
    S = gam.copy()                   # sum_{i<m} Phi^i Gamma
    while X.shape[0] < n:
        X = np.vstack([X, X @ P.T + S])
        S = P @ S + S
        P = P @ P
    return X[:n] @ C[0]


@dataclass
class AxisModel:
    """The cascade model :func:`design` works with: motor-side inertia ``J`` and viscous
    damping ``b``, the ODrive's torque constant and bandwidths, the nominal leg (foot
    height from the motor angles) and the experiment's step, duration and sampling."""

    J: float
    b: float
    torque_constant: float
    current_bandwidth: float
    encoder_bandwidth: float
    leg: object
    step: float = 0.4
    duration: float = 1.5
    sample_period: float = 0.002

    def foot_response(self, gains) -> tuple[np.ndarray, np.ndarray]:
        """(t [s], foot height [m]) of the model's step with ``gains``; raises
        ValueError when the closed loop is unstable."""
        A, B, C = axis_closed_loop_matrices(self.J, self.torque_constant, *gains, self.current_bandwidth,
                                            self.encoder_bandwidth, self.b)
        if np.max(np.linalg.eigvals(A).real) >= 0:
            raise ValueError("the model's closed loop is unstable at these gains")
        n = int(round(self.duration / self.sample_period))
        t = np.arange(n) * self.sample_period
        theta = lti_step(A, B, C, n, self.sample_period, self.step)
        ax = AxisMap.from_leg(self.leg)
        _, y = foot_position(self.leg, ax.joint_angle(theta, 0), ax.joint_angle(-theta, 1))
        return t, y

    def predict(self, gains) -> tuple[float, float]:
        """(zeta, fn [Hz]) of the model's foot-height step (NaN when unstable or not
        identifiable)."""
        try:
            t, y = self.foot_response(gains)
            f = second_order(t, y)
        except (ValueError, IdentificationError):
            return math.nan, math.nan
        return f.zeta, f.fn


def nominal_model(dev, payload_mass: float = 0.0, step: float = 0.4, duration: float = 1.5,
                  sample_period: float = 0.002) -> AxisModel:
    """The starting model of a device: its nominal leg's opening-mode inertia at rest (with a
    guessed foot payload [kg]) seen at the motor, no damping, the configured ODrive."""
    leg = dev.leg.scaled(1.0, 1.0, payload_mass) if payload_mass else dev.leg
    D = mass_matrix(leg, *leg.q0)
    ax = AxisMap.from_leg(dev.leg)
    J = motor_side_inertia(float(D[0, 0] - D[0, 1]), ax.gear_ratio)
    cfg = dev.config
    return AxisModel(J=J, b=0.0, torque_constant=cfg.torque_constant,
                     current_bandwidth=cfg.current_control_bandwidth, encoder_bandwidth=cfg.encoder_bandwidth,
                     leg=dev.leg, step=step, duration=duration, sample_period=sample_period)


def _log_err(measured, target) -> np.ndarray:
    return np.log(np.asarray(measured, float)) - np.log(np.asarray(target, float))


def fit_model(model: AxisModel, gains, measured, weights=None) -> AxisModel:
    """Refit ``J`` and ``b`` of ``model`` so that its (zeta, fn) at each of ``gains`` match
    ``measured`` (least squares of the log errors, ``weights`` per experiment). Returns a
    new model; the old one is the starting point."""
    gains = [tuple(g) for g in gains]
    meas = np.asarray(measured, float)
    w = np.ones(len(gains)) if weights is None else np.asarray(weights, float)

    def make(x):
        return AxisModel(**{**model.__dict__, "J": math.exp(x[0]), "b": x[1] * math.exp(x[0])})

    def resid(x):
        m = make(x)
        out = []
        for g, z, wi in zip(gains, meas, w):
            p = m.predict(g)
            out.extend(wi * (_log_err(p, z) if np.all(np.isfinite(p)) else np.full(2, 3.0)))
        return np.array(out)

    # b is scaled by J in the unknowns so that both are of the same order
    x0 = [math.log(model.J), model.b / model.J]
    res = least_squares(resid, x0, bounds=([x0[0] - 4.0, -200.0], [x0[0] + 4.0, 2000.0]), diff_step=1e-3,
                        max_nfev=60)
    return make(res.x)


def invert(model: AxisModel, target, vel_integrator_gain: float, bounds, start=None,
           bias=(0.0, 0.0)) -> tuple[tuple, tuple]:
    """Gains with which ``model`` (plus a log ``bias``) gives ``target`` (zeta, fn [Hz]):
    log(pos_gain), log(vel_gain) solved within ``bounds`` ((lo, hi) of each), from the
    analytic PD answer (wn^2 = Kv Kp / J, 2 zeta wn J = Kv + b) or ``start``. Returns
    (gains, the model's own (zeta, fn) there)."""
    zeta, fn = target
    lo = np.log([bounds[0][0], bounds[1][0]])
    hi = np.log([bounds[0][1], bounds[1][1]])
    bias = np.asarray(bias, float)
    if start is None:
        wn = 2 * math.pi * fn
        kv = max(2 * zeta * wn * model.J - model.b, 1e-4)
        start = (wn ** 2 * model.J / kv, kv)
    x0 = np.clip(np.log(start[:2]), lo + 1e-6, hi - 1e-6)

    def resid(x):
        p = model.predict((math.exp(x[0]), math.exp(x[1]), vel_integrator_gain))
        if not np.all(np.isfinite(p)):
            return np.array([3.0, 3.0])
        return _log_err(p, target) + bias

    best = None
    for d in ([0.0, 0.0], [0.0, -0.5], [0.0, 0.5], [0.5, 0.0]):
        res = least_squares(resid, np.clip(x0 + d, lo + 1e-6, hi - 1e-6), bounds=(lo, hi), diff_step=1e-3,
                            max_nfev=50)
        if best is None or res.cost < best.cost:
            best = res
        if np.max(np.abs(best.fun)) < 0.002:
            break
    gains = (math.exp(best.x[0]), math.exp(best.x[1]), vel_integrator_gain)
    return gains, model.predict(gains)


# ---------------------------------------------------------------------------------------
# the design loop
# ---------------------------------------------------------------------------------------

@dataclass
class Experiment:
    """One step :func:`design` ran: its gains, why it ran (``role``), the model's prediction
    for it, the response and its identification (:class:`leglib.design.points.PointResult`)."""

    gains: tuple
    role: str
    predicted: tuple
    response: object = field(repr=False)
    result: object = field(repr=False)

    @property
    def ok(self) -> bool:
        return self.result.status == "ok"

    @property
    def measured(self) -> tuple:
        return (self.result.zeta, self.result.fn) if self.ok else (math.nan, math.nan)

    @property
    def uncertainty(self) -> tuple:
        """Standard errors (zeta, fn [Hz]) of the measured values
        (:func:`leglib.identify.step.standard_errors`); NaN when the step was not identified."""
        if not self.ok or self.result.fit is None:
            return (math.nan, math.nan)
        se = standard_errors(self.result.fit, self.response.t, self.response.y)
        return (se["zeta"], se["fn"])

    @property
    def intervals(self) -> tuple:
        """90 % intervals ((zeta low, high), (fn low, high) [Hz]) of the measured values
        (NaN when the step was not identified)."""
        return (self.result.zeta_interval, self.result.fn_interval)


@dataclass
class Tuning:
    """What :func:`design` found.

    ``gains`` (pos_gain, vel_gain, vel_integrator_gain) of the final check, ``predicted``
    the final model's (zeta, fn [Hz]) for them, ``measured`` the final check's identified
    (zeta, fn) and ``uncertainty`` their standard errors, ``intervals`` their 90 % intervals,
    ``experiments`` every step run (the final check last), ``reached`` whether the measured
    values' intervals lie within ``tolerance`` of ``target`` (``verdict`` says why or why
    not); ``model`` the final :class:`AxisModel`."""

    target: tuple
    gains: tuple
    predicted: tuple
    measured: tuple
    experiments: list
    reached: bool
    tolerance: float
    model: AxisModel = field(repr=False)
    message: str = ""
    verdict: str = ""
    #: what the design did on the leg and its bench time (:class:`leglib.device.bench.BenchReport`;
    #: on the twin: what it would take on the leg)
    bench: object = field(default=None, repr=False)

    def _final(self):
        return next((e for e in reversed(self.experiments) if e.gains == self.gains), None)

    @property
    def uncertainty(self) -> tuple:
        """Standard errors (zeta, fn [Hz]) of ``measured`` (the final check's fit)."""
        final = self._final()
        return final.uncertainty if final is not None else (math.nan, math.nan)

    @property
    def intervals(self) -> tuple:
        """90 % intervals ((zeta low, high), (fn low, high) [Hz]) of ``measured``."""
        final = self._final()
        nan = (math.nan, math.nan)
        return final.intervals if final is not None else (nan, nan)

    @property
    def error(self) -> tuple:
        """Relative errors (zeta, fn) of the measured values against the target."""
        return tuple(float(m / t - 1) for m, t in zip(self.measured, self.target))

    @property
    def error_interval(self) -> tuple:
        """90 % intervals ((zeta low, high), (fn low, high)) of :attr:`error`: the final check's
        intervals relative to the target (:func:`leglib.design.validation.relative_intervals`;
        NaN when it was not identified)."""
        return relative_intervals(self.intervals, self.target)

    @property
    def model_error(self) -> tuple:
        """Relative errors (zeta, fn) of the model's prediction against the measurement:
        how wrong the model alone would have been."""
        return tuple(float(p / m - 1) for p, m in zip(self.predicted, self.measured))

    def table(self) -> str:
        """One line per experiment: role, gains, the model's predicted (zeta, fn) and the
        measured ones with their 90 % intervals (or the step's status)."""
        rows = [f"{'#':>2} {'role':14s} {'pos_gain':>9s} {'vel_gain':>9s} {'vel_int':>8s} "
                f"{'pred zeta':>9s} {'pred fn':>8s}  measured zeta, fn [Hz] (90 % intervals)"]
        for i, e in enumerate(self.experiments, 1):
            meas = e.result.text() if e.ok else e.result.status
            rows.append(f"{i:2d} {e.role:14s} {e.gains[0]:9.3f} {e.gains[1]:9.4f} {e.gains[2]:8.4f} "
                        f"{e.predicted[0]:9.3f} {e.predicted[1]:8.2f}  {meas}")
        return "\n".join(rows)

    def __str__(self) -> str:
        ez, ef = self.error
        zi, fi = self.intervals
        head = (f"target zeta {self.target[0]:.3g}, fn {self.target[1]:.3g} Hz: "
                f"{'reached' if self.reached else 'NOT reached'} in {len(self.experiments)} experiments; "
                f"gains ({', '.join(f'{g:.4g}' for g in self.gains)}), measured zeta "
                f"{interval_text(self.measured[0], zi)} ({ez:+.1%}), fn {interval_text(self.measured[1], fi)} Hz "
                f"({ef:+.1%}) (90 % intervals)")
        return head + "".join(f"\n{m}" for m in (self.verdict, self.message) if m)

    def _repr_markdown_(self) -> str:
        rows = ["| # | role | gains (pos, vel, vel_int) | predicted (ζ, fn [Hz]) | measured [90 % interval] |",
                "|---|---|---|---|---|"]
        for i, e in enumerate(self.experiments, 1):
            meas = e.result.text() if e.ok else e.result.status
            rows.append(f"| {i} | {e.role} | ({e.gains[0]:.3f}, {e.gains[1]:.4f}, {e.gains[2]:.4f}) | "
                        f"({e.predicted[0]:.3f}, {e.predicted[1]:.2f}) | {meas} |")
        return str(self).replace("\n", "\n\n") + "\n\n" + "\n".join(rows)

    def plot(self, ax=None):
        """Every experiment in the (zeta, fn) plane, the model's predictions and the target
        (:func:`leglib.plots.plot_design_path`)."""
        return plots.plot_design_path(self, ax=ax)


# the heaviest foot payload a starting model is made for (the plants' own bound, kg)
MAX_PAYLOAD_GUESS = 5.0


def _check_arguments(zeta, fn, max_experiments, tolerance, payload_guess, start, progress, on_experiment):
    """Every argument of :func:`tune` that needs no device, checked before the first step."""
    for name, v in (("zeta", zeta), ("fn", fn), ("tolerance", tolerance)):
        checks.number(v, f"tune: {name}", ArgumentError, low=0.0, low_open=True)
    checks.integer(max_experiments, "tune: max_experiments", ArgumentError, low=1)
    payload_guess = checks.number(payload_guess, "tune: payload_guess [kg]", ArgumentError, low=0.0,
                                  high=MAX_PAYLOAD_GUESS)
    if start is not None:
        if isinstance(start, (str, bytes)) or not hasattr(start, "__len__") or len(start) != 2:
            raise ArgumentError(f"tune: start must be the two gains (pos_gain, vel_gain) of the first experiment, "
                             f"got {start!r}")
        start = tuple(checks.number(g, f"tune: start[{i}] ({name})", ArgumentError, low=0.0, low_open=True)
                      for i, (g, name) in enumerate(zip(start, ("pos_gain", "vel_gain"))))
    checks.boolean(progress, "tune: progress", ValueError)
    if on_experiment is not None and not callable(on_experiment):
        raise ArgumentError(f"tune: on_experiment must be callable (called with each Experiment) or None, "
                         f"got {on_experiment!r}")
    return payload_guess, start


def tune(odrv, zeta: float, fn: float, max_experiments: int = 10, *, vel_integrator_gain: float = 0.01,
           tolerance: float = TOLERANCE, payload_guess: float = 0.0, step: float = 0.4,
           duration: float = 1.5, sample_period: float = 0.002, start=None, progress: bool = False,
           on_experiment=None, max_minutes: float | None = None) -> Tuning:
    """Gains that give the leg on ``odrv`` the step dynamics (``zeta``, ``fn`` [Hz]) of its
    foot height, found with at most ``max_experiments`` step responses on the device.

    Parameters
    ----------
    odrv : a connected, configured and calibrated ODrive (:func:`leglib.device.session.connect`;
        virtual or USB)
    zeta, fn : the target, in the measure of :func:`leglib.identify.step.second_order` ("fit")
        on the foot height
    max_experiments : the budget of step responses, the final check included
    vel_integrator_gain : kept fixed [N*m/turn]; pos_gain and vel_gain are designed
    tolerance : relative error in zeta and fn at which the design stops
    payload_guess : foot payload [kg] for the starting model (the loop corrects a wrong guess),
        in [0, :data:`MAX_PAYLOAD_GUESS`]
    step, duration, sample_period : the step experiment (:func:`leglib.experiments.step.step_response`)
    start : gains (pos_gain, vel_gain) of the first experiment instead of the model's, within
        the configuration's maxima
    progress : print one line per experiment
    on_experiment : called as ``on_experiment(experiment)`` after each step (None: not called)
    max_minutes : on a real leg, the longest the design may take [min] (default
        :data:`leglib.device.bench.DEFAULT_MAX_BENCH_MINUTES`): refused before the first step
        (:class:`leglib.errors.BenchLimitError`, giving the estimate) when ``max_experiments``
        steps would take longer; on the twin nothing is refused

    Every argument is checked before the first step runs on the device (:class:`leglib.errors.ArgumentError`, a ValueError, naming it).

    Returns
    -------
    :class:`Tuning`; ``reached`` is False (and ``message`` says why) when the budget ran out
    first, and then ``gains`` are the best experiment's; ``bench`` says what it did on the
    leg and its bench time (on the twin: what it would take on the leg).
    """

    payload_guess, start = _check_arguments(zeta, fn, max_experiments, tolerance, payload_guess, start, progress,
                                            on_experiment)
    dev = as_device(odrv)
    cfg = dev.config
    check_gains(cfg, 1.0, 1e-3, vel_integrator_gain)
    if start is not None:
        check_gains(cfg, start[0], start[1], vel_integrator_gain)
    target = (float(zeta), float(fn))
    bounds = ((0.5, float(cfg.max_pos_gain)), (1e-3, float(cfg.max_vel_gain)))
    bench.require(dev, max_experiments * bench.step_seconds(duration, bench.STEP_SETTLE, sample_period), max_minutes,
                  f"tune: up to {max_experiments} steps")
    model = nominal_model(dev, payload_guess, step, duration, sample_period)
    experiments: list[Experiment] = []
    since = bench.mark(dev)

    def run(gains, role, predicted):
        resp = step_response(dev, *gains, step=step, duration=duration, sample_period=sample_period)
        e = Experiment(tuple(float(g) for g in gains), role, tuple(map(float, predicted)), resp,
                       identify_response(resp, dev.leg))
        experiments.append(e)
        if progress:
            print(f"  experiment {len(experiments)}/{max_experiments} ({role}): gains "
                  f"({gains[0]:.3f}, {gains[1]:.4f}, {gains[2]:.4f}) -> "
                  + (f"{e.result.text()} (90 % intervals)" if e.ok else e.result.status), flush=True)
        if on_experiment is not None:
            on_experiment(e)
        return e

    def within(e):
        return e.ok and np.all(np.abs(np.asarray(e.measured) / np.asarray(target) - 1) <= tolerance)

    def distance(e):
        return float(np.max(np.abs(_log_err(e.measured, target)))) if e.ok else math.inf

    if start is not None:
        g0 = (float(start[0]), float(start[1]), vel_integrator_gain)
        p0 = model.predict(g0)
    else:
        g0, p0 = invert(model, target, vel_integrator_gain, bounds)
    e = run(g0, "model start", p0)
    while not within(e) and len(experiments) < max_experiments:
        good = [x for x in experiments if x.ok]
        if not good:
            # nothing identified yet: a gentler, better damped try (more vel_gain, less pos_gain)
            g = experiments[-1].gains
            nxt = (max(g[0] * 0.6, bounds[0][0]), min(g[1] * 1.5, bounds[1][1]), vel_integrator_gain)
            e = run(nxt, "back off", (math.nan, math.nan))
            continue
        best = min(good, key=distance)
        # refit the model on the identified experiments, those near the target weighted most
        d = np.array([distance(x) for x in good])
        model = fit_model(model, [x.gains for x in good], [x.measured for x in good], weights=1.0 / (0.05 + d))
        bias = _log_err(best.measured, model.predict(best.gains))
        if not np.all(np.isfinite(bias)):
            bias = np.zeros(2)
        gains, pred = invert(model, target, vel_integrator_gain, bounds, start=best.gains[:2], bias=bias)
        # a limited step from the best experiment
        dx = np.log(gains[:2]) - np.log(best.gains[:2])
        dx = np.clip(dx, -MAX_LOG_STEP, MAX_LOG_STEP)
        if not experiments[-1].ok:
            dx = 0.5 * (np.log(experiments[-1].gains[:2]) - np.log(best.gains[:2]))  # halfway back
        nxt = tuple(float(v) for v in np.exp(np.log(best.gains[:2]) + dx)) + (vel_integrator_gain,)
        nxt = (min(max(nxt[0], bounds[0][0]), bounds[0][1]), min(max(nxt[1], bounds[1][0]), bounds[1][1]), nxt[2])
        e = run(nxt, "correction", model.predict(nxt))
    good = [x for x in experiments if x.ok]
    final = e if within(e) else (min(good, key=distance) if good else experiments[-1])
    # reached only when the final check's intervals allow it, not its point values alone
    reached, why = verdict(*final.intervals, target, tolerance) if final.ok else (False, "")
    message = "" if within(final) else (
        f"the target was not reached within {max_experiments} experiments (tolerance {tolerance:.0%}); the gains "
        f"are the best experiment's" + ("" if good else "; no experiment could be identified"))
    pred = model.predict(final.gains)
    return Tuning(target=target, gains=final.gains, predicted=pred, measured=final.measured,
                  experiments=experiments, reached=reached, tolerance=tolerance, model=model, message=message,
                  verdict=why, bench=bench.report(since, dev))
