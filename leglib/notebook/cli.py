"""Command line: ``python -m leglib run`` executes every notebook into reports/;
``python -m leglib batch SPEC [--scheduler tcp://...]`` runs notebooks over a grid;
``python -m leglib robustness`` writes the robustness table to reports/robustness/;
``python -m leglib design --backend usb --zeta 0.24 --fn 5`` finds gains for prescribed
dynamics on a leg in a few steps (``lg.tune``), its bench time estimated first and limited;
``python -m leglib compile`` compiles the numba kernels ahead of their first use;
``python -m leglib odrivetool [--seed N --firmware 0.5.6 --plant NAME]`` opens odrivetool's
shell with ``odrv0`` on a virtual ODrive.

A bad argument (an unreachable or malformed scheduler, an output directory that cannot be
written, a payload out of range, a bad spec) is one line on stderr (``error: ...``) and
exit code 2, as argparse's own errors."""

from __future__ import annotations

import argparse
import errno
import math
import os
import secrets
import sys
from pathlib import Path

from ..errors import LeglibError, ParameterError, SpecError

# the payload the robustness command accepts [kg]: the leg's motors lift well under 1 kg
# at the foot (the bound of the plant's payload_mass)
MAX_PAYLOAD = 5.0
NO_WORKER_TIMEOUT = 120.0  # s, as leglib.notebook.batch.NO_WORKER_TIMEOUT (not imported: dask loads late)
CONNECT_TIMEOUT = 10.0  # s, as leglib.notebook.batch.CONNECT_TIMEOUT
# the design command: the most steps it may run, and its default bench limit [min] (as
# leglib.device.bench.DEFAULT_MAX_BENCH_MINUTES; not imported: the device layer loads late)
MAX_EXPERIMENTS = 50
MAX_BENCH_MINUTES = 5.0


def _number(text: str, what: str, low: float, high: float, unit: str = "") -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or not low <= value <= high:
        raise argparse.ArgumentTypeError(f"{text}{unit}: {what} must be within [{low:g}, {high:g}]{unit}")
    return value


def _payload(text: str) -> float:
    return _number(text, "the payload on the foot", 0.0, MAX_PAYLOAD, " kg")


def _seconds(text: str) -> float:
    value = _number(text, "a time", 0.0, 86400.0, " s")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} s: must be positive")
    return value


