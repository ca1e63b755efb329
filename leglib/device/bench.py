"""The bench: what a run does on the leg, how long that takes at real speed, and a limit.

Three parts, used by :mod:`~leglib.device.setup`, the experiments, :func:`leglib.design.tuning.tune`
and the notebooks:

- **The ledger.** Every configuration check and save, reboot, calibration, zeroing and
  experiment notes itself (:func:`note`, :func:`timed`) with the board it ran on. A
  :class:`Run` (or :func:`mark` and :func:`report`) turns the notes since its start into a
  :class:`BenchReport`: what the run did on the leg and the **bench time at real speed**,
  read off the board's own clock. On the twin that clock is the virtual one: it advances
  by the firmware's timings (calibration, the boot), every USB transaction's latency, every
  step, settle and hold, and by nothing the host computes; a step the twin ran whole in
  its kernel is charged what the same step costs on the leg's polling path
  (:func:`step_seconds`). Run on the twin, a notebook's report is its rehearsal: what it
  would do on the leg, and for how long. On USB the clock is the wall clock.
- **The cost model** (:func:`step_seconds`, :func:`calibration_seconds`, ...): the same
  costs before anything runs, from the firmware model's timings and the USB latency of the
  device model, plus the transactions leglib's own code does around each experiment
  (counted on the twin, see the constants).
- **The limit.** A :class:`Plan` of what a run will do gives its estimate before anything
  moves; :func:`leglib.device.setup.start_run` (a notebook, ``python -m leglib design``)
  and :func:`require` (a sweep, a design) refuse a run on the real leg whose estimate is
  longer than the limit the caller gives (``max_bench_minutes``), with
  :class:`leglib.errors.BenchLimitError` stating the estimate. On the twin nothing is
  refused: the estimate is reported.
"""

from __future__ import annotations

import contextlib
import math
import threading
from dataclasses import dataclass, field

from .. import checks
from ..errors import ArgumentError, BenchLimitError
from ..params import load_plant

#: the limit a run on the leg gets unless the caller gives one [min]
DEFAULT_MAX_BENCH_MINUTES = 5.0

# What leglib's own code adds around each experiment beyond its nominal times (the polling
# loops run for their duration, the waits for theirs): set-up and clean-up transactions,
# each costing the USB latency, measured on the virtual board as the time beyond the
# nominal, in transactions (tests/device/test_bench.py checks every cost below against the
# twin's polled runs):
#: a step (leglib.experiments.step): fault and calibration checks, limits, watchdog, gains,
#: modes, entering closed loop, the targets; IDLE confirmed, watchdog off, the final check
STEP_TRANSACTIONS = 58
#: a torque run (torque_loop): the same set-up without gains, torques zeroed after it
TORQUE_TRANSACTIONS = 66
#: a hold at the rest pose (return_to_rest): set-up, targets, the joint angles read after it
HOLD_TRANSACTIONS = 55
#: one axis's calibration is polled every 0.1 s: it is seen done half a poll after it ends
CALIBRATION_POLL = 0.1
#: the rest pose measured for zeroing (setup._rest_positions): states, then 8 + 8 reads of
#: both positions around a 0.25 s wait, after a 1 s settle; and the readiness checks
REST_SETTLE, REST_WAIT, REST_TRANSACTIONS = 1.0, 0.25, 53
#: the configuration read back and compared (setup.configure): 6 values on two axes and the
#: board's brake resistor settings, the axes confirmed IDLE
CONFIG_TRANSACTIONS = 23
#: a save: every value written and read back, the save, the rebooted board found and every
#: value read back again (beyond the comparison and the board's boot time)
SAVE_TRANSACTIONS = 61
#: the settle a step leaves the leg (step_response's default) [s]
STEP_SETTLE = 2.0


def usb_latency() -> float:
    """Seconds per USB transaction: the device model's (the default plant's ``usb_latency``,
    from odrive_ros2_control#19's ~5 ms per axis read and write)."""
    return float(load_plant("default").usb_latency)


def _firmware():
    from .virtual import firmware  # load time: the firmware model's timings import the twin (numba)
    return firmware


def step_seconds(duration: float = 1.5, settle: float = STEP_SETTLE, sample_period: float = 0.002,
                 latency: float | None = None) -> float:
    """Bench time of one step (Listing 7.4 on the polling path): its set-up, ``duration``
    (the last sample ends up to ``sample_period`` after it), and the ``settle`` [s]."""
    lat = usb_latency() if latency is None else latency
    return duration + sample_period + settle + STEP_TRANSACTIONS * lat


def torque_seconds(duration: float, latency: float | None = None) -> float:
    """Bench time of one torque run (playback or a live loop) of ``duration`` [s]."""
    lat = usb_latency() if latency is None else latency
    return duration + TORQUE_TRANSACTIONS * lat


