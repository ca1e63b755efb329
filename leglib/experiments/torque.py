"""Torque experiments (thesis Listing 7.3, 5.2): both joints in torque control from the host.

:func:`torque_loop` closes any policy ``(t, q1, q2) -> (tau1, tau2)`` over USB (or the
twin's simulated USB); :func:`play_torque_table` plays a table back; the friction experiment
of thesis 5.2 plays sine torques. Each records the actual read and write times.
"""

from __future__ import annotations

import math
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import plots
from ..device import bench
from ..device.session import (
    AXIS_STATE_CLOSED_LOOP_CONTROL,
    CONTROL_MODE_TORQUE,
    INPUT_MODE_PASSTHROUGH,
    any_error,
    as_device,
    describe_errors,
    enter_closed_loop,
    error_text,
    errors,
    prepare_closed_loop,
    safe,
)
from ..errors import ExperimentError
from ..files.measurements import (
    csv_bytes,
    read_companion,
    read_measurement,
    write_measurement,
)


@dataclass
class TorqueRun:
    """A played-back torque table: actual sample times ``t`` [s], joint angles ``q1``,
    ``q2`` [rad], commanded joint torques ``tau`` (n, 2) [N*m], measured ``iq`` (n, 2) [A]
    per axis, and the achieved loop rate [Hz]."""

    t: np.ndarray
    q1: np.ndarray
    q2: np.ndarray
    tau: np.ndarray
    iq: np.ndarray
    rate_hz: float
    meta: dict = field(default_factory=dict)
    table: np.ndarray | None = None
    period: float = 0.002
    t_cmd: np.ndarray | None = None   # (n, 2) when each joint's torque was written [s]
    t_read: np.ndarray | None = None  # (n, 2) when each joint's angle was read [s]

    def plot(self, ax=None):
        """The joint angles and the torques (:func:`leglib.plots.plot_torque_run`)."""
        return plots.plot_torque_run(self, ax=ax)

    def applied_torque(self, t_grid, bandwidth: float | None = None) -> np.ndarray:
        """Joint torque (M, 2) [N*m] at ``t_grid`` as the motors produced it: each written
        value held from its write time, through the current loop's first-order lag
        (``bandwidth`` [rad/s], default the run's configuration). Without write times
        (thesis files) the table is assumed to apply on schedule."""
        t_grid = np.asarray(t_grid, dtype=float)
        if self.t_cmd is not None and len(self.t_cmd) == len(self.tau):
            u = np.empty((t_grid.size, 2))
            for j in (0, 1):
                k = np.searchsorted(self.t_cmd[:, j], t_grid, side="right") - 1
                u[:, j] = np.where(k >= 0, self.tau[np.clip(k, 0, None), j], 0.0)
        else:
            rows = np.clip((t_grid / self.period).astype(int), 0, len(self.table) - 1)
            u = self.table[rows]
        wc = bandwidth or self.meta.get("current_control_bandwidth")
        if not wc:
            return u
        y = np.empty_like(u)
        acc = np.zeros(2)
        for i in range(len(t_grid)):
            h = t_grid[i] - t_grid[i - 1] if i else 0.0
            acc = acc + (1 - math.exp(-wc * h)) * (u[i] - acc)
            y[i] = acc
        return y

    def write(self, out_dir, when=None) -> Path:
        """Write as Listing 7.3 did, as one committed unit: ``<stamp>_positions.csv`` (time,
        q1, q2 [deg]) with its JSON sidecar, and ``<stamp>_torque.csv`` (time, tau1, tau2
        [N*m]) of the table, a companion the sidecar commits by its SHA-256 (written before
        the positions file, whose appearance is the commit: an interrupted or failed write
        leaves no measurement that :meth:`read` cannot read)."""
        meta = {"experiment": "torque_playback", "period_s": self.period, "rate_hz": self.rate_hz,
                **self.meta}
        for name in ("t_cmd", "t_read"):
            value = getattr(self, name)
            if value is not None:
                meta[name] = np.round(value, 7).tolist()
        companions = None
        if self.table is not None:
            tt = self.period * np.arange(len(self.table))
            companions = {TORQUE_SUFFIX: csv_bytes(np.column_stack([tt, self.table]))}
        return write_measurement(out_dir, self.t, np.degrees(self.q1), np.degrees(self.q2), meta, when=when,
                                 companions=companions)

    @classmethod
    def read(cls, path) -> "TorqueRun":
        """Read a torque run written by :meth:`write` (positions, sidecar and table)."""
        m = read_measurement(path)
        table = read_companion(path, TORQUE_SUFFIX, m.meta, columns=3)
        period = float(m.meta.get("period_s", table[1, 0] - table[0, 0]))
        rows = np.minimum((m.t / period).astype(int), len(table) - 1)
        extra = {k: np.asarray(m.meta[k]) for k in ("t_cmd", "t_read") if k in m.meta}
        return cls(t=m.t, q1=np.radians(m.angle1), q2=np.radians(m.angle2), tau=table[rows, 1:],
                   iq=np.full((m.t.size, 2), np.nan), rate_hz=float(m.meta.get("rate_hz", np.nan)),
                   meta=m.meta, table=table[:, 1:], period=period, **extra)


