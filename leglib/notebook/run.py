"""Execute the numbered notebooks with papermill; write executed copies, HTML, metrics.

Figures are part of the report: the kernels run matplotlib's inline backend (whatever
``MPLBACKEND`` the calling process uses, e.g. ``Agg`` in the tests), so every figure a cell
draws is embedded in the executed notebook and its HTML. Widget panels leave a static
picture: the images their output area held when the cell ran are copied beside the live
widget view (:func:`add_widget_snapshots`).
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import logging
import os
import time
import warnings
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

from tqdm.auto import tqdm

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


ENGINE = "leglib"
_ENGINE_REGISTERED = False
# while a cell's reply is awaited, the kernel's shell queue is probed this often: a probe
# answered before the cell's reply means the kernel finished the cell and its reply was
# lost (a kernel answers shell requests in order, one at a time)
PROBE_EVERY_S = 10.0
# after a lost reply is detected, outputs still in flight get this long to arrive
LOST_REPLY_GRACE_S = 5.0


def _register_engine() -> None:
    """Papermill's nbclient engine with one change (:data:`ENGINE`): a cell whose
    ``execute_reply`` is lost is completed from what the kernel published for it (its
    outputs; an error output fails the notebook as before), with a warning, instead of
    waiting out the cell timeout.

    Seen with ipykernel 6 under heavy load: the kernel idle and answering, the reply for
    its last cell never received. While a reply is awaited, a ``kernel_info_request``
    goes to the kernel's shell every :data:`PROBE_EVERY_S`; the kernel answers shell
    requests in order, so a probe answered first means the cell is done and its reply
    lost."""

    from nbclient.util import ensure_async  # load time: nbclient, only when notebooks run
    from papermill.clientwrap import (
        PapermillNotebookClient,  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run
    )
    from papermill.engines import (  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run
        NBClientEngine,
        papermill_engines,
    )
    from papermill.utils import (  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run
        merge_kwargs,
        remove_args,
    )

    global _ENGINE_REGISTERED
    if _ENGINE_REGISTERED:
        return

    class Client(PapermillNotebookClient):
        async def _async_poll_for_reply(self, msg_id, cell, timeout, task_poll_output_msg, task_poll_kernel_alive):
            channel = self.kc.shell_channel
            seen: set = set()   # parent ids of every shell message the reply loop receives
            if not getattr(channel, "_leglib_spy", False):
                receive = channel.get_msg

                async def get_msg(*args, **kwargs):
                    msg = await ensure_async(receive(*args, **kwargs))
                    channel._leglib_seen.add(msg.get("parent_header", {}).get("msg_id"))
                    return msg
                channel.get_msg, channel._leglib_spy = get_msg, True
            channel._leglib_seen = seen
            wait_reply = asyncio.ensure_future(super()._async_poll_for_reply(
                msg_id, cell, timeout, task_poll_output_msg, task_poll_kernel_alive))
            probes, next_probe = [], time.monotonic() + PROBE_EVERY_S
            while True:
                done, _ = await asyncio.wait({wait_reply}, timeout=0.5)
                if done:
                    return wait_reply.result()
                if not any(p in seen for p in probes):
                    if time.monotonic() >= next_probe:
                        probes.append(self.kc.kernel_info())
                        next_probe = time.monotonic() + PROBE_EVERY_S
                    continue
                # the kernel answered a later request first: our reply is lost
                if not task_poll_output_msg.done():
                    try:   # outputs (and the idle status) still in flight
                        await asyncio.wait_for(asyncio.shield(task_poll_output_msg), LOST_REPLY_GRACE_S)
                    except Exception:  # noqa: BLE001 - the outputs' task failing is seen below
                        pass
                if wait_reply.done():
                    return wait_reply.result()
                wait_reply.cancel()
                task_poll_output_msg.cancel()
                task_poll_kernel_alive.cancel()
                errors = [o for o in cell.get("outputs", []) if o.get("output_type") == "error"]
                warnings.warn(f"cell {cell.get('execution_count')}: the kernel finished it but its reply was "
                              f"lost; completed from its outputs", RuntimeWarning, stacklevel=1)
                content = {"status": "error" if errors else "ok", "execution_count": cell.get("execution_count")}
                if errors:
                    content.update(ename=errors[-1].get("ename"), evalue=errors[-1].get("evalue"),
                                   traceback=errors[-1].get("traceback", []))
                return {"parent_header": {"msg_id": msg_id}, "content": content, "metadata": {},
                        "header": {"msg_type": "execute_reply",
                                   "date": datetime.datetime.now(datetime.timezone.utc)}}

    class Engine(NBClientEngine):
        @classmethod
        def execute_managed_notebook(cls, nb_man, kernel_name, log_output=False, stdout_file=None,
                                     stderr_file=None, start_timeout=60, execution_timeout=None, **kwargs):
            # as NBClientEngine.execute_managed_notebook (papermill 2.7), with Client
            kwargs = remove_args(["input_path"], **kwargs)
            safe_kwargs = remove_args(["timeout", "startup_timeout"], **kwargs)
            final_kwargs = merge_kwargs(safe_kwargs, timeout=execution_timeout or kwargs.get("timeout"),
                                        startup_timeout=start_timeout, kernel_name=kernel_name,
                                        log=logging.getLogger("papermill"), log_output=log_output,
                                        stdout_file=stdout_file, stderr_file=stderr_file)
            return Client(nb_man, **final_kwargs).execute()

    papermill_engines.register(ENGINE, Engine)
    _ENGINE_REGISTERED = True


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
    progress : show papermill's progress bar
    timeout : per-cell timeout [s]

    Returns
    -------
    Path of the executed notebook. Its figures are inline (the kernel uses matplotlib's
    inline backend whatever ``MPLBACKEND`` this process has), widget panels carry a static
    picture. Raises papermill's ``PapermillExecutionError`` (naming the failing cell) when
    a cell fails.
    """
    import nbformat  # load time: nbformat (about 1 s), only when notebooks run
    import papermill as pm  # load time: papermill and the kernel machinery (about 2 s), only when notebooks run

    notebook = Path(notebook)
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    params = {"figures_dir": str(out_dir / "figures"),
              "metrics_path": str(out_dir / "metrics" / f"{notebook.stem}.json")}
    params.update(parameters or {})
    out = out_dir / notebook.name
    _register_engine()
    with _kernel_env(MPLBACKEND=INLINE_BACKEND):
        pm.execute_notebook(str(notebook), str(out), parameters=params, cwd=str(REPO),
                            progress_bar=progress, kernel_name="python3", execution_timeout=timeout,
                            engine_name=ENGINE)
    nb = nbformat.read(str(out), as_version=4)
    if add_widget_snapshots(nb):
        nbformat.write(nb, str(out))
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
    """Convert an executed notebook to HTML beside it (figures embedded)."""
    import nbformat  # load time: nbformat (about 1 s), only when notebooks run
    from nbconvert import HTMLExporter  # load time: nbconvert, only when a report is written

    nb = nbformat.read(str(executed), as_version=4)
    body, _ = HTMLExporter().from_notebook_node(nb)
    path = Path(executed).with_suffix(".html")
    path.write_text(body)
    return path


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


