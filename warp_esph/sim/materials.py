"""The per-material parameters as one ``wp.struct``: what every kernel of the step reads.

``Model.material_arrays()`` fills it with the model's own arrays (the same ``wp.array``
objects, so under a ``wp.Tape`` the gradients land in ``model.mu.grad`` and the other
parameter arrays: the tape's adjoint of a struct holds its arrays' ``.grad``).
A kernel indexes it with the particle's material, ``mat.mu[material[i]]``.
"""

import functools

import warp as wp

#: Differentiable per-material scalars (``Model.MATERIAL_FIELDS``, same order).
SCALAR_FIELDS = ("mu", "lam", "yield_stress", "flow_rate", "hardening", "pressure_stiffness", "viscosity")
#: Per-material scalars the step reads but no gradient reaches (not fitted).
FIXED_FIELDS = ("pair_repulsion",)
#: Per-material choices (indices into ``material.MODELS``, ``DEFORMATIONS``, ``ELASTIC_FORCES``; 0/1; ``PRESSURE_FORCES``).
INT_FIELDS = ("model", "deformation", "elastic_force", "clamp_pressure", "pressure_force")


@functools.cache
def struct(scalar):
    """The ``Materials`` struct type for one precision."""

    @wp.struct
    class Materials:
        mu: wp.array(dtype=scalar)
        lam: wp.array(dtype=scalar)
        yield_stress: wp.array(dtype=scalar)
        flow_rate: wp.array(dtype=scalar)
        hardening: wp.array(dtype=scalar)
        pressure_stiffness: wp.array(dtype=scalar)
        viscosity: wp.array(dtype=scalar)
        model: wp.array(dtype=wp.int32)
        deformation: wp.array(dtype=wp.int32)
        elastic_force: wp.array(dtype=wp.int32)
        clamp_pressure: wp.array(dtype=wp.int32)
        pressure_force: wp.array(dtype=wp.int32)
        pair_repulsion: wp.array(dtype=scalar)

    return Materials


def make(scalar, device=None, **arrays):
    """A ``Materials`` instance holding ``arrays`` (``{field: wp.array}``); a field not
    given gets a one-element array of zeros (for kernels launched on their own in tests)."""
    unknown = set(arrays) - set(SCALAR_FIELDS) - set(INT_FIELDS) - set(FIXED_FIELDS)
    if unknown:
        raise ValueError(f"fields {sorted(unknown)} are not allowed: must be in {SCALAR_FIELDS + INT_FIELDS + FIXED_FIELDS}")
    out = struct(scalar)()
    n = max((a.shape[0] for a in arrays.values()), default=1)
    for name in SCALAR_FIELDS + INT_FIELDS + FIXED_FIELDS:
        arr = arrays.get(name)
        if arr is None:
            arr = wp.zeros(n, dtype=wp.int32 if name in INT_FIELDS else scalar, device=device)
        setattr(out, name, arr)
    return out