def hold_seconds(move_time: float = 2.0, settle: float = 0.5, latency: float | None = None) -> float:
    """Bench time of bringing the leg back to its rest pose (``return_to_rest``)."""
    lat = usb_latency() if latency is None else latency
    return move_time + settle + HOLD_TRANSACTIONS * lat


def rest_seconds(latency: float | None = None) -> float:
    """Bench time of measuring the rest pose (zeroing, or checking a known zero)."""
    lat = usb_latency() if latency is None else latency
    return REST_SETTLE + REST_WAIT + REST_TRANSACTIONS * lat


def calibration_seconds(axes: int = 2, latency: float | None = None) -> float:
    """Bench time of calibrating ``axes`` axes (motor and encoder offset, one after the other,
    the firmware's timings: :data:`leglib.device.virtual.firmware.CALIBRATION_DURATION`),
    the rest pose measured before and after."""
    if axes <= 0:
        return 0.0
    fw = _firmware()
    return axes * (fw.CALIBRATION_DURATION + CALIBRATION_POLL / 2) + 2 * rest_seconds(latency)


def reboot_seconds(latency: float | None = None) -> float:
    """Bench time of writing, saving and checking the configuration, the board's reboot
    until it answers again included (the firmware model's
    :data:`leglib.device.virtual.firmware.BOOT_TIME`)."""
    lat = usb_latency() if latency is None else latency
    return float(_firmware().BOOT_TIME) + SAVE_TRANSACTIONS * lat


def config_check_seconds(latency: float | None = None) -> float:
    """Bench time of reading back and comparing the configuration."""
    lat = usb_latency() if latency is None else latency
    return CONFIG_TRANSACTIONS * lat


