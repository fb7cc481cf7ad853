"""Scalar, vector and matrix types for one floating-point precision.

Every kernel factory in the package takes a Warp scalar type (``wp.float32`` or
``wp.float64``) so the same equations compile in both precisions: float32 for
speed, float64 for gradient checks.
"""

from __future__ import annotations

import types

import numpy as np
import warp as wp

_SCALARS = {"float32": wp.float32, "float64": wp.float64}


def scalar_type(dtype) -> type:
    """Normalise ``dtype`` (a Warp type, numpy dtype or name) to ``wp.float32``/``wp.float64``."""
    # By identity: numpy's dtype compares equal to Warp's type (np.dtype("f8") == wp.float64), so
    # a membership test returned the numpy dtype itself, and finalize failed on its missing
    # __name__ with an AttributeError.
    if dtype is wp.float32 or dtype is wp.float64:
        return dtype
    if dtype is float:
        # Warp reads Python's float as float32, numpy (and Python) as 64-bit: a model of either
        # precision would surprise half the users (it was float32 without a word).
        raise ValueError("dtype = float is not allowed: Warp reads it as float32, numpy as float64; give wp.float32 or "
                         "wp.float64")
    name = getattr(dtype, "__name__", None) or str(dtype)
    name = {"float": "float32", "double": "float64"}.get(name, name)
    if name not in _SCALARS:
        raise ValueError(f"dtype = {dtype!r} is not allowed: use wp.float32 or wp.float64")
    return _SCALARS[name]


def type_set(scalar) -> types.SimpleNamespace:
    """The vector and matrix types built on ``scalar``."""
    return types.SimpleNamespace(
        scalar=scalar,
        vec3=wp.vec3f if scalar is wp.float32 else wp.vec3d,
        mat33=wp.mat33f if scalar is wp.float32 else wp.mat33d,
        np_dtype=np.float32 if scalar is wp.float32 else np.float64,
    )
