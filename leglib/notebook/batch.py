"""Batch re-runs of notebooks over a parameter grid, locally or on a Dask cluster.

A spec (TOML)::

    name = "payload"
    notebooks = ["04_pid_sweeps", "05_validation"]   # run in this order, in one run directory
    [parameters]                                     # the same for every run
    smoke = true
    [grid]                                           # every combination is a run
    payload_mass = [0.0, 0.5, 1.0]

Each run writes its executed notebooks, figures and metrics JSON under
``reports/batch/<name>/<run id>/`` and a ``status.json``; a run whose status says
"done" is skipped when the batch is re-run. A failing run records the notebook and cell
that failed and does not stop the others. ``index.html`` lists all runs, each linked to its
reports, with the chosen metrics of :data:`SUMMARY_METRICS` (validation errors, identified
parameters) and units; ``summary.png`` plots those against the swept parameter.
"""

from __future__ import annotations

import asyncio
import difflib
import hashlib
import html
import io
import itertools
import json
import math
import re
import sys
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from pathlib import Path

from tqdm.auto import tqdm

from .. import checks
from ..errors import LeglibError, SpecError
from ..files.atomic import write_bytes_atomic, write_json_atomic
from .run import NOTEBOOK_DIR, execute

SPEC_KEYS = ("name", "notebooks", "parameters", "grid")
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$", re.ASCII)
MAX_SPEC_BYTES = 1 << 20
MAX_RUNS = 10_000
_TYPES = {"int": (int,), "float": (int, float), "str": (str,), "bool": (bool,)}