def run_all(out_dir: str | Path = "reports", smoke: bool = False, workers: int | None = None) -> list[Path]:
    """Execute every numbered notebook against the virtual leg (``make run``).

    Notebooks run in ``workers`` processes at once (default: the cores present, at most
    2: each kernel also runs the twin's compiled kernel on its threads); a notebook
    starts only when the ones it reads from (:data:`DEPENDS_ON`) are done. When one fails,
    the others still run, except those that read from it; then the first failure is
    raised, with notes naming its notebook and the ones skipped. Returns the executed
    notebooks in number order.
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
    with tqdm(total=len(paths), desc="notebooks", unit="nb") as bar, \
            ProcessPoolExecutor(max_workers=workers) as pool:
        running = {}
        while waiting or running:
            for p in list(waiting):
                deps = [d for d in DEPENDS_ON.get(_number(p), ()) if d in by_number]
                if any(d in failed for d in deps):
                    waiting.remove(p)
                    failed.add(_number(p))
                    skipped.append(p)
                    bar.update(1)
                elif len(running) < workers and all(d in done for d in deps):
                    waiting.remove(p)
                    running[pool.submit(execute, p, out_dir, {"smoke": smoke})] = p
            if not running:
                if waiting:   # nothing can start and nothing runs: DEPENDS_ON has a cycle
                    raise RuntimeError(f"notebooks {[p.name for p in waiting]} wait for each other "
                                       f"(leglib.notebook.run.DEPENDS_ON)")
                continue
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                p = running.pop(f)
                try:
                    done[_number(p)] = f.result()
                except Exception as exc:  # noqa: BLE001 - noted and re-raised after the others
                    exc.add_note(f"while executing {p} (its executed copy: {Path(out_dir) / p.name})")
                    failed.add(_number(p))
                    error = error or exc
                bar.update(1)
    if error is not None:
        if skipped:
            error.add_note("not run, as they read from a failed notebook: "
                           + ", ".join(p.name for p in skipped))
        raise error
    return [done[_number(p)] for p in paths]