def _workers(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 1 <= value <= 256:
        raise argparse.ArgumentTypeError(f"{text}: between 1 and 256 processes")
    return value


def _positive(what: str, high: float, unit: str = ""):
    def parse(text: str) -> float:
        value = _number(text, what, 0.0, high, unit)
        if value <= 0:
            raise argparse.ArgumentTypeError(f"{text}{unit}: {what} must be positive")
        return value
    return parse


def _experiments(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 1 <= value <= MAX_EXPERIMENTS:
        raise argparse.ArgumentTypeError(f"{text}: between 1 and {MAX_EXPERIMENTS} steps")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 0 <= value <= 2**32 - 1:
        raise argparse.ArgumentTypeError(f"{text}: a seed is 0 to 2**32 - 1")
    return value


def _plant_names() -> list[str]:
    from ..params import plant_names  # load time: only to list the choices in --help
    try:
        return plant_names()
    except (OSError, ParameterError):
        return []


def writable_dir(path: str | Path, option: str = "--out") -> Path:
    """Create ``path`` (and its parents) and check a file can be written in it; one-line
    OSError naming the option and the directory otherwise."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".leglib-write-probe.{secrets.token_hex(4)}"
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
        probe.unlink()
    except FileExistsError:
        raise NotADirectoryError(errno.ENOTDIR, f"{option} {path}: exists and is not a directory") from None
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise OSError(exc.errno, f"{option} {path}: cannot write there ({reason})") from None
    return path


def _fail(exc: BaseException) -> int:
    text = str(exc)
    if isinstance(exc, OSError) and exc.strerror:  # not "[Errno 28] ...: 'path'": the message, the path once
        text = exc.strerror
        if exc.filename is not None and str(exc.filename) not in text:
            text = f"{exc.filename}: {text}"
    text = " ".join(text.split())  # one line
    print(f"error: {text}", file=sys.stderr)
    return 2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="leglib", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="execute every notebook against the virtual leg")
    run.add_argument("--out", default="reports", help="output directory (default: %(default)s)")
    run.add_argument("--smoke", action="store_true", help="short runs, the tests' mode (default: full runs)")
    batch = sub.add_parser("batch", help="run notebooks over a parameter grid (see leglib.notebook.batch)")
    batch.add_argument("spec", help="batch spec (TOML), e.g. data/batch_payload.toml")
    batch.add_argument("--out", default="reports/batch", help="output root (default: %(default)s)")
    batch.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="Dask scheduler address, e.g. tcp://host:8786 (default: none, local processes)")
    batch.add_argument("--workers", type=_workers, default=2,
                       help="local processes, without --scheduler, 1 to 256 (default: %(default)s)")
    batch.add_argument("--connect-timeout", type=_seconds, default=CONNECT_TIMEOUT, metavar="SECONDS",
                       help="how long to try reaching the scheduler (default: %(default)g s)")
    batch.add_argument("--no-worker-timeout", type=_seconds, default=NO_WORKER_TIMEOUT, metavar="SECONDS",
                       help="stop when no Dask worker is alive this long; the runs left are "
                            "recorded pending (default: %(default)g s)")
    plants = _plant_names()
    rob = sub.add_parser("robustness", help="every method on every twin plant (leglib.evaluation.robustness)")
    rob.add_argument("--out", default="reports/robustness", help="output directory (default: %(default)s)")
    rob.add_argument("--plants", nargs="*", default=None, metavar="PLANT", choices=plants or None,
                     help=f"plant names, of {{{', '.join(plants)}}} (default: all of them)")
    rob.add_argument("--payload", type=_payload, default=0.0, metavar="KG",
                     help=f"foot payload [kg], 0 to {MAX_PAYLOAD:g} (default: %(default)g)")
    rob.add_argument("--quick", action="store_true", help="fewer targets, a shorter friction run (default: off)")
    des = sub.add_parser("design", help="gains for prescribed dynamics on a leg in a few steps (lg.tune), the bench "
                                        "time estimated first and limited",
                         description="The fewest-experiment design (leglib.design.tuning.tune) on the real leg "
                                     "(--backend usb) or its twin: the board is configured and calibrated only where "
                                     "it needs it, the run's bench time is estimated before anything moves and on the "
                                     "leg refused past --max-minutes. Exit code 0 when the target was reached, 1 when "
                                     "not (the best gains are printed), 2 on a bad argument or a refused run.")
    des.add_argument("--backend", choices=("virtual", "usb"), default="virtual",
                     help="the real leg (usb) or the twin (virtual) (default: %(default)s)")
    des.add_argument("--zeta", type=_positive("zeta", 5.0), default=0.24,
                     help="target damping ratio of the foot's step, true measure (default: %(default)g)")
    des.add_argument("--fn", type=_positive("fn", 50.0, " Hz"), default=5.0,
                     help="target natural frequency [Hz] (default: %(default)g)")
    des.add_argument("--max-experiments", type=_experiments, default=10, metavar="N",
                     help=f"most steps on the leg, the final check included, 1 to {MAX_EXPERIMENTS} (default: %(default)s)")
    des.add_argument("--max-minutes", type=_positive("the bench limit", 600.0, " min"), default=MAX_BENCH_MINUTES,
                     metavar="MIN", help="longest run allowed on the real leg [min] (default: %(default)g)")
    des.add_argument("--leg", default="thesis", help="nominal leg parameters: leg_<name>.toml or a path (default: %(default)s)")
    des.add_argument("--odrive-config", default="thesis",
                     help="ODrive configuration and bounds: odrive_<name>.toml or a path (default: %(default)s)")
    des.add_argument("--serial-number", default=None, metavar="HEX",
                     help="the ODrive to find on USB (default: any)")
    des.add_argument("--timeout", type=_seconds, default=CONNECT_TIMEOUT, metavar="SECONDS",
                     help="USB search timeout (default: %(default)g s)")
    des.add_argument("--seed", type=_seed, default=0, help="the twin's seed, virtual only (default: %(default)s)")
    des.add_argument("--plant", default="default", choices=plants or None, metavar="PLANT",
                     help=f"the twin's plant, virtual only, of {{{', '.join(plants)}}} (default: %(default)s)")
    des.add_argument("--payload", type=_payload, default=0.0, metavar="KG",
                     help=f"the twin's foot payload [kg], virtual only, 0 to {MAX_PAYLOAD:g} (default: %(default)g)")
    des.add_argument("--save", default=None, metavar="PATH",
                     help="write the design (cascade gains, target, measured) to this JSON file (default: not saved)")
    comp = sub.add_parser("compile", help="compile the numba kernels now (make venv does; run does when their "
                                          "sources changed), one line per group as it ends")
    comp.add_argument("--if-changed", action="store_true",
                      help="only when a kernel's source changed since the last compile")
    tool = sub.add_parser("odrivetool", help="odrivetool's shell (IPython, odrv0) on a virtual ODrive v3.6")
    tool.add_argument("--seed", type=_seed, default=0, help="the virtual ODrive's seed: its serial number, "
                      "its noise (default: %(default)s)")
    tool.add_argument("--firmware", default="0.5.6", choices=("0.5.6", "0.5.1"),
                      help="firmware release (default: %(default)s)")
    tool.add_argument("--plant", default="default", choices=plants or None, metavar="PLANT",
                      help=f"the leg it drives, of {{{', '.join(plants)}}} (default: %(default)s)")
    tool.add_argument("--no-ipython", action="store_true", help="the plain Python console instead of IPython")
    return parser


def _design(args) -> int:
    """``python -m leglib design``: connect, estimate and limit, set up, tune, report."""
    from ..design import saved  # load time: the design layer (scipy), for this command only
    from ..design.tuning import tune  # load time: as above
    from ..device import bench  # load time: the device layer, for this command only
    from ..device.session import connect  # load time: as above
    from ..device.setup import calibrate, configure, start_run  # load time: as above
    from ..params import load_leg, load_odrive_config  # load time: parameter files, for this command only
    from .setup import device_options  # load time: matplotlib (through plots), for this command only

    if args.backend == "usb" and (args.seed, args.plant, args.payload) != (0, "default", 0.0):
        raise ParameterError("--seed, --plant and --payload are the twin's: not for --backend usb")
    leg = load_leg(args.leg)
    cfg = load_odrive_config(args.odrive_config)
    options = device_options(args.backend, args.seed, args.plant, args.payload)
    if args.backend == "usb":
        options = {"timeout": args.timeout, "serial_number": args.serial_number}
    if args.save:
        writable_dir(Path(args.save).parent or ".", "--save")
    with connect(args.backend, leg=leg, config=cfg, **options) as dev:
        run = start_run(dev, bench.Plan(steps=args.max_experiments), args.max_minutes, parameter="--max-minutes")
        configure(dev, verbose=True)
        calibrate(dev, verbose=True)
        result = tune(dev, args.zeta, args.fn, args.max_experiments, progress=True, max_minutes=args.max_minutes)
        if args.save:
            measured = result.measured if all(math.isfinite(x) for x in result.measured) else None
            # the final check's 90 % intervals, stored beside what they qualify
            design = saved.GainDesign(result.target, result.gains, "tune", result.predicted, measured,
                                      {"experiments": len(result.experiments), "reached": bool(result.reached),
                                       "tolerance": result.tolerance, "verdict": result.verdict},
                                      measured_intervals=result.intervals if measured is not None else None)
            path = saved.save(args.save, design, device=dev,
                              note=f"python -m leglib design --zeta {args.zeta:g} --fn {args.fn:g}")
    print(result)
    print(result.table())
    print(run.report())
    if args.save:
        print(f"wrote {path}: {design}")
    return 0 if result.reached else 1


def odrivetool(seed: int = 0, firmware: str = "0.5.6", plant: str = "default", no_ipython: bool = False) -> int:
    """odrivetool's interactive shell (``odrive.shell.launch_shell``: IPython, the
    ``odrive.utils`` and ``odrive.enums`` names, ``odrv0``) on the virtual ODrive of
    ``seed``, paced in real time; the client's device manager looks for ODrives on the
    virtual interface only, so odrv0 is the virtual board and is found again after every
    reboot (save_configuration, restore_config)."""
    import asyncio  # load time: for this command only

    async def shell():
        from odrive.device_manager import get_device_manager  # load time: the odrive client, for this command only
        from odrive.shell import launch_shell, load_default_ns  # load time: the odrive client, for this command only

        from ..device.virtual import wire  # load time: the device layer, for this command only
        dm = get_device_manager()                      # bound to this loop, as odrivetool's
        wire.find_any(seed=seed, firmware=firmware, plant=plant, realtime=True)
        _, intf = wire._manager()
        dm.default_interfaces = {intf}
        print(f"virtual ODrive v3.6-56V, firmware {firmware}, seed {seed} (serial "
              f"{wire.serial_for_seed(seed):012X}), plant {plant!r}, in real time")
        await launch_shell(load_default_ns(), {}, dm, no_ipython=no_ipython)

    asyncio.run(shell())
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "design":
        try:
            return _design(args)
        except (LeglibError, OSError) as exc:
            return _fail(exc)
    if args.command == "odrivetool":
        try:
            return odrivetool(args.seed, args.firmware, args.plant, args.no_ipython)
        except (LeglibError, ValueError) as exc:
            return _fail(exc)
    if args.command == "robustness":
        from ..evaluation import robustness  # load time: every layer (numba, control), for this command only
        try:
            writable_dir(args.out)
            table = robustness.run(args.plants, payload=args.payload, quick=args.quick)
            md = robustness.write(table, args.out)
        except (LeglibError, OSError) as exc:
            return _fail(exc)
        print(md.read_text())
        print(f"wrote {md} and {md.with_suffix('.json')}")
        return 0
    if args.command == "batch":
        from .batch import (  # load time: dask, papermill, for this command only
            SchedulerError,
            batch_root,
            load_spec,
            run_batch,
        )
        try:
            spec = load_spec(args.spec)
            writable_dir(args.out)
            results = run_batch(spec, args.out, scheduler=args.scheduler, workers=args.workers,
                                no_worker_timeout=args.no_worker_timeout, connect_timeout=args.connect_timeout)
        except (SpecError, SchedulerError, OSError) as exc:
            return _fail(exc)
        failed = {k: v for k, v in results.items() if v.get("status") != "done"}
        for k, v in failed.items():
            word = "NOT RUN" if v.get("status") == "pending" else "FAILED"
            print(f"{word} {k}: {v.get('notebook')} cell {v.get('cell')}: {v.get('error')}")
        index = batch_root(args.out, spec) / "index.html"
        print(f"{len(results) - len(failed)} runs done, {len(failed)} failed or not run; index: {index}")
        return 1 if failed else 0
    if args.command == "compile":
        from . import warmup  # load time: for this command only
        try:
            warmup.ensure() if args.if_changed else warmup.compile_kernels()
        except RuntimeError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        return 0
    if args.command == "run":
        from .run import run_all  # load time: papermill and the kernel machinery, for this command only
        try:
            writable_dir(args.out)
        except OSError as exc:
            return _fail(exc)
        for path in run_all(args.out, smoke=args.smoke):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
