"""Command line: ``python -m leglib run`` executes every notebook into reports/."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="leglib", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="execute every notebook against the virtual leg")
    run.add_argument("--out", default="reports", help="output directory (default: reports)")
    run.add_argument("--smoke", action="store_true", help="short runs (the tests' mode)")
    args = parser.parse_args(argv)
    if args.command == "run":
        from .notebooks import run_all
        for path in run_all(args.out, smoke=args.smoke):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
