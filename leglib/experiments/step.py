"""Listing 7.4's position step, on any device: :func:`step_response` and
:class:`StepResponse`; and :func:`return_to_rest`.

On the twin the step runs whole in the compiled kernel (``path="batched"``: a batch of one,
the path a sweep uses for many); on USB, and on a twin running in real time, it is a paced
polling loop (``path="polled"``) with the same abort rule (:mod:`leglib.abort`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import plots
from ..abort import N_OSC, oscillation_update
from ..abort import REASONS as ABORT_REASONS
from ..device import bench
from ..device.session import (
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    CONTROL_MODE_POSITION,
    HOLD_WATCHDOG,
    INPUT_MODE_PASSTHROUGH,
    Device,
    any_error,
    as_device,
    check_gains,
    describe_errors,
    enter_closed_loop,
    errors,
    hold_under_watchdog,
    prepare_closed_loop,
    safe,
)
from ..files.measurements import Measurement, write_measurement
from ..model.kinematics import foot_position
from ..params import LegParams

_STEP_FIELDS = {"experiment": "step_response"}   # in every step response's sidecar


@dataclass
class StepResponse:
    """A position step response of the leg.

    ``t`` [s], ``q1``, ``q2`` [rad] absolute joint angles, ``y`` [m] foot height (exact
    five-bar), ``gains`` (pos_gain, vel_gain, vel_integrator_gain); ``completed`` is False
    when the safety abort stopped it (``abort_reason`` says why): such a point is unstable
    and has no damping value.
    """

    t: np.ndarray
    q1: np.ndarray
    q2: np.ndarray
    y: np.ndarray
    gains: tuple
    step: float
    completed: bool = True
    abort_reason: str | None = None
    meta: dict = field(default_factory=dict)

    def plot(self, ax=None, fit=None):
        """The foot height over time; with ``fit`` (a :class:`leglib.identify.step.SecondOrderFit`
        of it) the fit too (:func:`leglib.plots.plot_step_identification`)."""
        if fit is not None:
            return plots.plot_step_identification(self.t, self.y, fit, ax=ax)
        ax = plots.axes(ax)
        ax.plot(self.t, self.y * 1e3, label="foot height" + ("" if self.completed else f" (aborted: {self.abort_reason})"))
        ax.set_xlabel("t [s]")
        ax.set_ylabel("y [mm]")
        ax.legend()
        return ax

    def write(self, out_dir, when=None) -> Path:
        """Write as a measurement file (CSV + sidecar) in ``out_dir``."""
        meta = {**_STEP_FIELDS, "step_turns": self.step, "completed": self.completed,
                "abort_reason": self.abort_reason, **self.meta}
        return write_measurement(out_dir, self.t, np.degrees(self.q1), np.degrees(self.q2),
                                        meta, gains=self.gains, when=when)

    @classmethod
    def from_measurement(cls, m: "Measurement", leg: LegParams) -> "StepResponse":
        """Rebuild from a file; thesis files (relative angles) are placed at the rest pose."""
        return cls.from_measurements([m], leg)[0]

    @classmethod
    def from_measurements(cls, measurements, leg: LegParams) -> list["StepResponse"]:
        """:meth:`from_measurement` of each file, the foot heights of all in one call."""
        measurements = list(measurements)
        if not measurements:
            return []
        # all files' angles at once (elementwise: the same numbers as file by file)
        cuts = np.cumsum([m.angle1.size for m in measurements])[:-1]
        Q1 = np.concatenate([m.angle1 for m in measurements])
        Q2 = np.concatenate([m.angle2 for m in measurements])
        np.radians(Q1, out=Q1)   # (in place: fewer fresh pages)
        np.radians(Q2, out=Q2)
        for m, a, b in zip(measurements, np.concatenate([[0], cuts]), np.concatenate([cuts, [Q1.size]])):
            if not m.absolute:
                # Listing 7.4 zeroes the angles at the start and records 360/cpr/3 * counts of
                # the motor, i.e. joint angle changes in the motor's sense: convert to joint
                Q1[a:b] = leg.q1 + leg.direction * Q1[a:b]
                Q2[a:b] = leg.q2 + leg.direction * Q2[a:b]
        _, Y = foot_position(leg, Q1, Q2)
        return [cls(t=m.t - m.t[0], q1=q1, q2=q2, y=y, gains=m.gains, step=m.meta.get("step_turns", 0.4),
                    completed=m.stable, abort_reason=m.meta.get("abort_reason"), meta=m.meta)
                for m, q1, q2, y in zip(measurements, np.split(Q1, cuts), np.split(Q2, cuts), np.split(Y, cuts))]


def _batch_points(dev: Device, gains, out: dict):
    """A twin batch's points: joint angles Q1, Q2 (B, samples) [rad] of all at once
    (elementwise: the same numbers as one by one), times from zero, the fields every
    point's sidecar shares, and per point (gains, samples kept, completed, abort reason)."""
    ax = dev.axes
    a1, a2 = ax.axis_of_joint
    Q1 = ax.counts_to_joint(out["counts"][:, :, a1], 0)
    Q2 = ax.counts_to_joint(out["counts"][:, :, a2], 1)
    t = out["t"] - out["t"][0]
    period = out["t"][1] - out["t"][0]
    points = []
    faulted = np.any(out["axis_error"], axis=1).tolist()
    ticks, codes = out["abort_tick"].tolist(), out["abort_reason"].tolist()
    for i, g in enumerate(np.atleast_2d(gains).tolist()):
        completed = ticks[i] < 0 and not faulted[i]
        reason = ABORT_REASONS[int(codes[i])]
        if reason is None and not completed:
            reason = f"axis error 0x{int(out['axis_error'][i].max()):x} (firmware fault)"
        n = len(t) if completed else max(2, int(ticks[i] * dev.sim.twin.dt / max(period, 1e-12)) + 1)
        points.append((tuple(g), min(n, len(t)), bool(completed), reason))
    return Q1, Q2, t, {**dev.describe(), "sample_rate_hz": 1.0 / period}, points


