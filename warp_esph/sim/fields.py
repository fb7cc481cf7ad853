"""Time-varying external force fields (the paper's Fig. 8 compression).

A ``CompressionField`` adds the acceleration ``-strength (x - center)`` in the horizontal
directions (X and Z; Y is up) to every particle while ``t_on <= t < t_off``: an analytic
compression that grows linearly away from the centre, applied and then released. ``t`` is
the simulated time of the step's input state (``State.time``). Fields are part of the
scene: ``SceneBuilder.add_compression_field`` stores them on the model.
"""

import dataclasses
import functools
import math
import types

import numpy as np
import warp as wp

from .. import checks
from .._types import type_set


@dataclasses.dataclass(frozen=True)
class CompressionField:
    """``a = -strength (x - center)`` horizontally (1/s^2) while ``t_on <= t < t_off`` (s)."""

    center: tuple[float, float, float]
    strength: float
    t_on: float = 0.0
    t_off: float = math.inf
    #: Index of the body it acts on (``-1``: every particle).
    body: int = -1

    def __post_init__(self):
        object.__setattr__(self, "center", checks.vector("CompressionField.center", self.center))
        object.__setattr__(self, "strength", checks.number("CompressionField.strength", self.strength))
        object.__setattr__(self, "t_on", checks.non_negative("CompressionField.t_on", self.t_on))
        t_off = checks.number("CompressionField.t_off", self.t_off, allow_inf=True)
        if not t_off > self.t_on:
            raise ValueError(f"CompressionField.t_off = {checks.shorten(self.t_off)!r} is not allowed: must be > t_on = {self.t_on:g}")
        object.__setattr__(self, "t_off", t_off)
        if isinstance(self.body, bool) or not isinstance(self.body, int) or self.body < -1:
            raise ValueError(f"CompressionField.body = {checks.shorten(self.body)!r} is not allowed: must be a body index >= 0 or -1 (all)")

    def active(self, t: float) -> bool:
        return self.t_on <= t < self.t_off


def precision_problem(fld: CompressionField, scalar) -> str | None:
    """Why the field ``fld`` cannot run in the float type ``scalar``, or None: its acceleration
    is its strength times a distance from its centre, so each is held to the square root of
    the largest float (1e39 in float32, or a centre 1e300 m out, wrote NaN positions in the
    first step), and its times to the largest float."""
    from ..model import wider_precision  # noqa: PLC0415 (the model imports this module's package)

    big = float(np.finfo(np.float32 if scalar is wp.float32 else np.float64).max)
    far = math.sqrt(big)
    T = scalar.__name__
    for label, v in (("center", fld.center), ("strength", fld.strength)):
        if not np.abs(np.asarray(v, dtype=np.float64)).max() <= far:
            return (f"CompressionField.{label} = {checks.shorten(v)!r} is not allowed in {T}: must be at most {far:.3g} in size; "
                    f"{wider_precision(scalar, 'a smaller value')}")
    if max((abs(t) for t in (fld.t_on, fld.t_off) if math.isfinite(t)), default=0.0) > big:
        return f"CompressionField times ({fld.t_on!r}, {fld.t_off!r}) are not allowed in {T}: must be at most {big:.3g} s"
    return None


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3

    @wp.func
    def compression_force(x: vec3, mass: scalar, center: vec3, strength: scalar) -> vec3:
        """A ``CompressionField``'s force on a particle of ``mass`` at ``x``: ``-strength m (x -
        center)`` in X and Z."""
        r = x - center
        return -strength * mass * vec3(r[0], scalar(0.0), r[2])

    return types.SimpleNamespace(compression_force=compression_force)


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    compression_force = funcs(scalar).compression_force

    @wp.kernel(module="unique")
    def add_compression(
        x: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        particle_body: wp.array(dtype=wp.int32),
        body: int,
        center: vec3,
        strength: scalar,
        f: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        if body >= 0 and particle_body[i] != body:
            return
        wp.atomic_add(f, i, compression_force(x[i], mass[i], center, strength))

    return types.SimpleNamespace(add_compression=add_compression)


def launch_force_fields(model, state_in, state_out):
    """The model's force fields active at ``state_in.time``, added to ``state_out.force``."""
    S = model.scalar
    for fld in model.force_fields:
        if fld.active(state_in.time):
            model.launches(
                kernels(S).add_compression,
                model.particle_count,
                [state_in.x, model.particle_mass, model.particle_body, int(fld.body), model.types.vec3(*fld.center), S(fld.strength)],
                [state_out.force],
                device=model.device,
            )
