"""Command line: ``python -m leglib run`` executes every notebook into reports/;
``python -m leglib batch SPEC [--scheduler tcp://...]`` runs notebooks over a grid;
``python -m leglib robustness`` writes the robustness table to reports/robustness/."""

from __future__ import annotations

import argparse
import sys

from ..errors import ParameterError, SpecError


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="leglib", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="execute every notebook against the virtual leg")
    run.add_argument("--out", default="reports", help="output directory (default: reports)")
    run.add_argument("--smoke", action="store_true", help="short runs (the tests' mode)")
    batch = sub.add_parser("batch", help="run notebooks over a parameter grid (see leglib.notebook.batch)")
    batch.add_argument("spec", help="batch spec (TOML)")
    batch.add_argument("--out", default="reports/batch", help="output root (default: reports/batch)")
    batch.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://host:8786")
    batch.add_argument("--workers", type=int, default=2, help="local processes (without --scheduler)")
    rob = sub.add_parser("robustness", help="every method on every twin plant (leglib.evaluation.robustness)")
    rob.add_argument("--out", default="reports/robustness", help="output directory (default: reports/robustness)")
    rob.add_argument("--plants", nargs="*", default=None, help="plant names (default: every shipped plant)")
    rob.add_argument("--payload", type=float, default=0.0, help="foot payload [kg] (default 0)")
    rob.add_argument("--quick", action="store_true", help="fewer targets, a shorter friction run")
    args = parser.parse_args(argv)
    if args.command == "robustness":
        from ..evaluation import robustness  # load time: every layer (numba, control), for this command only
        try:
            table = robustness.run(args.plants, payload=args.payload, quick=args.quick)
        except (ParameterError, FileNotFoundError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        md = robustness.write(table, args.out)
        print(md.read_text())
        print(f"wrote {md} and {md.with_suffix('.json')}")
        return 0
    if args.command == "batch":
        from .batch import (  # load time: dask, papermill, for this command only
            batch_root,
            load_spec,
            run_batch,
        )
        try:
            spec = load_spec(args.spec)
        except SpecError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        results = run_batch(spec, args.out, scheduler=args.scheduler, workers=args.workers)
        failed = {k: v for k, v in results.items() if v.get("status") != "done"}
        for k, v in failed.items():
            print(f"FAILED {k}: {v.get('notebook')} cell {v.get('cell')}: {v.get('error')}")
        index = batch_root(args.out, spec) / "index.html"
        print(f"{len(results) - len(failed)} runs done, {len(failed)} failed; index: {index}")
        return 1 if failed else 0
    if args.command == "run":
        from .run import run_all  # load time: papermill and the kernel machinery, for this command only
        for path in run_all(args.out, smoke=args.smoke):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
