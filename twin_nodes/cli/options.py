"""argparse ``type=`` functions for every numeric option of ``rotortwin``.

Each is a :class:`Number`: a finite number (or integer) in a closed or open range.  A value
outside it (``nan``, ``inf``, ``1e999``, a negative count, ``--heldout 1``...) is refused by
argparse itself with one line, ``rotortwin: error: --heldout: expected a number in (0, 1), got
nan``, exit code 2, before anything runs or is written.  ``tests/test_options.py`` walks the
whole parser: every numeric option must have one of these types and refuse nan, inf and an
out-of-range value, so a new option cannot miss it.

Use the helpers (``positive_float(hi)``, ``fraction()``, ``count(lo, hi)``, ``port()``...) or
:class:`Number` directly for another range.
"""

from __future__ import annotations

import argparse
import math


def _g(v: float) -> str:
    """``v`` short: ``4294967295``, ``0.05``, ``1e+06``."""
    if float(v).is_integer() and abs(v) < 1e12:
        return str(int(v))
    return f"{v:g}"


class Number:
    """A finite float (or int with ``integer=True``) in ``lo..hi``; ``lo_open``/``hi_open``
    exclude the end.  ``None`` for an end means unbounded (finite numbers only, always)."""

    def __init__(self, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                 hi_open: bool = False, integer: bool = False, unit: str = "") -> None:
        self.lo, self.hi = lo, hi
        self.lo_open, self.hi_open = lo_open, hi_open
        self.integer = integer
        self.unit = unit
        self.__name__ = "integer" if integer else "number"  # argparse names a type by it

    # ------------------------------------------------------------------ description
    def describe(self) -> str:
        """``a number in (0, 1)``, ``an integer >= 1``, ``a number in [0, 65535] s``..."""
        what = "an integer" if self.integer else "a number"
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            rng = f"in {'(' if self.lo_open else '['}{_g(lo)}, {_g(hi)}{')' if self.hi_open else ']'}"
        elif lo is not None:
            rng = f"{'>' if self.lo_open else '>='} {_g(lo)}"
        elif hi is not None:
            rng = f"{'<' if self.hi_open else '<='} {_g(hi)}"
        else:
            rng = "(finite)"
        return f"{what} {rng}" + (f" {self.unit}" if self.unit else "")

    def __repr__(self) -> str:
        return f"Number({self.describe()})"

    # ------------------------------------------------------------------ checking
    def contains(self, v: float) -> bool:
        if not math.isfinite(v):
            return False
        if self.lo is not None and not (v > self.lo if self.lo_open else v >= self.lo):
            return False
        if self.hi is not None and not (v < self.hi if self.hi_open else v <= self.hi):
            return False
        return True

    def __call__(self, text: object) -> float | int:
        if isinstance(text, (int, float)) and not isinstance(text, bool):
            s = repr(text)
            value: float | int | None = text
        else:
            s = str(text).strip()
            value = None
            try:
                value = int(s, 10) if self.integer else float(s)
            except ValueError:
                value = None
        shown = s if len(s) <= 40 else s[:37] + "..."
        if value is None or (self.integer and isinstance(value, float) and not value.is_integer()):
            raise argparse.ArgumentTypeError(f"expected {self.describe()}, got {shown or repr(s)}")
        try:
            ok = self.contains(float(value))
        except OverflowError:  # an integer too large for a float
            ok = False
        if not ok:
            raise argparse.ArgumentTypeError(f"expected {self.describe()}, got {shown}")
        return int(value) if self.integer else float(value)

    def bad_values(self) -> list[str]:
        """Values this type must refuse (for the tests): nan, +-inf and just outside each end."""
        out = ["nan", "inf", "-inf", "1e999"]
        if self.lo is not None:
            out.append(_g(self.lo) if self.lo_open else _g(self.lo - (1 if self.integer else max(abs(self.lo), 1.0))))
        if self.hi is not None:
            out.append(_g(self.hi) if self.hi_open else _g(self.hi + (1 if self.integer else max(abs(self.hi), 1.0))))
        if self.integer:
            out.append("1.5")
        return out


# ---------------------------------------------------------------------- the usual kinds


def finite_float(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                 hi_open: bool = False, unit: str = "") -> Number:
    """A finite number in ``[lo, hi]`` (ends excluded with ``lo_open``/``hi_open``)."""
    return Number(lo, hi, lo_open=lo_open, hi_open=hi_open, unit=unit)


def positive_float(hi: float | None = None, unit: str = "") -> Number:
    """A finite number ``> 0`` (and ``<= hi``)."""
    return Number(0.0, hi, lo_open=True, unit=unit)


def nonneg_float(hi: float | None = None, unit: str = "") -> Number:
    """A finite number ``>= 0`` (and ``<= hi``)."""
    return Number(0.0, hi, unit=unit)


def fraction() -> Number:
    """A number strictly between 0 and 1."""
    return Number(0.0, 1.0, lo_open=True, hi_open=True)


def integer(lo: int | None = None, hi: int | None = None) -> Number:
    """An integer in ``[lo, hi]``."""
    return Number(lo, hi, integer=True)


def positive_int(hi: int | None = None) -> Number:
    """An integer ``>= 1`` (and ``<= hi``)."""
    return Number(1, hi, integer=True)


def port(lo: int = 0) -> Number:
    """A TCP/UDP port ``lo..65535`` (0: any free one, where the option says so)."""
    return Number(lo, 65535, integer=True)


def domain_id() -> Number:
    """A ROS domain id 0..232 (twin_nodes.graph.domains.DOMAIN_MAX)."""
    from twin_nodes.graph.domains import DOMAIN_MAX

    return Number(0, DOMAIN_MAX, integer=True)


def seed() -> Number:
    """A random seed 0..2**32-1 (what numpy accepts)."""
    return Number(0, 2**32 - 1, integer=True)


# ---------------------------------------------------------------------- shared physical ranges

#: a vehicle's take-off mass [kg]: twin_nodes.vehicle.params.LIMITS["mass_kg"]
MASS_KG = finite_float(1e-3, 1e4, unit="kg")
#: a duration or period [s]: up to 10 days
SECONDS = positive_float(864000.0, unit="s")
#: a rolling window or re-sync horizon [s]
WINDOW_S = positive_float(3600.0, unit="s")
#: a PWM pulse width [us]
PWM_US = finite_float(500.0, 2500.0, unit="us")
#: number of motors / rotors: twin_nodes.vehicle.params.LIMITS["rotors"]
MOTORS = positive_int(32)
#: worker processes
WORKERS = positive_int(256)
#: a rate [Hz]
RATE_HZ = positive_float(100000.0, unit="Hz")
#: a replay speed in multiples of real time (0: as fast as possible / unpaced)
SPEED = nonneg_float(10000.0)
