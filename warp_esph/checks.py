"""Input checks that run before any kernel does.

Every failure is a ``ValueError`` whose message names the parameter, the value given
and what is allowed, so a user can fix the input without reading code.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def _fail(name: str, value, allowed: str):
    raise ValueError(f"{name} = {value!r} is not allowed: {allowed}")


def number(name: str, value, *, allow_inf: bool = False) -> float:
    """A real number (bools, strings and NaN rejected); ``inf`` only when ``allow_inf``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(value, "__float__"):
        _fail(name, value, "must be a number")
    try:
        v = float(value)
    except (TypeError, ValueError):
        _fail(name, value, "must be a number")
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        _fail(name, value, "must be a finite number")
    return v


def positive(name: str, value, **kw) -> float:
    v = number(name, value, **kw)
    if not v > 0.0:
        _fail(name, value, "must be > 0")
    return v


def non_negative(name: str, value, **kw) -> float:
    v = number(name, value, **kw)
    if not v >= 0.0:
        _fail(name, value, "must be >= 0")
    return v


def in_range(name: str, value, lo: float, hi: float) -> float:
    v = number(name, value)
    if not lo <= v <= hi:
        _fail(name, value, f"must be in [{lo}, {hi}]")
    return v


def greater_than(name: str, value, bound: float, bound_text: str) -> float:
    v = number(name, value)
    if not v > bound:
        _fail(name, value, f"must be > {bound_text} = {bound:g}")
    return v


def vector(name: str, value, length: int = 3) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) and not hasattr(value, "__len__"):
        _fail(name, value, f"must be a sequence of {length} numbers")
    if len(value) != length:
        _fail(name, value, f"must be a sequence of {length} numbers")
    return tuple(number(f"{name}[{k}]", c) for k, c in enumerate(value))


def positive_vector(name: str, value, length: int = 3) -> tuple[float, ...]:
    v = vector(name, value, length)
    if not all(c > 0.0 for c in v):
        _fail(name, value, f"every component must be > 0")
    return v


def positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) and not (hasattr(value, "__index__")):
        _fail(name, value, "must be an integer >= 1")
    v = int(value)
    if v < 1:
        _fail(name, value, "must be an integer >= 1")
    return v


def choice(name: str, value, allowed: Sequence[str]) -> str:
    if value not in allowed:
        _fail(name, value, "must be one of " + ", ".join(repr(a) for a in allowed))
    return value
