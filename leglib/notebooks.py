"""Execute the numbered notebooks with papermill; write executed copies, HTML, metrics."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
NOTEBOOK_DIR = REPO / "notebooks"


def notebook_paths() -> list[Path]:
    """The numbered notebooks (``notebooks/NN_*.ipynb``) in order."""
    return sorted(p for p in NOTEBOOK_DIR.glob("[0-9][0-9]_*.ipynb"))


def execute(notebook: str | Path, out_dir: str | Path, parameters: dict | None = None,
            html: bool = True, progress: bool = False, timeout: int = 1200) -> Path:
    """Run one notebook with papermill from the repository root.

    The notebook gets ``figures_dir`` and ``metrics_path`` under ``out_dir`` unless
    ``parameters`` sets them. Returns the executed notebook's path. Raises papermill's
    ``PapermillExecutionError`` (naming the failing cell) when a cell fails.
    """
    import papermill as pm

    notebook = Path(notebook)
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    params = {"figures_dir": str(out_dir / "figures"),
              "metrics_path": str(out_dir / "metrics" / f"{notebook.stem}.json")}
    params.update(parameters or {})
    out = out_dir / notebook.name
    env_backend = os.environ.get("MPLBACKEND")
    os.environ["MPLBACKEND"] = "Agg" if env_backend is None else env_backend
    pm.execute_notebook(str(notebook), str(out), parameters=params, cwd=str(REPO),
                        progress_bar=progress, kernel_name="python3", execution_timeout=timeout)
    if html:
        to_html(out)
    return out


def to_html(executed: Path) -> Path:
    """Convert an executed notebook to HTML beside it."""
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
