"""Scalar, vector and matrix types for one floating-point precision.

Every kernel factory in the package takes a Warp scalar type (``wp.float32`` or
``wp.float64``) so the same equations compile in both precisions: float32 for
speed, float64 for gradient checks.
"""

from __future__ import annotations

import types

import numpy as np
import warp as wp

from .checks import shorten

#: What ``scalar_type`` takes, for its message.
DTYPE_ALLOWED = "use wp.float32 or wp.float64 (or 'float32'/'float64', numpy's float32/float64 or 'f4'/'f8')"


def scalar_type(dtype) -> type:
    """Normalise ``dtype`` to ``wp.float32``/``wp.float64``: a Warp type, a numpy float32/float64
    dtype or type, or any name numpy reads as one ('float32'/'float64' as ``--dtype`` takes
    them, 'f4'/'f8', 'single'/'double')."""
    # By identity: numpy's dtype compares equal to Warp's type (np.dtype("f8") == wp.float64), so
    # a membership test returned the numpy dtype itself, and finalize failed on its missing
    # __name__ with an AttributeError.
    if dtype is wp.float32 or dtype is wp.float64:
        return dtype
    if dtype is float or isinstance(dtype, str) and dtype == "float":
        # Warp reads Python's float as float32, numpy (and Python) as 64-bit: a model of either
        # precision would surprise half the users (it was float32 without a word; the name
        # 'float' was float32 too, where np.dtype('float') is float64).
        raise ValueError(f"dtype = {'float' if dtype is float else repr(dtype)} is not allowed: Warp reads it as "
                         "float32, numpy as float64; give wp.float32 or wp.float64")
    # numpy's reading of a dtype and of its names: np.dtype("f8") was taken and "f8" refused.
    # None is refused, not numpy's default float64; so is a value (np.float64(1.0), b"f8"),
    # which numpy also reads as a dtype: only a name, a numpy dtype or a type is one.
    try:
        np_dtype = np.dtype(dtype) if isinstance(dtype, (str, np.dtype, type)) else None
    except (TypeError, ValueError):
        np_dtype = None
    if np_dtype is not None and np_dtype.kind == "f" and np_dtype.itemsize in (4, 8):
        return wp.float32 if np_dtype.itemsize == 4 else wp.float64
    raise ValueError(f"dtype = {shorten(dtype)!r} is not allowed: {DTYPE_ALLOWED}")


def type_set(scalar) -> types.SimpleNamespace:
    """The vector and matrix types built on ``scalar``."""
    return types.SimpleNamespace(
        scalar=scalar,
        vec3=wp.vec3f if scalar is wp.float32 else wp.vec3d,
        mat33=wp.mat33f if scalar is wp.float32 else wp.mat33d,
        np_dtype=np.float32 if scalar is wp.float32 else np.float64,
    )
