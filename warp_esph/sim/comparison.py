"""The comparison deformation models of the paper's Fig. 8 (SPEC §7).

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
from . import deformation, forces, plasticity


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    flow = plasticity.kernels(scalar).flow
    stress = forces.funcs(scalar).stress
    dk = deformation.kernels(scalar)
    moment_sums, step_gradient, unless_inverted = dk.moment_sums, dk.step_gradient, dk.unless_inverted
    third = scalar(1.0 / 3.0)

    @wp.kernel
    def constitutive_update(
        F_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        Fp_in: wp.array(dtype=mat33),
        material: wp.array(dtype=wp.int32),
        deform: wp.array(dtype=wp.int32),
        mu: wp.array(dtype=scalar),
        lam: wp.array(dtype=scalar),
        yield_stress: wp.array(dtype=scalar),
        flow_rate: wp.array(dtype=scalar),
        hardening: wp.array(dtype=scalar),
        model: wp.array(dtype=wp.int32),
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
        kind = model[m]
        d = deform[m]
        I = wp.identity(n=3, dtype=scalar)
        if d == 2:
            # Additive: F = I + eps, flow on dev eps, linear stress, no back projection.
            eps = F - I
            tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
            dev = eps - tr * third * I
            dn2 = wp.ddot(dev, dev)
            s_norm2 = scalar(4.0) * mu[m] * mu[m] * dn2
            y = wp.max(yield_stress[m] + hardening[m] * a, scalar(0.0))
            a_new = a
            if flow_rate[m] > scalar(0.0) and s_norm2 > y * y:
                s_norm = wp.sqrt(s_norm2)
                rate = flow_rate[m] * dt * (s_norm - y) / s_norm
                if kind == 1:
                    rate = rate / s_norm
                gamma = wp.min(rate, scalar(1.0))
                eps = eps - gamma * dev
                a_new = a + gamma * wp.sqrt(dn2)
            tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
            F_out[i] = I + eps
            alpha_out[i] = a_new
            Fp_out[i] = Fp
            stress_out[i] = scalar(2.0) * mu[m] * eps + lam[m] * tr * I
            F_inv_out[i] = I
        else:
            Fe, a_new = flow(F, a, mu[m], yield_stress[m], flow_rate[m], hardening[m], kind, dt, counters)
            Fe_inv = wp.inverse(Fe)
            if d == 1:
                # Rest configuration: F_total = F_e F_p is kept, F_p <- F_e_new^-1 F_total.
                Fp = Fe_inv * (F * Fp)
            F_out[i] = Fe
            alpha_out[i] = a_new
            Fp_out[i] = Fp
            stress_out[i] = stress(Fe, mu[m], lam[m], kind)
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
        deform: wp.array(dtype=wp.int32),
        F_prev: wp.array(dtype=mat33),
        Fp: wp.array(dtype=mat33),
        h: scalar,
        F_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """``deformation.update_deformation`` for every deformation model."""
        i = wp.tid()
        F = F_prev[i]
        d = deform[material[i]]
        I = wp.identity(n=3, dtype=scalar)
        if d == 1:
            # Rest configuration: the total F against X, always with the initial lists.
            A, B, same = moment_sums(i, rest_x, y, body, rest_nbr, rest_count[i], h)
            F = unless_inverted((B * wp.inverse(A)) * wp.inverse(Fp[i]), F, counters)
        else:
            dF = step_gradient(i, x, y, body, nbr, count[i], h, guard[i], counters)
            if d == 2:
                # Additive: F = I + eps, eps <- eps + (dF^T dF - I) / 2.
                F = F + scalar(0.5) * (wp.transpose(dF) * dF - I)
            else:
                F = unless_inverted(dF * F, F, counters)
        F_out[i] = F

    return types.SimpleNamespace(constitutive_update=constitutive_update, update_deformation=update_deformation)
