"""Command line: ``python -m leglib run`` executes every notebook into reports/;
``python -m leglib batch SPEC [--scheduler tcp://...]`` runs notebooks over a grid;
``python -m leglib robustness`` writes the robustness table to reports/robustness/;
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
    tool = sub.add_parser("odrivetool", help="odrivetool's shell (IPython, odrv0) on a virtual ODrive v3.6")
    tool.add_argument("--seed", type=_seed, default=0, help="the virtual ODrive's seed: its serial number, "
                      "its noise (default: %(default)s)")
    tool.add_argument("--firmware", default="0.5.6", choices=("0.5.6", "0.5.1"),
                      help="firmware release (default: %(default)s)")
    tool.add_argument("--plant", default="default", choices=plants or None, metavar="PLANT",
                      help=f"the leg it drives, of {{{', '.join(plants)}}} (default: %(default)s)")
    tool.add_argument("--no-ipython", action="store_true", help="the plain Python console instead of IPython")
    return parser


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text}: a seed is a non-negative integer")
    return value


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
