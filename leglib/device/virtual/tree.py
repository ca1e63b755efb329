"""The virtual ODrive's object tree, declared: one row per endpoint, built into nodes and
properties with the firmware's endpoint names.

A row (:class:`Endpoint`) names an endpoint as the firmware's table does
(``endpoints_fw-v0.5.x.json``; ``axis*`` stands for both axes) and says

- where its value lives in the model, its *store*: a slot of the kernel's arrays
  (:class:`C` configuration, :class:`S` float state, :class:`I` int state, :class:`Err` an
  error word), a key of an axis's or the board's Python state (:class:`Key`,
  :class:`Board`), an attribute of the device (:class:`Attr`), a constant (:class:`Const`),
  a reading a method of the device computes (:class:`Get`), or a function (:class:`Call`);
- its type (``float``, ``int`` or ``bool``: what a write is coerced to and a read returns);
- ``check``: a test of a written value, ``check(where, value)``, raising ValueError
  (:func:`positive`);
- ``setter``: the name of a device method that takes a write instead of the store, where
  the firmware acts on it (``_request_state``, ``_set_input_pos``, ...);
- ``since`` / ``until``: the first and the last firmware release that has the endpoint.

:func:`build_tree` makes the tree of one boot from the rows of a firmware version; nothing
in the tree is typed by hand, so adding an endpoint to the model is adding a row.
``tests/device/test_endpoints.py`` checks every row against the firmware's table of each
version it is marked for.

A tree belongs to one boot of the device: after a reboot every access raises
:class:`leglib.errors.DeviceLostError`, as the USB object of a real ODrive does. Every
property read or write and every call is one USB transaction on the device's clock.
"""

from __future__ import annotations

import functools
import math
import struct
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import numpy as np

from ...errors import DeviceLostError, LeglibError

# the firmware releases a v3.6 runs (tags fw-v0.5.1 ... fw-v0.5.6): what since/until name
RELEASES = ("0.5.1", "0.5.2", "0.5.3", "0.5.4", "0.5.5", "0.5.6")

# the axes an ``axis*`` row stands for
AXES = (0, 1)


class UnmodeledError(LeglibError, NotImplementedError):
    """The virtual ODrive cannot honour this use of an endpoint (a value it does not model,
    a function or state it refuses); the message names the endpoint and why. The real board
    would act on it: the model is stricter, never silently different."""


class _Prop:
    """One property of the tree: getter, optional setter, value type; ``nan_ok``: a NaN is
    stored (a setting the model holds, as the firmware holds any float) rather than refused
    (a value the kernel would compute with)."""

    def __init__(self, get, set=None, kind=float, nan_ok=False):
        self.get, self.set, self.kind, self.nan_ok = get, set, kind, nan_ok


