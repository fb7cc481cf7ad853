"""Multiplicative plasticity (Bargteil et al. 2007; paper §3, docs/method.md §4) applied to the
stored elastic deformation gradient, and the per-particle constitutive update.

In the SVD frame ``F = U diag(sigma) V^T`` the deviatoric stress is
``s = 2 mu (sigma - mean(sigma))``. Where ``|s| > Y + K alpha``:

    gamma   = min(nu_f dt (|s| - Y - K alpha) / |s|, 1)       (non-Newtonian: / |s|^2)
    sigma_k <- sigma_k^(1 - gamma) J^(gamma/3),  J = sigma_1 sigma_2 sigma_3
    alpha   <- alpha + gamma |ln sigma - mean(ln sigma)|

which is ``F_e = F F_p^-1`` with ``F_p <- V (J^(-1/3) F^)^gamma V^T F_p`` without storing
``F_p``. ``nu_f`` is a rate (1/s): ``nu_f dt`` is the paper's per-step fraction, so a result
does not depend on the time step. Where ``J`` leaves [0.8, 1.25] the flow uses
``J_c^(1/3) J^(-1/3) F^`` with ``J_c`` the nearer end of the range, relaxing the volume
change beyond it (paper §4: relaxing volume preservation under large volume change improves
stability; the paper's ``F^`` alone would make the flow jump where ``J`` crosses an end), and
where ``min sigma < 0.01`` the flow is skipped.
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import forces, isotropic, materials

#: Index into the solver's guard counters: plastic flow skipped because min sigma < 0.01.
COUNT_PLASTICITY_SKIPPED = 3
MIN_SINGULAR_VALUE = 0.01
VOLUME_PRESERVING_RANGE = (0.8, 1.25)


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    iso = isotropic.funcs(scalar)
    # Below this relative gap the divided difference of sigma^(1-gamma) is replaced by
    # its derivative at the midpoint (error ~ gap^2).
    close = scalar(1.0e-3 if scalar is wp.float32 else 1.0e-5)
    j_lo = scalar(VOLUME_PRESERVING_RANGE[0])
    j_hi = scalar(VOLUME_PRESERVING_RANGE[1])
    min_sigma = scalar(MIN_SINGULAR_VALUE)

    @wp.func
    def power_difference(a: scalar, b: scalar, p: scalar, c: scalar) -> scalar:
        # c (a^p - b^p) / (a - b) and its limit c p a^(p-1) as a -> b.
        if wp.abs(a - b) < close * (a + b):
            m = scalar(0.5) * (a + b)
            return c * p * wp.pow(m, p - scalar(1.0))
        return c * (wp.pow(a, p) - wp.pow(b, p)) / (a - b)

    @wp.func
    def flow_fraction(
        s_norm2: scalar,
        yield_stress: scalar,
        hardening: scalar,
        alpha: scalar,
        flow_rate: scalar,
        dt: scalar,
        non_newtonian: int,
    ):
        """Returns (flowed, gamma): whether the deviatoric stress ``|s|`` (given squared)
        exceeds the yield surface ``Y + K alpha``, and the flow fraction
        ``gamma = min(nu_f dt (|s| - Y - K alpha) / |s|, 1)`` (non-Newtonian: ``/ |s|^2``)."""
        y = wp.max(yield_stress + hardening * alpha, scalar(0.0))
        flowed = int(0)
        gamma = scalar(0.0)
        # Compare squares: |s| = 0 at rest, where sqrt has an infinite derivative.
        if s_norm2 > y * y:
            s_norm = wp.sqrt(s_norm2)
            rate = flow_rate * dt * (s_norm - y) / s_norm
            if non_newtonian != 0:
                rate = rate / s_norm
            gamma = wp.min(rate, scalar(1.0))
            flowed = 1
        return flowed, gamma

    @wp.func
    def flow_step(
        s: vec3,
        mu: scalar,
        yield_stress: scalar,
        flow_rate: scalar,
        hardening: scalar,
        alpha: scalar,
        dt: scalar,
        non_newtonian: int,
    ):
        """The flow of the singular values ``s``; returns (flowed, new singular values
        g = c s^p, c, p, new alpha)."""
        mean = (s[0] + s[1] + s[2]) / scalar(3.0)
        dev = s - vec3(mean, mean, mean)
        flowed, gamma = flow_fraction(
            scalar(4.0) * mu * mu * wp.dot(dev, dev), yield_stress, hardening, alpha, flow_rate, dt, non_newtonian
        )
        g = s
        c = scalar(1.0)
        p = scalar(1.0)
        alpha_new = alpha
        if flowed != 0:
            # Volume is kept inside [j_lo, j_hi]; outside, only the volume change beyond
            # the range is relaxed (paper §4), so c is continuous in J (docs/method.md §4).
            J = s[0] * s[1] * s[2]
            c = wp.pow(wp.min(wp.max(J, j_lo), j_hi), gamma / scalar(3.0))
            p = scalar(1.0) - gamma
            g = c * vec3(wp.pow(s[0], p), wp.pow(s[1], p), wp.pow(s[2], p))
            ls = vec3(wp.log(s[0]), wp.log(s[1]), wp.log(s[2]))
            lm = (ls[0] + ls[1] + ls[2]) / scalar(3.0)
            ld = ls - vec3(lm, lm, lm)
            alpha_new = alpha + gamma * wp.sqrt(wp.dot(ld, ld))
        return flowed, g, c, p, alpha_new

    @wp.func
    def guarded_flow_step(
        s: vec3,
        mu: scalar,
        yield_stress: scalar,
        flow_rate: scalar,
        hardening: scalar,
        alpha: scalar,
        dt: scalar,
        kind: int,
        counters: wp.array(dtype=wp.int32),
    ):
        """``flow_step`` unless the smallest singular value is below ``MIN_SINGULAR_VALUE``
        (paper §4): then no flow, counted. ``kind``: the material model (1: non-Newtonian)."""
        flowed = int(0)
        g = s
        c = scalar(1.0)
        p = scalar(1.0)
        alpha_new = alpha
        if wp.min(wp.min(s[0], s[1]), s[2]) >= min_sigma:
            flowed, g, c, p, alpha_new = flow_step(
                s, mu, yield_stress, flow_rate, hardening, alpha, dt, wp.where(kind == 1, 1, 0)
            )
        else:
            wp.atomic_add(counters, COUNT_PLASTICITY_SKIPPED, 1)
        return flowed, g, c, p, alpha_new

    @wp.func
    def flow(
        F: mat33,
        a: scalar,
        mu: scalar,
        yield_stress: scalar,
        flow_rate: scalar,
        hardening: scalar,
        kind: int,
        dt: scalar,
        counters: wp.array(dtype=wp.int32),
    ):
        """``(F_e, alpha)`` after this step's plastic flow of ``F``, differentiable: the new
        singular values through ``isotropic_map`` with the divided differences of
        ``g = c s^p`` its adjoint needs."""
        Fe = F
        a_new = a
        if flow_rate > scalar(0.0):
            s = iso.singular_values(F)
            flowed, g, c, p, a_flow = guarded_flow_step(s, mu, yield_stress, flow_rate, hardening, a, dt, kind, counters)
            if flowed != 0:
                d1 = vec3(
                    power_difference(s[0], s[1], p, c),
                    power_difference(s[0], s[2], p, c),
                    power_difference(s[1], s[2], p, c),
                )
                Fe = iso.isotropic_map(F, g, d1)
                a_new = a_flow
        return Fe, a_new

    return types.SimpleNamespace(
        flow=flow, flow_step=flow_step, guarded_flow_step=guarded_flow_step, flow_fraction=flow_fraction,
        power_difference=power_difference,
    )


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    mat33 = T.mat33
    flow = funcs(scalar).flow
    stress = forces.funcs(scalar).stress
    Materials = materials.struct(scalar)

    @wp.kernel
    def constitutive_update(
        F_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        dt: scalar,
        F_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        stress_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """Plastic flow of the stored F, then the stress P* and F^-1 for the pair forces."""
        i = wp.tid()
        m = material[i]
        kind = mat.model[m]
        mu = mat.mu[m]
        Fe, a_new = flow(F_in[i], alpha_in[i], mu, mat.yield_stress[m], mat.flow_rate[m], mat.hardening[m], kind, dt, counters)
        F_out[i] = Fe
        alpha_out[i] = a_new
        stress_out[i] = stress(Fe, mu, mat.lam[m], kind)
        F_inv_out[i] = wp.inverse(Fe)

    return types.SimpleNamespace(constitutive_update=constitutive_update, flow=flow)


def launch_constitutive_update(model, state_in, state_out, dt, counters):
    """Plastic flow of ``state_in.F`` (paper §3), stress and ``F^-1`` into ``state_out``."""
    wp.launch(
        kernels(model.scalar).constitutive_update,
        model.particle_count,
        [state_in.F, state_in.alpha, model.particle_material, model.material_arrays(), model.scalar(dt)],
        [state_out.F_flowed, state_out.alpha, state_out.stress, state_out.F_inv, counters],
        device=model.device,
    )


def launch_constitutive_update_adjoint(model, state_in, state_out, dt, counters, tape):
    """Warp's generated adjoint of ``constitutive_update``, launched by hand (for the fused
    step under a tape, which writes the same outputs in its own kernel): the gradients of
    ``state_out.F_flowed, alpha, stress, F_inv`` into those of ``state_in.F, alpha`` and the
    material parameters."""
    mats = model.material_arrays()
    inputs = [state_in.F, state_in.alpha, model.particle_material, mats, model.scalar(dt)]
    outputs = [state_out.F_flowed, state_out.alpha, state_out.stress, state_out.F_inv, counters]
    wp.launch(
        kernels(model.scalar).constitutive_update, model.particle_count, inputs, outputs,
        adj_inputs=[tape.get_adjoint(a) for a in inputs], adj_outputs=[tape.get_adjoint(a) for a in outputs],
        device=model.device, adjoint=True, record_tape=False,
    )
