"""leglib's version, and the code's provenance for files that record what made them.

:func:`provenance` is what a file written by leglib records (version and git commit);
:func:`stamp` adds the date. :func:`staleness` is the other side: whether a result read
back from a file was made by an older version of the code it depends on (a commit since
the one that made it changed that code), as one sentence to show beside the result.
"""

from __future__ import annotations

import datetime
import subprocess
from pathlib import Path

__version__ = "0.1.0"

#: the repository leglib runs from (its git checkout, when it is one)
REPO = Path(__file__).resolve().parents[1]


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


def stamp() -> dict:
    """:func:`provenance` and the date (UTC, ISO 8601, seconds): what a result file records
    of what made it and when."""
    return {**provenance(), "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def short(commit) -> str:
    """A commit as people quote it (its first 7 hex digits), or "unknown"."""
    return str(commit)[:7] if commit and commit != "unknown" else "unknown"


def staleness(commit, depends_on, *, what: str = "This result", code: str = "the code it depends on",
              rerun: str = "", repo=None) -> str | None:
    """Whether a result made at ``commit`` is older than the code it depends on.

    Parameters
    ----------
    commit : str or None
        The commit that made the result (its file's ``git_commit``); None or "unknown" when
        the file does not say.
    depends_on : sequence of str
        The paths, relative to the repository, of the code the result's numbers depend on.
    what, code, rerun : str
        How the sentence names the result ("This table"), the code ("the code it scores")
        and what to run for a current one ("Rerun `make robustness` for a current table.").
    repo : path, optional
        The git checkout (default: the one leglib runs from).

    Returns
    -------
    None when no commit since ``commit`` changed ``depends_on``; else one sentence to show
    beside the result: "Made by an older version: N commit(s) since C changed <code>
    (latest: ...)." and ``rerun``; or, without git, without the commit or with a commit this
    checkout does not have, that it cannot tell.
    """
    root = Path(repo) if repo is not None else REPO
    if not commit or commit == "unknown":
        return f"{what} does not say which commit made it: it may be older than {code}."
    shown = short(commit)
    try:
        out = subprocess.run(["git", "log", "--format=%h %s", f"{commit}..HEAD", "--", *depends_on],
                             capture_output=True, text=True, cwd=root, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return f"Made at commit {shown}; git is not available here to tell whether {code} changed since."
    if out.returncode != 0:
        return f"Made at commit {shown}, which this checkout does not have: it may be older than {code}."
    changes = [line for line in out.stdout.splitlines() if line.strip()]
    if not changes:
        return None
    latest = changes[0] if len(changes[0]) <= 100 else changes[0][:97] + "..."
    return (f"Made by an older version: {len(changes)} commit(s) since {shown} changed {code} "
            f"(latest: {latest}).{' ' + rerun if rerun else ''}")