class _Node:
    """A node of the object tree with a fixed set of properties, children and methods.

    A tree belongs to one boot of the device: after a reboot every access raises
    :class:`DeviceLostError`, as the USB object of a real ODrive does.
    """

    def __init__(self, dev, path, props=None, children=None, methods=None):
        object.__setattr__(self, "_dev", dev)
        object.__setattr__(self, "_path", path)
        object.__setattr__(self, "_props", props or {})
        object.__setattr__(self, "_children", children or {})
        object.__setattr__(self, "_methods", methods or {})
        object.__setattr__(self, "_boot", dev.boot_count)

    def _alive(self):
        if self._boot != self._dev.boot_count:
            raise DeviceLostError(f"'{self._path}': the ODrive rebooted (boot {self._dev.boot_count}); "
                                  f"this handle is from boot {self._boot}: reconnect")

    def __getattr__(self, name):
        if name in self._children:
            self._alive()
            return self._children[name]
        if name in self._props:
            self._alive()
            self._dev._transaction()
            return self._props[name].get()
        if name in self._methods:
            fn = self._methods[name]

            def call(*args, **kwargs):
                self._alive()
                self._dev._transaction()
                return fn(*args, **kwargs)
            return call
        raise AttributeError(f"'{self._path}' has no attribute '{name}'")

    def __setattr__(self, name, value):
        prop = self._props.get(name)
        if prop is None:
            if name in self._children or name in self._methods:
                raise AttributeError(f"'{self._path}.{name}' cannot be assigned")
            raise AttributeError(f"'{self._path}' has no attribute '{name}'")
        if prop.set is None:
            raise AttributeError(f"'{self._path}.{name}' is read-only")
        if prop.kind is bool:
            if not isinstance(value, (bool, int, np.integer)):
                raise TypeError(f"'{self._path}.{name}' expects a bool, got {value!r}")
            value = bool(value)
        elif prop.kind is int:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"'{self._path}.{name}' expects an integer, got {value!r}")
            value = int(value)
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise TypeError(f"'{self._path}.{name}' expects a number, got {value!r}")
            value = float(value)
            if math.isnan(value) and not prop.nan_ok:
                raise ValueError(f"'{self._path}.{name}' must be a number, got {value!r}")
        self._alive()
        self._dev._transaction()
        prop.set(value)

    def __dir__(self):
        return sorted(set(self._props) | set(self._children) | set(self._methods))

    def __repr__(self):
        return f"<virtual ODrive node {self._path}>"


# ---------------------------------------------------------------------------------------
# checks of written values: check(where, value), where the endpoint's full name
# ---------------------------------------------------------------------------------------

def positive(where: str, value) -> None:
    """The value must be > 0 (NaN never gets here: the tree refuses it as a number)."""
    if not value > 0:
        raise ValueError(f"{where} must be positive, got {value}")


def honoured(value, reason: str) -> Callable:
    """A check accepting only ``value``, the one the model honours: another raises
    :class:`UnmodeledError` naming the endpoint and ``reason`` (the firmware would store it
    and act on it)."""
    def check(where, v):
        if v != value:
            raise UnmodeledError(f"{where} = {v!r}: {reason}; the virtual ODrive accepts only {value!r}")
    return check


# ---------------------------------------------------------------------------------------
# stores: where a row's value lives. ``bind(dev, a, kind)`` gives the getter and the setter
# (None: read-only) for axis ``a``, None on a board row; a board row's kernel slots are
# those of axis 0 (leglib/twin/layout.py: the system's slots on axis 0).
# ---------------------------------------------------------------------------------------

class Store:
    """Base of the row kinds. ``writable``: the store takes writes itself; ``per_axis``:
    only on ``axis*`` rows; ``function``: the row is a function, not a property."""

    writable = False
    per_axis = False
    function = False

    def bind(self, dev, a, kind, where: str = "") -> tuple[Callable, Callable | None]:
        raise NotImplementedError


def _slot_axis(a):
    return 0 if a is None else a


@dataclass(frozen=True)
class C(Store):
    """A slot of the kernel's float configuration, ``st.C[0, a, slot]`` (``layout.C_*``)."""

    slot: int
    writable = True

    def bind(self, dev, a, kind, where=""):
        st, i, slot = dev.st, _slot_axis(a), self.slot

        def set_(v):
            st.C[0, i, slot] = v
        return (lambda: kind(st.C[0, i, slot])), set_


@dataclass(frozen=True)
class _Slot(Store):
    """A slot of one of the kernel's per-axis state arrays (``ARRAY``: ``st.AS`` or
    ``st.AI``), read-only unless ``writable``."""

    ARRAY = ""
    slot: int
    writable: bool = False

    def bind(self, dev, a, kind, where=""):
        st, name, i, slot = dev.st, self.ARRAY, _slot_axis(a), self.slot

        def set_(v):
            getattr(st, name)[0, i, slot] = v
        return (lambda: kind(getattr(st, name)[0, i, slot])), (set_ if self.writable else None)


