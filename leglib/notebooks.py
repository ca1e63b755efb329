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
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
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
    import nbformat
    import papermill as pm

    notebook = Path(notebook)
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    params = {"figures_dir": str(out_dir / "figures"),
              "metrics_path": str(out_dir / "metrics" / f"{notebook.stem}.json")}
    params.update(parameters or {})
    out = out_dir / notebook.name
    with _kernel_env(MPLBACKEND=INLINE_BACKEND):
        pm.execute_notebook(str(notebook), str(out), parameters=params, cwd=str(REPO),
                            progress_bar=progress, kernel_name="python3", execution_timeout=timeout)
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
    import nbformat

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
    import nbformat
    from nbconvert import HTMLExporter

    nb = nbformat.read(str(executed), as_version=4)
    body, _ = HTMLExporter().from_notebook_node(nb)
    path = Path(executed).with_suffix(".html")
    path.write_text(body)
    return path


def run_all(out_dir: str | Path = "reports", smoke: bool = False) -> list[Path]:
    """Execute every numbered notebook against the virtual leg (``make run``)."""
    from tqdm.auto import tqdm

    done = []
    for nb in tqdm(notebook_paths(), desc="notebooks", unit="nb"):
        done.append(execute(nb, out_dir, {"smoke": smoke}))
    return done
