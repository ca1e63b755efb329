"""What every notebook does first and last: the parameters check, metrics, figure output.

Notebooks keep a ``parameters`` cell of plain typed values (``seed: int = 11  # ...``); the
first cell after it calls :func:`check_parameters` once, before any experiment runs, so a
bad value stops the notebook at once with a message that names the parameter. The types
come from the parameters cell's own annotations (papermill's injected values are checked
against them); the call states only what types cannot say: ranges, choices, relations.
:func:`require` and its siblings check one value, for what a notebook computes itself.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import re
import warnings
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .. import plots
from ..errors import NotebookParameterError, ParameterError
from ..files.atomic import write_bytes_atomic, write_json_atomic
from ..params import load_plant
from ..units import pretty
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


def check_parameters(ns: dict, *, ranges: dict | None = None, choices: dict | None = None,
                     relations: Iterable = (), readable: Iterable = (), optional: Iterable = (),
                     smoke: dict | None = None) -> None:
    """Check every parameter of a notebook's parameters cell, in one call.

    Each parameter's type is its annotation in the parameters cell (``float`` also accepts an
    int, no number accepts a bool); then by name: ``seed`` and ``*_seed`` are seeds
    (0 .. 2**32 - 1), ``*_dir`` a writable (or creatable) directory, ``*_path`` a writable
    file, ``*_file`` an existing readable file or ``""`` (none); each name in ``readable`` an
    existing readable file and each in ``optional`` a path that may not exist yet. Then the
    ranges and choices, then ``smoke``'s shortened values (when the ``smoke`` parameter is
    True), then the relations, which see the shortened values.

    Parameters
    ----------
    ns : dict
        The notebook's namespace, ``globals()``: its ``__annotations__`` are the parameters.
    ranges : dict, optional
        ``{name: (low, high)}``, inclusive; either bound may be None.
    choices : dict, optional
        ``{name: allowed values}``.
    relations : iterable of str
        Expressions over the parameters that must hold, e.g. ``"pos_min < pos_max"`` or
        ``"fit_start <= duration - 1"``.
    readable, optional : iterable of str
        Parameters naming input files that must exist, and paths that may be missing.
    smoke : dict, optional
        ``{name: value or callable(value)}`` applied in ``ns`` when ``ns["smoke"]`` is True
        (a short run), before the relations are checked.

    Raises
    ------
    NotebookParameterError
        The first parameter that is of the wrong type, out of range, not one of its choices,
        breaks a relation, or is a path that cannot be used; the message names it.
    """
    annotations = ns.get("__annotations__") or {}
    if not annotations:
        raise NotebookParameterError("the notebook's parameters cell has no annotated parameters "
                                     "(write them as 'name: type = value  # unit, meaning')")
    ranges, choices, readable, optional = dict(ranges or {}), dict(choices or {}), set(readable), set(optional)
    relations = list(relations)
    named = set(ranges) | set(choices) | readable | optional | set(smoke or {})
    for expr in relations:
        named |= {n for n in re.findall(r"[A-Za-z_]\w*", expr) if n not in ("and", "or", "not", "abs")}
    for name in sorted(named - set(annotations)):
        raise NotebookParameterError(f"check_parameters names {name!r}, which is no parameter of this notebook "
                                     f"(its parameters cell has {sorted(annotations)})")
    for name, kind in annotations.items():
        value = ns[name]
        low, high = ranges.get(name, (None, None))
        if name in readable:
            require_readable_file(name, value)
        elif name in optional:
            require(name, value, str)
        elif name == "seed" or name.endswith("_seed"):
            require_seed(name, value)
        elif name.endswith("_dir"):
            require_writable_dir(name, value)
        elif name.endswith("_path"):
            require_writable_file(name, value)
        elif name.endswith("_file"):
            require(name, value, str)
            if value:
                require_readable_file(name, value)
        else:
            require(name, value, kind, choices=choices.get(name), low=low, high=high)
    if smoke and ns.get("smoke"):
        for name, new in smoke.items():
            ns[name] = new(ns[name]) if callable(new) else new
    values = {name: ns[name] for name in annotations}
    for expr in relations:
        if not eval(expr, {"__builtins__": {"abs": abs}}, dict(values)):  # noqa: S307 - the notebook's own expressions
            used = {n: values[n] for n in re.findall(r"[A-Za-z_]\w*", expr) if n in values}
            raise NotebookParameterError(f"parameters {', '.join(f'{k} = {v!r}' for k, v in used.items())}: "
                                         f"need {expr}")


def load_parameter_file(name: str, value: Any, loader):
    """Load the parameter file a notebook parameter names, e.g. ``load_parameter_file(
    "odrive_config", odrive_config, load_odrive_config)``: the leg, motor, ODrive
    configuration or plant a notebook runs with. A name that is no file, or a file with a bad
    value, stops the notebook with a :class:`NotebookParameterError` naming the parameter
    (and the file and field)."""
    require(name, value, str)
    try:
        return loader(value)
    except ParameterError as exc:
        raise NotebookParameterError(f"parameter {name!r} = {value!r}: {exc}") from None


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


def write_metrics(path: str | Path, **metrics) -> Path:
    """The small metrics JSON every notebook writes (tests assert on it), with
    ``figure_text_overlaps``: the figures this process saved whose texts overlap or whose
    legends sit on data (:data:`FIGURE_OVERLAPS`, empty when every figure reads)."""
    metrics.setdefault("figure_text_overlaps", {k: v for k, v in FIGURE_OVERLAPS.items() if v})
    return write_json_atomic(path, metrics)


def add_metrics(path: str | Path, **metrics) -> Path:
    """Add fields to the metrics JSON a notebook wrote (:func:`write_metrics`), e.g. its
    bench report after the metrics cell."""
    path = Path(path)
    return write_json_atomic(path, {**json.loads(path.read_text()), **metrics})


class FigureLayoutWarning(UserWarning):
    """A saved figure has texts that overlap (:func:`leglib.plots.text_overlaps`) or a legend
    on data (:func:`leglib.plots.legends_on_data`)."""


# figure name -> its overlapping texts, for every figure save_figure wrote in this process
FIGURE_OVERLAPS: dict[str, list[str]] = {}


def save_figure(fig, figures_dir: str | Path, name: str) -> Path:
    """Save ``fig`` as ``<figures_dir>/<name>.png`` (whole or not at all; a full disk names
    the file) and return the path. A legend that covers data is moved off it first
    (:func:`leglib.plots.keep_legends_off_data`); then the texts are checked for overlaps and
    the legends for data they still cover: any found are a :class:`FigureLayoutWarning` and
    go into the notebook's metrics (:func:`write_metrics`)."""
    plots.keep_legends_off_data(fig)
    overlaps = plots.text_overlaps(fig) + plots.legends_on_data(fig)
    FIGURE_OVERLAPS[name] = overlaps
    if overlaps:
        warnings.warn(f"figure {name}: {len(overlaps)} overlapping text(s) or legend(s) on data: " + "; ".join(overlaps[:4])
                      + (" ..." if len(overlaps) > 4 else ""), FigureLayoutWarning, stacklevel=2)
    out = Path(figures_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.png"
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return write_bytes_atomic(path, buf.getvalue(), overwrite=True)


def matrix_comparison_markdown(name: str, ours, theirs, digits: int = 2, units=None) -> str:
    """Markdown table of two matrices side by side with the relative error of each entry;
    ``units`` (a matrix of unit strings, e.g. :func:`leglib.design.statefeedback.model_units`)
    adds each row's entries' units."""
    ours, theirs = np.asarray(ours), np.asarray(theirs)
    rows = [f"**{name}** — leglib │ thesis │ relative error", "",
            "| row | leglib | thesis | rel. error |" + (" units |" if units is not None else ""),
            "|---|---|---|---|" + ("---|" if units is not None else "")]
    for i in range(ours.shape[0]):
        o = ", ".join(f"{v:.{digits}f}" for v in ours[i])
        t = ", ".join(f"{v:.{digits}f}" for v in theirs[i])
        err = ", ".join("—" if v == 0 else f"{abs(a - v) / abs(v):.1e}" for a, v in zip(ours[i], theirs[i]))
        u = f" {', '.join(pretty(x) for x in units[i])} |" if units is not None else ""
        rows.append(f"| {i} | {o} | {t} | {err} |{u}")
    return "\n".join(rows)


def parameter_markdown(params, digits: int = 6) -> str:
    """A parameter set (the frozen dataclasses of :mod:`leglib.params`: a leg, a plant, a motor)
    as a Markdown table, one row per section of its file: each value with the unit its field
    declares (angles in degrees), as the file gives it (up to ``digits`` significant digits,
    no zeros added: 0.09 m stays 0.09 m)."""
    sections: dict[str, list[str]] = {}
    for f in dataclasses.fields(params):
        unit = f.metadata.get("unit")
        if unit is None:
            continue
        value = getattr(params, f.name)
        if isinstance(value, str):
            text = value
        elif unit == "rad":
            text = f"{math.degrees(value):.{digits}g} deg"
        else:
            text = f"{value:.{digits}g}" + (f" {pretty(unit)}" if unit not in ("", "-") else "")
        sections.setdefault(f.metadata.get("section", ""), []).append(f"{f.name} = {text}")
    rows = ["| section | values [unit] |", "|---|---|"]
    rows += [f"| {sec} | {', '.join(vals)} |" for sec, vals in sections.items()]
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