@dataclass(frozen=True)
class S(_Slot):
    """A slot of the kernel's float state, ``st.AS[0, a, slot]`` (``layout.S_*``)."""

    ARRAY = "AS"


@dataclass(frozen=True)
class I(_Slot):  # noqa: E742 - named as the layout's I_ slots, beside C and S
    """A slot of the kernel's int state, ``st.AI[0, a, slot]`` (``layout.I_*``)."""

    ARRAY = "AI"


@dataclass(frozen=True)
class Err(I):
    """An error word in the kernel's int state (``layout.I_*_ERR``): read and written (the
    firmware's error endpoints are rw; writing 0 clears)."""

    writable: bool = True


@dataclass(frozen=True)
class Key(Store):
    """A key of the axis's Python state, ``dev._axis[a][key]`` (configuration the kernel
    does not need, and the state machine's own state); read-only unless ``writable``."""

    key: str
    writable: bool = True
    per_axis = True

    def bind(self, dev, a, kind, where=""):
        ax, key = dev._axis[a], self.key

        def set_(v):
            ax[key] = v
        return (lambda: kind(ax[key])), (set_ if self.writable else None)


@dataclass(frozen=True)
class Board(Store):
    """A key of the board's Python configuration, ``dev._board[key]`` (saved with it)."""

    key: str
    writable: bool = True

    def bind(self, dev, a, kind, where=""):
        board, key = dev._board, self.key

        def set_(v):
            board[key] = v
        return (lambda: kind(board[key])), (set_ if self.writable else None)


@dataclass(frozen=True)
class Attr(Store):
    """An attribute of the device, read-only (``fw_revision``, ``_brake_armed``)."""

    name: str

    def bind(self, dev, a, kind, where=""):
        name = self.name
        return (lambda: kind(getattr(dev, name))), None


@dataclass(frozen=True)
class Const(Store):
    """A fixed value, read-only."""

    value: Any

    def bind(self, dev, a, kind, where=""):
        value = kind(self.value)
        return (lambda: value), None


@dataclass(frozen=True)
class Get(Store):
    """A reading computed by a method of the device, by name: ``dev.<method>(a, *args)`` on
    an axis row, ``dev.<method>(*args)`` on a board row; read-only."""

    method: str
    args: tuple = ()

    def bind(self, dev, a, kind, where=""):
        fn = getattr(dev, self.method)
        args = self.args if a is None else (a, *self.args)
        return (lambda: kind(fn(*args))), None


@dataclass(frozen=True)
class Call(Store):
    """A function of the firmware: a method of the device, by name, called as
    ``dev.<method>(a, *bound, *args)`` on an axis row, ``dev.<method>(*bound, *args)`` on a
    board row (``bound``: the row's own arguments, ``args``: the call's)."""

    method: str
    bound: tuple = ()
    function = True

    def bind(self, dev, a, kind, where=""):
        fn = getattr(dev, self.method)
        head = self.bound if a is None else (a, *self.bound)
        return (functools.partial(fn, *head) if head else fn), None


_INT_BITS = {"int8": (8, True), "uint8": (8, False), "int16": (16, True), "uint16": (16, False),
             "int32": (32, True), "uint32": (32, False), "int64": (64, True), "uint64": (64, False),
             "endpoint_ref": (32, False)}


def c_value(codec: str, value):
    """``value`` as the firmware's member of type ``codec`` holds it: C's conversion of an
    integer to the member's width (``uint8 axis_to_mirror = -1`` reads 255)."""
    spec = _INT_BITS.get(codec)
    if spec is None or isinstance(value, bool):
        return value
    bits, signed = spec
    v = int(value) % (1 << bits)
    return v - (1 << bits) if signed and v >= 1 << (bits - 1) else v


def _same(kind, a, b) -> bool:
    """Equal as the firmware stores them (floats as float32, NaN equal to NaN)."""
    if kind is float:
        pack = struct.Struct("<f").pack
        try:
            return pack(float(a)) == pack(float(b))
        except OverflowError:
            return float(a) == float(b)
    return a == b


