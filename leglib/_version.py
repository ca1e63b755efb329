"""leglib's version, and the code's provenance for files that record what made them."""

from __future__ import annotations

import subprocess
from pathlib import Path

__version__ = "0.1.0"


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=5)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


_COMMIT = None


def provenance() -> dict:
    """leglib version and git commit (``"unknown"`` outside a git checkout), for sidecars
    and design files."""
    global _COMMIT
    if _COMMIT is None:
        _COMMIT = _git_commit() or "unknown"
    return {"leglib_version": __version__, "git_commit": _COMMIT}
