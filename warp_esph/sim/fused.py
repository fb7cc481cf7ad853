"""Forward-only kernels of the step, used when no ``wp.Tape`` is recording.

``constitutive_forces`` does, per particle, what ``plasticity.constitutive_update``,
``forces.elastic_forces`` and ``pressure.pressure_forces`` do in three launches, with
the same formulas:

* one SVD of ``F`` instead of four: the plastic flow ``F_e = U diag(g) V^T`` keeps the
  singular vectors, so the stress reuses ``U, g, V`` instead of decomposing ``F_e``
  again (and the SVD maps' own decompositions, there for their adjoints, are gone);
  the stress is an isotropic function of ``F_e``, so the result is the same up to
  round-off (in float32 closer to a float64 step than the differentiable kernels:
  one SVD's error instead of two);
* the divided differences the SVD maps' adjoints need are not computed;
* the stress and ``F^-1`` of particle ``i`` are used where they are computed (they are
  still written to the state), and one loop over the neighbours applies the elastic
  pair force and the SPH pressure and viscosity forces, with each particle's pressure
  and volume ``m / rho`` computed once, in the neighbour pass;
* per pair, ``P* grad W(F^-1 d)`` is evaluated as ``phi(|r|) (P* F^-1) d`` with
  ``cos`` a polynomial in ``|r|^2`` (float32) and the kernels' ``h``-dependent
  constants computed once per particle.

``update_deformation`` is ``deformation.update_deformation`` with the neighbourhood
guard evaluated on the fit's own moment matrix (the neighbour pass then skips it).

Neither has an adjoint: under a tape the solver launches the differentiable kernels.
``tests/test_physics.py::test_fused_step_matches_the_differentiable_step`` compares
the two.
"""
import functools
import math
import types

import warp as wp

from .._types import type_set
from . import deformation, forces, neighbors, plasticity, pressure, smoothing

