"""Execute the numbered notebooks with papermill; write executed copies, HTML, metrics.

Figures are part of the report: the kernels run matplotlib's inline backend (whatever
``MPLBACKEND`` the calling process uses, e.g. ``Agg`` in the tests), so every figure a cell
draws is embedded in the executed notebook and its HTML. Widget panels leave a static
picture: the images their output area held when the cell ran are copied beside the live
widget view (:func:`add_widget_snapshots`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
import warnings
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

from ..files.atomic import oserror_naming, write_bytes_atomic
from . import warmup
from .offline import offline_notebook
from .progress import StageLog, clock

REPO = Path(__file__).resolve().parents[2]
NOTEBOOK_DIR = REPO / "notebooks"
INLINE_BACKEND = "module://matplotlib_inline.backend_inline"
WIDGET_VIEW = "application/vnd.jupyter.widget-view+json"
WIDGET_STATE = "application/vnd.jupyter.widget-state+json"


def notebook_paths() -> list[Path]:
    """The numbered notebooks (``notebooks/NN_*.ipynb``) in order."""
    return sorted(p for p in NOTEBOOK_DIR.glob("[0-9][0-9]_*.ipynb"))


@contextlib.contextmanager
def _kernel_env(**env):
    """Set environment variables for kernels started inside the block (they inherit the
    process environment), restoring the previous values afterwards."""
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# jupyter_client's words (client.py, wait_for_ready) for a kernel that was started and never
# answered: most often a port it was given and another process took first (the kernel's
# "Address already in use" on its standard error), a race of kernels started at once
KERNEL_NOT_STARTED = ("Kernel died before replying to kernel_info", "Kernel didn't respond in")


def kernel_not_started(exc: BaseException) -> bool:
    """Whether ``exc`` is nbclient's start of a kernel that never answered (no cell ran)."""
    return isinstance(exc, RuntimeError) and str(exc).startswith(KERNEL_NOT_STARTED)


def execute(notebook: str | Path, out_dir: str | Path, parameters: dict | None = None,
            html: bool = True, progress: bool = False, timeout: int = 1200) -> Path:
    """Run one notebook with papermill from the repository root.

    Parameters
    ----------
    notebook : path of the notebook to run
    out_dir : directory of the executed copy (``<out_dir>/<name>.ipynb``), its HTML,
        ``figures/`` and ``metrics/``
    parameters : papermill parameters; ``figures_dir`` and ``metrics_path`` default to
        places under ``out_dir``
    html : also write the HTML beside the executed notebook
    progress : print progress lines on standard error (:class:`leglib.notebook.progress.StageLog`:
        start, each section as the run reaches it, a heartbeat while a cell runs long, the end)
    timeout : per-cell timeout [s]: a cell that runs longer stops the run with nbclient's
        ``CellTimeoutError``, which shows the cell.

    Returns
    -------
    Path of the executed notebook. Its figures are inline (the kernel uses matplotlib's
    inline backend whatever ``MPLBACKEND`` this process has), widget panels carry a static
    picture.

    Raises
    ------
    papermill.PapermillExecutionError
        A cell failed (the error names it).
    nbclient.exceptions.CellTimeoutError, nbclient.exceptions.DeadKernelError
        A cell ran past ``timeout``, or the kernel died, twice: on the twin such a run is
        tried once more (a retry of a real leg's notebook would move it again: on
        ``backend="usb"`` the first failure stands).
    RuntimeError
        The kernel did not start, twice (:func:`kernel_not_started`; a start that failed
        once is tried again on any backend: no cell ran).

    The notebooks run on papermill's own engine; nbclient's kernel client is given the
    re-armed shell channel of :mod:`leglib.notebook.wakeup` (``kernel_manager_class``).
    After the last cell a kernel on the leg exits on its own (its exit handlers run); one on
    the twin is stopped at once.
    """
    import nbformat  # load time: nbformat (about 1 s), only when notebooks run
    import papermill as pm  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run
    from nbclient.exceptions import CellTimeoutError, DeadKernelError  # load time: as papermill

    from .wakeup import RearmingKernelManager  # load time: jupyter_client, only when notebooks run

    notebook = Path(notebook)
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    params = {"figures_dir": str(out_dir / "figures"),
              "metrics_path": str(out_dir / "metrics" / f"{notebook.stem}.json")}
    params.update(parameters or {})
    out = out_dir / notebook.name
    # after the last cell: on the leg the kernel is asked to exit and given the time to (its
    # exit handlers run, the odrive library's among them); on the twin it is stopped at once,
    # as nothing outside it waits on its exit (a kernel with leglib loaded took 0.6-1.0 s to
    # exit, an empty one 0.2 s: the teardown of what it imported)
    shutdown = "graceful" if params.get("backend") == "usb" else "immediate"
    for attempt in (1, 2):
        hooks, log = {}, None
        if progress:
            # papermill adds one cell, its injected parameters (there are always some: params)
            cells = len(nbformat.read(str(notebook), as_version=4).cells) + 1
            log = StageLog(notebook.name, cells).start()
            hooks = {"on_cell_start": log.on_cell_start, "on_cell_executed": log.on_cell_executed}
        try:
            with _kernel_env(MPLBACKEND=INLINE_BACKEND):
                pm.execute_notebook(str(notebook), str(out), parameters=params, cwd=str(REPO),
                                    progress_bar=False, kernel_name="python3", execution_timeout=timeout,
                                    kernel_manager_class=RearmingKernelManager, shutdown_kernel=shutdown,
                                    **hooks)
            if log is not None:
                log.finish(ok=True)
            break
        except (CellTimeoutError, DeadKernelError, RuntimeError) as exc:
            if log is not None:
                log.finish(ok=False)
            # a kernel that never started ran no cell and moved nothing: tried again on a
            # real leg too; a timed-out or dead run, on the twin only
            retry = kernel_not_started(exc) or (isinstance(exc, (CellTimeoutError, DeadKernelError))
                                                and params.get("backend") != "usb")
            if attempt == 2 or not retry:
                raise
            warnings.warn(f"{notebook.name}: {type(exc).__name__}: {str(exc).splitlines()[0]}; running it "
                          f"once more", RuntimeWarning, stacklevel=2)
        except BaseException as exc:
            if log is not None:
                log.finish(ok=False)
            if isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError):
                # papermill writing the executed copy on a full or read-only disk: name it
                raise oserror_naming(exc, out, "writing") from exc
            raise
    nb = nbformat.read(str(out), as_version=4)
    if add_widget_snapshots(nb):
        write_bytes_atomic(out, nbformat.writes(nb).encode(), overwrite=True)
    if html:
        to_html(out)
    return out