def _did_you_mean(name, known) -> str:
    close = difflib.get_close_matches(str(name), list(known), n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else f"; known: {', '.join(sorted(known))}"


def _short(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


_INSPECTED: dict = {}


def _inspect(path: Path) -> dict:
    """papermill's view of a notebook's parameters, cached while the file is unchanged."""
    import papermill as pm  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run
    key = (str(path), path.stat().st_mtime_ns)
    if key not in _INSPECTED:
        _INSPECTED[key] = pm.inspect_notebook(str(path))
    return _INSPECTED[key]


# parameters a batch sets itself for every run (each run's own files under its directory)
BATCH_SET = ("figures_dir", "metrics_path", "identified_path")
MAX_MESSAGE = 560  # characters of a SpecError listing several problems


def _value_key(v):
    """A grid value by value: 0 and 0.0 are one value, True and 1 are not."""
    if isinstance(v, bool):
        return ("bool", v)
    if isinstance(v, (int, float)):
        return ("number", v)  # int and float equal by value hash alike
    return (type(v).__name__, v)


def _spec_error(path: Path, problems: list[str]) -> SpecError:
    """One SpecError naming the spec file and every problem found (as many as fit)."""
    if len(problems) == 1:
        return SpecError(f"{path}: {problems[0]}")
    head = f"{path}: {len(problems)} problems: "
    shown, size = [], len(head)
    for k, text in enumerate(problems):
        text = text if len(text) <= 200 else text[:200] + "..."
        rest = len(problems) - k - 1
        tail = f"; and {rest} more" if rest else ""
        if shown and size + len(text) + 2 + len(tail) > MAX_MESSAGE:
            shown.append(f"and {len(problems) - k} more")
            break
        shown.append(text)
        size += len(text) + 2
    return SpecError(head + "; ".join(shown))


def load_spec(path: str | Path) -> dict:
    """Read and check a batch spec; SpecError names the file and every field in error (all
    problems found, in one message).

    Refused: unknown top-level keys (with a suggestion), a ``name`` that is not a plain
    directory name (letters, digits, ``.``, ``_``, ``-``; at most 64 characters; not
    ``.``/``..``), notebooks that do not exist, parameters no notebook of the spec takes,
    parameters the batch sets itself for each run (:data:`BATCH_SET`: ``figures_dir``,
    ``metrics_path``, ``identified_path``), values whose type differs from the notebook's
    parameter (an int where a float is expected is fine), empty grid values, values
    repeated by value (``0`` and ``0.0`` are one value), and more than MAX_RUNS runs. The
    values' ranges are checked by each notebook's first cell.
    """
    path = Path(path)
    text = checks.text_file(path, "spec", SpecError, form="TOML", max_bytes=MAX_SPEC_BYTES)
    try:
        spec = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{path}: not valid TOML: {str(exc)[:200]}") from None
    problems: list[str] = []
    for key in spec:
        if key not in SPEC_KEYS:
            problems.append(f"unknown key {key!r}{_did_you_mean(key, SPEC_KEYS)}")
    name = spec.get("name")
    if not isinstance(name, str) or not NAME_RE.match(name) or name in (".", ".."):
        problems.append("field 'name' must be a plain directory name (letters, digits, '.', "
                        f"'_', '-'; at most 64 characters; not '.' or '..'), got {_short(name)}")
    nbs = spec.get("notebooks")
    nbs_ok = isinstance(nbs, list) and bool(nbs)
    if not nbs_ok:
        problems.append("field 'notebooks' must be a non-empty list of notebook names")
    else:
        for nb in nbs:
            if not isinstance(nb, str) or not NAME_RE.match(nb):
                problems.append(f"field 'notebooks': {_short(nb)} is not a notebook name")
                nbs_ok = False
            elif not (NOTEBOOK_DIR / f"{nb}.ipynb").is_file():
                known_nbs = sorted(q.stem for q in NOTEBOOK_DIR.glob("*.ipynb"))
                problems.append(f"notebook {nb!r} not found in {NOTEBOOK_DIR}{_did_you_mean(nb, known_nbs)}")
                nbs_ok = False
        if nbs_ok and len(set(nbs)) != len(nbs):
            problems.append("field 'notebooks' names a notebook twice")
    grid = spec.get("grid", {})
    grid_ok = isinstance(grid, dict) and all(isinstance(v, list) and v for v in grid.values())
    if not grid_ok:
        problems.append("field 'grid' must map parameter names to non-empty lists")
    parameters = spec.get("parameters", {})
    params_ok = isinstance(parameters, dict)
    if not params_ok:
        problems.append("field 'parameters' must be a table")
    if nbs_ok:  # the notebooks' parameters are known: check every value against them
        inspected = [_inspect(NOTEBOOK_DIR / f"{nb}.ipynb") for nb in dict.fromkeys(nbs)]
        known = set().union(*inspected)
        types = {}
        for params in inspected:
            for k, v in params.items():
                types.setdefault(k, v.get("inferred_type_name"))
        for field, table, ok in (("parameters", parameters, params_ok), ("grid", grid, grid_ok)):
            if not ok:
                continue
            for key, value in table.items():
                if key in BATCH_SET:
                    problems.append(f"{field}.{key}: the batch sets it itself (each run's own, under "
                                    f"its run directory); leave it out")
                    continue
                if key not in known:
                    problems.append(f"{field}.{key} is not a parameter of {', '.join(nbs)}"
                                    f"{_did_you_mean(key, known - set(BATCH_SET))}")
                    continue
                if field == "grid" and params_ok and key in parameters:
                    problems.append(f"{key} is both in [parameters] and in [grid]")
                    continue
                values = value if field == "grid" else [value]
                accepted = _TYPES.get(types.get(key))
                typed = True
                for v in values:
                    bad_type = (isinstance(v, bool) and accepted != (bool,)) or \
                        (accepted is not None and not isinstance(v, accepted))
                    if bad_type or not isinstance(v, (bool, int, float, str)):
                        problems.append(f"{field}.{key} = {_short(v)}: expected "
                                        f"{types.get(key) or 'a plain value'}")
                        typed = False
                        break
                    if isinstance(v, float) and not math.isfinite(v):
                        problems.append(f"{field}.{key} = {v!r}: not finite")
                        typed = False
                        break
                if typed and field == "grid" and len({_value_key(v) for v in values}) != len(values):
                    problems.append(f"grid.{key} repeats a value: {_short(values)} (compared by value: "
                                    f"0 and 0.0 are one value)")
    if problems:
        raise _spec_error(path, problems)
    n_runs = math.prod(len(v) for v in grid.values())
    if n_runs > MAX_RUNS:
        raise SpecError(f"{path}: the grid makes {n_runs} runs, more than {MAX_RUNS}")
    return {"name": name, "notebooks": nbs, "parameters": parameters, "grid": grid}


def runs_of(spec: dict) -> list[dict]:
    """Every combination of the grid, merged over the fixed parameters, with a run id."""
    keys = sorted(spec["grid"])
    runs = []
    for values in itertools.product(*(spec["grid"][k] for k in keys)):
        params = {**spec["parameters"], **dict(zip(keys, values))}
        label = "_".join(f"{k}={v}" for k, v in zip(keys, values)) or "run"
        # a plain directory name whatever the values hold; the digest keeps it unique
        label = re.sub(r"[^A-Za-z0-9._=+-]", "-", label)[:80]
        digest = hashlib.sha1(json.dumps(params, sort_keys=True).encode()).hexdigest()[:8]
        runs.append({"id": f"{label}-{digest}", "params": params, "grid": dict(zip(keys, values))})
    return runs


def run_one(notebooks: list[str], params: dict, out_dir: str) -> dict:
    """Execute ``notebooks`` in order with ``params`` into ``out_dir``; returns the status
    (also written to ``status.json``). Never raises for a failing notebook."""
    import papermill as pm  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    status = {"status": "running", "params": params, "metrics": {}}
    for nb in notebooks:
        nb_params = {**params, "figures_dir": str(out / "figures"), "metrics_path": str(out / "metrics" / f"{nb}.json")}
        for key in ("raw_dir", "sweep_dir", "processed_dir"):
            nb_params.setdefault(key, str(out / key.replace("_dir", "")))
        nb_params["identified_path"] = str(out / "processed" / "friction_identified.json")
        known = set(pm.inspect_notebook(str(NOTEBOOK_DIR / f"{nb}.ipynb")))
        nb_params = {k: v for k, v in nb_params.items() if k in known}
        try:
            execute(NOTEBOOK_DIR / f"{nb}.ipynb", out, nb_params, html=True)
        except pm.PapermillExecutionError as exc:
            status.update(status="failed", notebook=nb, cell=int(exc.cell_index),
                          error=f"{exc.ename}: {exc.evalue}")
            break
        except Exception as exc:  # noqa: BLE001 - the kernel died, a file was unreadable, ...: reported
            status.update(status="failed", notebook=nb, cell=None, error=f"{type(exc).__name__}: {exc}")
            break
        mpath = out / "metrics" / f"{nb}.json"
        if mpath.exists():
            status["metrics"][nb] = json.loads(mpath.read_text())
    else:
        status["status"] = "done"
    write_json_atomic(out / "status.json", status)
    return status


def batch_root(out_root: str | Path, spec: dict) -> Path:
    """The directory of a batch's runs and index (absolute: Dask workers run elsewhere)."""
    return Path(out_root).resolve() / spec["name"]


NO_WORKER_TIMEOUT = 120.0  # s a distributed batch waits while no Dask worker is alive
CONNECT_TIMEOUT = 10.0  # s to reach a Dask scheduler


class SchedulerError(LeglibError, ConnectionError):
    """The Dask scheduler of a batch cannot be reached or its address is malformed."""


def connect_scheduler(scheduler: str, timeout: float = CONNECT_TIMEOUT):
    """A Dask ``Client`` of ``scheduler`` (``tcp://host:port``); SchedulerError (one line,
    naming the address) when it is malformed or does not answer within ``timeout`` s."""
    from dask.distributed import Client  # load time: dask (about 1 s), only with a scheduler

    if not isinstance(scheduler, str) or not re.match(r"^\S{1,200}$", scheduler):
        raise SchedulerError(f"--scheduler {_short(scheduler)}: not a scheduler address (tcp://host:port)")
    from distributed.comm import connect  # load time: as above

    async def probe():
        comm = await connect(scheduler, timeout=timeout)
        await comm.close()

    try:
        # a bare connection first: a Client that failed to connect would complain again
        # when it is collected (its close times out)
        with ThreadPoolExecutor(max_workers=1) as pool:  # its own event loop, also under Jupyter's
            pool.submit(asyncio.run, probe()).result()
        return Client(scheduler, timeout=timeout)
    except Exception as exc:  # noqa: BLE001 - dask raises OSError, ValueError, TypeError, TimeoutError: one message
        reason = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise SchedulerError(f"--scheduler {scheduler}: cannot connect ({reason})") from None


def _live_workers(client) -> int | None:
    """How many workers the scheduler has; None when the scheduler does not answer."""
    try:
        return len(client.scheduler_info(n_workers=-1).get("workers", {}))
    except Exception:  # noqa: BLE001 - a lost scheduler: counted as no worker
        return None


def _task_failure(exc: BaseException) -> str:
    """A one-line reason for a run whose Dask task failed (not a failing notebook)."""
    if type(exc).__name__ == "KilledWorker":
        worker = getattr(getattr(exc, "last_worker", None), "address", "?")
        tries = getattr(exc, "allowed_failures", 0) + 1
        return (f"KilledWorker: the Dask worker running this run died ({tries} time(s), more than the "
                f"scheduler's allowed failures); last worker {worker}")
    return f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"


def _run_distributed(client, pending: list[dict], args: list[tuple], results: dict, bar,
                     no_worker_timeout: float, poll: float = 0.25) -> None:
    """Submit every pending run and record each as it ends; a run whose task failed
    (KilledWorker, ...) is recorded failed with the reason; when no worker is alive for
    ``no_worker_timeout`` s, the runs not finished are recorded ``pending`` with the reason."""
    futures = {client.submit(run_one, *a, pure=False): r for a, r in zip(args, pending)}
    waiting = dict(futures)
    since = None
    while waiting:
        ended = [f for f in waiting if f.done()]
        for fut in ended:
            r = waiting.pop(fut)
            if fut.status == "finished":
                results[r["id"]] = fut.result()
            else:
                try:
                    exc = fut.exception()
                except Exception as e:  # noqa: BLE001 - cancelled: its own exception
                    exc = e
                status = {"status": "failed", "params": r["params"], "metrics": {}, "notebook": None,
                          "cell": None, "error": _task_failure(exc)}
                results[r["id"]] = status
                _write_status(Path(args[pending.index(r)][2]), status)
            bar.update(1)
        if ended or not waiting:
            continue
        n = _live_workers(client)
        now = time.monotonic()
        if n:
            since = None
        elif since is None:
            since = now
        elif now - since > no_worker_timeout:
            what = "the scheduler did not answer" if n is None else "no Dask worker was alive"
            reason = f"not run: {what} for {no_worker_timeout:g} s"
            print(f"batch: {reason}; {len(waiting)} run(s) left pending", file=sys.stderr, flush=True)
            for fut, r in waiting.items():
                status = {"status": "pending", "params": r["params"], "metrics": {}, "notebook": None,
                          "cell": None, "error": reason}
                results[r["id"]] = status
                _write_status(Path(args[pending.index(r)][2]), status)
            try:
                client.cancel(list(waiting))
            except Exception:  # noqa: BLE001 - a lost scheduler: nothing to cancel
                pass
            return
        time.sleep(poll)


def _write_status(run_dir: Path, status: dict) -> None:
    try:
        write_json_atomic(run_dir / "status.json", status)
    except OSError:
        pass  # the index still shows it


def run_batch(spec: str | Path | dict, out_root: str | Path = "reports/batch", scheduler: str | None = None,
              workers: int = 2, progress: bool = True, cluster=None,
              no_worker_timeout: float = NO_WORKER_TIMEOUT, connect_timeout: float = CONNECT_TIMEOUT) -> dict:
    """Run every grid point of the spec (a path, or a spec from :func:`load_spec`); skip
    runs already done; write the index (``batch_root(out_root, spec) / "index.html"``).

    ``scheduler``: a Dask scheduler address (``tcp://host:8786``; SchedulerError when it is
    malformed or does not answer within ``connect_timeout`` s; raised before anything is
    written); ``cluster``: a Dask cluster object (tests use a
    LocalCluster); otherwise local processes (``workers``). On Dask, a run whose worker
    died more often than the scheduler allows (``KilledWorker``) is recorded failed with
    the reason and the others go on; when no worker is alive for ``no_worker_timeout`` s,
    the runs not finished are recorded ``pending`` with the reason and the index is
    written. Returns {run id: status}.
    """

    spec = spec if isinstance(spec, dict) else load_spec(spec)
    # the scheduler first: an unreachable one fails before anything is written
    client = connect_scheduler(scheduler, connect_timeout) if scheduler and cluster is None else None
    try:
        root = batch_root(out_root, spec)
        root.mkdir(parents=True, exist_ok=True)
        runs = runs_of(spec)
        results, pending = {}, []
        for r in runs:
            st = root / r["id"] / "status.json"
            if st.exists() and json.loads(st.read_text()).get("status") == "done":
                results[r["id"]] = json.loads(st.read_text())
            else:
                pending.append(r)
        args = [(spec["notebooks"], r["params"], str(root / r["id"])) for r in pending]
        with tqdm(total=len(runs), initial=len(runs) - len(pending), desc=f"batch {spec['name']}", unit="run",
                  disable=not progress) as bar:
            if pending and (client is not None or cluster is not None):
                if client is None:
                    from dask.distributed import Client  # load time: dask (about 1 s), only with a scheduler
                    client = Client(cluster)
                _run_distributed(client, pending, args, results, bar, no_worker_timeout)
            elif pending:
                with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
                    futures = {pool.submit(run_one, *a): r for a, r in zip(args, pending)}
                    for fut in as_completed(futures):
                        r = futures[fut]
                        try:
                            results[r["id"]] = fut.result()
                        except Exception as exc:  # noqa: BLE001 - a worker process died (BrokenProcessPool): recorded
                            status = {"status": "failed", "params": r["params"], "metrics": {}, "notebook": None,
                                      "cell": None, "error": _task_failure(exc)}
                            results[r["id"]] = status
                            _write_status(root / r["id"], status)
                        bar.update(1)
    finally:
        if client is not None:
            try:
                client.close(timeout=5)
            except Exception:  # noqa: BLE001 - a lost scheduler: the client is gone anyway
                pass
    write_index(root, runs, results, spec["notebooks"])
    return results


# The metrics a batch summary shows, per notebook: (notebook, path in its metrics JSON,
# label, unit, factor from the JSON's value to the unit). Validation errors and identified
# parameters, the answers a parameter study asks for; timings and constants stay in
# status.json.
SUMMARY_METRICS = [
    ("05_validation", ("summary", "map", "median"), "map method: median error", "%", 100.0),
    ("05_validation", ("summary", "map", "worst"), "map method: worst error", "%", 100.0),
    ("05_validation", ("summary", "model", "median"), "model method: median error", "%", 100.0),
    ("05_validation", ("summary", "model", "worst"), "model method: worst error", "%", 100.0),
    ("05_validation", ("thesis_target", "error_zeta"), "thesis target: zeta error", "%", 100.0),
    ("05_validation", ("thesis_target", "error_fn"), "thesis target: fn error", "%", 100.0),
    ("04_pid_sweeps", ("counts", "unstable"), "unstable grid points", "count", 1.0),
    ("04_pid_sweeps", ("counts", "failed"), "failed grid points", "count", 1.0),
    ("04_pid_sweeps", ("zeta_range", 1), "largest achievable zeta", "-", 1.0),
    ("04_pid_sweeps", ("fn_range", 1), "highest achievable fn", "Hz", 1.0),
    ("04_pid_sweeps", ("thesis_target_nearest", "fn"), "fn nearest the thesis target", "Hz", 1.0),
    ("03_pole_placement", ("runs", "identified: live closed loop", "final_error_pct"),
     "live state feedback: final error", "%", 1.0),
    ("03_pole_placement", ("runs", "identified: live closed loop", "overshoot_pct"),
     "live state feedback: overshoot", "%", 1.0),
    ("02_friction_fitting", ("single_joint", "coulomb"), "identified Coulomb (single joint)", "N m", 1.0),
    ("02_friction_fitting", ("single_joint", "viscous"), "identified viscous (single joint)", "N m s/rad", 1.0),
    ("02_friction_fitting", ("single_joint", "inertia"), "identified inertia (single joint)", "kg m^2", 1.0),
    ("02_friction_fitting", ("step_fit", "zeta"), "identified zeta of the Fig. 6.9 step", "-", 1.0),
    ("01_derivation", ("eq511_max_rel_error",), "eq. 5.11 largest relative error", "%", 100.0),
]


def _lookup(d, path):
    for k in path:
        if isinstance(d, dict) and k in d:
            d = d[k]
        elif isinstance(d, list) and isinstance(k, int) and -len(d) <= k < len(d):
            d = d[k]
        else:
            return None
    return float(d) if isinstance(d, (int, float)) and not isinstance(d, bool) else None


def summary_values(status: dict) -> dict:
    """{(notebook, label, unit): value in the unit} of the :data:`SUMMARY_METRICS` a run's
    status holds (missing and non-finite values left out)."""
    out = {}
    metrics = status.get("metrics", {})
    for nb, path, label, unit, factor in SUMMARY_METRICS:
        v = _lookup(metrics.get(nb, {}), path)
        if v is not None and math.isfinite(v):
            out[(nb, label, unit)] = v * factor
    return out


def _parameter_units(notebooks) -> dict:
    """{parameter: its unit} from the notebooks' parameter comments ("kg, point mass ..."):
    the comment's first word when it is followed by a comma and looks like a unit."""
    import papermill as pm  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run

    units = {}
    for nb in notebooks:
        path = NOTEBOOK_DIR / f"{nb}.ipynb"
        if not path.exists():
            continue
        for name, info in pm.inspect_notebook(str(path)).items():
            head = (info.get("help") or "").split(",")[0].strip()
            if head and "," in (info.get("help") or "") and len(head) <= 12 and " " not in head.strip("()"):
                units.setdefault(name, head)
    return units


def write_index(root: Path, runs: list[dict], results: dict, notebooks: list[str] | None = None) -> Path:
    """Write ``index.html`` and ``summary.png`` for a batch.

    Parameters
    ----------
    root : the batch directory (runs in ``root / run id``)
    runs : from :func:`runs_of`
    results : {run id: status} (as ``status.json``)
    notebooks : the spec's notebooks (for the links to each run's reports and the swept
        parameters' units); default: those with a report in the run directories

    ``index.html``: one row per run, its swept parameters (with units), status, failing
    cell, the chosen metrics (:data:`SUMMARY_METRICS`: validation errors, identified
    parameters) with units, and links to the run's reports and ``status.json`` (every
    metric). ``summary.png``: each chosen metric against the first swept parameter (one
    line per combination of the others), axes with units.
    """

    import matplotlib  # load time: matplotlib (about 0.5 s), only when drawing
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # load time: matplotlib (about 0.5 s), only when drawing

    root = Path(root)
    keys = list(runs[0]["grid"]) if runs else []
    if notebooks is None:
        notebooks = sorted({p.stem for r in runs for p in (root / r["id"]).glob("*.ipynb")})
    units = _parameter_units(notebooks) if keys else {}

    def with_unit(name, unit):
        return f"{name} [{unit}]" if unit and unit != "-" else name

    rows, chosen = [], []
    for r in runs:
        st = results.get(r["id"], {"status": "missing"})
        vals = summary_values(st)
        for k in vals:
            if k not in chosen:
                chosen.append(k)
        rows.append((r, st, vals))
    order = {(nb, label, unit): i for i, (nb, _, label, unit, _) in enumerate(SUMMARY_METRICS)}
    chosen.sort(key=lambda k: order[k])
    head = ["run", *(with_unit(k, units.get(k)) for k in keys), "status", "failure",
            *(f"{nb[:2]}: {with_unit(label, unit)}" for nb, label, unit in chosen), "reports"]
    lines = ["<html><head><meta charset='utf-8'><title>batch</title>",
             "<style>td,th{padding:2px 6px;font-family:sans-serif;font-size:13px}</style></head><body>",
             f"<h1>batch {html.escape(root.name)}</h1>",
             "<p>Chosen metrics of every run against the swept parameters; each run's reports and "
             "its <code>status.json</code> (every metric) are linked.</p>",
             "<img src='summary.png' alt='chosen metrics against the swept parameters'>",
             "<table border='1'><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r, st, vals in rows:
        fail = "" if st.get("status") == "done" else f"{st.get('notebook', '')} cell {st.get('cell')}: {st.get('error', '')}"
        cells = [html.escape(r["id"]), *(html.escape(str(v)) for v in r["grid"].values()),
                 html.escape(str(st.get("status", ""))), html.escape(fail),
                 *(f"{vals[k]:.4g}" if k in vals else "" for k in chosen)]
        run_dir = root / r["id"]
        links = []
        for nb in notebooks:
            for ext in (".html", ".ipynb"):
                if (run_dir / f"{nb}{ext}").exists():
                    links.append(f"<a href='{html.escape(r['id'])}/{nb}{ext}'>{html.escape(nb[:2])}</a>")
                    break
        if (run_dir / "status.json").exists():
            links.append(f"<a href='{html.escape(r['id'])}/status.json'>status.json</a>")
        cells.append(" ".join(links))
        lines.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    lines.append("</table></body></html>")
    write_bytes_atomic(root / "index.html", "\n".join(lines).encode(), overwrite=True)
    if keys and chosen:
        n = len(chosen)
        ncol = min(n, 4)
        nrow = (n + ncol - 1) // ncol
        fig, axes = plt.subplots(nrow, ncol, figsize=(4.0 * ncol, 3.2 * nrow), squeeze=False)
        for ax, k in zip(axes.ravel(), chosen):
            nb, label, unit = k
            series = {}
            for r, st, vals in rows:
                if k in vals:
                    rest = tuple((p, r["grid"][p]) for p in keys[1:])
                    series.setdefault(rest, []).append((r["grid"][keys[0]], vals[k]))
            for rest, pts in series.items():
                x, y = zip(*sorted(pts))
                ax.plot(x, y, "o-", label=", ".join(f"{p}={v}" for p, v in rest) or None)
            if any(rest for rest in series):
                ax.legend(fontsize=7)
            ax.set_xlabel(with_unit(keys[0], units.get(keys[0])))
            ax.set_ylabel(f"{label.split(': ')[-1]} [{unit}]", fontsize=8)
            ax.set_title(f"{nb[:2]}: {label}", fontsize=9)
            ax.grid(alpha=0.3)
        for ax in axes.ravel()[n:]:
            ax.set_visible(False)
        fig.suptitle(f"batch {root.name}: chosen metrics against {keys[0]}")
        fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90)
        plt.close(fig)
        write_bytes_atomic(root / "summary.png", buf.getvalue(), overwrite=True)
    return root / "index.html"