# Taylor coefficients of cos(pi s / 2) in t = s^2 up to t^7: on s in [0, 1] the
# truncation error is below 1e-8, under float32 rounding (max error measured against
# float64: 1.4e-7, libm cosf: 1.1e-7).
_COS_COEFFS = [(-1) ** k * (math.pi / 2) ** (2 * k) / math.factorial(2 * k) for k in range(8)]


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    sm = smoothing.funcs(scalar)
    viscous_force = pressure.kernels(scalar).viscous_force
    flow_step = plasticity.funcs(scalar).flow_step
    min_sigma = scalar(plasticity.MIN_SINGULAR_VALUE)
    guard_code = neighbors.kernels(scalar).guard_code
    moment_sums = deformation.kernels(scalar).moment_sums
    variational_map = forces.funcs(scalar).variational_map
    c0, c1, c2, c3, c4, c5, c6, c7 = (scalar(c) for c in _COS_COEFFS)
    exact_cos = scalar is wp.float64

    @wp.func
    def cos_half_pi(t: scalar) -> scalar:
        """cos(pi s / 2) of s = sqrt(t) in [0, 1]: a polynomial in t in float32 (a third
        of a pair's elastic-force cost was the libm call and its wait for the square
        root), the library cosine in float64."""
        if wp.static(exact_cos):
            return wp.cos(scalar(math.pi) * wp.sqrt(t) / scalar(2.0))
        return c0 + t * (c1 + t * (c2 + t * (c3 + t * (c4 + t * (c5 + t * (c6 + t * c7))))))

    @wp.func
    def linear_stress(U: mat33, s: vec3, V: mat33, mu: scalar, lam: scalar) -> mat33:
        # forces.funcs().stress for model 0/1 given the SVD of F: U diag(s o P^) V^T.
        tr = s[0] + s[1] + s[2] - scalar(3.0)
        one = vec3(scalar(1.0), scalar(1.0), scalar(1.0))
        p_hat = scalar(2.0) * mu * (s - one) + lam * tr * one
        f = wp.cw_mul(s, p_hat)
        return U * wp.diag(f) * wp.transpose(V)

    @wp.func
    def polynomial_stress(F: mat33, mu: scalar, lam: scalar, model: int) -> mat33:
        # forces.funcs().stress for the hyperelastic (2) and stvk (3) models.
        scale = wp.where(model == 2, scalar(1.0), scalar(0.5))
        C = wp.transpose(F) * F
        tr = C[0, 0] + C[1, 1] + C[2, 2]
        return scale * (scalar(2.0) * mu * (F * C - F) + lam * (tr - scalar(3.0)) * F)

    @wp.kernel(enable_backward=False)
    def constitutive_forces(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        F_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        body: wp.array(dtype=wp.int32),
        volume: wp.array(dtype=scalar),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        p: wp.array(dtype=scalar),
        vol: wp.array(dtype=scalar),
        mu: wp.array(dtype=scalar),
        lam: wp.array(dtype=scalar),
        yield_stress: wp.array(dtype=scalar),
        flow_rate: wp.array(dtype=scalar),
        hardening: wp.array(dtype=scalar),
        model: wp.array(dtype=wp.int32),
        viscosity: wp.array(dtype=scalar),
        elastic_force: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        dt: scalar,
        sph: int,
        min_neighbors: int,
        max_condition: scalar,
        F_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        stress_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        f: wp.array(dtype=vec3),
        counters: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        m = material[i]
        F = F_in[i]
        a = alpha_in[i]
        kind = model[m]
        mu_m = mu[m]
        lam_m = lam[m]

        # 1. Plastic flow (plasticity.constitutive_update) with a single SVD.
        Fe = F
        a_new = a
        U = mat33()
        s = vec3()
        V = mat33()
        have_svd = int(0)
        if flow_rate[m] > scalar(0.0):
            wp.svd3(F, U, s, V)
            have_svd = 1
            if wp.min(wp.min(s[0], s[1]), s[2]) >= min_sigma:
                flowed, g, c_flow, p_flow, a_flow = flow_step(
                    s, mu_m, yield_stress[m], flow_rate[m], hardening[m], a, dt, wp.where(kind == 1, 1, 0)
                )
                if flowed != 0:
                    Fe = U * wp.diag(g) * wp.transpose(V)
                    s = g
                    a_new = a_flow
            else:
                wp.atomic_add(counters, 3, 1)

        # 2. Stress P* and F^-1 (forces.funcs().stress).
        P = mat33()
        if kind >= 2:
            P = polynomial_stress(Fe, mu_m, lam_m, kind)
        else:
            if have_svd == 0:
                wp.svd3(Fe, U, s, V)
            P = linear_stress(U, s, V, mu_m, lam_m)
        Finv = wp.inverse(Fe)
        F_out[i] = Fe
        alpha_out[i] = a_new
        stress_out[i] = P
        F_inv_out[i] = Finv

        # 3. Pair forces: elastic (forces.elastic_forces), then pressure and viscosity
        # (pressure.pressure_forces) with the pressure p and volume m / rho of every
        # particle from the neighbour pass, each pair's share applied equal and opposite.
        xi = x[i]
        bi = body[i]
        Vol_i = volume[i]
        vi = v[i]
        Vi = scalar(0.0)
        pi = scalar(0.0)
        visc_i = viscosity[m]
        if sph != 0:
            Vi = vol[i]
            pi = p[i]
        h2 = h * h
        inv_h2 = scalar(1.0) / h2
        PF = P * Finv
        c_el = sm.elastic_coef(h)
        # Elastic force: 0 the paper's (eqs. 10-13), 1 variational (forces.py), 2 none (a
        # guarded particle of the variational force).
        kind_el = elastic_force[m]
        M = mat33()
        if kind_el == 1:
            A, B, same = moment_sums(i, x, x, body, nbr, count[i], h)
            if guard_code(A, same, min_neighbors, max_condition) == 0:
                M = variational_map(Vol_i, P, Fe, A)
            else:
                kind_el = 2
        c6 = sm.poly6_coef(h)
        c_spiky = sm.spiky_coef(h)
        c_visc = sm.viscosity_coef(h)
        fi = vec3()
        for k in range(count[i]):
            j = nbr[i, k]
            xj = x[j]
            fj = vec3()
            if body[j] == bi and kind_el == 1:
                # forces.py, variational: f_j -= w_ij M_i xb_ij.
                dj = xj - xi
                g = sm.w_poly6_c(wp.dot(dj, dj), h, c6) * (M * dj)
                fj = -g
                fi += g
            elif body[j] == bi and kind_el == 0:
                # ½ g_ij = V_i V_j P*_i grad W(r),  r = F_i^-1 (x_j - x_i), with
                # grad W(r) = phi(|r|) r (smoothing.grad_w_elastic), so P*_i grad W(r) =
                # phi (P*_i F_i^-1) (x_j - x_i).
                dj = xj - xi
                r = Finv * dj
                r2 = wp.dot(r, r)
                if r2 < h2 and r2 > scalar(1.0e-24) * h2:
                    phi = -c_el * cos_half_pi(r2 * inv_h2) / wp.sqrt(r2)
                    g = (Vol_i * volume[j] * phi) * (PF * dj)
                    fj = g
                    fi -= g
            if sph != 0:
                # smoothing.grad_w_spiky and lap_w_viscosity sharing one |r_ij|.
                rij = xi - xj
                r2 = wp.dot(rij, rij)
                if r2 < h2:
                    VV = Vi * vol[j]
                    rl = wp.sqrt(r2)
                    gs = vec3()
                    if r2 > scalar(1.0e-24) * h2:
                        d = h - rl
                        gs = c_spiky * d * d / rl * rij
                    pair = -VV * scalar(0.5) * (pi + p[j]) * gs
                    eta = scalar(0.5) * (visc_i + viscosity[material[j]])
                    pair += viscous_force(eta * VV, rij, r2, c_visc * (h - rl), v[j] - vi)
                    half = scalar(0.5) * pair
                    fj -= half
                    fi += half
            wp.atomic_add(f, j, fj)
        wp.atomic_add(f, i, fi)

    @wp.kernel(enable_backward=False)
    def update_deformation(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        F_prev: wp.array(dtype=mat33),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        F_out: wp.array(dtype=mat33),
        guard: wp.array(dtype=wp.int32),
        counters: wp.array(dtype=wp.int32),
    ):
        """deformation.update_deformation with the neighbourhood guard of
        neighbors.select_neighbors evaluated here, on the moment matrix A of the fit."""
        i = wp.tid()
        A, B, same = moment_sums(i, x, y, body, nbr, count[i], h)
        code = guard_code(A, same, min_neighbors, max_condition)
        guard[i] = code
        F = F_prev[i]
        if code == 1:
            wp.atomic_add(counters, 0, 1)
        elif code == 2:
            wp.atomic_add(counters, 1, 1)
        else:
            candidate = B * wp.inverse(A) * F
            if wp.determinant(candidate) > scalar(0.0):
                F = candidate
            else:
                wp.atomic_add(counters, 2, 1)
        F_out[i] = F

    return types.SimpleNamespace(constitutive_forces=constitutive_forces, update_deformation=update_deformation)