@dataclass(frozen=True)
class Setting(Store):
    """A setting the device holds as the firmware does (``dev._settings[a][key]``, ``a``
    None on a board row), saved with the configuration when its path is a configuration
    path and reset to the firmware's default by a boot (volatile) or an erase.

    ``only``: the model honours only the firmware's default; another value raises
    :class:`UnmodeledError` naming the endpoint and ``reason``. ``reader``: ``(method,
    args)`` of a device method that computes the reading instead of the stored value (a
    counter the host may also write).
    """

    key: str
    only: bool = False
    reason: str = ""
    reader: tuple | None = None
    codec: str = ""
    writable = True

    def bind(self, dev, a, kind, where=""):
        values, key, only, reason, codec = dev._settings[a], self.key, self.only, self.reason, self.codec

        def set_(v):
            v = c_value(codec, v)
            if only:
                honoured = dev._setting_default(a, key)
                if not _same(kind, v, honoured):
                    raise UnmodeledError(f"{where or key} = {v!r}: {reason}; the virtual ODrive "
                                         f"accepts only the firmware's default {kind(honoured)!r}")
            values[key] = v
        if self.reader is not None:
            fn = getattr(dev, self.reader[0])
            args = self.reader[1] if a is None else (a, *self.reader[1])
            return (lambda: kind(fn(*args))), set_
        return (lambda: kind(values[key])), set_


# ---------------------------------------------------------------------------------------
# rows
# ---------------------------------------------------------------------------------------

def _release(version: str) -> int:
    if version not in RELEASES:
        raise ValueError(f"firmware {version!r} is not a release of a v3.6 (one of {RELEASES})")
    return RELEASES.index(version)


@dataclass(frozen=True)
class Endpoint:
    """One endpoint of the model: see the module's docstring.

    Parameters
    ----------
    path : the firmware table's name, ``axis*`` for both axes ("axis*.controller.config.pos_gain")
    store : where the value lives (:class:`C`, :class:`S`, :class:`I`, :class:`Err`,
        :class:`Key`, :class:`Board`, :class:`Attr`, :class:`Const`, :class:`Get`, :class:`Call`)
    kind : float, int or bool (ignored for a :class:`Call`)
    check : ``check(where, value)`` raising ValueError for a refused write
    setter : name of the device method that takes a write, ``(a, value)`` on an axis row,
        ``(value)`` on a board row
    since, until : the first and the last release that has the endpoint (None: the latest)
    """

    path: str
    store: Store
    kind: type = float
    check: Callable | None = None
    setter: str | None = None
    since: str = RELEASES[0]
    until: str | None = None

    def __post_init__(self):
        where = f"Endpoint({self.path!r})"
        parts = self.path.split(".")
        numbered = any(p.startswith("axis") and p[4:].isdigit() for p in parts)
        if not all(parts) or numbered or "axis*" in parts[1:] or parts == ["axis*"]:
            raise ValueError(f"{where}: a path of the firmware's table, 'axis*' for the axes")
        if not isinstance(self.store, Store):
            raise TypeError(f"{where}: store must be a row kind (C, S, I, Err, Key, Board, Attr, Const, Get, "
                            f"Call, Setting)")
        if self.store.per_axis and not self.per_axis:
            raise ValueError(f"{where}: {type(self.store).__name__} is per axis: the path must start with 'axis*.'")
        if not self.function and self.kind not in (float, int, bool):
            raise TypeError(f"{where}: kind must be float, int or bool, got {self.kind!r}")
        if self.function and (self.check is not None or self.setter is not None):
            raise ValueError(f"{where}: a function has no check or setter")
        if self.check is not None and not self.writable:
            raise ValueError(f"{where}: a check on a read-only endpoint")
        if self.setter is not None and not isinstance(self.setter, str):
            raise TypeError(f"{where}: setter names a method of the device")
        first = _release(self.since)
        if self.until is not None and _release(self.until) < first:
            raise ValueError(f"{where}: until {self.until} is before since {self.since}")

    @property
    def per_axis(self) -> bool:
        return self.path.startswith("axis*.")

    @property
    def function(self) -> bool:
        return self.store.function

    @property
    def writable(self) -> bool:
        return not self.function and (self.setter is not None or self.store.writable)

    def active(self, firmware: str) -> bool:
        """Whether firmware ``firmware`` (a release, "0.5.6") has this endpoint."""
        v = _release(firmware)
        return _release(self.since) <= v and (self.until is None or v <= _release(self.until))

    def concrete(self) -> list[tuple[int | None, str]]:
        """(axis or None, the endpoint's name on the device) for each instance of the row."""
        if self.per_axis:
            rest = self.path[len("axis*."):]
            return [(a, f"axis{a}.{rest}") for a in AXES]
        return [(None, self.path)]

    def bind(self, dev, a, where: str):
        """The tree's member of this row on ``dev`` for axis ``a`` (None: board): a
        :class:`_Prop`, or the function to call. ``where`` names it in messages."""
        get, set_ = self.store.bind(dev, a, self.kind, where)
        if self.function:
            return get
        if self.setter is not None:
            special = getattr(dev, self.setter)
            set_ = special if a is None else functools.partial(special, a)
        if set_ is not None and self.check is not None:
            set_ = functools.partial(_checked, self.check, where, set_)
        return _Prop(get, set_, self.kind, nan_ok=isinstance(self.store, Setting))


