"""Numbers as a reader takes them: with their unit, and with the digits their doubt supports.

One place for how leglib prints a number:

- :func:`interval_text`: a value with its interval, both to the decimals the interval's
  half-width supports ("0.371 [0.365, 0.378]", not "0.37093 [0.36472, 0.37801]" nor "0.4 [0.4, 0.4]");
- :func:`quantity_text`: a value without an interval, to a few significant digits, with its unit;
- :class:`Unit` and :func:`derived`: the unit of a gain or a derivative, derived from the
  quantities it relates (a state-feedback gain from torque to an angle is N·m/rad, to an
  angular velocity N·m·s/rad), written for a reader ("N·m·s/rad", "1/s²", "kg·m²").

The digits rule is the Particle Data Group's: the interval's half-width is rounded to two
significant digits when its three leading digits are 100-354, else to one (950-999 round
up to two digits of the next decade), and the value and its bounds are written to that
decimal. A wider interval gets fewer digits, so a number
never claims more than its interval allows; an infinite or missing interval falls back to
:data:`SIGNIFICANT` significant digits and says the interval is unbounded.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

#: significant digits of a number printed without an interval
SIGNIFICANT = 3


def decimals(half_width: float) -> int | None:
    """The decimal place (digits after the point; negative: tens, hundreds) to which a value
    whose interval has ``half_width`` is written; None when the half-width is zero, negative
    or not finite (no interval to go by). The Particle Data Group's rule on the half-width's
    three leading digits: 100-354 keeps two significant digits, 355-949 one, 950-999 rounds
    up to 1000 and keeps two."""
    h = float(half_width)
    if not math.isfinite(h) or h <= 0:
        return None
    e = math.floor(math.log10(h))
    lead = round(h / 10.0 ** (e - 2))     # the three leading digits, 100 ... 1000
    if lead < 355:
        return 1 - e
    if lead < 950:
        return -e
    return -e                             # 0.0996 -> 0.10: two digits of the next decade


def _fixed(x: float, places: int) -> str:
    if math.isinf(x):
        return "∞" if x > 0 else "−∞"
    if math.isnan(x):
        return "nan"
    if places >= 0:
        s = f"{x:.{places}f}"
    else:
        s = f"{round(x, places):.0f}"
    return "0" + s[2:] if s.startswith("-0") and float(s) == 0 else s  # no "-0.00"


def significant(x: float, sig: int = SIGNIFICANT) -> str:
    """``x`` to ``sig`` significant digits, plainly (no exponent between 1e-4 and 1e6)."""
    x = float(x)
    if not math.isfinite(x):
        return _fixed(x, 0)
    if x == 0:
        return "0"
    e = math.floor(math.log10(abs(x)))
    if -4 <= e < 6:
        return _fixed(x, max(0, sig - 1 - e))
    return f"{x:.{sig - 1}e}"


def _suffix(unit: str) -> str:
    return f" {pretty(unit)}" if unit and unit != "-" else ""


def quantity_text(value: float, unit: str = "", sig: int = SIGNIFICANT) -> str:
    """"0.0980 N·m·s/rad": ``value`` to ``sig`` significant digits and its unit (in
    :func:`pretty` form; "" or "-" for none)."""
    return significant(value, sig) + _suffix(unit)


def interval_text(value: float, interval, unit: str = "", sig: int = SIGNIFICANT) -> str:
    """"0.371 [0.365, 0.378] Hz": ``value`` and its ``interval`` (low, high) to the decimal
    the interval's half-width supports (:func:`decimals`), then the unit. An interval that
    is missing, NaN or unbounded gives the value to ``sig`` significant digits and says so
    ("0.371 [0.2, ∞]", "0.371 (no interval)")."""
    value = float(value)
    if interval is None:
        return f"{significant(value, sig)} (no interval)" + _suffix(unit)
    lo, hi = (float(b) for b in interval)
    if math.isnan(lo) or math.isnan(hi):
        return f"{significant(value, sig)} (no interval)" + _suffix(unit)
    places = decimals((hi - lo) / 2) if math.isfinite(hi - lo) else None
    if places is None:
        if lo == hi == value:   # an exact value: nothing to round to
            return significant(value, sig) + _suffix(unit)
        bounds = [_fixed(b, 0) if math.isinf(b) else significant(b, sig) for b in (lo, hi)]
        return f"{significant(value, sig)} [{bounds[0]}, {bounds[1]}]" + _suffix(unit)
    return f"{_fixed(value, places)} [{_fixed(lo, places)}, {_fixed(hi, places)}]" + _suffix(unit)


def shown(value: float, interval) -> float:
    """``value`` as :func:`interval_text` writes it (rounded to the interval's decimal), for
    what is computed from the number a reader sees."""
    lo, hi = (float(b) for b in interval)
    places = decimals((hi - lo) / 2) if math.isfinite(hi - lo) else None
    return float(value) if places is None else round(float(value), places)


def dynamics_text(zeta: float, fn: float, zeta_interval=None, fn_interval=None, zeta_name: str = "zeta",
                  sep: str = " ") -> str:
    """A step's damping ratio and natural frequency [Hz], each with its interval when given:
    "zeta 0.24 [0.17, 0.31], fn 5.0 [4.5, 5.6] Hz" (``sep`` "=" gives "zeta = 0.24 ...")."""
    join = f" {sep} " if sep.strip() else " "
    z = interval_text(zeta, zeta_interval) if zeta_interval is not None else significant(zeta)
    f = interval_text(fn, fn_interval) if fn_interval is not None else significant(fn)
    return f"{zeta_name}{join}{z}, fn{join}{f} Hz"


def percent_interval_text(value: float, interval, sign: bool = True) -> str:
    """A relative quantity (a fraction) and its interval in percent, to the digits the
    interval supports: "+1.2 % [−0.3, +2.7] %"."""
    v, (lo, hi) = 100 * float(value), (100 * float(b) for b in interval)
    places = decimals((hi - lo) / 2) if math.isfinite(hi - lo) else None
    places = 1 if places is None else max(places, 0)
    f = (lambda x: ("+" if sign and x >= 0 else "") + _fixed(x, places).replace("-", "−"))
    return f"{f(v)} % [{f(lo)}, {f(hi)}] %"


# ---------------------------------------------------------------------------------------
# units: parsed, combined, written
# ---------------------------------------------------------------------------------------

_TOKEN = re.compile(r"([A-Za-z]+|1)(?:\^(-?\d+))?")
_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")
_PLAIN = str.maketrans("⁰¹²³⁴⁵⁶⁷⁸⁹⁻", "0123456789-")


@dataclass(frozen=True, eq=False)
class Unit:
    """A product of named units with integer powers, kept in the order first named (rad is a
    unit here: a gain per radian says so). ``Unit.parse("N*m*s/rad")``; ``*`` and ``/``
    combine; ``str()`` writes it for a reader: "N·m·s/rad", "1/s²", "N·m/(rad·s)"."""

    powers: tuple = ()   # ((name, power), ...), no zero powers

    @classmethod
    def parse(cls, text: str) -> "Unit":
        """From leglib's unit strings ("N*m*s/rad", "kg*m^2", "m/s^2", "1/s", "-" or "" for
        none) or as :meth:`__str__` writes them ("N·m/(rad·s)", "1/s²"); a "·" or a space also
        multiplies, and each "/" divides what follows it."""
        text = re.sub(r"([⁻]?[⁰¹²³⁴⁵⁶⁷⁸⁹]+)", lambda m: "^" + m.group(1).translate(_PLAIN), str(text).strip())
        if text in ("", "-", "1"):
            return cls()
        if "(" in text.partition("/")[0]:   # a grouped numerator, "(turn/s)/turn": not a product of names
            raise ValueError(f"unit {text!r}: cannot read a grouped numerator")
        num, *dens = re.split(r"/(?![^(]*\))", text)   # a / b / c = a / (b c); "N*m/(rad*s)" keeps its group
        out = cls()
        for part, sign in [(num, 1)] + [(d.strip().strip("()"), -1) for d in dens]:
            for tok in re.split(r"[*·\s]+", part.strip()):
                if not tok or tok == "1":
                    continue
                m = _TOKEN.fullmatch(tok)
                if m is None:
                    raise ValueError(f"unit {text!r}: cannot read {tok!r}")
                out = out * cls(((m.group(1), sign * int(m.group(2) or 1)),))
        return out

    def __eq__(self, other) -> bool:   # the same powers in any order
        return isinstance(other, Unit) and dict(self.powers) == dict(other.powers)

    def __hash__(self) -> int:
        return hash(frozenset(self.powers))

    def __mul__(self, other: "Unit") -> "Unit":
        powers = dict(self.powers)
        for name, p in other.powers:
            powers[name] = powers.get(name, 0) + p
        return Unit(tuple((n, p) for n, p in powers.items() if p))

    def __truediv__(self, other: "Unit") -> "Unit":
        return self * Unit(tuple((n, -p) for n, p in other.powers))

    def __str__(self) -> str:
        def term(name, p):
            return name + (str(p).translate(_SUPERSCRIPT) if p != 1 else "")
        # seconds last on either side, as written by hand: N·m·s/rad, rad/(N·m·s²)
        ordered = sorted(self.powers, key=lambda np_: np_[0] == "s")
        num = [term(n, p) for n, p in ordered if p > 0]
        den = [term(n, -p) for n, p in ordered if p < 0]
        top = "·".join(num) or ("1" if den else "-")
        if not den:
            return top
        bottom = "·".join(den)
        return f"{top}/({bottom})" if len(den) > 1 else f"{top}/{bottom}"


def derived(numerator: str, *denominators: str) -> str:
    """The unit of a quantity that is ``numerator`` per each of ``denominators``, for a
    reader: ``derived("N*m", "rad/s")`` is "N·m·s/rad", ``derived("rad/s", "rad", "s")``
    is "1/s²"."""
    u = Unit.parse(numerator)
    for d in denominators:
        u = u / Unit.parse(d)
    return str(u)


def pretty(unit: str) -> str:
    """A unit string as written for a reader: "kg*m^2" -> "kg·m²", "m/s^2" -> "m/s²"."""
    if unit in ("", "-"):
        return unit
    try:
        return str(Unit.parse(unit))
    except ValueError:   # a unit of units ("(turn/s)/turn"): written as it is, its operators for a reader
        return re.sub(r"\^(-?\d+)", lambda m: m.group(1).translate(_SUPERSCRIPT), unit.replace("*", "·"))


#: the ODrive cascade's gains, in the device's own units (Listing 7.4's grid, the thesis's tables)
GAIN_UNITS = {"pos_gain": "(turn/s)/turn", "vel_gain": "N*m/(turn/s)", "vel_integrator_gain": "N*m/turn"}