def minutes(seconds: float) -> str:
    """``"24 s"``, ``"3.5 min"``, ``"1.2 h"``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


# ---------------------------------------------------------------------------------------
# the ledger
# ---------------------------------------------------------------------------------------

#: what each kind of note is called in a report (singular, plural)
KINDS = {
    "configure": ("configuration check", "configuration checks"),
    "save": ("configuration saved", "configurations saved"),
    "reboot": ("reboot", "reboots"),
    "calibration": ("axis calibrated", "axes calibrated"),
    "zeroing": ("zeroing", "zeroings"),
    "rest check": ("rest pose check", "rest pose checks"),
    "step": ("step", "steps"),
    "sweep": ("sweep", "sweeps"),
    "torque": ("torque run", "torque runs"),
    "hold": ("return to rest", "returns to rest"),
}


@dataclass
class Note:
    """One thing a board did: its ``kind`` (see :data:`KINDS`), how many, the bench seconds
    it took (``seconds``, read off the board's clock) of which ``charged`` were added
    because the twin ran it faster than the leg would (a batched step), and what was said."""

    serial: int
    backend: str
    kind: str
    count: int = 1
    seconds: float = 0.0
    charged: float = 0.0
    text: str = ""


_NOTES: list[Note] = []
_LOCK = threading.Lock()


def note(dev, kind: str, count: int = 1, seconds: float = 0.0, charged: float = 0.0, text: str = "") -> Note:
    """Add a note about ``dev``'s board to the ledger (``charged``: bench seconds the board's
    clock did not see)."""
    if kind not in KINDS:
        raise ValueError(f"unknown bench note kind {kind!r}; known: {sorted(KINDS)}")
    n = Note(dev.serial, dev.backend, kind, int(count), float(seconds) + float(charged), float(charged), text)
    with _LOCK:
        _NOTES.append(n)
    return n


_OPEN = threading.local()   # the timed blocks open on this thread, innermost last


@contextlib.contextmanager
def timed(dev, kind: str, count: int = 1, text: str = ""):
    """Note ``kind`` with the board-clock seconds the block took (also when it raises),
    without the seconds of the timed blocks inside it (a sweep's steps, a save's reboot):
    each second is a note's once. The block may set ``entry["count"]``, ``entry["text"]``
    and ``entry["charged"]`` (seconds the board's clock did not see)."""
    serial = dev.serial
    t0 = dev.board_clock()
    entry = {"count": count, "charged": 0.0, "text": text, "inner": 0.0}
    stack = _OPEN.__dict__.setdefault("stack", [])
    stack.append(entry)
    try:
        yield entry
    finally:
        stack.pop()
        with contextlib.suppress(Exception):   # the clock of a lost board: noted without its time
            took = dev.board_clock() - t0 + float(entry["charged"])
            n = Note(serial, dev.backend, kind, int(entry["count"]), took - entry["inner"],
                     float(entry["charged"]), entry["text"])
            if stack:   # what the board's clock saw of this block is not the outer block's own
                stack[-1]["inner"] += took - float(entry["charged"])
            with _LOCK:
                _NOTES.append(n)


@dataclass(frozen=True)
class Mark:
    """A point in the ledger (its length then) and, with a device, its board and clock."""

    index: int
    serial: int | None = None
    clock: float | None = None


def mark(dev=None) -> Mark:
    """The ledger now; with ``dev`` also its board's clock (a report since then counts the
    board's time from here)."""
    with _LOCK:
        index = len(_NOTES)
    if dev is None:
        return Mark(index)
    return Mark(index, dev.serial, dev.board_clock())


@dataclass
class BenchReport:
    """What a run did on one board and its bench time.

    ``seconds`` is the bench time at real speed (the board's clock from the start to the end,
    plus what the twin ran faster than the leg would, ``charged``); ``counts`` and
    ``by_kind`` count and time each kind of note (:data:`KINDS`); ``said`` what the session
    said (configuration differences, zeroing); ``planned`` the estimate made before (a
    :class:`Plan`), ``limit`` the limit it was held to [s]; ``backend`` ``"virtual"`` makes
    it a rehearsal (what the run would do on the leg).
    """

    backend: str
    serial: int | None
    seconds: float
    counts: dict = field(default_factory=dict)
    by_kind: dict = field(default_factory=dict)
    charged: float = 0.0
    said: list = field(default_factory=list)
    planned: float | None = None
    limit: float | None = None
    extra: str = ""

    @property
    def minutes(self) -> float:
        return self.seconds / 60.0

    def what(self) -> str:
        """The run's work, e.g. ``"1 reboot, 2 axes calibrated, 33 steps, 1 torque run"``."""
        parts = []
        for kind in ("save", "reboot", "calibration", "sweep", "step", "torque", "hold"):
            n = self.counts.get(kind, 0)
            one, many = KINDS[kind]
            if n:
                parts.append(f"{n} {one if n == 1 else many}")
            elif kind == "reboot":
                parts.append("no reboot")
            elif kind == "calibration":
                parts.append("no calibration")
        return ", ".join(parts)

    def __str__(self) -> str:
        head = ("Rehearsal on the twin: on the leg this run would do " if self.backend == "virtual"
                else "On the leg: ")
        times = ", ".join(f"{KINDS[k][1]} {minutes(v)}" for k, v in sorted(self.by_kind.items(), key=lambda kv: -kv[1])
                          if v >= 0.5)
        text = f"{head}{self.what()}: about {minutes(self.seconds)} of bench time" + (f" ({times})" if times else "")
        if self.planned is not None:
            text += f"; estimated beforehand: {minutes(self.planned)}"
        if self.limit is not None:
            text += f" (limit {minutes(self.limit)})"
        if self.extra:
            text += f"; {self.extra}"
        return text + "".join(f"\n  {s}" for s in self.said)

    def _repr_markdown_(self) -> str:
        return str(self).replace("\n  ", "\n\n- ", 1).replace("\n  ", "\n- ")

    def to_dict(self) -> dict:
        return {"backend": self.backend, "serial": None if self.serial is None else f"{self.serial:012X}",
                "bench_s": self.seconds, "counts": dict(self.counts), "by_kind_s": dict(self.by_kind),
                "charged_s": self.charged, "said": list(self.said), "planned_s": self.planned,
                "limit_s": self.limit, "summary": str(self).splitlines()[0]}


def report(since: Mark, dev=None, *, serial: int | None = None, clock: float | None = None,
           backend: str | None = None, planned: float | None = None, limit: float | None = None) -> BenchReport:
    """What happened on one board since ``since``: ``dev``'s board (or ``serial``), its time
    from ``since.clock`` (or its first note since) to its clock now (``dev``) or ``clock``."""
    if dev is not None:
        serial, backend = dev.serial, dev.backend
        clock = dev.board_clock() if clock is None else clock
    serial = since.serial if serial is None else serial
    if serial is None:
        raise ArgumentError("bench.report: which board? give dev, serial or a mark made with a device")
    with _LOCK:
        notes = [n for n in _NOTES[since.index:] if n.serial == serial]
    counts: dict = {}
    by_kind: dict = {}
    said = []
    for n in notes:
        counts[n.kind] = counts.get(n.kind, 0) + n.count
        by_kind[n.kind] = by_kind.get(n.kind, 0.0) + n.seconds
        if n.text:
            said.append(n.text)
    charged = sum(n.charged for n in notes)
    if since.clock is not None and since.serial == serial and clock is not None:
        span = clock - since.clock
    else:   # no clock at the start: the notes' own times
        span = sum(n.seconds - n.charged for n in notes)
    return BenchReport(backend or (notes[0].backend if notes else "usb"), serial, max(span, 0.0) + charged,
                       counts, by_kind, charged, said, planned, limit)


# ---------------------------------------------------------------------------------------
# the estimate beforehand and the limit
# ---------------------------------------------------------------------------------------

@dataclass
class Plan:
    """What a run will do on the leg, for its estimate before anything moves.

    Parameters
    ----------
    steps : steps (each ``step_duration`` [s] and ``step_settle`` [s])
    sweep_points : steps a sweep will measure (points not yet in its directory)
    torque : durations [s] of the torque runs (playbacks, live loops)
    holds : returns to the rest pose (``return_to_rest``, 2 s and 0.5 s each)
    sessions : connections that set the board up (each checks the configuration and the
        rest pose; the first also configures and calibrates what the board needs)
    note : what the estimate leaves out (e.g. a slider panel's steps)
    """

    steps: int = 0
    sweep_points: int = 0
    torque: tuple = ()
    holds: int = 0
    sessions: int = 1
    step_duration: float = 1.5
    step_settle: float = STEP_SETTLE
    note: str = ""

    def seconds(self, reboot: bool = False, calibrate_axes: int = 0, latency: float | None = None) -> float:
        """The estimate [s]; ``reboot``: the configuration is saved and the board reboots,
        ``calibrate_axes``: axes still to calibrate."""
        lat = usb_latency() if latency is None else latency
        t = self.sessions * (config_check_seconds(lat) + rest_seconds(lat))
        if reboot:
            t += reboot_seconds(lat)
        if calibrate_axes:
            # the calibration measures the rest pose before and after: one of them replaces
            # the first session's check
            t += calibration_seconds(calibrate_axes, lat) - rest_seconds(lat)
        t += (self.steps + self.sweep_points) * step_seconds(self.step_duration, self.step_settle, latency=lat)
        t += sum(torque_seconds(float(d), lat) for d in self.torque)
        t += self.holds * hold_seconds(latency=lat)
        return t

    def what(self, save: bool = False, reboot: bool = False, calibrate_axes: int = 0) -> str:
        """The plan in words, e.g. ``"the configuration saved (1 reboot), 2 axes calibrated, 1 step"``."""
        parts = []
        if save:
            parts.append("the configuration saved" + (" (1 reboot)" if reboot else ""))
        parts.append(f"{calibrate_axes} axes calibrated" if calibrate_axes else "no calibration")
        if self.sweep_points:
            parts.append(f"a sweep of {self.sweep_points} steps")
        if self.steps:
            parts.append(f"{self.steps} step{'s' if self.steps != 1 else ''}")
        if self.torque:
            parts.append(f"{len(self.torque)} torque run{'s' if len(self.torque) != 1 else ''}")
        if self.holds:
            parts.append(f"{self.holds} return{'s' if self.holds != 1 else ''} to rest")
        return ", ".join(parts)


def limit_seconds(max_minutes, what: str) -> float:
    """``max_minutes`` [min] checked (a positive number, the message naming ``what``), in seconds."""
    return 60.0 * checks.number(max_minutes, what, ArgumentError, low=0.0, low_open=True, unit="min")


def require(dev, seconds: float, max_minutes, what: str, parameter: str = "max_minutes") -> None:
    """Refuse (:class:`BenchLimitError`) ``what`` on a real leg when its estimate
    ``seconds`` is over ``max_minutes`` (None: :data:`DEFAULT_MAX_BENCH_MINUTES`); the
    message gives the estimate and names ``parameter``. On the twin nothing is refused."""
    limit = limit_seconds(DEFAULT_MAX_BENCH_MINUTES if max_minutes is None else max_minutes, parameter)
    if dev.backend != "virtual" and seconds > limit:
        raise BenchLimitError(f"{what} takes about {minutes(seconds)} on the leg ({seconds:.0f} s), more than "
                              f"{parameter} = {limit / 60:g} min allows: set {parameter} to at least "
                              f"{math.ceil(seconds / 60)} to run it")


class Run:
    """A run on the leg from its start (:func:`leglib.device.setup.start_run`) to its report (:meth:`report`)."""

    def __init__(self, dev, plan: Plan, planned: float, limit: float, what: str):
        self.serial, self.backend, self.plan = dev.serial, dev.backend, plan
        self.planned, self.limit, self.what = planned, limit, what
        self._clock = dev.board_clock
        self.mark = mark(dev)

    def report(self) -> BenchReport:
        """What the run did on the leg so far, its bench time, and the estimate beforehand."""
        r = report(self.mark, serial=self.serial, clock=self._clock(), backend=self.backend,
                   planned=self.planned, limit=self.limit)
        r.extra = self.plan.note
        return r
