"""``python -m leglib``: the command line (:mod:`leglib.notebook.cli`)."""

import sys

from leglib.notebook.cli import main

if __name__ == "__main__":
    sys.exit(main())
