"""Small helpers that every notebook uses: parameter checks, metrics, figure output.

Notebooks keep a ``parameters`` cell of plain typed values; the first cell after it calls
:func:`require` (and :func:`require_seed`, :func:`require_order`,
:func:`require_writable_dir`, :func:`require_writable_file`, :func:`require_readable_file`)
for every parameter, before any experiment runs, so a bad value stops the notebook at once
with a message that names the parameter.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..errors import NotebookParameterError
from ..files.atomic import write_bytes_atomic
from ..params import load_plant
from .run import REPO


def require(name: str, value: Any, kind: type | tuple, *, choices: Iterable | None = None,
            low: float | None = None, high: float | None = None) -> Any:
    """Check one notebook parameter and return it.

    Parameters
    ----------
    name : the parameter's name, used in the message
    kind : accepted type(s); ``float`` also accepts ``int`` (not ``bool``)
    choices : allowed values
    low, high : inclusive numeric bounds
    """
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if float in kinds:
        kinds = kinds + (int,)
    if isinstance(value, bool) and bool not in kinds:
        ok = False
    else:
        ok = isinstance(value, kinds)
    if not ok:
        names = "/".join(k.__name__ for k in (kind if isinstance(kind, tuple) else (kind,)))
        raise NotebookParameterError(f"parameter {name!r} must be {names}, got {value!r}")
    if choices is not None and value not in tuple(choices):
        raise NotebookParameterError(f"parameter {name!r} must be one of {tuple(choices)}, "
                                     f"got {value!r}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if isinstance(value, float) and not math.isfinite(value):
            raise NotebookParameterError(f"parameter {name!r} must be finite, got {value!r}")
        if low is not None and value < low:
            raise NotebookParameterError(f"parameter {name!r} must be >= {low}, got {value!r}")
        if high is not None and value > high:
            raise NotebookParameterError(f"parameter {name!r} must be <= {high}, got {value!r}")
    return value


SEED_MAX = 2**32 - 1  # numpy's SeedSequence accepts 0 .. 2**32 - 1 for a plain int seed


def require_seed(name: str, value: Any) -> int:
    """Check a random seed: an int in 0 .. 2**32 - 1 (numpy refuses negative seeds)."""
    return require(name, value, int, low=0, high=SEED_MAX)


def require_order(low_name: str, low_value: float, high_name: str, high_value: float,
                  allow_equal: bool = False) -> None:
    """Check that ``low_value`` is below ``high_value`` (or equal, with ``allow_equal``)."""
    ok = low_value <= high_value if allow_equal else low_value < high_value
    if not ok:
        rel = "at most" if allow_equal else "below"
        raise NotebookParameterError(f"parameter {low_name!r} ({low_value!r}) must be {rel} "
                                     f"{high_name!r} ({high_value!r})")


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def require_writable_dir(name: str, value: Any) -> Path:
    """Check that directory ``value`` exists and is writable, or can be created: its nearest
    existing ancestor is a writable directory. Nothing is created."""
    require(name, value, str)
    if not value.strip():
        raise NotebookParameterError(f"parameter {name!r} must be a directory path, got {value!r}")
    path = Path(value).expanduser().absolute()
    base = _nearest_existing(path)
    if base == path and not path.is_dir():
        raise NotebookParameterError(f"parameter {name!r}: {value} exists and is not a directory")
    if not base.is_dir():
        raise NotebookParameterError(f"parameter {name!r}: {value} cannot be created: {base} is not a directory")
    if not os.access(base, os.W_OK | os.X_OK):
        raise NotebookParameterError(f"parameter {name!r}: {value} is not writable ({base} is read-only)")
    return path


def require_writable_file(name: str, value: Any) -> Path:
    """Check that file ``value`` can be written: not a directory, its directory writable
    (or creatable)."""
    require(name, value, str)
    path = Path(value).expanduser().absolute()
    if path.is_dir() or not path.name:
        raise NotebookParameterError(f"parameter {name!r}: {value} is a directory, expected a file path")
    if os.path.lexists(path) and not path.is_file():
        raise NotebookParameterError(f"parameter {name!r}: {value} exists and is not a regular file")
    require_writable_dir(name, str(path.parent))
    return path


def require_readable_file(name: str, value: Any) -> Path:
    """Check that ``value`` names an existing, readable regular file."""
    require(name, value, str)
    path = Path(value).expanduser()
    if not path.is_file():
        what = "is not a regular file" if os.path.lexists(path) else "does not exist"
        raise NotebookParameterError(f"parameter {name!r}: {value} {what}")
    if not os.access(path, os.R_OK):
        raise NotebookParameterError(f"parameter {name!r}: {value} is not readable")
    return path


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, complex):
        return [obj.real, obj.imag]
    return obj


def write_json_atomic(path: str | Path, data: dict) -> Path:
    """Write ``data`` as JSON via a temporary file and rename (never a half-written file;
    created with the user's umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_jsonable(data), indent=2, sort_keys=True) + "\n"
    return write_bytes_atomic(path, text.encode(), overwrite=True)


def write_metrics(path: str | Path, **metrics) -> Path:
    """The small metrics JSON every notebook writes (tests assert on it)."""
    return write_json_atomic(path, metrics)


def save_figure(fig, figures_dir: str | Path, name: str) -> Path:
    """Save ``fig`` as ``<figures_dir>/<name>.png`` and return the path."""
    out = Path(figures_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return path


def matrix_comparison_markdown(name: str, ours, theirs, digits: int = 2) -> str:
    """Markdown table of two matrices side by side with the relative error of each entry."""
    ours, theirs = np.asarray(ours), np.asarray(theirs)
    rows = [f"**{name}** — leglib │ thesis │ relative error", "",
            "| row | leglib | thesis | rel. error |", "|---|---|---|---|"]
    for i in range(ours.shape[0]):
        o = ", ".join(f"{v:.{digits}f}" for v in ours[i])
        t = ", ".join(f"{v:.{digits}f}" for v in theirs[i])
        err = ", ".join("—" if v == 0 else f"{abs(a - v) / abs(v):.1e}" for a, v in zip(ours[i], theirs[i]))
        rows.append(f"| {i} | {o} | {t} | {err} |")
    return "\n".join(rows)


def device_options(backend: str, seed: int, plant: str, payload_mass: float = 0.0) -> dict:
    """The ``connect`` options a notebook's parameters ask for: on the twin its seed and its
    plant (with a payload on the foot [kg]); nothing for the real leg, where a payload is
    mounted by hand."""
    if backend != "virtual":
        return {}
    return {"seed": seed, "plant": load_plant(plant, payload_mass=float(payload_mass))}


def device_identity(backend: str, options: dict) -> dict:
    """What a notebook knows of its leg before connecting, in ``Device.describe()``'s terms:
    the backend and, on the twin, the plant's values (payload included)."""
    ident = {"backend": backend}
    plant = options.get("plant")
    if plant is not None:
        ident["twin_plant_values"] = {k: v for k, v in vars(plant).items() if k != "source_file"}
    return ident


def use_repo_root() -> Path:
    """Make the repository root the working directory, so a notebook's relative paths
    (``data/...``, ``reports/...``) mean the same opened in JupyterLab (whose kernels start
    in ``notebooks/``) as under papermill. Returns the root."""
    os.chdir(REPO)
    return REPO