def _checked(check, where, set_, value):
    check(where, value)
    set_(value)


class Leaf(NamedTuple):
    """An endpoint of a built tree: its node, its name there, its row."""

    node: _Node | None
    name: str
    row: Endpoint


def model_paths(rows, firmware: str) -> dict[str, tuple[int | None, Endpoint]]:
    """``{"axis0.controller.config.pos_gain": (0, row), ...}``: the endpoints the rows give
    on firmware ``firmware``. Two rows for one endpoint, or an endpoint inside another, are
    an error."""
    out: dict[str, tuple[int | None, Endpoint]] = {}
    for row in rows:
        if not row.active(firmware):
            continue
        for a, path in row.concrete():
            if path in out:
                raise ValueError(f"two rows for {path} on firmware {firmware}: {out[path][1]!r} and {row!r}")
            out[path] = (a, row)
    for path in out:
        head = path.rpartition(".")[0]
        while head:
            if head in out:
                raise ValueError(f"{path}: its parent {head} is an endpoint of its own")
            head = head.rpartition(".")[0]
    return out


def build_tree(dev, rows, firmware: str) -> tuple[_Node, dict[str, Leaf]]:
    """The object tree of ``dev`` (one boot) on firmware ``firmware`` from ``rows``.

    Returns
    -------
    root : the tree's root node, ``odrv``
    leaves : ``{endpoint name: Leaf(node, name, row)}`` for every endpoint of the tree
    """
    nested: dict = {}
    for path, (a, row) in model_paths(rows, firmware).items():
        *parents, name = path.split(".")
        spec = nested
        for p in parents:
            spec = spec.setdefault(p, {})
        spec[name] = (a, row)
    leaves: dict[str, Leaf] = {}

    def make(spec: dict, prefix: str) -> _Node:
        props, children, methods, mine = {}, {}, {}, []
        for name, item in spec.items():
            if isinstance(item, dict):
                children[name] = make(item, f"{prefix}{name}.")
                continue
            a, row = item
            member = row.bind(dev, a, f"odrv.{prefix}{name}")
            (methods if row.function else props)[name] = member
            mine.append((name, row))
        node = _Node(dev, f"odrv.{prefix}".rstrip("."), props, children, methods)
        for name, row in mine:
            leaves[prefix + name] = Leaf(node, name, row)
        return node

    return make(nested, ""), leaves