TORQUE_SUFFIX = "_torque.csv"   # a torque run's table, beside its positions file


def _fall_headroom(dev, quiet: bool = False) -> None:
    """Raise both axes' ``vel_limit`` to the configuration's ``step_vel_limit`` for the fall
    that follows a torque run. On firmware 0.5.5+ the controller updates every tick in every
    state (main.cpp:438-446), so its overspeed check (controller.cpp:331-341) also judges
    the leg falling back while IDLE, against the run's vel_limit x vel_limit_tolerance
    (2.0 x 1.2 turn/s): a trip there blocks the next closed loop. With the torques at zero
    the limit has no other use until the next experiment sets its own (measured on the twin:
    falls after the friction experiment peak at 1.04 turn/s, after notebook 03's playback at
    1.42 turn/s; after a step at 3.9 turn/s). ``quiet``: after an abort, never raise."""
    for a in (0, 1):
        try:
            dev.set(a, "vel_limit", dev.config.step_vel_limit)
        except Exception as exc:  # noqa: BLE001 - quiet: the abort's own exception is the one to see
            if not quiet:
                raise
            warnings.warn(f"axis{a}.controller.config.vel_limit could not be raised for the fall after the "
                          f"aborted run ({type(exc).__name__}: {exc}): an OVERSPEED may be flagged while IDLE",
                          stacklevel=3)
            return


@contextmanager
def _released_with_headroom(dev):
    """:func:`safe` for a torque run, and :func:`_fall_headroom` for the fall after it:
    before the axes go IDLE when the run ends normally (its torques are zero then), right
    after they went IDLE when it was aborted (the abort's IDLE comes first)."""
    ended = False
    try:
        with safe(dev):
            yield
            _fall_headroom(dev)
            ended = True
    finally:
        if not ended:
            _fall_headroom(dev, quiet=True)


