"""The comparison deformation models of the paper's Fig. 8 (docs/method.md §7).

Selected per material with ``Material(deformation=...)``:

- ``"incremental"`` (default): the paper's method, ``F <- dF F`` (``deformation.py``).
- ``"rest"`` (Müller et al. 2004 style): the total ``F = (Σ w yb Xbᵀ)(Σ w Xb Xbᵀ)⁻¹`` is
  fitted against the rest positions ``X`` with the initial (same-body) neighbour lists;
  a plastic ``F_p`` per particle is stored, ``F_e = F F_p⁻¹``. The plastic flow of
  ``plasticity.py`` updates ``F_e`` and then ``F_p <- F_e⁻¹ F``. ``State.F`` holds ``F_e``.
- ``"additive"``: a symmetric strain ``ε`` per particle, ``ε <- ε + ½(dFᵀdF − I)`` with the
  step's MLS ``dF``; plastic flow removes the fraction ``γ = min(nu_f dt (|s| − Y − K α)/|s|, 1)``
  of ``dev ε`` where ``|s| = 2 mu |dev ε| > Y + K α``; stress ``σ = 2 mu ε + lam tr(ε) I``,
  pair forces with ``P* = σ`` and no back projection (``F⁻¹ = I``). ``State.F`` holds ``I + ε``.

Both run only on the solver's differentiable (non-fused) path; the incremental particles of
a model that mixes models go through the same kernels as in ``plasticity``/``deformation``.
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import deformation, forces, materials, plasticity


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    pf = plasticity.funcs(scalar)
    flow, flow_fraction = pf.flow, pf.flow_fraction
    stress = forces.funcs(scalar).stress
    df = deformation.funcs(scalar)
    moment_sums, step_gradient, unless_inverted = df.moment_sums, df.step_gradient, df.unless_inverted
    Materials = materials.struct(scalar)
    third = scalar(1.0 / 3.0)

    @wp.kernel
    def constitutive_update(
        F_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        Fp_in: wp.array(dtype=mat33),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        dt: scalar,
        F_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        Fp_out: wp.array(dtype=mat33),
        stress_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """``plasticity.constitutive_update`` for every deformation model."""
        i = wp.tid()
        m = material[i]
        F = F_in[i]
        a = alpha_in[i]
        Fp = Fp_in[i]
        kind = mat.model[m]
        d = mat.deformation[m]
        mu = mat.mu[m]
        lam = mat.lam[m]
        I = wp.identity(n=3, dtype=scalar)
        if d == 2:
            # Additive: F = I + eps, flow on dev eps, linear stress, no back projection.
            eps = F - I
            tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
            dev = eps - tr * third * I
            dn2 = wp.ddot(dev, dev)
            a_new = a
            if mat.flow_rate[m] > scalar(0.0):
                flowed, gamma = flow_fraction(
                    scalar(4.0) * mu * mu * dn2, mat.yield_stress[m], mat.hardening[m], a, mat.flow_rate[m], dt,
                    wp.where(kind == 1, 1, 0),
                )
                if flowed != 0:
                    eps = eps - gamma * dev
                    a_new = a + gamma * wp.sqrt(dn2)
            tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
            F_out[i] = I + eps
            alpha_out[i] = a_new
            Fp_out[i] = Fp
            stress_out[i] = scalar(2.0) * mu * eps + lam * tr * I
            F_inv_out[i] = I
        else:
            Fe, Fe_lo, a_new = flow(F, mat33(), a, mu, mat.yield_stress[m], mat.flow_rate[m], mat.hardening[m], kind, dt, counters)
            Fe_inv = wp.inverse(Fe)
            if d == 1:
                # Rest configuration: F_total = F_e F_p is kept, F_p <- F_e_new^-1 F_total.
                Fp = Fe_inv * (F * Fp)
            F_out[i] = Fe
            alpha_out[i] = a_new
            Fp_out[i] = Fp
            stress_out[i] = stress(Fe, mu, lam, kind)
            F_inv_out[i] = Fe_inv

    @wp.kernel
    def update_deformation(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        F_prev: wp.array(dtype=mat33),
        Fp: wp.array(dtype=mat33),
        h: scalar,
        F_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """``deformation.update_deformation`` for every deformation model."""
        i = wp.tid()
        F = F_prev[i]
        d = mat.deformation[material[i]]
        I = wp.identity(n=3, dtype=scalar)
        if d == 1:
            # Rest configuration: the total F against X, always with the initial lists.
            # (Round-off arrays y, y: the positions' round-off is not carried here.)
            A, B, same = moment_sums(i, rest_x, y, y, y, body, rest_nbr, rest_count[i], h)
            F = unless_inverted((I + df.affine_fit(A, B)) * wp.inverse(Fp[i]), F, counters)
        else:
            A, B, same = moment_sums(i, x, y, y, y, body, nbr, count[i], h)
            dF = step_gradient(A, B, guard[i], counters)
            if d == 2:
                # Additive: F = I + eps, eps <- eps + (dF^T dF - I) / 2.
                F = F + scalar(0.5) * (wp.transpose(dF) * dF - I)
            else:
                F = unless_inverted(dF * F, F, counters)
        F_out[i] = F

    return types.SimpleNamespace(constitutive_update=constitutive_update, update_deformation=update_deformation)


def launch_constitutive_update(model, state_in, state_out, dt, counters):
    """``plasticity.launch_constitutive_update`` for models with a Fig. 8 comparison material."""
    wp.launch(
        kernels(model.scalar).constitutive_update,
        model.particle_count,
        [state_in.F, state_in.alpha, state_in.F_p, model.particle_material, model.material_arrays(), model.scalar(dt)],
        [state_out.F_flowed, state_out.alpha, state_out.F_p, state_out.stress, state_out.F_inv, counters],
        device=model.device,
    )


def launch_update_deformation(model, state_in, state_out, counters):
    """``deformation.launch_update_deformation`` for models with a Fig. 8 comparison material."""
    rest_x, rest_nbr, rest_count = model.rest_neighbors()
    wp.launch(
        kernels(model.scalar).update_deformation,
        model.particle_count,
        [
            state_in.x, state_out.x, rest_x, model.particle_body, state_out.neighbors, state_out.neighbor_count,
            rest_nbr, rest_count, state_out.guard, model.particle_material, model.material_arrays(), state_out.F_flowed,
            state_out.F_p, model.scalar(model.support_radius),
        ],
        [state_out.F, counters],
        device=model.device,
    )