def _widget_images(model_id: str, states: dict, seen: set) -> list[dict]:
    """Image outputs held by widget ``model_id`` and its children (Output widgets)."""
    if model_id in seen or model_id not in states:
        return []
    seen.add(model_id)
    st = states[model_id].get("state", {})
    found = [o for o in st.get("outputs", []) if "image/png" in o.get("data", {})]
    for child in st.get("children", []):
        if isinstance(child, str) and child.startswith("IPY_MODEL_"):
            found += _widget_images(child[len("IPY_MODEL_"):], states, seen)
    return found


def add_widget_snapshots(nb) -> int:
    """Copy the images a widget panel showed when its cell ran into the cell's outputs, as
    ordinary ``display_data`` after the widget view, so a static report (HTML, GitHub)
    shows them. Returns how many images were added; the notebook is changed in place."""
    import nbformat  # load time: nbformat (about 1 s), only when notebooks run

    states = nb.metadata.get("widgets", {}).get(WIDGET_STATE, {}).get("state", {})
    added = 0
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        new = []
        for o in cell.get("outputs", []):
            new.append(o)
            view = o.get("data", {}).get(WIDGET_VIEW) if o.get("output_type") in ("display_data", "execute_result") else None
            if not view:
                continue
            for img in _widget_images(view.get("model_id", ""), states, set()):
                new.append(nbformat.v4.new_output("display_data", data={
                    "image/png": img["data"]["image/png"],
                    "text/plain": "static picture of the panel when the notebook ran"},
                    metadata={"leglib": {"widget_snapshot": True}}))
                added += 1
        cell.outputs = new
    return added


def count_figures(nb) -> int:
    """Number of images (PNG, SVG or JPEG outputs) in a notebook's cells."""
    return sum(1 for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
               if {"image/png", "image/svg+xml", "image/jpeg"} & set(o.get("data", {})))


def to_html(executed: Path) -> Path:
    """Convert an executed notebook to HTML beside it (figures embedded, maths as MathML,
    nothing loaded from the network: :mod:`leglib.notebook.offline`)."""
    import nbformat  # load time: nbformat (about 1 s), only when notebooks run
    from nbconvert import HTMLExporter  # load time: nbconvert, only when a report is written

    nb = nbformat.read(str(executed), as_version=4)
    offline_notebook(nb)  # maths as MathML, players without a CDN: the report works offline
    body, _ = HTMLExporter().from_notebook_node(nb)
    path = Path(executed).with_suffix(".html")
    return write_bytes_atomic(path, body.encode(), overwrite=True)


# which notebooks read what another one writes under make run's defaults: 03 designs on
# the friction 02 identified (data/processed/friction_identified.json), 05 validates the
# map of 04's sweep (data/raw/sweep_thesis_grid); the rest are independent
DEPENDS_ON = {"03": ("02",), "05": ("04",)}


def _number(path: Path) -> str:
    return Path(path).name[:2]


def run_order(paths: list[Path]) -> list[Path]:
    """The order a pool takes the notebooks in: ones that others wait for first (the
    critical path), then by number."""
    needed = {d for deps in DEPENDS_ON.values() for d in deps}
    return sorted(paths, key=lambda p: (_number(p) not in needed, _number(p)))


def _data_files() -> dict:
    """The files under the repository's data/ with their modification times."""
    root = REPO / "data"
    return {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()} if root.is_dir() else {}


