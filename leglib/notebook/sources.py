"""Where a result a notebook reads from a file came from, and whether it is current.

A notebook that shows a result it did not compute (notebook 04's resumed sweep, notebook
05's sweep and robustness table, notebook 03's identified leg, a saved design started from)
shows beside it which commit made it, when and on which leg, and, when a commit since then
changed the code the result depends on, a visible "Made by an older version" notice
(:func:`leglib._version.staleness`: the one check, also behind the robustness table's
notice). Each function here reads one kind of file and returns a :class:`Source`, which
renders itself in a notebook and goes into the metrics as :meth:`Source.to_dict`.

What a result depends on (the paths a commit must touch to make it older):

- a measurement on the twin: the twin, the virtual device, the experiments, the parameter
  files and the model the twin's plant is built from (:data:`MEASURED_ON_TWIN`); on the real
  leg only what ran the experiment (:data:`MEASURED_ON_LEG`);
- an identified leg: the identification and the model, and its measurement's code;
- a saved state-feedback design: the design and the linear model; a saved gain design: the
  design package, the identification and its measurements' code;
- the robustness table: :data:`leglib.evaluation.robustness.TABLE_DEPENDS_ON`.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from .._version import short, staleness
from ..design import saved
from ..evaluation import robustness
from ..files.names import sidecar_path
from ..files.sweepdir import PROVENANCE_FILE, list_measurements

#: what ran an experiment on any device: its code makes a measurement what it is
MEASURED_ON_LEG = ("leglib/device", "leglib/experiments", "leglib/abort.py", "leglib/files/measurements.py")
#: ... and on the twin also the simulated leg and the parameter files its plant is built from
MEASURED_ON_TWIN = MEASURED_ON_LEG + ("leglib/twin", "leglib/params", "leglib/model", "leglib/kernelmath.py")
#: an identified leg (notebook 02): the identification and the model it fits, besides its measurement
IDENTIFIED = ("leglib/identify", "leglib/model", "leglib/params")
#: a saved design, by kind (besides the measurements a gain design came from)
DESIGN = {"state_feedback": ("leglib/design/statefeedback.py", "leglib/model", "leglib/params"),
          "cascade_gains": ("leglib/design", "leglib/identify", "leglib/model")}


def measured_with(backend: str | None) -> tuple:
    """The code a measurement made on ``backend`` depends on ("virtual": the twin's too; the
    real leg or unknown: what ran the experiment)."""
    return MEASURED_ON_TWIN if backend == "virtual" else MEASURED_ON_LEG


@dataclass
class Source:
    """A result read from a file: what it is (``what``), the file (``path``), the commit(s)
    that made it with how many of its files each made (``commits``), when (``dates``: the
    first and last), on what (``made_on``: backend, plant, seed...), and ``notice``: the
    "Made by an older version" sentence, or that it cannot tell, or None when it is current."""

    what: str
    path: str
    commits: dict = field(default_factory=dict)
    dates: tuple = ()
    made_on: str = ""
    notice: str | None = None

    @property
    def stale(self) -> bool:
        return bool(self.notice) and self.notice.startswith("Made by an older version")

    def text(self) -> str:
        """One line: "<what> read from <path>: made <when> at commit <c> (<on what>)"."""
        when = ""
        dates = [str(d)[:16].replace("T", " ") for d in self.dates]   # to the minute
        if dates:
            when = f" {dates[0]}" if len(set(dates)) == 1 else f" {dates[0]} to {dates[-1]}"
        if not self.commits:
            by = " by a commit it does not record"
        elif len(self.commits) == 1:
            by = f" at commit {short(next(iter(self.commits)))}"
        else:
            by = " at commits " + ", ".join(f"{short(c)} ({n} file(s))" for c, n in self.commits.items())
        on = f", {self.made_on}" if self.made_on else ""
        return f"{self.what} read from `{self.path}`: made{when}{by}{on}."

    def markdown(self) -> str:
        return (f"**{self.notice}**\n\n" if self.notice else "") + self.text()

    def _repr_markdown_(self) -> str:
        return self.markdown()

    def __str__(self) -> str:
        return (f"{self.notice}\n" if self.notice else "") + self.text().replace("`", "")

    def to_dict(self) -> dict:
        return {"what": self.what, "path": self.path, "commits": dict(self.commits), "dates": list(self.dates),
                "made_on": self.made_on, "notice": self.notice, "stale": self.stale}


def _worst(commits, depends_on, what: str, rerun: str, repo=None) -> str | None:
    """The notice of the commit that is oldest against ``depends_on`` (the most commits since
    changed that code); None when every one is current."""
    notices = [n for n in (staleness(c, depends_on, what=what, rerun=rerun, repo=repo) for c in commits) if n]
    older = [n for n in notices if n.startswith("Made by an older version")]

    def count(n):
        return int(n.split("Made by an older version: ")[1].split(" ")[0])
    if older:
        return max(older, key=count)
    return notices[0] if notices else None


def _made_on(meta: dict) -> str:
    parts = [f"backend {meta['backend']}"] if meta.get("backend") else []
    plant = meta.get("twin_plant")
    if plant:
        parts.append(f"plant {Path(str(plant)).stem.removeprefix('plant_')}")
    payload = (meta.get("twin_plant_values") or {}).get("payload_mass")
    if payload:
        parts.append(f"payload {payload:g} kg")
    if meta.get("twin_seed") is not None:
        parts.append(f"seed {meta['twin_seed']}")
    if meta.get("serial_number") or meta.get("device_serial"):
        parts.append(f"serial {meta.get('serial_number') or meta.get('device_serial')}")
    return ", ".join(parts)


def _json(path: Path) -> dict:
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _stamp_date(stamp: str) -> str:
    """"20261202_070740" -> "2026-12-02 07:07" (a measurement file's name)."""
    return f"{stamp[0:4]}-{stamp[4:6]}-{stamp[6:8]} {stamp[9:11]}:{stamp[11:13]}"


def sweep(directory, repo=None) -> Source:
    """A sweep directory (notebook 04's ``sweep_dir``): the commits that measured its files
    (each file's sidecar; ``sweep.json`` when no file says), when (the files' names) and on
    which leg; older than its measurement code (:func:`measured_with` its backend) when a
    commit since the oldest of them changed that code. Files without a sidecar (the thesis's
    own CSVs) were measured without leglib and count for no commit."""
    d = Path(directory)
    commits: Counter = Counter()
    dates, meta = [], {}
    for p in list_measurements(d) if d.is_dir() else []:
        side = _json(sidecar_path(p))
        stamp = re.match(r"[0-9]{8}_[0-9]{6}", p.name)   # a leglib file's name starts with when it was measured
        if side and stamp:
            dates.append(_stamp_date(stamp.group(0)))
        if side.get("git_commit"):
            commits[side["git_commit"]] += 1
            meta = meta or side
    record = _json(d / PROVENANCE_FILE)
    if not commits and record.get("git_commit"):
        commits[record["git_commit"]] += 1
    meta = meta or {**record.get("device", {})}
    backend = meta.get("backend")
    notice = None   # no commit: the thesis's own files, measured without leglib
    if commits:
        notice = _worst(commits, measured_with(backend), "This sweep",
                        "Measure it again (an empty sweep_dir, or delete the directory) for a current map.", repo)
    made_on = _made_on(meta) if commits else "files without a leglib record (the thesis's own measurements)"
    dates = sorted(dates)
    return Source("The sweep", str(d), dict(commits), (dates[0], dates[-1]) if dates else (), made_on, notice)


def identified(path, repo=None) -> Source:
    """Notebook 02's identified leg (``friction_identified.json``): the commit and date it
    records (``provenance``), else its measurement's; older than the identification, the model
    and its measurement's code when a commit since changed them."""
    p = Path(path)
    doc = _json(p)
    prov = doc.get("provenance") or {}
    source = doc.get("source")
    measured = _json(sidecar_path(source)) if source else {}
    commit = prov.get("git_commit")
    backend = doc.get("backend") or measured.get("backend")
    depends = IDENTIFIED + measured_with(backend)
    what = "The identified leg"
    if commit:
        notice = staleness(commit, depends, what=f"{what}", rerun="Run notebook 02_friction_fitting again.", repo=repo)
        commits = {commit: 1}
    else:
        # an older file records no commit: its measurement's says at least how old the data are
        notice = staleness(None, depends, what=f"{what} file", repo=repo)
        commits = {}
    made_on = _made_on({**measured, "backend": backend})
    if source:
        made_on += (", " if made_on else "") + f"from {Path(source).name}"
    return Source(what, str(p), commits, (prov["date"],) if prov.get("date") else (), made_on, notice)


def design(path, repo=None) -> Source:
    """A saved design (:func:`leglib.design.saved.save`): its provenance (commit, date,
    backend, device); older than the code of its kind (:data:`DESIGN`, and for a gain design
    its sweep's measurement code) when a commit since changed it."""
    data = saved.read(path)
    prov = data["provenance"]
    depends = DESIGN.get(data["kind"], ("leglib/design",))
    if data["kind"] == "cascade_gains":
        depends = depends + measured_with(prov.get("backend"))
    what = "The saved " + ("state-feedback design" if data["kind"] == "state_feedback" else "gain design")
    notice = staleness(prov.get("git_commit"), depends, what=what, rerun="Save the design again from a current run.",
                       repo=repo)
    return Source(what, str(path), {prov["git_commit"]: 1} if prov.get("git_commit") not in (None, "unknown") else {},
                  (prov["date"],), _made_on(prov), notice)


def table(doc: dict, path, repo=None) -> Source:
    """The robustness table (:func:`leglib.evaluation.robustness.load_table`'s document):
    :func:`leglib.evaluation.robustness.staleness`."""
    commit = doc.get("commit")
    return Source("The robustness table", str(path), {commit: 1} if commit else {},
                  (str(doc["date"]),) if doc.get("date") else (),
                  f"payload {doc.get('payload', 0):g} kg" + (", quick" if doc.get("quick") else ""),
                  robustness.staleness(doc, repo=repo))