def _responses_from_batch(dev: Device, gains, out: dict, step: float) -> list[StepResponse]:
    Q1, Q2, t, meta, points = _batch_points(dev, gains, out)
    _, Y = foot_position(dev.leg, Q1, Q2)   # all points at once
    return [StepResponse(t=t[:n], q1=Q1[i, :n], q2=Q2[i, :n], y=Y[i, :n], gains=g, step=step,
                         completed=completed, abort_reason=reason, meta=dict(meta))
            for i, (g, n, completed, reason) in enumerate(points)]


def _step_polled(dev: Device, gains, step, duration, sample_period, vel_limit, abort_error,
              on_sample=None) -> StepResponse:
    """Listing 7.4 on a real device (and on a real-time twin): a paced polling loop with
    safety checks. Completed only when no abort and no firmware error happened."""
    ax = dev.axes
    a_q1, a_q2 = ax.axis_of_joint
    ts, c1, c2 = [], [], []
    reason = None
    with safe(dev):
        prepare_closed_loop(dev, vel_limit, watchdog=max(0.5, 5 * sample_period))
        for a in (0, 1):
            dev.set(a, "pos_gain", gains[0])
            dev.set(a, "vel_gain", gains[1])
            dev.set(a, "vel_integrator_gain", gains[2])
            dev.set(a, "control_mode", CONTROL_MODE_POSITION)
            dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
        enter_closed_loop(dev)
        start_pos = {a: float(dev.get(a, "pos_estimate")) for a in (0, 1)}
        target = {a_q1: start_pos[a_q1] + step, a_q2: start_pos[a_q2] - step}
        for a in (0, 1):
            dev.set(a, "input_pos", target[a])
        setpoint = (float(ax.joint_angle(target[a_q1], 0)), float(ax.joint_angle(target[a_q2], 1)))
        t0 = dev.time()
        monitors = {a: np.zeros(N_OSC) for a in (0, 1)}
        next_sample = 0.0
        # each property is one USB transaction (about 0.4 ms): read the counts every sample
        # and do one housekeeping transaction per sample, in turn: feed axis 0, feed axis 1,
        # check the state of axis 0, of axis 1
        k = 0
        dropped = None
        while True:
            now = dev.time() - t0
            if now > duration:
                break
            if now < next_sample:
                dev.sleep(min(next_sample - now, sample_period))
                continue
            # the next slot on the grid; slots already missed are skipped, not caught up in a burst
            next_sample += sample_period * max(1, math.ceil((now - next_sample) / sample_period + 1e-9))
            n1, n2 = dev.counts(a_q1), dev.counts(a_q2)
            ts.append(dev.time() - t0)
            c1.append(n1)
            c2.append(n2)
            task, k = k % 4, k + 1
            if task < 2:
                dev.axis(task).watchdog_feed()
            elif int(dev.get(task - 2, "current_state")) != AXIS_STATE_CLOSED_LOOP_CONTROL:
                dropped = task - 2
            if on_sample is not None:
                on_sample({"t": ts[-1], "q1": float(ax.counts_to_joint(n1, 0)),
                           "q2": float(ax.counts_to_joint(n2, 1)), "iq": None, "setpoint": setpoint})
            # safety, as the twin's kernel: position error bound and non-decaying oscillation
            errs = {a_q1: target[a_q1] - n1 / ax.cpr, a_q2: target[a_q2] - n2 / ax.cpr}
            if max(abs(e) for e in errs.values()) > abort_error:
                reason = "position error past bound"
                break
            if any(oscillation_update(monitors[a], errs[a], 0.025 * abort_error) for a in (0, 1)):
                reason = "oscillation not decaying (growing or sustained)"
                break
            if dropped is not None:
                reason = f"axis{dropped} dropped out of closed loop ({describe_errors(errors(dev))})"
                break
        if reason is None and any_error(dev):
            reason = f"firmware error during the step ({describe_errors(errors(dev))})"
        if reason is None and len(ts) < 2:
            reason = "fewer than two samples were taken"
    t = np.asarray(ts)
    q1 = ax.counts_to_joint(np.asarray(c1), 0)
    q2 = ax.counts_to_joint(np.asarray(c2), 1)
    _, y = foot_position(dev.leg, q1, q2)
    rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else float("nan")
    return StepResponse(t=t, q1=q1, q2=q2, y=y, gains=tuple(map(float, gains)), step=step,
                        completed=reason is None, abort_reason=reason,
                        meta={**dev.describe(), "sample_rate_hz": rate})