def _data_written(before: dict) -> dict:
    """``{data/<dir>: count}`` of the files new or changed since ``before``."""
    counts: dict = {}
    for p, mtime in _data_files().items():
        if before.get(p) != mtime:
            rel = p.relative_to(REPO).parts
            key = "/".join(rel[:2]) if len(rel) > 2 else rel[0]
            counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items()))


def core_of(index: int, count: int, cores: list[int]) -> int | None:
    """The core the ``index``-th of ``count`` processes keeps to when there is one process
    per usable core (``cores``, as ``os.sched_getaffinity``); None when there are more or
    fewer (the system spreads them: a process of several threads, such as a sweep on the
    twin's vectorized kernel, then keeps every core it may use).

    Why keep to a core: the twin is driven through the ``odrive`` client, which hands every
    property access to its event loop's thread, two thread wake-ups per access; across the
    cores of a virtual machine a wake-up costs about twice the CPU it costs on one core (a
    bare asyncio round trip to another thread: 80 against 43 us of CPU on a 2-core machine;
    a twin's property read through the client: 170 against 84 us)."""
    if count != len(cores):
        return None
    return cores[index % len(cores)]


def usable_cores() -> list[int]:
    """The cores this process may run on and be kept to; none where the system cannot keep
    a process to a core (no ``os.sched_setaffinity``: then :func:`core_of` names none)."""
    if hasattr(os, "sched_getaffinity") and hasattr(os, "sched_setaffinity"):
        return sorted(os.sched_getaffinity(0))
    return []


def _execute_on(core: int | None, notebook: Path, out_dir, parameters: dict) -> Path:
    """:func:`execute` in a pool's process, kept to ``core`` with its kernel (None: anywhere)."""
    if core is not None:
        os.sched_setaffinity(0, {core})   # this process, and the kernel it starts
    return execute(notebook, out_dir, parameters, progress=True)


def run_all(out_dir: str | Path = "reports", smoke: bool = False, workers: int | None = None) -> list[Path]:
    """Execute every numbered notebook against the virtual leg (``make run``).

    Notebooks run in ``workers`` processes at once (default: the cores present, at most
    2: each kernel also runs the twin's compiled kernel on its threads); a notebook
    starts only when the ones it reads from (:data:`DEPENDS_ON`) are done. With one
    process per core, each notebook and its kernel keep to a free core (:func:`core_of`).
    When one fails, the others still run, except those that read from it; then the first
    failure is raised, with notes naming its notebook and the ones skipped. Returns the
    executed notebooks in number order.
    """


    paths = notebook_paths()
    if workers is None:
        workers = max(1, min(2, os.cpu_count() or 1))
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    by_number = {_number(p): p for p in paths}
    done: dict[str, Path] = {}
    failed: set = set()
    skipped: list[Path] = []
    waiting = run_order(paths)
    error = None
    t0 = time.monotonic()
    ended = 0

    def tally(p: Path, what: str) -> None:
        nonlocal ended
        ended += 1
        print(f"[run] {p.name} {what}: {ended}/{len(paths)} notebooks ended after "
              f"{clock(time.monotonic() - t0)}", file=sys.stderr, flush=True)

    # the kernels once, here, with a line per group: not in two notebook kernels at once,
    # silently, after an edit of a kernel's source (leglib.notebook.warmup)
    warmup.ensure()
    print(f"[run] {len(paths)} notebooks, {workers} at a time, into {out_dir}", file=sys.stderr, flush=True)
    data_before = _data_files()
    cores = usable_cores()
    free = [c for c in (core_of(k, workers, cores) for k in range(workers)) if c is not None]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        running = {}
        while waiting or running:
            for p in list(waiting):
                deps = [d for d in DEPENDS_ON.get(_number(p), ()) if d in by_number]
                if any(d in failed for d in deps):
                    waiting.remove(p)
                    failed.add(_number(p))
                    skipped.append(p)
                    tally(p, "skipped (it reads from a failed notebook)")
                elif len(running) < workers and all(d in done for d in deps):
                    waiting.remove(p)
                    core = free.pop(0) if free else None
                    running[pool.submit(_execute_on, core, p, out_dir, {"smoke": smoke})] = (p, core)
            if not running:
                if waiting:   # nothing can start and nothing runs: DEPENDS_ON has a cycle
                    raise RuntimeError(f"notebooks {[p.name for p in waiting]} wait for each other "
                                       f"(leglib.notebook.run.DEPENDS_ON)")
                continue
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                p, core = running.pop(f)
                if core is not None:
                    free.append(core)
                try:
                    done[_number(p)] = f.result()
                except Exception as exc:  # noqa: BLE001 - noted and re-raised after the others
                    exc.add_note(f"while executing {p} (its executed copy: {Path(out_dir) / p.name})")
                    failed.add(_number(p))
                    error = error or exc
                tally(p, "failed" if _number(p) in failed else "done")
    written = _data_written(data_before)
    if written:
        print("[run] the notebooks also wrote " + ", ".join(f"{n} file(s) under {d}" for d, n in written.items()),
              file=sys.stderr, flush=True)
    if error is not None:
        if skipped:
            error.add_note("not run, as they read from a failed notebook: "
                           + ", ".join(p.name for p in skipped))
        raise error
    return [done[_number(p)] for p in paths]
