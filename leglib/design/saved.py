"""Designs as files: a state-feedback design or a set of cascade gains, saved and loaded.

A design file is JSON (indented, one field per line, human-readable) holding

- ``kind``: ``"state_feedback"`` or ``"cascade_gains"``, and ``format``: the file format's version;
- ``provenance``: leglib version and git commit, the date (UTC, ISO 8601), the backend and
  the device serial number the design was made for (``null`` when made without a device);
- the design itself (see :func:`save`).

Floats are written with Python's shortest round-tripping representation, so a loaded
design equals the saved one exactly (:func:`same`). Complex arrays (poles) are written as
``{"re": [...], "im": [...]}``. A malformed file raises :class:`DesignFileError` naming
the file and the field.

Example
-------
>>> d = SF.place_poles(M.linearize(leg), observer_factor=6)
>>> designs.save("data/processed/design_03_thesis.json", d, observer_factor=6,
...              linearization={"leg": "thesis", "coupled": False, "model": "parallelogram"})
>>> d2 = designs.load("data/processed/design_03_thesis.json")   # a statefeedback.StateFeedback
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import checks
from .._version import provenance as _prov
from ..errors import DesignFileError
from ..params import OdriveConfig, load_odrive_config
from ..units import interval_text
from .statefeedback import StateFeedback

FORMAT = 1
KINDS = ("state_feedback", "cascade_gains")

# a design file is a few kilobytes; anything far larger is not one
MAX_BYTES = 1 << 20
# the largest magnitude of any matrix entry of a state-feedback design (the thesis's are
# below 1e3); beyond it a value is a corrupted file, not a design
MAX_ENTRY = 1e9
# how closely the eigenvalues of A - B K (A - L C) must match the stored poles (observer
# poles), relative to the largest pole: place() reaches 1e-8 on the thesis's design
POLE_TOLERANCE = 1e-5
#: what a gain design says of a (zeta, fn) stored without its intervals (a file written before
#: they were stored, or a value that had none): never a silent default
NO_INTERVAL = "no interval recorded"


def dynamics_text(pair, intervals=None, missing: str = NO_INTERVAL) -> str:
    """A (zeta, fn [Hz]) pair as text: with its 90 % ``intervals`` ((zeta low, high), (fn
    low, high)) to the digits they support (:func:`leglib.units.interval_text`), else to the
    digits a step's identification supports at best (zeta to three decimals, fn to 0.01 Hz)
    and ``missing`` saying why there is no interval; "none (not a second-order step)" for None."""
    if pair is None:
        return "none (not a second-order step)"
    if intervals is None:
        return f"zeta {float(pair[0]):.3f}, fn {float(pair[1]):.2f} Hz ({missing})"
    return f"zeta {interval_text(pair[0], intervals[0])}, fn {interval_text(pair[1], intervals[1])} Hz"


# the target, predicted and measured step dynamics of a gain design
MAX_ZETA, MAX_FN_HZ = 100.0, 1000.0



@dataclass
class GainDesign:
    """Cascade gains chosen for a prescribed step response of the foot.

    Attributes
    ----------
    target : (zeta, fn) requested: damping ratio [-], natural frequency [Hz]
    gains : (pos_gain [(turn/s)/turn], vel_gain [N*m/(turn/s)], vel_integrator_gain [N*m/turn])
    method : how the gains were found, e.g. ``"map"`` (nearest achievable point of a
        :class:`leglib.design.gainmap.GainMap`) or ``"model"`` (:class:`leglib.design.plantfit.LegPlantModel`)
    predicted : (zeta, fn [Hz]) the map or model predicts at ``gains``, or None
    measured : (zeta, fn [Hz]) identified from a step with ``gains`` on the leg, or None
    source : where the design came from, plain values (e.g. the sweep directory and its
        point counts, or the fitted plant's parameters)
    measured_intervals : the 90 % intervals ((zeta low, high), (fn low, high) [Hz]) of
        ``measured``, from the identification of the step that measured it
        (:func:`leglib.design.points.identify_response`); None when none was recorded (a
        file written before they were stored says so: :data:`NO_INTERVAL`)
    predicted_intervals : the 90 % intervals of ``predicted`` where the prediction has them
        (the map's, interpolated from its measured points); None otherwise
    """

    target: tuple
    gains: tuple
    method: str
    predicted: tuple | None = None
    measured: tuple | None = None
    source: dict = field(default_factory=dict)
    measured_intervals: tuple | None = None
    predicted_intervals: tuple | None = None

    def __post_init__(self):
        self.target = _pair("target", self.target)
        self.gains = tuple(float(g) for g in self.gains)
        if len(self.gains) != 3:
            raise ValueError(f"gains must be (pos_gain, vel_gain, vel_integrator_gain), got {self.gains!r}")
        self.predicted = None if self.predicted is None else _pair("predicted", self.predicted)
        self.measured = None if self.measured is None else _pair("measured", self.measured)
        self.measured_intervals = _intervals("measured_intervals", self.measured_intervals, self.measured)
        self.predicted_intervals = _intervals("predicted_intervals", self.predicted_intervals, self.predicted)
        self.source = _plain(dict(self.source))

    def measured_text(self) -> str:
        """The measured (zeta, fn) with its 90 % intervals, or saying none was recorded."""
        return dynamics_text(self.measured, self.measured_intervals)

    def predicted_text(self) -> str:
        """The predicted (zeta, fn) with its 90 % intervals where the prediction has them (the
        map's), else saying it has none."""
        return dynamics_text(self.predicted, self.predicted_intervals,
                             missing=f"{self.method}'s prediction, no interval recorded")

    def __str__(self) -> str:
        return (f"gains ({', '.join(f'{g:.4g}' for g in self.gains)}) by {self.method} for zeta {self.target[0]:g}, "
                f"fn {self.target[1]:g} Hz: predicted {self.predicted_text()}; measured {self.measured_text()}"
                + (" (90 % intervals)" if self.measured_intervals is not None else ""))

    def _repr_markdown_(self) -> str:
        return ("| target (ζ, fn [Hz]) | gains (pos, vel, vel_int) | method | predicted | measured [90 % interval] |\n"
                "|---|---|---|---|---|\n"
                f"| ({self.target[0]:g}, {self.target[1]:g}) | ({', '.join(f'{g:.4g}' for g in self.gains)}) | "
                f"{self.method} | {self.predicted_text()} | {self.measured_text()} |")


def _pair(name, value) -> tuple:
    v = tuple(float(x) for x in value)
    if len(v) != 2:
        raise ValueError(f"{name} must be (zeta, fn), got {value!r}")
    return v


def _intervals(name, value, pair):
    """((zeta low, high), (fn low, high)) as floats, each holding its value of ``pair``; None
    for None, and for an interval with a NaN bound (the identification gave none)."""
    if value is None:
        return None
    if pair is None:
        raise ValueError(f"{name} given without the values they belong to")
    try:
        iv = tuple(tuple(float(b) for b in x) for x in value)
    except TypeError:
        raise ValueError(f"{name} must be ((zeta low, high), (fn low, high)), got {value!r}") from None
    if len(iv) != 2 or any(len(x) != 2 for x in iv):
        raise ValueError(f"{name} must be ((zeta low, high), (fn low, high)), got {value!r}")
    if any(math.isnan(b) for x in iv for b in x):
        return None
    for (lo, hi), v, what in zip(iv, pair, ("zeta", "fn")):
        if not lo <= v <= hi:
            raise ValueError(f"{name}: the {what} interval [{lo:g}, {hi:g}] does not hold its value {v:g}")
    return iv


def _plain(obj):
    """Plain JSON values (numpy scalars and arrays to Python; NaN and inf to None)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_plain(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} {obj!r} in a design file")


# ---------------------------------------------------------------------------------------
# provenance
# ---------------------------------------------------------------------------------------

def provenance(device=None, backend: str | None = None, serial: str | None = None) -> dict:
    """leglib version and commit, the date (UTC), backend and device serial number.

    Parameters
    ----------
    device : an :class:`leglib.device.session.Device` (or None): gives backend and serial
    backend, serial : given explicitly when there is no device (they override it)
    """
    dev_backend, dev_serial = None, None
    if device is not None:
        dev_backend = getattr(device, "backend", None)
        try:
            dev_serial = f"{int(device.serial_number):012X}"  # as the odrive tool prints it
        except Exception:  # noqa: BLE001 - a device without the property, or a lost link: not fatal here
            dev_serial = None
    return {**_prov(), "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "backend": backend if backend is not None else dev_backend,
            "device_serial": serial if serial is not None else dev_serial}


# ---------------------------------------------------------------------------------------
# arrays to and from JSON
# ---------------------------------------------------------------------------------------

def _array_out(a):
    a = np.asarray(a)
    if np.iscomplexobj(a):
        return {"re": a.real.tolist(), "im": a.imag.tolist()}
    return a.astype(float).tolist()


def _bad(path, name: str, why: str) -> DesignFileError:
    return DesignFileError(f"{path}: field {name!r} {why}")


def _number(path, name: str, v, low: float | None = None, high: float | None = None,
            low_open: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _bad(path, name, f"must be a finite number, got {v!r}")
    try:
        return checks.number(v, "", DesignFileError, low=low, high=high, low_open=low_open)
    except DesignFileError as exc:
        raise _bad(path, name, str(exc).strip()) from None


def _array_in(path, name: str, v, shape: tuple, allow_complex: bool = False) -> np.ndarray:
    """``v`` as a float (or complex) array of ``shape`` (None in shape: any length)."""
    desc = " x ".join("n" if s is None else str(s) for s in shape)
    if allow_complex and isinstance(v, dict):
        if set(v) != {"re", "im"}:
            raise _bad(path, name, f"as a complex array must have exactly the keys 're' and 'im', got {sorted(v)}")
        re = _array_in(path, f"{name}.re", v["re"], shape)
        im = _array_in(path, f"{name}.im", v["im"], re.shape)
        return re + 1j * im
    leaf = _bad_leaf(v)
    if leaf is not None:
        raise _bad(path, name, f"must be a {desc} array of numbers, got {leaf!r} in it")
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise _bad(path, name, f"must be a {desc} array of numbers, got {v!r}") from None
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        raise _bad(path, name, f"must be a {desc} array of numbers, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise _bad(path, name, "must hold finite numbers only")
    if np.any(np.abs(a) > MAX_ENTRY):
        raise _bad(path, name, f"holds {float(np.max(np.abs(a))):.3g}: no entry of a design exceeds "
                               f"{MAX_ENTRY:g} in magnitude")
    return a


def _bad_leaf(v):
    """The first value in nested lists ``v`` that is not a number (a bool, a string, an
    object, null), or None when they are all numbers."""
    if isinstance(v, list):
        for x in v:
            bad = _bad_leaf(x)
            if bad is not None:
                return bad
        return None
    if v is None:      # null: NaN or inf when saved; refused as not finite
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return v
    return None


def _get(path, data: dict, name: str, kinds=None):
    if name not in data:
        raise _bad(path, name, "is missing")
    v = data[name]
    if kinds is not None and (not isinstance(v, kinds) or isinstance(v, bool)):
        what = {dict: "a JSON object", str: "a string", int: "an integer"}.get(kinds, str(kinds))
        raise _bad(path, name, f"must be {what}, got {v!r}")
    return v


# ---------------------------------------------------------------------------------------
# save / load
# ---------------------------------------------------------------------------------------

def _state_feedback_body(d, observer_factor, linearization) -> dict:
    sys = d.sys
    if observer_factor is None:
        # the observer poles are factor * poles (statefeedback.design)
        ratios = np.asarray(d.observer_poles) / np.asarray(d.poles)
        observer_factor = float(np.real(ratios[0]))
    return {
        "poles": _array_out(d.poles),
        "observer_factor": float(observer_factor),
        "observer_poles": _array_out(d.observer_poles),
        "integral_poles": None if d.integral_poles is None else _array_out(d.integral_poles),
        "K": _array_out(d.K), "L": _array_out(d.L), "Nbar": _array_out(d.Nbar),
        "Ki": None if d.Ki is None else _array_out(d.Ki),
        "controllability_rank": int(d.controllability_rank),
        "observability_rank": int(d.observability_rank),
        "linearization": {"A": _array_out(sys.A), "B": _array_out(sys.B), "C": _array_out(sys.C),
                          "D": _array_out(sys.D), "about": _plain(dict(linearization or {}))},
    }


def _zeta_fn_out(pair, intervals) -> dict | None:
    """{"zeta", "fn_hz"} and, when there are intervals, {"zeta_interval", "fn_interval_hz"}:
    [low, high], a bound that is not finite (an unbounded interval) written as null."""
    if pair is None:
        return None
    out = {"zeta": pair[0], "fn_hz": pair[1]}
    if intervals is not None:
        out["zeta_interval"], out["fn_interval_hz"] = (_plain(list(x)) for x in intervals)
    return out


def _gain_body(g: GainDesign) -> dict:
    return {"target": {"zeta": g.target[0], "fn_hz": g.target[1]},
            "gains": {"pos_gain": g.gains[0], "vel_gain": g.gains[1], "vel_integrator_gain": g.gains[2]},
            "method": g.method,
            "predicted": _zeta_fn_out(g.predicted, g.predicted_intervals),
            "measured": _zeta_fn_out(g.measured, g.measured_intervals),
            "source": g.source}


def save(path: str | Path, design, *, observer_factor: float | None = None, linearization: dict | None = None,
         device=None, backend: str | None = None, serial: str | None = None, note: str = "") -> Path:
    """Write a design to ``path`` (JSON, atomically: never a half-written file).

    Parameters
    ----------
    path : file to write; its directory is created
    design : a :class:`leglib.design.statefeedback.StateFeedback` (poles, observer poles and factor,
        integral poles, K (2, 4), L (4, 2), Nbar (2, 2), Ki (2, 2) or None, the ranks, and
        the linearization A, B, C, D it was placed on) or a :class:`GainDesign`
    observer_factor : for a state-feedback design; default: observer_poles / poles
    linearization : plain values saying where the linear model came from (e.g. leg name,
        operating point, ``coupled``, ``model``); stored with its matrices
    device, backend, serial : provenance, see :func:`provenance`
    note : free text kept in the file

    Returns
    -------
    Path written.
    """
    if isinstance(design, StateFeedback):
        kind, body = "state_feedback", _state_feedback_body(design, observer_factor, linearization)
    elif isinstance(design, GainDesign):
        kind, body = "cascade_gains", _gain_body(design)
    else:
        raise TypeError(f"can save a StateFeedback (place_poles) or a GainDesign, got {type(design).__name__}")
    data = {"kind": kind, "format": FORMAT,
            "provenance": provenance(device, backend, serial), "note": str(note), **body}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=1, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix="." + path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read(path: str | Path) -> dict:
    """The raw content of a design file, its ``kind``, ``format`` and ``provenance`` checked."""
    path = Path(path)
    text = checks.text_file(path, "design file", DesignFileError, form="JSON", max_bytes=MAX_BYTES)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DesignFileError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    except RecursionError:
        raise DesignFileError(f"{path}: not a design file: its JSON is nested too deeply") from None
    except ValueError as exc:    # an integer of more digits than Python converts
        raise DesignFileError(f"{path}: not a design file: {exc}") from None
    if not isinstance(data, dict):
        raise DesignFileError(f"{path}: a design file holds one JSON object, got {type(data).__name__}")
    kind = _get(path, data, "kind", str)
    if kind not in KINDS:
        raise _bad(path, "kind", f"must be one of {KINDS}, got {kind!r}")
    fmt = _get(path, data, "format", int)
    if fmt != FORMAT:
        raise _bad(path, "format", f"is {fmt}; this leglib reads format {FORMAT}")
    prov = _get(path, data, "provenance", dict)
    for key in ("leglib_version", "git_commit", "date"):
        if not isinstance(prov.get(key), str):
            raise _bad(path, f"provenance.{key}", f"must be a string, got {prov.get(key, 'nothing')!r}")
    for key in ("backend", "device_serial"):
        if key not in prov:
            raise _bad(path, f"provenance.{key}", "is missing")
        if prov[key] is not None and not isinstance(prov[key], str):
            raise _bad(path, f"provenance.{key}", f"must be a string or null, got {prov[key]!r}")
    return data


def _load_state_feedback(path, data):
    import control  # load time: python-control (about 2 s), only for a design's linear system

    lin = _get(path, data, "linearization", dict)
    A = _array_in(path, "linearization.A", _get(path, lin, "A"), (None, None))
    n = A.shape[0]
    if A.shape != (n, n):
        raise _bad(path, "linearization.A", f"must be square, got shape {A.shape}")
    B = _array_in(path, "linearization.B", _get(path, lin, "B"), (n, None))
    m = B.shape[1]
    C = _array_in(path, "linearization.C", _get(path, lin, "C"), (None, n))
    p = C.shape[0]
    D = _array_in(path, "linearization.D", _get(path, lin, "D"), (p, m))
    if "about" in lin and not isinstance(lin["about"], dict):
        raise _bad(path, "linearization.about", f"must be an object, got {lin['about']!r}")
    poles = _array_in(path, "poles", _get(path, data, "poles"), (n,), allow_complex=True)
    obs = _array_in(path, "observer_poles", _get(path, data, "observer_poles"), (n,), allow_complex=True)
    _number(path, "observer_factor", _get(path, data, "observer_factor"), low=0.0, low_open=True)
    K = _array_in(path, "K", _get(path, data, "K"), (m, n))
    L = _array_in(path, "L", _get(path, data, "L"), (n, p))
    Nbar = _array_in(path, "Nbar", _get(path, data, "Nbar"), (m, p))
    Ki = _get(path, data, "Ki")
    Ki = None if Ki is None else _array_in(path, "Ki", Ki, (m, p))
    ip = _get(path, data, "integral_poles")
    ip = None if ip is None else _array_in(path, "integral_poles", ip, (p,), allow_complex=True)
    if (Ki is None) != (ip is None):
        raise _bad(path, "Ki", "and 'integral_poles' must both be null or both be given")
    ranks = {}
    for name in ("controllability_rank", "observability_rank"):
        r = _get(path, data, name)
        if isinstance(r, bool) or not isinstance(r, int) or not 0 <= r <= n:
            raise _bad(path, name, f"must be an integer in [0, {n}], got {r!r}")
        ranks[name] = r
    for name, pl in (("poles", poles), ("observer_poles", obs), ("integral_poles", ip)):
        if pl is not None and np.any(pl.real >= 0):
            raise _bad(path, name, f"holds {pl[pl.real >= 0]}, not in the open left half plane: the "
                                   f"closed loop would be unstable")
    if Ki is None:
        _check_placed(path, "K", A - B @ K, poles, "A - B K", "'poles'")
    else:
        Aa = np.block([[A, np.zeros((n, p))], [C, np.zeros((p, p))]])
        Ba = np.vstack([B, np.zeros((p, m))])
        _check_placed(path, "K", Aa - Ba @ np.hstack([K, Ki]), np.concatenate([poles, ip]),
                      "A - B K with the integrators (Ki)", "'poles' and 'integral_poles'")
    _check_placed(path, "L", A - L @ C, obs, "A - L C", "'observer_poles'")
    return StateFeedback(sys=control.ss(A, B, C, D), poles=poles, observer_poles=obs, K=K, L=L, Nbar=Nbar, Ki=Ki,
                  integral_poles=ip, **ranks)


def _check_placed(path, name: str, closed: np.ndarray, poles: np.ndarray, what: str, pole_field: str) -> None:
    """The eigenvalues of ``closed`` are ``poles`` (each matched to its nearest, within
    :data:`POLE_TOLERANCE` of the largest pole): the gain ``name`` places the file's poles."""
    eig = list(np.linalg.eigvals(closed))
    scale = max(1.0, float(np.max(np.abs(poles))))
    worst = 0.0
    for pole in poles:
        k = int(np.argmin([abs(e - pole) for e in eig]))
        worst = max(worst, abs(eig.pop(k) - pole) / scale)
    if not worst <= POLE_TOLERANCE:
        got = ", ".join(f"{complex(e):.4g}" for e in np.sort_complex(np.linalg.eigvals(closed)))
        raise _bad(path, name, f"does not place the file's {pole_field}: the eigenvalues of {what} are "
                               f"{got} (off by {worst:.2g} relative to the largest pole)")


def _zeta_fn(path, data, name, optional: bool):
    v = _get(path, data, name)
    if v is None and optional:
        return None
    if not isinstance(v, dict):
        raise _bad(path, name, f"must be an object with 'zeta' and 'fn_hz', got {v!r}")
    return tuple(_number(path, f"{name}.{k}", _field(path, v, k, name), low=0.0, low_open=True, high=high)
                 for k, high in (("zeta", MAX_ZETA), ("fn_hz", MAX_FN_HZ)))


def _zeta_fn_intervals(path, data, name, pair):
    """The intervals stored beside ``name``'s (zeta, fn): None when the file holds none (one
    written before they were stored: the design then says :data:`NO_INTERVAL`), an error
    naming the field when they are malformed or do not hold their value."""
    v = data.get(name)
    if pair is None or not isinstance(v, dict):
        return None
    keys = ("zeta_interval", "fn_interval_hz")
    present = [k in v for k in keys]
    if not any(present):
        return None
    if not all(present):
        missing = keys[present.index(False)]
        raise _bad(path, f"{name}.{missing}", "is missing (the other interval is there)")
    out = []
    for k, value, high in zip(keys, pair, (MAX_ZETA, MAX_FN_HZ)):
        iv = v[k]
        if not isinstance(iv, list) or len(iv) != 2:
            raise _bad(path, f"{name}.{k}", f"must be [low, high], got {iv!r}")
        lo = _number(path, f"{name}.{k}[0]", iv[0], low=0.0)
        hi = math.inf if iv[1] is None else _number(path, f"{name}.{k}[1]", iv[1], low=0.0)
        if not lo <= value <= hi:
            raise _bad(path, f"{name}.{k}", f"[{lo:g}, {hi:g}] does not hold the value {value:g}")
        out.append((lo, hi))
    return tuple(out)


def _field(path, obj: dict, key: str, parent: str):
    if key not in obj:
        raise _bad(path, f"{parent}.{key}", "is missing")
    return obj[key]


def _load_gains(path, data, config: OdriveConfig) -> GainDesign:
    g = _get(path, data, "gains", dict)
    gains = []
    for k in ("pos_gain", "vel_gain", "vel_integrator_gain"):
        v = _number(path, f"gains.{k}", _field(path, g, k, "gains"))
        if v < 0:
            raise _bad(path, "gains", f"must not be negative, got {k} = {v!r}")
        high = getattr(config, f"max_{k}")
        if v > high:
            raise _bad(path, f"gains.{k}", f"= {v:g} is beyond the configured maximum {high:g} "
                                           f"({config.source_file}, [experiment] max_{k})")
        gains.append(v)
    predicted = _zeta_fn(path, data, "predicted", True)
    measured = _zeta_fn(path, data, "measured", True)
    return GainDesign(target=_zeta_fn(path, data, "target", False), gains=tuple(gains),
                      method=_get(path, data, "method", str), predicted=predicted, measured=measured,
                      source=_get(path, data, "source", dict),
                      measured_intervals=_zeta_fn_intervals(path, data, "measured", measured),
                      predicted_intervals=_zeta_fn_intervals(path, data, "predicted", predicted))


def load(path: str | Path, kind: str | None = None, config: str | Path | OdriveConfig = "thesis"):
    """Read a design written by :func:`save`, checked as a design: every number finite and of
    a sane size, the poles stable, K (and Ki) placing the file's poles and L its observer
    poles, ``observer_factor`` positive, cascade gains within ``config``'s maxima, the target
    and measured zeta and fn positive.

    Parameters
    ----------
    path : the design file (a regular file of at most :data:`MAX_BYTES`)
    kind : None (either), ``"state_feedback"`` or ``"cascade_gains"``: the kind expected
    config : the ODrive configuration whose ``max_pos_gain``, ``max_vel_gain`` and
        ``max_vel_integrator_gain`` bound a cascade design's gains (name, path or OdriveConfig)

    Returns
    -------
    :class:`leglib.design.statefeedback.StateFeedback` or :class:`GainDesign`, equal (:func:`same`) to
    the one saved. The provenance is available from :func:`read`.

    Raises
    ------
    DesignFileError
        naming the file and the field that is missing or malformed.
    """
    if kind is not None and kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS} or None, got {kind!r}")
    data = read(path)
    if kind is not None and data["kind"] != kind:
        raise _bad(path, "kind", f"is {data['kind']!r}, but a {kind!r} design is needed here")
    if data["kind"] == "state_feedback":
        return _load_state_feedback(Path(path), data)
    return _load_gains(Path(path), data, config if isinstance(config, OdriveConfig) else load_odrive_config(config))


def same(a, b) -> bool:
    """True when two designs are exactly equal, field by field (arrays bitwise, dtype kind
    and shape included; the linear models' A, B, C, D)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, GainDesign):
        return a == b

    def eq(x, y):
        if x is None or y is None:
            return x is None and y is None
        x, y = np.asarray(x), np.asarray(y)
        return x.shape == y.shape and np.iscomplexobj(x) == np.iscomplexobj(y) and np.array_equal(x, y)

    if not isinstance(a, StateFeedback):
        raise TypeError(f"not a design: {type(a).__name__}")
    return (all(eq(getattr(a.sys, k), getattr(b.sys, k)) for k in "ABCD")
            and all(eq(getattr(a, k), getattr(b, k)) for k in
                    ("poles", "observer_poles", "K", "L", "Nbar", "Ki", "integral_poles"))
            and a.controllability_rank == b.controllability_rank
            and a.observability_rank == b.observability_rank
            and a.sys.dt == b.sys.dt)


def gain_design_from_map(gm, zeta: float, fn: float, sweep_dir: str | Path | None = None,
                         measured=None, measured_intervals=None) -> GainDesign:
    """The map's answer for (zeta, fn [Hz]) as a :class:`GainDesign` (method ``"map"``), its
    prediction with the map's 90 % intervals; the source records the sweep directory, the
    map's point counts and its gain axes."""
    c = gm.nearest(zeta, fn)
    return GainDesign(target=(zeta, fn), gains=c.gains, method="map", predicted=(c.zeta, c.fn), measured=measured,
                      source={"sweep_dir": None if sweep_dir is None else str(sweep_dir), "counts": gm.counts(),
                              "axes": [list(map(float, a)) for a in gm.axes], "distance": c.distance},
                      measured_intervals=measured_intervals, predicted_intervals=(c.zeta_interval, c.fn_interval))


def gain_design_from_model(model, zeta: float, fn: float, vel_integrator_gain: float = 0.01,
                           measured=None, measured_intervals=None) -> GainDesign:
    """The gains a fitted :class:`leglib.design.plantfit.LegPlantModel` gives for (zeta, fn [Hz]) as
    a :class:`GainDesign` (method ``"model"``); the source records the fitted plant."""
    gains, pred = model.gains_for(zeta, fn, vel_integrator_gain=vel_integrator_gain)
    return GainDesign(target=(zeta, fn), gains=gains, method="model", predicted=pred, measured=measured,
                      measured_intervals=measured_intervals,
                      source={"plant_params": dict(model.params), "experiments": model.experiments,
                              "rms_turns": model.rms_turns, "step_turns": model.step,
                              "duration_s": model.duration, "sample_period_s": model.sample_period})
