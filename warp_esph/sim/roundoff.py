"""Compensated sums: the state's round-off carried from step to step.

Near rest a particle moves by about one unit in the last place of its float32 position per
step, and its elastic ``F`` changes by a few units in the last place of an entry near 1.
Rounding each step's new value to the stored precision then adds noise as large as the
change itself, and a material at yield keeps flowing on it (docs/physics.md, the float32
creep floor). So ``x`` and ``F`` are stored with their round-off (``State.x_lo``,
``State.F_lo``): ``x + x_lo`` is the position to about twice the precision of ``x``, and each
step's change is added to that sum, not to ``x`` alone.
"""
from typing import Any

import warp as wp


@wp.func
def compensated_sum(a: Any, b: Any):
    """``(s, e)`` with ``s = fl(a + b)`` and ``s + e = a + b`` exactly, entry by entry
    (Knuth's TwoSum): ``e`` is the round-off ``s`` lost, carried to the next sum. In exact
    arithmetic ``e = 0`` identically, so its adjoint is 0 and ``s``'s is the sum's."""
    s = a + b
    bb = s - a
    e = (a - (s - bb)) + (b - bb)
    return s, e