STEP_PATHS = ("auto", "polled", "batched")


def _check_step(dev: Device, step, duration, sample_period, vel_limit) -> None:
    def number(name, value):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
    number("duration", duration)
    number("sample_period", sample_period)
    number("step", step)
    if not (0 < duration <= 30):
        raise ValueError(f"duration must be in (0, 30] s, got {duration}")
    if not (0 < sample_period < duration):
        raise ValueError(f"sample_period must be positive and shorter than duration ({duration} s), "
                         f"got {sample_period}")
    if not (0 < abs(step) <= 1.0):
        raise ValueError(f"step must be a non-zero motor step of at most 1 turn, got {step}")
    if abs(step) * dev.axes.cpr < 2:
        raise ValueError(f"step = {step} turn is below the encoder's resolution (1/{dev.axes.cpr} turn): "
                         f"at least 2 counts are needed")
    if vel_limit is not None:
        number("vel_limit", vel_limit)
        high = dev.config.step_vel_limit
        if not 0 < vel_limit <= high:
            raise ValueError(f"vel_limit must be in (0, {high}] turn/s, got {vel_limit} "
                             f"({dev.config.source_file}: step_vel_limit, the experiments' safety bound)")


def step_response(odrv, pos_gain: float, vel_gain: float, vel_integrator_gain: float,
                  step: float = 0.4, duration: float = 1.5, sample_period: float = 0.002,
                  vel_limit: float | None = None, settle: float = 2.0, on_sample=None,
                  path: str = "auto") -> StepResponse:
    """Listing 7.4's position step with the given gains, from the leg at rest.

    The axis driving q1 moves by +``step`` motor turns, the other by -``step``. The
    experiment aborts, sets IDLE and marks the response not completed when the position
    error passes 2*|step|, the oscillation stops decaying (:mod:`leglib.abort`), or any
    firmware error is raised during it. Afterwards the axes are IDLE and the leg is left
    ``settle`` s to come to rest.

    Parameters
    ----------
    odrv : Device or an ODrive object (calibrated, zeroed)
    pos_gain, vel_gain, vel_integrator_gain : float
        The cascade's gains [(turn/s)/turn, N*m/(turn/s), N*m/turn], each within the
        configuration's ``[experiment]`` bounds.
    step : float
        Motor step [turn], 0 < |step| <= 1, at least two encoder counts.
    duration, sample_period : float
        Response length and sampling period [s].
    vel_limit : float, optional
        Velocity limit during the step [turn/s] (default: the configuration's
        ``step_vel_limit``, its safety bound).
    settle : float
        Seconds left for the leg to come to rest afterwards.
    on_sample : callable, optional
        Called from the polling loop as ``on_sample({"t": s, "q1": rad, "q2": rad,
        "iq": None, "setpoint": (q1, q2) rad})`` (a live view); it runs between samples and
        must be cheap (well under ``sample_period``).
    path : {"auto", "polled", "batched"}
        How the step is run. ``"polled"``: a paced polling loop over the device's
        properties, as on a real leg (USB, and a twin in real time). ``"batched"``: the twin
        runs the whole step in its compiled kernel, as a batch of one (the path
        :func:`leglib.experiments.sweep.sweep` uses for many), with the same abort rule
        and numbers to the encoder's resolution; only for a twin not in real time, and it
        calls no ``on_sample``. ``"auto"``: batched where it can be and no ``on_sample`` is
        given, polled otherwise.

    Returns
    -------
    StepResponse
        ``t`` [s], ``q1``, ``q2`` [rad], ``y`` [m] (foot height), the gains, ``completed``
        and ``abort_reason``.

    Raises
    ------
    ValueError
        Gains outside the configured bounds, or a bad step, duration, sample period,
        velocity limit or ``path`` (also ``"batched"`` on a real leg or with ``on_sample``).
    TypeError
        ``on_sample`` is not callable.
    ExperimentError
        The device is not calibrated, has a stale fault, or does not enter closed loop.
    """
    dev = as_device(odrv)
    check_gains(dev.config, pos_gain, vel_gain, vel_integrator_gain)
    _check_step(dev, step, duration, sample_period, vel_limit)
    if on_sample is not None and not callable(on_sample):
        raise TypeError(f"on_sample must be callable, got {on_sample!r}")
    sim = dev.sim
    can_batch = sim is not None and not sim.realtime
    if path not in STEP_PATHS:
        raise ValueError(f"path must be one of {STEP_PATHS}, got {path!r}")
    if path == "batched" and not can_batch:
        raise ValueError("path='batched' runs the step in the twin's kernel: it needs a virtual device that is "
                         "not paced to the wall clock (connect('virtual', realtime=False)); use 'polled' or 'auto'")
    if path == "batched" and on_sample is not None:
        raise ValueError("path='batched' calls no on_sample (the kernel runs the whole step at once); use "
                         "'polled' for a live view")
    if path == "auto":
        path = "batched" if can_batch and on_sample is None else "polled"
    gains = (float(pos_gain), float(vel_gain), float(vel_integrator_gain))
    vl = dev.config.step_vel_limit if vel_limit is None else vel_limit
    if path == "batched":
        with bench.timed(dev, "step") as entry:
            t0 = dev.board_clock()
            with safe(dev):
                prepare_closed_loop(dev, vl, watchdog=None)   # the kernel's step is one transaction: nothing to lose
                out = sim.step_batch(np.array([gains]), step_turns=step, duration=duration,
                                     sample_period=sample_period, vel_limit=vl,
                                     abort_error_turns=2 * abs(step))
            entry["charged"] = batch_charge(dev, out, dev.board_clock() - t0, duration, settle, sample_period)
        return _responses_from_batch(dev, [gains], out, step)[0]
    with bench.timed(dev, "step"):
        resp = _step_polled(dev, gains, step, duration, sample_period, vl, 2 * abs(step), on_sample=on_sample)
        dev.sleep(settle)
    return resp


