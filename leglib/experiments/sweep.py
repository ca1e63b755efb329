"""Listing 7.4's sweep: a step response for every point of a gain grid, written as
measurement files, resumable, shared safely between writers.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ..device import bench
from ..device.session import (
    Device,
    any_error,
    as_device,
    check_gains,
    clear_errors,
    prepare_closed_loop,
    safe,
)
from ..errors import MeasurementError
from ..files.atomic import deferred_sync
from ..files.claims import claim, claim_many
from ..files.measurements import read_file, write_batch
from ..files.names import gains_key
from ..files.sweepdir import (
    check_provenance,
    committed_gains,
    find_uncommitted,
    list_measurements,
    set_aside,
    uncommitted_claim_key,
)
from .step import _STEP_FIELDS, _batch_points, batch_charge, step_response


@dataclass
class SweepResult:
    """What :func:`sweep` did: files written now (``written``; a twin batch is one file of
    many points) and the points ``measured`` now, points skipped (already measured, here or
    meanwhile by another writer), unstable points, and files set aside into
    ``incomplete/`` (damaged or unfinished; their points were measured again)."""

    written: list[Path]
    skipped: int
    unstable: int
    out_dir: Path
    set_aside: list[Path] = field(default_factory=list)
    measured: int = 0   # points measured now (a twin batch writes many into one file)
    #: what the sweep did on the leg and its bench time (:class:`leglib.device.bench.BenchReport`;
    #: on the twin: what it would take on the leg)
    bench: object = None

    @property
    def paths(self) -> list[Path]:
        return list_measurements(self.out_dir)


def thesis_grid(pos_n: int = 4, vel_n: int = 10, vint_n: int = 10) -> np.ndarray:
    """Listing 7.4's grid of gains (or a coarser one over the same ranges).

    Parameters
    ----------
    pos_n, vel_n, vint_n : int
        Values of each gain (the listing's 4, 10, 10; the notebooks' smoke runs take 2, 4, 4).

    Returns
    -------
    (pos_n * vel_n * vint_n, 3) ndarray
        pos_gain 20..50 [(turn/s)/turn], vel_gain 0.002..0.18 [N*m/(turn/s)],
        vel_integrator_gain 0.002..0.08 [N*m/turn], every combination.
    """
    for name, n in (("pos_n", pos_n), ("vel_n", vel_n), ("vint_n", vint_n)):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"thesis_grid: {name} must be a positive integer, got {n!r}")
    pos = np.linspace(20, 50, pos_n)
    vel = np.linspace(0.002, 0.18, vel_n)
    vint = np.linspace(0.002, 0.08, vint_n)
    return np.array([(p, v, i) for p in pos for v in vel for i in vint])


def pending_points(grid, out_dir: str | Path) -> int:
    """How many points of ``grid`` a sweep into ``out_dir`` would measure now: the distinct
    triples without a committed measurement there (read from names and batch sidecars
    only, nothing changed; a thesis-named file is not counted as done, so this is at most
    what the sweep measures)."""
    grid = np.atleast_2d(np.asarray(list(grid), dtype=float))
    if grid.size == 0:
        return 0
    if grid.shape[1] != 3:
        raise ValueError(f"grid must hold (pos_gain, vel_gain, vel_integrator_gain) triples, got shape {grid.shape}")
    done = committed_gains(out_dir) if Path(out_dir).is_dir() else set()
    return len({tuple(float(x) for x in g) for g in grid} - done)


def sweep_seconds(points: int, duration: float = 1.5, sample_period: float = 0.002) -> float:
    """Bench time [s] of a sweep of ``points`` steps on the leg (each step and its 2 s settle,
    :func:`leglib.device.bench.step_seconds`)."""
    return points * bench.step_seconds(duration, bench.STEP_SETTLE, sample_period)


def _write_batch(dev: Device, gains, out: dict, step: float, out_dir: Path) -> tuple[Path, int]:
    """A twin batch as one batch file (:func:`leglib.files.measurements.write_batch`), with the fields
    :meth:`StepResponse.write` gives a point's own file; (its path, the unstable points)."""
    Q1, Q2, t, meta, points = _batch_points(dev, gains, out)
    D1, D2 = np.degrees(Q1, out=Q1), np.degrees(Q2, out=Q2)   # (in place: fewer fresh pages)
    series = [(t[:n], D1[i, :n], D2[i, :n], g, {"completed": completed, "abort_reason": reason})
              for i, (g, n, completed, reason) in enumerate(points)]
    path = write_batch(out_dir, series, {**_STEP_FIELDS, "step_turns": step, **meta})
    return path, sum(not completed for _, _, completed, _ in points)