def torque_loop(odrv, policy, duration: float, period: float | None = None,
                max_joint_speed: float = 20.0, meta: dict | None = None,
                record_current: bool = True, check_every: int = 1, on_sample=None) -> TorqueRun:
    """Both joints in torque control; each cycle reads the joint angles, asks
    ``policy(t, q1, q2) -> (tau1, tau2)`` [N*m at the joints] and writes the torques.

    With ``period`` the cycles are paced to t = k * period (a controller's sample time);
    without, the loop runs as fast as the link allows (the thesis's playback). Records the
    actual read and write time of every value. Aborts to IDLE when a joint moves faster than
    ``max_joint_speed`` or an axis drops out of closed loop, and when the firmware flags an
    error during the run. The watchdog (0.2 s) is fed every fifth cycle.

    Parameters
    ----------
    odrv : Device or an ODrive object (calibrated)
    policy : callable
        ``policy(t [s], q1 [rad], q2 [rad]) -> (tau1, tau2)`` [N*m at the joints], finite.
    duration : float
        Run length [s].
    period : float, optional
        Pace the cycles to this sample time [s]; None runs as fast as the link allows.
    max_joint_speed : float
        Abort above this joint speed [rad/s].
    meta : dict, optional
        Extra fields for the run's record (written to its sidecar).
    record_current : bool
        Read Iq of both motors every cycle (one USB transaction each).
    check_every : int
        Cycles between checks that both axes are still in closed loop.
    on_sample : callable, optional
        Called every cycle as ``on_sample({"t": s, "q1": rad, "q2": rad, "iq": (A, A) or None,
        "setpoint": None})`` (a live view); it runs inside the loop and must be cheap.

    Returns
    -------
    TorqueRun
        ``t``, ``q1``, ``q2``, the torques applied (after the current limit), ``iq``, the loop
        rate, and the read and write time of every value.

    Raises
    ------
    ValueError
        ``duration``, ``max_joint_speed`` or ``period`` is not a positive number.
    TypeError
        ``on_sample`` is not callable.
    ExperimentError
        The policy returned something else than two finite torques, a joint moved too fast, an
        axis dropped out of closed loop, or the firmware flagged an error.
    """
    dev = as_device(odrv)
    for name, value in (("duration", duration), ("max_joint_speed", max_joint_speed)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    if period is not None and (isinstance(period, bool) or not math.isfinite(period) or not 0 < period < duration):
        raise ValueError(f"period must be positive and shorter than duration ({duration} s), got {period!r}")
    if on_sample is not None and not callable(on_sample):
        raise TypeError(f"on_sample must be callable, got {on_sample!r}")
    ax = dev.axes
    a_q1, a_q2 = ax.axis_of_joint
    limit = dev.config.current_lim * dev.config.torque_constant
    ts, t_cmd, t_read, c1, c2, iq, applied = [], [], [], [], [], [], []
    with bench.timed(dev, "torque"), _released_with_headroom(dev):
        prepare_closed_loop(dev, dev.config.vel_limit, watchdog=0.2)
        for a in (0, 1):
            dev.set(a, "input_torque", 0.0)
            dev.set(a, "control_mode", CONTROL_MODE_TORQUE)
            dev.set(a, "input_mode", INPUT_MODE_PASSTHROUGH)
        enter_closed_loop(dev)
        t0 = dev.time()
        k = 0
        prev = None
        while True:
            now = dev.time() - t0
            if period is not None and now < k * period:
                dev.sleep(k * period - now)
                now = dev.time() - t0
            if now > duration:
                break
            if period is not None:   # slots already missed are skipped, not caught up in a burst
                k = max(k, math.floor(now / period + 1e-9))
            k += 1
            n1 = dev.counts(a_q1)
            r1 = dev.time() - t0
            n2 = dev.counts(a_q2)
            r2 = dev.time() - t0
            q1, q2 = float(ax.counts_to_joint(n1, 0)), float(ax.counts_to_joint(n2, 1))
            tau = np.asarray(policy(r2, q1, q2), dtype=float)
            if tau.shape != (2,) or not np.all(np.isfinite(tau)):
                raise ExperimentError(f"policy returned {tau!r} at t = {r2:.3f} s; expected two finite torques")
            motor = ax.motor_torque(tau)
            dev.set(a_q1, "input_torque", float(np.clip(motor[0], -limit, limit)))
            w1 = dev.time() - t0
            dev.set(a_q2, "input_torque", float(np.clip(motor[1], -limit, limit)))
            w2 = dev.time() - t0
            t_cmd.append((w1, w2))
            t_read.append((r1, r2))
            ts.append(r2)
            c1.append(n1)
            c2.append(n2)
            applied.append(ax.joint_torque(np.clip(motor, -limit, limit)))
            if record_current:
                iq.append((float(dev.get(a_q1, "Iq_measured")), float(dev.get(a_q2, "Iq_measured"))))
            else:
                iq.append((math.nan, math.nan))
            # one USB transaction each: feed the watchdog (0.2 s) every 10th cycle, axes in turn
            if k % 10 in (0, 5):
                dev.axis(0 if k % 10 == 0 else 1).watchdog_feed()
            if on_sample is not None:
                on_sample({"t": r2, "q1": q1, "q2": q2,
                           "iq": None if not record_current else tuple(iq[-1]), "setpoint": None})
            if prev is not None and ts[-1] > prev[0]:
                speed = max(abs(n1 - prev[1]), abs(n2 - prev[2])) / ax.cpr * 2 * math.pi / ax.gear_ratio / (ts[-1] - prev[0])
                if speed > max_joint_speed:
                    raise ExperimentError(f"joint speed {speed:.1f} rad/s exceeds {max_joint_speed} rad/s "
                                          f"at t = {ts[-1]:.3f} s: aborted, axes IDLE")
            prev = (ts[-1], n1, n2)
            if k % check_every == 0:
                for a in (a_q1, a_q2) if check_every == 1 else (a_q1,):
                    if int(dev.get(a, "current_state")) != AXIS_STATE_CLOSED_LOOP_CONTROL:
                        raise ExperimentError(f"axis{a} dropped out of closed loop at t = {ts[-1]:.3f} s: "
                                              f"{error_text(dev, a)}")
        for a in (0, 1):
            dev.set(a, "input_torque", 0.0)
        if any_error(dev):
            raise ExperimentError(f"a firmware error was raised during the run: {describe_errors(errors(dev))}")
    t = np.asarray(ts)
    rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else float("nan")
    return TorqueRun(t=t, q1=ax.counts_to_joint(np.asarray(c1), 0), q2=ax.counts_to_joint(np.asarray(c2), 1),
                     tau=np.asarray(applied), iq=np.asarray(iq), rate_hz=rate,
                     meta={**dev.describe(), "current_control_bandwidth": dev.config.current_control_bandwidth,
                           **(meta or {})},
                     period=period if period is not None else float(np.median(np.diff(t))) if len(t) > 1 else 0.0,
                     t_cmd=np.asarray(t_cmd), t_read=np.asarray(t_read))


def play_torque_table(odrv, tau, period: float = 0.002, duration: float | None = None,
                      max_joint_speed: float = 20.0) -> TorqueRun:
    """Play joint torques ``tau``, one row per ``period`` s, on both joints in torque control
    (Listing 7.3), recording the actual timestamps, joint angles and Iq.

    The loop runs as fast as the link allows; rows are chosen by elapsed time, as in the
    thesis (see :func:`torque_loop` for the safety checks).

    Parameters
    ----------
    odrv : Device or an ODrive object (calibrated)
    tau : (N, 2) array_like
        Joint torques [N*m], finite.
    period : float
        Seconds per row.
    duration : float, optional
        Run length [s] (default: the table's, ``N * period``).
    max_joint_speed : float
        Abort above this joint speed [rad/s].

    Returns
    -------
    TorqueRun

    Raises
    ------
    ValueError
        ``tau`` is not a finite (N, 2) table, or ``period`` is not positive.
    ExperimentError
        The run was aborted (speed, an axis out of closed loop, a firmware error).
    """
    dev = as_device(odrv)
    tau = np.asarray(tau, dtype=float)
    if tau.ndim != 2 or tau.shape[1] != 2 or len(tau) < 1 or not np.all(np.isfinite(tau)):
        raise ValueError(f"tau must be a finite (N, 2) table of joint torques, got shape {tau.shape}")
    if period <= 0:
        raise ValueError(f"period must be positive, got {period}")
    duration = len(tau) * period if duration is None else duration
    limit = dev.config.current_lim * dev.config.torque_constant
    peak = float(np.max(np.abs(dev.axes.motor_torque(tau))))
    if peak > limit:
        warnings.warn(f"torque table asks up to {peak:.3f} N*m at the motor; the current limit "
                      f"allows {limit:.3f} N*m: it will saturate", stacklevel=2)
    run = torque_loop(dev, lambda t, q1, q2: tau[min(int(t / period), len(tau) - 1)], duration,
                      max_joint_speed=max_joint_speed, meta={"experiment": "torque_playback"})
    run.table = tau
    run.period = period
    return run


def sine_torque_table(bias: float = 0.045, amplitude: float = 0.025, freqs=(0.45, 0.7),
                      duration: float = 8.0, ramp: float = 0.5, period: float = 0.002) -> np.ndarray:
    """Joint torques (N, 2) [N*m] of the friction experiment: an opening bias that holds the
    leg off its stops plus a sine on each joint at its own frequency [Hz] (so the two
    joints' friction can be told apart), both faded in over ``ramp`` s."""
    t = period * np.arange(int(round(duration / period)))
    fade = np.clip(t / ramp, 0.0, 1.0) if ramp > 0 else np.ones_like(t)
    open1 = -(bias + amplitude * np.sin(2 * np.pi * freqs[0] * t))   # q1 down opens the leg
    open2 = bias + amplitude * np.sin(2 * np.pi * freqs[1] * t)      # q2 up opens the leg
    return np.column_stack([fade * open1, fade * open2])


def friction_experiment(odrv, bias: float = 0.045, amplitude: float = 0.025, freqs=(0.45, 0.7),
                        duration: float = 8.0, ramp: float = 0.5, period: float = 0.002) -> TorqueRun:
    """Thesis 5.2's experiment: sine torques on both joints (see :func:`sine_torque_table`),
    played back with :func:`play_torque_table`. The defaults move the thesis's leg over
    q2 - q1 of about 15-60 deg without touching its stops.

    Parameters
    ----------
    odrv : Device or an ODrive object (calibrated)
    bias : float
        Opening torque that holds the leg off its stops [N*m at a joint].
    amplitude : float
        Sine amplitude [N*m].
    freqs : (2,) sequence
        Each joint's sine frequency [Hz] (different, so the joints' friction can be told apart).
    duration, ramp, period : float
        Run length, fade-in and table row period [s].

    Returns
    -------
    TorqueRun
        With the experiment's settings in ``meta``.
    """
    table = sine_torque_table(bias, amplitude, freqs, duration, ramp, period)
    run = play_torque_table(odrv, table, period=period)
    run.meta.update({"bias_Nm": bias, "amplitude_Nm": amplitude, "freqs_hz": list(freqs), "ramp_s": ramp})
    return run