def batch_charge(dev: Device, out: dict, took: float, duration: float, settle: float, sample_period: float) -> float:
    """Bench seconds to add to the steps of a twin batch ``out`` that its kernel ran in ``took``
    seconds of the board's clock (each charged its full duration and a 2 s settle, no
    polling): what the same steps cost on the leg's polling path
    (:func:`leglib.device.bench.step_seconds`, at this board's USB latency; an aborted step
    ends at its abort), less what the clock saw."""
    latency = float(dev.sim.twin.plant.usb_latency)
    ticks = np.asarray(out["abort_tick"], dtype=float)
    ran = np.where(ticks >= 0, np.minimum(ticks * dev.sim.twin.dt, duration), duration)
    return float(sum(bench.step_seconds(float(d), settle, sample_period, latency=latency) for d in ran)) - took


def return_to_rest(odrv, pos_gain: float = 20.0, vel_gain: float = 0.05, vel_integrator_gain: float = 0.3,
                   move_time: float = 2.0, settle: float = 0.5) -> tuple[float, float]:
    """Bring the leg back to its rest pose (the zeroed motor positions, see
    :func:`zero_joints`) with soft position control, then IDLE and let it settle. Returns
    the joint angles [rad] it ends at. Experiments that start "from rest" call it between
    runs on a real bench.

    The leg is held under the watchdog (:data:`HOLD_WATCHDOG` s, fed every
    :data:`HOLD_FEED_PERIOD` s): a link lost or an interrupt while it holds leaves both axes
    IDLE within the watchdog time, as in every other experiment."""
    dev = as_device(odrv)
    check_gains(dev.config, pos_gain, vel_gain, vel_integrator_gain)
    for name, value in (("move_time", move_time), ("settle", settle)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value) or not 0 <= value <= 60:
            raise ValueError(f"{name} must be a number of seconds in [0, 60], got {value!r}")
    with bench.timed(dev, "hold"):
        with safe(dev):
            prepare_closed_loop(dev, min(dev.config.vel_limit, 2.0), watchdog=HOLD_WATCHDOG)
            for a in (0, 1):
                dev.set(a, "pos_gain", pos_gain)
                dev.set(a, "vel_gain", vel_gain)
                dev.set(a, "vel_integrator_gain", vel_integrator_gain)
                dev.set(a, "control_mode", CONTROL_MODE_POSITION)
                dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
            enter_closed_loop(dev)
            for j, a in enumerate(dev.axes.axis_of_joint):
                dev.set(a, "input_pos", dev.axes.zero[j])
            hold_under_watchdog(dev, move_time)
        dev.sleep(settle)
        a1, a2 = dev.axes.axis_of_joint
        return float(dev.axes.counts_to_joint(dev.counts(a1), 0)), float(dev.axes.counts_to_joint(dev.counts(a2), 1))