def sweep(odrv, grid, out_dir: str | Path, resume: bool = True, progress: bool = True,
          step: float = 0.4, duration: float = 1.5, sample_period: float = 0.002,
          chunk: int = 400, max_minutes: float | None = None) -> SweepResult:
    """Measure a step response for every (pos_gain, vel_gain, vel_integrator_gain) in
    ``grid`` and write them as measurement files in ``out_dir``: on the twin each batch of
    points as one batch file (:func:`leglib.files.measurements.write_batch`), on a real leg
    each point as its own file, as it is measured.

    Resumable: a point is done when a readable measurement with exactly its gains exists.
    Files that cannot be read (damaged, or the orphan of an interrupted write) and
    uncommitted leftovers are moved to ``out_dir/incomplete/`` and their points measured
    again. The directory's provenance (``sweep.json``: the device's identity from
    ``Device.describe()`` -- backend, serial, firmware, twin seed and plant with its payload
    -- and step, duration, sample period) is written by the first sweep. Each point is
    claimed (:func:`leglib.files.claims.claim`) while it is measured and written, so two
    sweeps into one directory share the grid: neither loses nor duplicates a point. Each file
    is committed when its point is done, so an interruption (exception, lost device,
    KeyboardInterrupt) loses no finished point; the axes go IDLE whatever happens. On the
    twin a batch's file is not flushed to disk by itself, only its directory at the batch's
    end (:func:`leglib.files.atomic.deferred_sync`: after a power loss it may be missing or
    cut, which the reader refuses and a resumed sweep measures again); on USB each file is
    flushed as it is written.

    Parameters
    ----------
    odrv : Device or an ODrive object (calibrated, zeroed)
    grid : (N, 3) array_like
        The gain triples, each within the configuration's bounds.
    out_dir : str or Path
        The sweep's directory (created if needed).
    resume : bool
        Complete a directory that already holds measurements (False refuses a non-empty one).
    progress : bool
        Show a progress bar.
    step, duration, sample_period : float
        Each step's motor step [turn], length and sampling period [s] (see
        :func:`leglib.experiments.step.step_response`).
    chunk : int
        On the twin, points per compiled batch (the thesis grid in one: a batch costs a fixed
        setup, and the kernel shares a batch out best when it is large).
    max_minutes : float, optional
        On a real leg, the longest the sweep may take [min] (default
        :data:`leglib.device.bench.DEFAULT_MAX_BENCH_MINUTES`): a sweep whose estimate
        (:func:`sweep_seconds` of the points still to measure) is longer is refused before
        anything moves or is written, the message giving the estimate. The thesis grid
        takes about 24 minutes. On the twin nothing is refused.

    Returns
    -------
    SweepResult
        The files written now, the points measured now and skipped, the unstable ones, the
        files set aside, and ``bench``: what it did on the leg (on the twin: would do) and its
        bench time at real speed.

    Raises
    ------
    NotADirectoryError, PermissionError
        ``out_dir`` cannot be a writable directory.
    ValueError
        ``grid`` does not hold gain triples, or a gain is outside the configured bounds.
    FileExistsError
        ``out_dir`` holds measurements and ``resume`` is False.
    ProvenanceError
        ``out_dir`` holds another leg's or experiment's sweep.
    BenchLimitError
        On a real leg: the sweep would take longer than ``max_minutes``.
    """
    dev = as_device(odrv)
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise NotADirectoryError(f"{out_dir}: not a directory (a file is in the way)") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise PermissionError(f"{out_dir}: directory not writable")
    grid = np.atleast_2d(np.asarray(list(grid), dtype=float))
    if grid.shape[1] != 3:
        raise ValueError(f"grid must hold (pos_gain, vel_gain, vel_integrator_gain) triples, "
                         f"got shape {grid.shape}")
    for g in grid:
        check_gains(dev.config, *g)
    todo = pending_points(grid, out_dir)
    bench.require(dev, sweep_seconds(todo, duration, sample_period), max_minutes,
                  f"the sweep of {todo} point(s) into {out_dir}")
    record = {"device": dev.describe(),
              "experiment": {"step": step, "duration": duration, "sample_period": sample_period,
                             "step_vel_limit": dev.config.step_vel_limit}}
    existing = list_measurements(out_dir)
    if existing and not resume:
        raise FileExistsError(f"{out_dir} already holds {len(existing)} measurements; pass resume=True "
                              f"to complete the sweep, or choose an empty directory")
    check_provenance(out_dir, record, write=True)

    moved: list[Path] = []
    done: set = set()
    done_rounded: set = set()
    for p in existing:
        try:
            found = read_file(p)
        except MeasurementError:
            moved.append(set_aside(p))  # damaged or unfinished: measured again
            continue
        for m in found:
            if m.gains is not None:
                done.add(tuple(float(x) for x in m.gains))
                if not m.meta.get("gains"):  # a thesis file: its name holds three decimals only
                    done_rounded.add(gains_key(m.gains))
    for p in find_uncommitted(out_dir):
        g = uncommitted_claim_key(p)
        c = claim(out_dir, g) if g is not None else None
        if c is not None:  # its writer is gone (a live writer holds the claim)
            # a sidecar whose CSV appeared meanwhile was committed by a writer that has
            # finished since it was listed: it stays
            committed = p.suffix == ".json" and os.path.lexists(p.with_suffix(".csv"))
            if os.path.lexists(p) and not committed:
                moved.append(set_aside(p))
            c.release()

    pending, seen = [], set(done)
    for g in grid:
        k = tuple(float(x) for x in g)
        if k not in seen and gains_key(g) not in done_rounded:
            seen.add(k)
            pending.append(g)
    skipped = len(grid) - len(pending)
    written: list[Path] = []
    unstable = measured = 0
    vl = dev.config.step_vel_limit
    size = chunk if dev.backend == "virtual" else 1
    bar = tqdm(total=len(grid), initial=skipped, desc="sweep", unit="step", disable=not progress)
    queue = pending
    claims: list = []
    since = bench.mark(dev)
    try:
        with bench.timed(dev, "sweep", text=f"sweep into {out_dir}") as sweep_note, safe(dev):
            batched = dev.sim is not None and not dev.sim.realtime
            if batched:
                prepare_closed_loop(dev, vl, watchdog=None)
            else:
                size = 1
            while queue:
                held, taken = claim_many(out_dir, queue, limit=size)
                claims.append(held)
                block = [g for g, ok in zip(queue, taken) if ok]
                waiting = [g for g, ok in zip(queue, taken) if not ok]
                if block:  # a point another writer committed meanwhile is done
                    now = committed_gains(out_dir)
                    keep = [tuple(float(x) for x in g) not in now for g in block]
                    skipped += keep.count(False)
                    bar.update(keep.count(False))
                    block = [g for g, k in zip(block, keep) if k]
                if not block and waiting:
                    # every point left is being measured by another writer: wait for one
                    for c in claims:
                        c.release()
                    claims = []
                    claim(out_dir, waiting[0], wait=True).release()
                    queue = waiting
                    continue
                if block:
                    if batched:
                        # the twin's batch: one batch file, its directory flushed at the
                        # end (deferred_sync)
                        arr = np.array(block)
                        with bench.timed(dev, "step", count=len(block)) as entry:
                            t0 = dev.board_clock()
                            out = dev.sim.step_batch(arr, step_turns=step, duration=duration,
                                                     sample_period=sample_period, vel_limit=vl,
                                                     abort_error_turns=2 * abs(step))
                            entry["charged"] = batch_charge(dev, out, dev.board_clock() - t0, duration,
                                                            bench.STEP_SETTLE, sample_period)
                        with deferred_sync():
                            path, bad = _write_batch(dev, arr, out, step, out_dir)
                        written.append(path)
                        unstable += bad
                    else:
                        # a real leg's measurement: its own file, flushed as it is written
                        resp = step_response(dev, *block[0], step=step, duration=duration,
                                             sample_period=sample_period)
                        written.append(resp.write(out_dir))
                        unstable += not resp.completed
                    measured += len(block)
                    bar.update(len(block))
                    if any_error(dev):   # recorded with the failed point; the sweep goes on
                        clear_errors(dev)
                for c in claims:
                    c.release()
                claims = []
                queue = waiting
            sweep_note["text"] = (f"sweep into {out_dir}: {measured} point(s) measured, {skipped} already there, "
                                  f"{unstable} unstable")
    finally:
        for c in claims:
            c.release()
        bar.close()
    return SweepResult(written=written, skipped=skipped, unstable=unstable, out_dir=out_dir,
                       set_aside=moved, measured=measured, bench=bench.report(since, dev))
