"""Multiplicative plasticity (Bargteil et al. 2007; paper §3, SPEC §4) applied to the
stored elastic deformation gradient, and the per-particle constitutive update.

In the SVD frame ``F = U diag(sigma) V^T`` the deviatoric stress is
``s = 2 mu (sigma - mean(sigma))``. Where ``|s| > Y + K alpha``:

    gamma   = min(nu_f dt (|s| - Y - K alpha) / |s|, 1)       (non-Newtonian: / |s|^2)
    sigma_k <- sigma_k^(1 - gamma) J^(gamma/3),  J = sigma_1 sigma_2 sigma_3
    alpha   <- alpha + gamma |ln sigma - mean(ln sigma)|

which is ``F_e = F F_p^-1`` with ``F_p <- V (J^(-1/3) F^)^gamma V^T F_p`` without storing
``F_p``. ``nu_f`` is a rate (1/s): ``nu_f dt`` is the paper's per-step fraction, so a result
does not depend on the time step. Where ``J`` leaves [0.8, 1.25] the flow uses ``F^``
instead of ``J^(-1/3) F^`` (paper §4: relaxing volume preservation under large volume
change improves stability), and where ``min sigma < 0.01`` the flow is skipped.
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import forces, isotropic

#: Index into the solver's guard counters: plastic flow skipped because min sigma < 0.01.
COUNT_PLASTICITY_SKIPPED = 3
MIN_SINGULAR_VALUE = 0.01
VOLUME_PRESERVING_RANGE = (0.8, 1.25)


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    # Below this relative gap the divided difference of sigma^(1-gamma) is replaced by
    # its derivative at the midpoint (error ~ gap^2).
    close = scalar(1.0e-3 if scalar is wp.float32 else 1.0e-5)
    j_lo = scalar(VOLUME_PRESERVING_RANGE[0])
    j_hi = scalar(VOLUME_PRESERVING_RANGE[1])

    @wp.func
    def power_difference(a: scalar, b: scalar, p: scalar, c: scalar) -> scalar:
        # c (a^p - b^p) / (a - b) and its limit c p a^(p-1) as a -> b.
        if wp.abs(a - b) < close * (a + b):
            m = scalar(0.5) * (a + b)
            return c * p * wp.pow(m, p - scalar(1.0))
        return c * (wp.pow(a, p) - wp.pow(b, p)) / (a - b)

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
        """Returns (flowed, new singular values g = c s^p, c, p, new alpha)."""
        mean = (s[0] + s[1] + s[2]) / scalar(3.0)
        dev = s - vec3(mean, mean, mean)
        s_norm2 = scalar(4.0) * mu * mu * wp.dot(dev, dev)
        y = wp.max(yield_stress + hardening * alpha, scalar(0.0))
        flowed = int(0)
        g = s
        c = scalar(1.0)
        p = scalar(1.0)
        alpha_new = alpha
        # Compare squares: |s| = 0 at rest, where sqrt has an infinite derivative.
        if s_norm2 > y * y:
            s_norm = wp.sqrt(s_norm2)
            rate = flow_rate * dt * (s_norm - y) / s_norm
            if non_newtonian != 0:
                rate = rate / s_norm
            gamma = wp.min(rate, scalar(1.0))
            J = s[0] * s[1] * s[2]
            if J >= j_lo and J <= j_hi:
                c = wp.pow(J, gamma / scalar(3.0))
            p = scalar(1.0) - gamma
            g = c * vec3(wp.pow(s[0], p), wp.pow(s[1], p), wp.pow(s[2], p))
            ls = vec3(wp.log(s[0]), wp.log(s[1]), wp.log(s[2]))
            lm = (ls[0] + ls[1] + ls[2]) / scalar(3.0)
            ld = ls - vec3(lm, lm, lm)
            alpha_new = alpha + gamma * wp.sqrt(wp.dot(ld, ld))
            flowed = 1
        return flowed, g, c, p, alpha_new

    @wp.func
    def plastic_flow(
        s: vec3,
        mu: scalar,
        yield_stress: scalar,
        flow_rate: scalar,
        hardening: scalar,
        alpha: scalar,
        dt: scalar,
        non_newtonian: int,
    ):
        """Returns (flowed, new singular values, divided differences, new alpha).

        The divided differences ``d1`` of ``g(sigma)`` only feed the adjoint of
        ``isotropic.isotropic_map``; the forward-only kernel calls ``flow_step``."""
        flowed, g, c, p, alpha_new = flow_step(s, mu, yield_stress, flow_rate, hardening, alpha, dt, non_newtonian)
        d1 = vec3(scalar(1.0), scalar(1.0), scalar(1.0))
        if flowed != 0:
            d1 = vec3(
                power_difference(s[0], s[1], p, c),
                power_difference(s[0], s[2], p, c),
                power_difference(s[1], s[2], p, c),
            )
        return flowed, g, d1, alpha_new

    return types.SimpleNamespace(plastic_flow=plastic_flow, flow_step=flow_step, power_difference=power_difference)


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    iso = isotropic.funcs(scalar)
    plastic_flow = funcs(scalar).plastic_flow
    stress = forces.funcs(scalar).stress
    min_sigma = scalar(MIN_SINGULAR_VALUE)

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
        """``(F_e, alpha)`` after this step's plastic flow of ``F`` (eq. 7-8); a particle whose
        smallest singular value is below ``MIN_SINGULAR_VALUE`` keeps ``F`` and is counted."""
        Fe = F
        a_new = a
        if flow_rate > scalar(0.0):
            s = iso.singular_values(F)
            if wp.min(wp.min(s[0], s[1]), s[2]) >= min_sigma:
                flowed, g, d1, a_flow = plastic_flow(s, mu, yield_stress, flow_rate, hardening, a, dt, wp.where(kind == 1, 1, 0))
                if flowed != 0:
                    Fe = iso.isotropic_map(F, g, d1)
                    a_new = a_flow
            else:
                wp.atomic_add(counters, 3, 1)
        return Fe, a_new

    @wp.kernel
    def constitutive_update(
        F_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mu: wp.array(dtype=scalar),
        lam: wp.array(dtype=scalar),
        yield_stress: wp.array(dtype=scalar),
        flow_rate: wp.array(dtype=scalar),
        hardening: wp.array(dtype=scalar),
        model: wp.array(dtype=wp.int32),
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
        kind = model[m]
        Fe, a_new = flow(F_in[i], alpha_in[i], mu[m], yield_stress[m], flow_rate[m], hardening[m], kind, dt, counters)
        F_out[i] = Fe
        alpha_out[i] = a_new
        stress_out[i] = stress(Fe, mu[m], lam[m], kind)
        F_inv_out[i] = wp.inverse(Fe)

    return types.SimpleNamespace(constitutive_update=constitutive_update, flow=flow)
