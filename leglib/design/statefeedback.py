"""State feedback by pole placement with a Luenberger observer (thesis 5.4-5.5, Listing 7.5).

:func:`design` places the closed-loop poles (python-control's ``place``, MIMO), the
observer poles ``observer_factor`` times faster, and computes the setpoint gain Nbar of
Listing 7.5; optional integral action (``integral_poles``) removes the steady-state error
that friction leaves. :class:`Controller` is the discrete-time law (exact ZOH observer at
the controller period) used both by :func:`simulate_closed_loop` -- the nonlinear leg with
quantized angles and torque limits, which produces the thesis's torque table -- and by the
live loop on the device (:func:`leglib.experiments.torque.torque_loop`).

Deviation coordinates: x = (q1, dq1, q2, dq2) - (q1_0, 0, q2_0, 0), u = tau - tau_0.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import control
import numpy as np
from scipy.linalg import expm

from .. import checks, plots
from .. import model as M
from ..device.session import as_device
from ..errors import ArgumentError, PoleError
from ..experiments.torque import torque_loop
from ..params import LegParams
from ..units import derived, pretty, significant

THESIS_POLES = (-7.0, -7.007, -7.014, -7.021)

# the linear model's quantities (leglib.model.linear.linearize): states x = (q1, dq1, q2, dq2),
# inputs u = (tau1, tau2), outputs y = (q1, q2); every gain's unit follows from them
STATE_UNITS = {"q1": "rad", "dq1": "rad/s", "q2": "rad", "dq2": "rad/s"}
INPUTS, INPUT_UNIT = ("tau1", "tau2"), "N*m"
OUTPUTS, OUTPUT_UNIT = ("q1", "q2"), "rad"


def model_units() -> dict:
    """The unit of every entry of the linear model's A and B (x' = A x + B u), from its
    quantities: A[i, j] is state i's rate per state j (1/s, 1/s², or - where a velocity is an
    angle's rate), B[i, j] state i's rate per joint torque (rad/(N·m·s²) on a velocity's row,
    1/kg m² in SI). Returns {"A": rows, "B": rows} of unit strings."""
    states = list(STATE_UNITS.values())
    return {"A": [[derived(s, x, "s") for x in states] for s in states],
            "B": [[derived(s, INPUT_UNIT, "s") for _ in INPUTS] for s in states]}


def gain_units() -> dict:
    """The unit of every entry of K, L, Nbar and Ki, derived from the model's quantities
    (:data:`STATE_UNITS`): u = -K x, so K[i, j] is N·m per state j (N·m/rad on an angle,
    N·m·s/rad on a velocity); the observer adds L (y - C x̂) to dx̂/dt, so L[i, j] is state i's
    rate per output angle (1/s on an angle's row, 1/s² on a velocity's); u = Nbar r with r an
    angle, N·m/rad; u = -Ki z with z = ∫(y - r) dt, N·m/(rad·s). Returns {name: list of rows
    of unit strings}."""
    states = list(STATE_UNITS.values())
    return {"K": [[derived(INPUT_UNIT, s) for s in states] for _ in INPUTS],
            "L": [[derived(s, OUTPUT_UNIT, "s") for _ in OUTPUTS] for s in states],
            "Nbar": [[derived(INPUT_UNIT, OUTPUT_UNIT) for _ in OUTPUTS] for _ in INPUTS],
            "Ki": [[derived(INPUT_UNIT, OUTPUT_UNIT + "*s") for _ in OUTPUTS] for _ in INPUTS]}

# the longest closed loop :func:`simulate_closed_loop` runs (the thesis's is 4.5 s), and the
# most controller samples: it steps the nonlinear leg in Python, about 1 ms a sample
MAX_DURATION = 600.0   # s
MAX_SAMPLES = 300_000




def check_poles(poles, n: int, rank_b: int, what: str = "poles") -> np.ndarray:
    """Validate requested poles: count, stability, conjugate pairs, multiplicity.

    python-control's ``place`` (scipy's YT algorithm) cannot place a pole repeated more
    than rank(B) times; the thesis spread its poles (-7, -7.007, ...) for that reason.
    """
    a = np.asarray(poles) if not isinstance(poles, (str, bytes)) else np.asarray([poles])
    if a.dtype.kind not in "iufc" or isinstance(poles, (bool, np.bool_)):
        raise PoleError(f"{what}: must be numbers (real or complex), got {poles!r}")
    if a.ndim != 1:
        raise PoleError(f"{what}: must be a flat sequence of {n} poles, got an array of shape {a.shape}")
    p = a.astype(complex)
    if p.size != n:
        raise PoleError(f"{what}: {p.size} given, the system has {n} states")
    if not np.all(np.isfinite(p)):
        raise PoleError(f"{what}: must be finite, got {p}")
    if np.any(p.real >= 0):
        raise PoleError(f"{what}: {p[p.real >= 0]} not in the open left half plane: the closed "
                        f"loop would be unstable")
    cplx = p[np.abs(p.imag) > 1e-12]
    for z in cplx:
        if np.sum(np.isclose(cplx, np.conj(z), rtol=1e-9, atol=1e-12)) != np.sum(np.isclose(cplx, z, rtol=1e-9, atol=1e-12)):
            raise PoleError(f"{what}: complex pole {z} has no conjugate partner")
        if np.sum(cplx == np.conj(z)) != np.sum(cplx == z):
            near = cplx[np.isclose(cplx, np.conj(z), rtol=1e-9, atol=1e-12)][0]
            raise PoleError(f"{what}: complex poles {z} and {near} are conjugates only to within rounding; "
                            f"give an exact pair (a + bj, a - bj): place() needs exact conjugates")
    for z in np.unique(np.round(p, 9)):
        mult = int(np.sum(np.isclose(p, z, rtol=1e-9, atol=1e-12)))
        if mult > rank_b:
            raise PoleError(f"{what}: {z} is repeated {mult} times but rank(B) = {rank_b}; place "
                            f"cannot do that. Spread them (the thesis used -7, -7.007, -7.014, -7.021), "
                            f"e.g. with leglib.design.statefeedback.spread_poles")
    return np.where(np.abs(p.imag) > 1e-12, p, p.real)


def parse_poles(text: str) -> np.ndarray:
    """Poles from a string such as "-7, -7.007, -7.014, -7.021" or "-3+4j, -3-4j, -10, -11"."""
    if not isinstance(text, str) or not text.strip():
        raise PoleError(f"poles must be a non-empty comma-separated string, got {text!r}")
    out = []
    for part in text.split(","):
        try:
            out.append(complex(part.strip().replace(" ", "")))
        except ValueError:
            raise PoleError(f"cannot read pole {part.strip()!r} in {text!r}") from None
    p = np.array(out)
    if not np.all(np.isfinite(p)):
        raise PoleError(f"poles must be finite numbers, got {', '.join(str(z) for z in p[~np.isfinite(p)])} "
                        f"in {text!r}")
    return p.real if np.all(p.imag == 0) else p


def spread_poles(center: float, count: int = 4, spread: float = 0.007) -> np.ndarray:
    """``count`` real poles at center, center - spread, ... (the thesis's -7 ... -7.021)."""
    return center - spread * np.arange(count) * np.sign(-center)


def dominant_pair_poles(wn: float, zeta: float, fast_factor: float = 3.0, spread: float = 0.007) -> np.ndarray:
    """Four poles: a dominant pair with natural frequency ``wn`` [rad/s] and damping
    ``zeta`` (real and spread when zeta >= 1), and two real poles ``fast_factor`` times
    further left. Used by the notebook's sliders."""
    if zeta < 1:
        wd = wn * math.sqrt(1 - zeta ** 2)
        pair = [complex(-zeta * wn, wd), complex(-zeta * wn, -wd)]
    else:
        r = wn * math.sqrt(zeta ** 2 - 1)
        pair = [-zeta * wn + r, -zeta * wn - r]
        if abs(pair[0] - pair[1]) < spread:
            pair[1] = pair[0] - spread
    fast = -fast_factor * zeta * wn if zeta < 1 else fast_factor * min(pair)
    return np.array(pair + [fast, fast - spread], dtype=complex)


@dataclass
class StateFeedback:
    """A state-feedback design on the linear model ``sys``.

    K (2, 4), L (4, 2), Nbar (2, 2) as in Listing 7.5; Ki (2, 2) integral gains or None;
    poles and observer_poles requested; ranks of the controllability and observability
    matrices.
    """

    sys: control.StateSpace
    poles: np.ndarray
    observer_poles: np.ndarray
    K: np.ndarray
    L: np.ndarray
    Nbar: np.ndarray
    Ki: np.ndarray | None
    controllability_rank: int
    observability_rank: int
    integral_poles: np.ndarray | None = None

    @property
    def controllable(self) -> bool:
        return self.controllability_rank == self.sys.nstates

    @property
    def observable(self) -> bool:
        return self.observability_rank == self.sys.nstates

    def gains_markdown(self, sig: int = 4) -> str:
        """K, L, Nbar (and Ki) as Markdown tables, every entry with its unit (:func:`gain_units`),
        to ``sig`` significant digits: K and Nbar by input row and state / reference column,
        L by state row and output column."""
        units = gain_units()

        def table(name, matrix, rows, cols, what):
            m = np.atleast_2d(np.asarray(matrix, dtype=float))
            u = units[name]
            same_col = all(len({r[j] for r in u}) == 1 for j in range(m.shape[1]))
            head = [f"{c} [{pretty(u[0][j])}]" if same_col else c for j, c in enumerate(cols)]
            out = [f"**{name}** ({what})", "", "| | " + " | ".join(head) + " |" + ("" if same_col else " unit |"),
                   "|---|" + "---|" * (len(cols) + (0 if same_col else 1))]
            for i, r in enumerate(rows):
                cells = " | ".join(significant(v, sig) for v in m[i])
                out.append(f"| {r} | {cells} |" + ("" if same_col else f" {pretty(u[i][0])} |"))
            return "\n".join(out)

        states = list(STATE_UNITS)
        parts = [table("K", self.K, INPUTS, states, "u = −K x̂"),
                 table("L", self.L, states, [f"{o} error" for o in OUTPUTS], "observer: dx̂/dt += L (y − C x̂)"),
                 table("Nbar", self.Nbar, INPUTS, [f"r {o}" for o in OUTPUTS], "u = Nbar r")]
        if self.Ki is not None:
            parts.append(table("Ki", self.Ki, INPUTS, [f"∫({o} − r) dt" for o in OUTPUTS], "u −= Ki z"))
        return "\n\n".join(parts)

    def _repr_markdown_(self) -> str:
        fmt = (lambda z: f"{z.real:.4g}" if abs(z.imag) < 1e-12 else f"{z.real:.4g}{z.imag:+.4g}j")
        rows = ["| | |", "|---|---|",
                f"| poles [1/s] | {', '.join(fmt(complex(p)) for p in self.poles)} |",
                f"| observer poles [1/s] | {', '.join(fmt(complex(p)) for p in self.observer_poles)} |"]
        return "**State feedback by pole placement**\n\n" + "\n".join(rows) + "\n\n" + self.gains_markdown()

    def plot(self, ax=None):
        """The placed and observer poles and the model's open-loop poles
        (:func:`leglib.plots.plot_pole_map`)."""
        return plots.plot_pole_map(self, ax=ax)

    def closed_loop(self) -> control.StateSpace:
        """Linear closed loop with full state feedback, reference r (2) -> y (2):
        x' = (A - BK) x + B Nbar r (no integrator)."""
        A, B, C = self.sys.A, self.sys.B, self.sys.C
        return control.ss(A - B @ self.K, B @ self.Nbar, C, np.zeros((C.shape[0], B.shape[1])))

    def predicted_step(self, r, t) -> np.ndarray:
        """Predicted outputs (N, 2) [rad] of the linear closed loop for a constant reference
        deviation ``r`` (2,) [rad]."""
        t = np.asarray(t, dtype=float)
        resp = control.forced_response(self.closed_loop(), t, np.tile(np.asarray(r, float)[:, None], t.size))
        return resp.outputs.T


def place_poles(sys: control.StateSpace, poles=THESIS_POLES, observer_factor: float = 6.0,
           integral_poles=None) -> StateFeedback:
    """Pole placement with observer.

    Parameters
    ----------
    sys : linear model (e.g. :func:`leglib.model.linear.linearize`), 4 states, 2 inputs, 2 outputs
    poles : closed-loop poles (4) [1/s]; repeated at most rank(B) = 2 times
    observer_factor : observer poles = factor * poles (the thesis: 6)
    integral_poles : None, or 2 poles for integrators of the output error (augmented
        design; the state poles then are ``poles`` and the integrators' these)

    Returns
    -------
    StateFeedback
        ``K`` (2, 4), ``L`` (4, 2), ``Nbar`` (2, 2), ``Ki`` (2, 2) or None, the poles placed
        and the observer's.

    Raises
    ------
    PoleError
        The wrong number of poles, unstable poles, an unpaired complex pole, a multiplicity
        place cannot handle, or a non-positive ``observer_factor``.
    ArgumentError
        A model holding NaN or inf, or whose B is zero.
    ValueError
        The system is not controllable or not observable.
    """
    A, B, C = np.asarray(sys.A), np.asarray(sys.B), np.asarray(sys.C)
    for name, mat in (("A", A), ("B", B), ("C", C), ("D", np.asarray(sys.D))):
        if not np.all(np.isfinite(mat)):
            raise ArgumentError(f"place_poles: the linear model's {name} holds NaN or inf: no design from it "
                             f"(check the linearization's parameters)")
    n, m = B.shape
    observer_factor = checks.number(observer_factor, "observer_factor", PoleError, low=0.0, low_open=True)
    if not np.any(B):
        raise ArgumentError("place_poles: the linear model's B is zero: the inputs do not act on the states, "
                         "no gain can move its poles")
    rank_b = int(np.linalg.matrix_rank(B))
    p = check_poles(poles, n, rank_b)
    po = check_poles(observer_factor * p, n, int(np.linalg.matrix_rank(C)), "observer poles")
    ctrb = int(np.linalg.matrix_rank(control.ctrb(A, B)))
    obsv = int(np.linalg.matrix_rank(control.obsv(A, C)))
    if ctrb < n:
        raise ValueError(f"the system is not controllable (rank {ctrb} < {n}): poles cannot be placed")
    if obsv < n:
        raise ValueError(f"the system is not observable from {C.shape[0]} outputs (rank {obsv} < {n})")
    Ki = None
    pi = None
    if integral_poles is None:
        K = _place(A, B, p, "controller")
    else:
        pi = check_poles(integral_poles, C.shape[0], rank_b, "integral poles")
        # augmented state (x, z), z' = y - r: u = -K x - Ki z
        Aa = np.block([[A, np.zeros((n, C.shape[0]))], [C, np.zeros((C.shape[0], C.shape[0]))]])
        Ba = np.vstack([B, np.zeros((C.shape[0], m))])
        allp = check_poles(np.concatenate([p, pi]), n + C.shape[0], rank_b, "poles with integrators")
        Ka = _place(Aa, Ba, allp, "controller with integrators")
        K, Ki = Ka[:, :n], Ka[:, n:]
    L = _place(A.T, C.T, po, "observer").T
    # setpoint gain of Listing 7.5: Nbar = inv(-C (A - BK)^-1 B + D)
    Nbar = np.linalg.inv(-C @ np.linalg.inv(A - B @ K) @ B + np.asarray(sys.D))
    return StateFeedback(sys=sys, poles=p, observer_poles=po, K=K, L=L, Nbar=Nbar, Ki=Ki,
                  controllability_rank=ctrb, observability_rank=obsv, integral_poles=pi)


def placement_error(A, B, K, poles) -> float:
    """Largest distance between the eigenvalues of A - B K and ``poles``, each matched to its
    nearest, relative to the pole's size (at least 1/s)."""
    achieved = np.linalg.eigvals(np.asarray(A) - np.asarray(B) @ np.asarray(K))
    wanted = np.asarray(poles, dtype=complex)
    from scipy.optimize import linear_sum_assignment  # load time: scipy.optimize, only for a design
    cost = np.abs(achieved[:, None] - wanted[None, :])
    rows, cols = linear_sum_assignment(cost)
    return float(np.max(cost[rows, cols] / np.maximum(1.0, np.abs(wanted[cols]))))


def _place(A, B, poles, what: str) -> np.ndarray:
    """python-control's ``place`` (scipy's YT method), its convergence warning explained: the
    method iterates to make the eigenvector basis robust, and its "Convergence was not
    reached" is about that, not about where the poles went. The poles are checked here; the
    warning is passed on, with the placement error, only when they are not where asked."""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        K = np.asarray(control.place(A, B, poles))
    error = placement_error(A, B, K, poles)
    for w in seen:
        converged_note = "Convergence was not reached" in str(w.message)
        if converged_note and error <= PLACEMENT_TOLERANCE:
            continue
        note = (f" ({what}: the placed poles are off by {error:.1e} relative, more than "
                f"{PLACEMENT_TOLERANCE:g})") if converged_note else ""
        warnings.warn_explicit(f"{w.message}{note}", w.category, w.filename, w.lineno)
    return K


# the placed poles' relative error below which scipy's convergence note is not a concern
PLACEMENT_TOLERANCE = 1e-6


class Controller:
    """The discrete-time state-feedback law with observer, at ``period`` seconds.

    ``u = tau0 + Nbar r - K xhat - Ki z`` where xhat follows the observer ODE
    xhat' = (A - LC) xhat + B (u - tau0) + L (y - y0), discretized exactly (ZOH) over one
    period, and z integrates y - y0 - r. Angles in, joint torques out (absolute, N*m),
    clipped to ``torque_limit``.
    """

    def __init__(self, d: StateFeedback, q0, tau0, period: float = 0.002, torque_limit: float = np.inf):
        self.d = d
        self.q0 = np.asarray(q0, dtype=float)
        self.tau0 = np.asarray(tau0, dtype=float)
        self.period = float(period)
        self.torque_limit = float(torque_limit)
        A, B, C, L = d.sys.A, d.sys.B, d.sys.C, d.L
        n = A.shape[0]
        Ao = A - L @ C
        Bo = np.hstack([B, L])
        big = np.zeros((n + Bo.shape[1], n + Bo.shape[1]))
        big[:n, :n] = Ao
        big[:n, n:] = Bo
        E = expm(big * self.period)
        self.Phi, self.Gamma = E[:n, :n], E[:n, n:]
        self.reset()

    def reset(self, xhat=None) -> None:
        self.xhat = np.zeros(self.d.sys.nstates) if xhat is None else np.asarray(xhat, float).copy()
        self.z = np.zeros(self.d.sys.noutputs)
        self.u_dev = np.zeros(self.d.sys.ninputs)

    def update(self, q, r) -> np.ndarray:
        """One sample: measured angles ``q`` (2,) [rad], reference deviation ``r`` (2,) [rad]
        -> joint torques (2,) [N*m] to apply until the next sample."""
        y = np.asarray(q, dtype=float) - self.q0
        r = np.asarray(r, dtype=float)
        u = self.d.Nbar @ r - self.d.K @ self.xhat
        if self.d.Ki is not None:
            u -= self.d.Ki @ self.z
        # np.clip's own numbers, without its Python wrapper (a third of a sample's time)
        tau = np.minimum(np.maximum(self.tau0 + u, -self.torque_limit), self.torque_limit)
        self.u_dev = tau - self.tau0
        # advance the observer and the integrator over the coming period
        self.xhat = self.Phi @ self.xhat + self.Gamma @ np.concatenate([self.u_dev, y])
        if self.d.Ki is not None:
            self.z += self.period * (y - r)
        return tau


@dataclass
class ClosedLoopResult:
    """Simulated closed loop: ``t`` (N,) [s], true state ``x`` (N, 4), estimate ``xhat``
    (N, 4) (absolute, rad and rad/s), measured angles ``y`` (N, 2), torque table ``tau``
    (N, 2) [N*m] (row i held over [t_i, t_i + period)), reference ``r`` (2,) [rad]."""

    t: np.ndarray
    x: np.ndarray
    xhat: np.ndarray
    y: np.ndarray
    tau: np.ndarray
    r: np.ndarray
    period: float
    meta: dict = field(default_factory=dict)


def simulate_closed_loop(leg: LegParams, d: StateFeedback, step=(0.0, math.radians(20.0)), duration: float = 4.5,
                         period: float = 0.002, model: str = "fivebar", counts_per_joint_turn: int | None = None,
                         torque_limit: float = np.inf, substeps: int = 16, friction=None) -> ClosedLoopResult:
    """The nonlinear leg under the discrete controller with observer.

    Only q1, q2 are measured, quantized; torques are limited; the leg starts at rest at its
    operating point and at t = 0 the reference steps by ``step``. The torques form the table
    that :func:`leglib.experiments.torque.play_torque_table` plays back.

    Parameters
    ----------
    leg : LegParams
        The simulated leg (its friction unless ``friction`` is given).
    d : StateFeedback
        The design (:func:`place_poles`).
    step : (2,) sequence
        The reference step of (q1, q2) [rad] (default: segment 2 by 20 deg, as in thesis 5.5).
    duration, period : float
        Simulated time and the controller's sample time [s]: 0 < period <= duration <=
        :data:`MAX_DURATION` (600 s), at most :data:`MAX_SAMPLES` samples.
    model : {"fivebar", "parallelogram"}
        The plant: the exact five-bar or the thesis's model (a).
    counts_per_joint_turn : int, optional
        Quantization of the measured angles (default: encoder CPR x gear ratio, the thesis's
        4000 x 3).
    torque_limit : float
        |torque| limit at each joint [N*m], positive (inf: none).
    substeps : int
        Integration steps per sample period (1 to 1000).
    friction : (6,) array_like, optional
        The plant's friction vector (:func:`leglib.model.dynamics.friction_vector`) instead
        of the leg's.

    Returns
    -------
    ClosedLoopResult
        ``t`` (N,) [s], ``x`` and ``xhat`` (N, 4), ``y`` (N, 2) [rad], ``tau`` (N, 2) [N*m].

    Raises
    ------
    ArgumentError
        An argument out of its range (named).
    ValueError
        The simulated leg left the model's valid configuration.
    """
    duration = checks.number(duration, "simulate_closed_loop: duration [s]", ArgumentError, low=0.0, low_open=True,
                             high=MAX_DURATION)
    period = checks.number(period, "simulate_closed_loop: period [s]", ArgumentError, low=0.0, low_open=True,
                           high=duration)
    if duration / period > MAX_SAMPLES:
        raise ArgumentError(f"simulate_closed_loop: duration / period = {duration / period:.3g} controller samples; "
                         f"at most {MAX_SAMPLES} (a longer period or a shorter duration)")
    if torque_limit != np.inf:
        torque_limit = checks.number(torque_limit, "simulate_closed_loop: torque_limit [N*m]", ArgumentError,
                                     low=0.0, low_open=True)
    substeps = checks.integer(substeps, "simulate_closed_loop: substeps", ArgumentError, low=1, high=1000)
    q0 = np.array(leg.q0)
    tau0 = M.equilibrium_torque(leg, q0, model=model)
    ctrl = Controller(d, q0, tau0, period, torque_limit)
    res = counts_per_joint_turn or int(leg.encoder_cpr * leg.gear_ratio)
    quantum = 2 * math.pi / res
    n = int(round(duration / period))
    x = np.zeros((n, 4))
    xh = np.zeros((n, 4))
    y = np.zeros((n, 2))
    tau = np.zeros((n, 2))
    state = np.array([q0[0], 0.0, q0[1], 0.0])
    r = np.asarray(step, dtype=float)
    advance = M.held_torque_stepper(leg, period, substeps, model=model, friction=friction)
    offset = np.array([q0[0], 0.0, q0[1], 0.0])
    for i in range(n):
        x[i] = state
        meas = np.round(state[0::2] / quantum) * quantum
        y[i] = meas
        xh[i] = ctrl.xhat + offset
        tau[i] = ctrl.update(meas, r)
        nxt = advance(state, tau[i])
        if not (math.isfinite(nxt[0]) and math.isfinite(nxt[1]) and math.isfinite(nxt[2]) and math.isfinite(nxt[3])):
            raise ValueError(f"simulate_closed_loop: the {model} model left its valid configuration at "
                             f"t = {i * period:.3f} s (q = {np.degrees(state[[0, 2]])} deg)")
        state = nxt
    return ClosedLoopResult(t=period * np.arange(n), x=x, xhat=xh, y=y, tau=tau, r=r, period=period,
                            meta={"model": model, "poles": d.poles.tolist(), "q0": q0.tolist(),
                                  "tau0": tau0.tolist()})


def response_metrics(t, y, y0: float, target: float) -> dict:
    """Step metrics of a measured or simulated series (python-control's ``step_info`` on the
    normalized data) plus the RMS error to the target over the whole record."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    span = target - y0
    if span == 0:
        raise ValueError("target equals the initial value: no step")
    norm = (y - y0) / span
    out = {"final_error_pct": float(100 * abs(norm[-1] - 1)),
           "rms_error": float(np.sqrt(np.mean((y - target) ** 2))),
           "overshoot_pct": float(max(0.0, 100 * (np.max(norm) - 1)))}
    if np.max(norm) < 0.9:
        # never reached 90 % of the step: no rise or settling time (step_info cannot say)
        out.update(rise_time=float("nan"), settling_time=float("nan"))
        return out
    info = control.step_info(norm, timepts=t, final_output=1.0)
    out.update(rise_time=float(info["RiseTime"]), settling_time=float(info["SettlingTime"]))
    return out


def response_metrics_markdown(rows: dict) -> str:
    """A markdown table of :func:`response_metrics` (``{run name: metrics}``), each number in
    its unit: "never" for a rise or settling time the run did not reach (the response never
    came within 90 % / 2 % of the step), the RMS error [deg] to two significant digits."""
    def seconds(v, digits):
        return f"{v:.{digits}f}" if math.isfinite(v) else "never"

    lines = ["| run | rise time [s] | overshoot [%] | settling (2 %) [s] | final error [%] | RMS error [deg] |",
             "|---|---|---|---|---|---|"]
    for name, m in rows.items():
        lines.append(f"| {name} | {seconds(m['rise_time'], 3)} | {m['overshoot_pct']:.1f} | "
                     f"{seconds(m['settling_time'], 2)} | {m['final_error_pct']:.2f} | "
                     f"{math.degrees(m['rms_error']):.2g} |")
    return "\n".join(lines)


def run_live(odrv, d: StateFeedback, leg: LegParams, step=(0.0, math.radians(20.0)), duration: float = 4.5,
             period: float = 0.002, model: str = "fivebar"):
    """Close the loop on the device: observer and state feedback computed on the host from
    the measured angles every ``period`` s (the link's latency included), torques written
    back. Returns the :class:`leglib.experiments.torque.TorqueRun` (``tau`` are the applied torques).
    """

    dev = as_device(odrv)
    limit = dev.config.current_lim * dev.config.torque_constant * leg.gear_ratio
    ctrl = Controller(d, leg.q0, M.equilibrium_torque(leg, model=model), period, limit)
    r = np.asarray(step, dtype=float)
    return torque_loop(dev, lambda t, q1, q2: ctrl.update((q1, q2), r), duration, period=period,
                          record_current=False, check_every=25,
                          meta={"experiment": "live_state_feedback", "poles": np.asarray(d.poles).tolist(),
                                "step_rad": r.tolist()})
