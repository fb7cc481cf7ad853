"""The comparison deformation models of the paper's Fig. 8 (docs/method.md §7).

Selected per material with ``Material(deformation=...)``:

- ``"incremental"`` (default): the paper's method, ``F <- dF F`` (``deformation.py``).
- ``"rest"`` (Müller et al. 2004 style): the total ``F = (Σ w yb Xbᵀ)(Σ w Xb Xbᵀ)⁻¹`` is
  fitted against the rest positions ``X`` with the initial (same-body) neighbour lists;
  a plastic ``F_p`` per particle is stored, ``F_e = F F_p⁻¹``. The plastic flow of
  ``plasticity.py`` updates ``F_e`` and then, where it changed ``F_e``, ``F_p <- F_e⁻¹ F``.
  ``State.F`` holds ``F_e``. The moments of the rest offsets alone, ``A~^-1`` and ``K``, are
  evaluated once per rest set, fit and fit weight (``Model.rest_moments``; a solver keeps the
  rest set it obtained, ``Solver.rest_set``), not at every step. Where the fit inverts
  (a body crushed through zero thickness), a variational material that cannot flow takes it,
  its energy continued through det = 0 (``inverted_stress``; the linear models' corotated
  stress, ``forces.corotated_stress``, needs no continuation); others keep the last ``F``.
- ``"additive"``: a symmetric strain ``ε`` per particle, ``ε <- ε + ½(dFᵀdF − I)`` with the
  step's MLS ``dF``; plastic flow removes the fraction ``γ = min(nu_f dt (|s| − Y − K α)/|s|, 1)``
  of ``dev ε`` where ``|s| = 2 mu |dev ε| > Y + K α``; stress ``σ = 2 mu ε + lam tr(ε) I``,
  pair forces with ``P* = σ`` and no back projection (``F⁻¹ = I``). ``State.F`` holds ``I + ε``.

Both run only on the solver's differentiable (non-fused) path; the incremental particles of
a model that mixes models go through the same kernels as in ``plasticity``/``deformation``.
Under a tape, where every material runs the rest model (the solver's ``rest_model``, or
every material ``"rest"``), the total fit and the rest variational force record hand-written
adjoints (``adjoint_kernels``), of either fit; a model that mixes deformation models, and
``Solver.hand_adjoints = False``, keep Warp's generated ones. The constitutive update and
the hand-over keep the generated ones.
"""

import functools
import types

import numpy as np
import warp as wp

from .._types import type_set
from . import curvature, deformation, forces, isotropic, materials, plasticity
from .replay import kept_through_backward, recording_tape

COUNT_FEW_NEIGHBORS = deformation.COUNT_FEW_NEIGHBORS
COUNT_ILL_CONDITIONED = deformation.COUNT_ILL_CONDITIONED
COUNT_BODY = deformation.COUNT_BODY
COUNT_INVERTED = deformation.COUNT_INVERTED


@functools.cache
def kernels(scalar, weight: str) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    pf = plasticity.funcs(scalar)
    flow, flow_fraction = pf.flow, pf.flow_fraction
    stress = forces.funcs(scalar, weight).stress
    df = deformation.funcs(scalar, weight)
    gf = deformation.guards.guard_funcs(scalar)
    moment_sums, step_gradient, unless_inverted = df.moment_sums, df.step_gradient, df.unless_inverted
    Materials = materials.struct(scalar)
    cf = curvature.funcs(scalar, weight)
    iso = isotropic.funcs(scalar)
    ff = forces.funcs(scalar, weight)

    @wp.func
    def pair_difference(gi: scalar, gj: scalar, si: scalar, sj: scalar) -> scalar:
        """``(g_i - g_j) / (s_i - s_j)`` for ``s_i > 0 >= s_j`` (``inverted_stress``): apart
        but where both are 0, an ``F`` of rank 1 at most."""
        return (gi - gj) / wp.max(si - sj, scalar(1.0e-6))

    @wp.func
    def inverted_stress(F: mat33, mu: scalar, lam: scalar, model: int) -> mat33:
        """P* of an inverted rest fit (det ``F`` <= 0; ``forces.stress`` where det > 0) of a
        polynomial model (``hyperelastic``, ``stvk``), the stress of the energy continued
        through det = 0 as invertible finite elements do: in the rotation-variant SVD
        (``isotropic.py``: ``U``, ``V`` rotations, the smallest singular value ``s_2 <= 0``)
        ``psi(s_0, s_1, 0) + k s_2^2 / 2``, ``k`` the model's stiffness along one singular value
        at rest (``lam + 2 mu``; ``2 (lam + 2 mu)`` for ``hyperelastic``). ``P*`` is ``s_2``
        times a factor in its third principal value, so ``P*`` and the energy are continuous at
        det = 0, and the inverted side pushes back out (``k s_2``) where ``forces.stress`` of
        the mirrored ``F`` pulled on through (St. Venant-Kirchhoff's energy is even in each
        ``s``: the mirror image of the rest shape costs none). The linear models need none:
        where the fit is taken inverted they run ``forces.corotated_stress``, whose energy is
        already smooth and restoring through det = 0 in the signed singular values.
        ``d1``: the divided differences ``isotropic_map``'s adjoint needs."""
        s = iso.singular_values(F)
        z = vec3(s[0], s[1], scalar(0.0))
        c = wp.where(model == 2, scalar(1.0), scalar(0.5))
        tr = s[0] * s[0] + s[1] * s[1] - scalar(3.0)
        # polynomial_stress in the SVD frame: c (2 mu (s^3 - s) + lam (sum s^2 - 3) s)
        g_poly = c * (scalar(2.0) * mu * (wp.cw_mul(wp.cw_mul(z, z), z) - z) + lam * tr * z)
        d_poly = c * (scalar(2.0) * mu * (s[0] * s[0] + s[0] * s[1] + s[1] * s[1] - scalar(1.0)) + lam * tr)
        k = wp.where(model == 2, scalar(2.0), scalar(1.0)) * (lam + scalar(2.0) * mu)
        g2 = k * s[2]
        d1 = vec3(d_poly, pair_difference(g_poly[0], g2, s[0], s[2]), pair_difference(g_poly[1], g2, s[1], s[2]))
        return iso.isotropic_map(F, vec3(g_poly[0], g_poly[1], g2), d1)

    @wp.func
    def continues_inverted(mat: Materials, m: int) -> bool:
        """Whether material ``m``'s rest fit is taken where it inverts, its energy continued
        through det = 0 (``inverted_stress``, or the corotated stress's own, smooth there): a
        variational force that cannot flow (``forces.cannot_flow_variational``: ``yield_stress
        = inf`` or ``flow_rate <= 0``), the rest model that ``fit="auto"`` runs. Elsewhere an
        inverted fit keeps the last ``F``, as before: the paper's force is the gradient of no
        energy anyway, and a flow of an inverted ``F_e`` would write a mirrored ``F_p``."""
        return ff.cannot_flow_variational(mat, m)

    @wp.func
    def takes_rest_fit(mat: Materials, m: int, det: scalar) -> bool:
        """Whether material ``m``'s rest fit ``F_e`` of determinant ``det`` is taken: where
        ``det > 0``, and where ``det <= 0`` if ``continues_inverted``. A ``det`` that is neither
        (NaN: a fit overflowed in float32) is not: the last ``F`` is kept, counted as inverted."""
        return det > scalar(0.0) or (det <= scalar(0.0) and continues_inverted(mat, m))

    @wp.func
    def rest_elastic_part(G: mat33, Fp: mat33) -> mat33:
        """The rest model's ``F_e = G F_p^-1``: the elastic part of its total fit ``G`` in the
        multiplicative split ``G = F_e F_p`` (module docstring)."""
        return G * wp.inverse(Fp)

    @wp.func
    def rest_total_fit(
        i: int,
        rest_x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        At_inv: mat33,
        K: mat33,
        curved: int,
    ):
        """``G_i(y)``, the rest model's total fit of the positions ``y`` against particle ``i``'s
        rest neighbourhood (the paper's eqs. 5-6 with the rest offsets in place of the current
        ones; ``curved``: the curvature-corrected fit, ``curvature.corrected_fit``): ``I + (Bu
        - Eu K) A~^-1`` of the displacement moments ``Bu``, ``Eu`` (``Eu = 0``, ``K = 0``: the
        linear fit's ``I + Bu A^-1``), with ``A~^-1`` and ``K`` of the rest offsets alone
        (``rest_moments``, ``Model.rest_moments``). The sums from their own functions, as
        every fit's (docs/method.md, Warp pitfall 1). The positions' round-off is not carried
        (y, y)."""
        Bu = mat33()
        Eu = mat33()
        if curved != 0:
            A, B, C, D, E, same = cf.moment_sums(i, rest_x, y, y, y, body, rest_nbr, n, h)
            Bu = B
            Eu = E
        else:
            A, B, same = moment_sums(i, rest_x, y, y, y, body, rest_nbr, n, h)
            Bu = B
        return wp.identity(n=3, dtype=scalar) + cf.corrected_moment(Bu, Eu, K) * At_inv

    @wp.kernel(module="unique")
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
            dev = pf.deviatoric_tensor(eps)
            dn2 = wp.ddot(dev, dev)
            a_new = a
            if mat.flow_rate[m] > scalar(0.0):
                flowed, gamma = flow_fraction(
                    pf.deviatoric_stress_norm2(mu, dn2), mat.yield_stress[m], mat.hardening[m], a, mat.flow_rate[m], dt,
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
            # Rest configuration: F_total = F_e F_p is kept, F_p <- F_e_new^-1 F_total, only
            # where the flow changed F: unflowed, F_e^-1 (F_e F_p) is F_p exactly (of zero
            # derivative in F), but its float32 round-off walked F_p a few ulps a step, a
            # creeping rest shape that kept relaxed bodies from settling (docs/physics.md,
            # "The energy of undamped elastic bodies").
            D = Fe - F
            if d == 1 and wp.ddot(D, D) > scalar(0.0):
                Fp = Fe_inv * (F * Fp)
            F_out[i] = Fe
            alpha_out[i] = a_new
            Fp_out[i] = Fp
            sk = ff.stress_model(mat, m)
            if d == 1 and kind >= 2 and wp.determinant(Fe) <= scalar(0.0) and continues_inverted(mat, m):
                # An inverted rest fit (update_deformation takes it): the continued energy's stress.
                stress_out[i] = inverted_stress(Fe, mu, lam, kind)
            else:
                stress_out[i] = stress(Fe, mu, lam, sk)
            F_inv_out[i] = Fe_inv

    @wp.kernel(module="unique")
    def update_deformation(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        rest_guard: wp.array(dtype=wp.int32),
        rest_At_inv: wp.array(dtype=mat33),
        rest_K: wp.array(dtype=mat33),
        guard: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        F_prev: wp.array(dtype=mat33),
        Fp: wp.array(dtype=mat33),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        curved: int,
        F_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """``deformation.update_deformation`` for every deformation model (``curved``: the rest
        model's total fit is the curvature-corrected one, ``curvature.corrected_fit``;
        ``rest_At_inv``, ``rest_K``: its rest moments, ``Model.rest_moments``). An inverted rest
        fit is taken where ``continues_inverted`` (counted), else the last ``F`` is kept
        (counted); so is the last ``F`` where the fit's determinant is NaN (``takes_rest_fit``)."""
        i = wp.tid()
        F = F_prev[i]
        d = mat.deformation[material[i]]
        I = wp.identity(n=3, dtype=scalar)
        if d == 1:
            # Rest configuration: the total F against X, always with the initial lists; F kept
            # (and counted) where the rest neighbourhood's guard holds (a singular A there). The
            # positions' round-off is not carried here (round-off arrays y, y).
            code = rest_guard[i]
            if code == 1 or code == 2:
                deformation.count_guarded(code, COUNT_BODY + body[i], counters)
            else:
                G = rest_total_fit(i, rest_x, y, body, rest_nbr, rest_count[i], h, rest_At_inv[i], rest_K[i], curved)
                # Taken inverted too (counted): its energy is continued through det = 0
                # (inverted_stress, or the corotated stress's, smooth there). Keeping the last F
                # there left a frozen stress whose force is the gradient of no energy, which
                # pumped a crushed body up until it diverged.
                # A NaN det (an overflowed fit) is neither side of 0: it keeps the last F,
                # counted, as every fit not > 0 did before; taking it hid it from the counts.
                Fe = rest_elastic_part(G, Fp[i])
                det = wp.determinant(Fe)
                if takes_rest_fit(mat, material[i], det):
                    F = Fe
                if not (det > scalar(0.0)):
                    wp.atomic_add(counters, COUNT_INVERTED, 1)
        else:
            A, B, same = moment_sums(i, x, y, y, y, body, nbr, count[i], h)
            dF = step_gradient(A, B, guard[i], gf.guard_scale(A, same, min_neighbors, max_condition),
                               COUNT_BODY + body[i], counters)
            if d == 2:
                # Additive: F = I + eps, eps <- eps + (dF^T dF - I) / 2.
                F = F + scalar(0.5) * (wp.transpose(dF) * dF - I)
            else:
                F = unless_inverted(dF * F, F, counters)
        F_out[i] = F

    fn = forces.funcs(scalar, weight)

    @wp.func
    def rest_map_moments(
        i: int,
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        curved: int,
    ):
        """The fixed moments of particle ``i``'s rest fit and variational force: ``A~`` and ``K``
        of its rest neighbourhood (``curved``: the curvature-corrected fit's, ``curvature.py``;
        else ``A`` and ``K = 0``), from their own functions: an inverse must not see a loop
        accumulator (docs/method.md, Warp pitfall 1). Evaluated once per rest set, fit and weight
        (``rest_moments``)."""
        K = mat33()
        At = mat33()
        if curved != 0:
            A, B, C, D, E, same = cf.moment_sums(i, rest_x, rest_x, rest_x, rest_x, body, rest_nbr, n, h)
            K = cf.curvature_projection(A, C, D)
            At = cf.corrected_moment(A, C, K)
        else:
            A, B, same = moment_sums(i, rest_x, rest_x, rest_x, rest_x, body, rest_nbr, n, h)
            At = A
        return At, K

    @wp.kernel(enable_backward=False, module="unique")
    def rest_moments(
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        h: scalar,
        curved: int,
        At_inv: wp.array(dtype=mat33),
        K_out: wp.array(dtype=mat33),
    ):
        """``A~^-1`` and ``K`` of ``rest_map_moments`` for every particle (``Model.rest_moments``):
        the moments of the rest offsets alone, the same at every step (at a guarded rest
        neighbourhood, which nothing reads them at, whatever the inverse of a near-singular
        ``A~`` gives)."""
        i = wp.tid()
        At, K = rest_map_moments(i, rest_x, body, rest_nbr, rest_count[i], h, curved)
        At_inv[i] = wp.inverse(At)
        K_out[i] = K

    @wp.kernel(module="unique")
    def rest_variational_forces(
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        rest_guard: wp.array(dtype=wp.int32),
        rest_At_inv: wp.array(dtype=mat33),
        rest_K: wp.array(dtype=mat33),
        volume: wp.array(dtype=scalar),
        stress: wp.array(dtype=mat33),
        Fp: wp.array(dtype=mat33),
        h: scalar,
        curved: int,
        f: wp.array(dtype=vec3),
    ):
        """The variational force of a rest-configuration material (``Material(deformation="rest",
        elastic_force="variational")``): minus the gradient of ``E = sum_i V_i psi(G_i F_p,i^-1)``
        (``psi`` continued through det = 0 where the fit inverts, ``inverted_stress``)
        with ``G_i = (sum_j w_ij yb_j Xb_j^T) A_i^-1`` the total fit of the end positions ``y``
        against the rest ones (weights and ``A_i`` of the rest neighbourhood, fixed). ``G_i`` is
        linear in ``y``, so ``g_ij = w_ij V_i P*_i F_p,i^-T A_i^-1 Xb_ij`` is the exact gradient
        of an energy of the positions alone: a conservative force, where the incremental
        composition ``F <- dF F`` is path dependent (docs/physics.md, "The energy of undamped
        elastic bodies"). The same ``variational_map`` and pair force as the incremental one,
        with ``F_p^-1`` in place of ``F`` and the rest offsets in place of the current ones.
        ``curved``: with the curvature-corrected total fit, ``A~_i`` and ``Xb - K_i^T q(Xb)`` in
        place of ``A_i`` and ``Xb`` (``curvature.py``), also of the rest positions alone
        (``rest_At_inv``, ``rest_K``: ``Model.rest_moments``)."""
        i = wp.tid()
        m = material[i]
        # A guarded rest neighbourhood keeps its F whatever the positions do: no energy
        # gradient, no force (as the incremental fit's guard).
        if mat.deformation[m] == 1 and mat.elastic_force[m] == 1 and rest_guard[i] == 0:
            K = rest_K[i]
            M = fn.variational_map(volume[i], stress[i], wp.inverse(Fp[i]), rest_At_inv[i])
            fi = vec3()
            if curved != 0:
                fi = cf.variational_forces(i, rest_x, body, rest_nbr, rest_count[i], M, K, h, f)
            else:
                fi = fn.variational_forces(i, rest_x, body, rest_nbr, rest_count[i], M, h, f)
            wp.atomic_add(f, i, fi)

    @wp.kernel(module="unique")
    def rest_handover(
        x: wp.array(dtype=vec3),
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        rest_guard: wp.array(dtype=wp.int32),
        rest_At_inv: wp.array(dtype=mat33),
        rest_K: wp.array(dtype=mat33),
        F: wp.array(dtype=mat33),
        h: scalar,
        curved: int,
        Fp_out: wp.array(dtype=mat33),
    ):
        """``F_p = F^-1 G(x)``: the plastic part that makes the rest model's ``F_e = G F_p^-1``
        the stored ``F`` of an incremental run at the positions ``x``, so the solver's switch
        from the incremental composition to the rest model (``Solver``, ``fit="auto"``) keeps
        the stress where it is instead of jumping to the rest fit of a body that flowed, or
        drifted. Where the rest neighbourhood is guarded (no ``G``) or ``G`` inverted (a rest
        neighbourhood mirrored: no ``F_p`` of positive determinant gives ``F``), a new state's
        ``I``: the rest fit is the particle's ``F_e`` once it is valid again, as on a start. The
        incoming ``F_p`` is no choice: an incremental step does not write it, so it holds what
        its buffer last held (an earlier rest period's in a loop of two reused states, ``I``
        in a rollout's), and it entered the rest force at once."""
        i = wp.tid()
        out = wp.identity(n=3, dtype=scalar)
        if rest_guard[i] == 0:
            G = rest_total_fit(i, rest_x, x, body, rest_nbr, rest_count[i], h, rest_At_inv[i], rest_K[i], curved)
            if wp.determinant(G) > scalar(0.0):
                out = wp.inverse(F[i]) * G
        Fp_out[i] = out

    @wp.kernel(module="unique")
    def rest_handback(
        F: wp.array(dtype=mat33),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        F_out: wp.array(dtype=mat33),
    ):
        """The ``F`` an incremental step reads from a state a rest step wrote: the stored one,
        but ``-F`` where it is an inverted rest fit (det < 0) of a particle the incremental
        composition runs (deformation code "incremental"). That composition keeps the last
        ``F`` where a step would invert it (paper §4), and from an inverted ``F`` every step
        would: the fit stayed as it was for the rest of the run, whatever the body did. ``-F``
        is a mirror image of positive determinant with the same stretches: ``F F^T``, so the
        stress ``P F^T`` of every (isotropic) model, is unchanged, and it is what the
        composition holds of a neighbourhood that turned inside out in its own steps, up to a
        rotation of the rest frame. Linear in ``F``, it is smooth where the singular-value
        mirror ``U diag(s_0, s_1, -s_2) V^T`` jumps (``|s_1| = |s_2|``: a neighbourhood
        mirrored through a plane, ``s = (1, 1, -1)``)."""
        i = wp.tid()
        if mat.deformation[material[i]] == 0 and wp.determinant(F[i]) < scalar(0.0):
            F_out[i] = -F[i]
        else:
            F_out[i] = F[i]

    @wp.kernel(enable_backward=False, module="unique")
    def rest_start_fit(
        x: wp.array(dtype=vec3),
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        rest_guard: wp.array(dtype=wp.int32),
        rest_At_inv: wp.array(dtype=mat33),
        rest_K: wp.array(dtype=mat33),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        F: wp.array(dtype=mat33),
        Fp: wp.array(dtype=mat33),
        h: scalar,
        curved: int,
        F_out: wp.array(dtype=mat33),
    ):
        """The ``F`` that ``update_deformation`` takes at the positions ``x`` (not counted): a
        rest particle's ``G(x) F_p^-1`` where its guard holds no singular neighbourhood and the
        fit is taken (``takes_rest_fit``), else the stored ``F``. The strain a start holds
        against the rest shape, whatever its stored ``F`` says (``Solver.start_deformation``)."""
        i = wp.tid()
        out = F[i]
        m = material[i]
        if mat.deformation[m] == 1 and rest_guard[i] == 0:
            G = rest_total_fit(i, rest_x, x, body, rest_nbr, rest_count[i], h, rest_At_inv[i], rest_K[i], curved)
            Fe = rest_elastic_part(G, Fp[i])
            if takes_rest_fit(mat, m, wp.determinant(Fe)):
                out = Fe
        F_out[i] = out

    return types.SimpleNamespace(constitutive_update=constitutive_update, update_deformation=update_deformation,
                                 rest_variational_forces=rest_variational_forces, rest_handover=rest_handover,
                                 rest_start_fit=rest_start_fit, rest_handback=rest_handback,
                                 rest_map_moments=rest_map_moments, rest_moments=rest_moments,
                                 rest_total_fit=rest_total_fit, rest_elastic_part=rest_elastic_part,
                                 continues_inverted=continues_inverted,
                                 takes_rest_fit=takes_rest_fit, inverted_stress=inverted_stress)


def launch_rest_moments(model, rest_x, rest_nbr, rest_count, curved: bool) -> tuple[wp.array, wp.array]:
    """``rest_moments`` of the rest set ``rest_x, rest_nbr, rest_count``: new arrays of every
    particle's ``A~^-1`` and ``K`` (``Model.rest_moments`` keeps them per fit and weight)."""
    mat33 = model.types.mat33
    At_inv = wp.empty(model.particle_count, dtype=mat33, device=model.device)
    K = wp.empty(model.particle_count, dtype=mat33, device=model.device)
    # Not on a tape a step may be recording: a constant of the model, not of the step.
    model.launches(kernels(model.scalar, model.fit_weight).rest_moments, model.particle_count,
                   [rest_x, model.particle_body, rest_nbr, rest_count, model.scalar(model.support_radius), int(curved)],
                   [At_inv, K], device=model.device, record_tape=False)
    return At_inv, K


def launch_rest_handover(model, state_in, Fp_out, curved: bool = False, rest_guard=None, rest=None):
    """``rest_handover`` of ``state_in`` into ``Fp_out`` (read by the step's constitutive update in
    place of ``state_in.F_p``; ``state_in`` is only read). ``rest_guard``: the rest
    neighbourhoods' guard with the solver's thresholds (``Model.rest_guard_for``; None: the
    default ``Model.rest_guard``), as in the launches below; ``rest``: the rest neighbourhoods
    and their moments the solver holds (``Solver.rest_set``; None: the model's)."""
    rest_x, rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K = _rest_set(model, rest, rest_guard, curved)
    model.launches(
        kernels(model.scalar, model.fit_weight).rest_handover,
        model.particle_count,
        [state_in.x, rest_x, model.particle_body, rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K,
         state_in.F,
         model.scalar(model.support_radius), int(curved)],
        [Fp_out],
        device=model.device,
    )


def launch_rest_handback(model, state_in, F_out):
    """``rest_handback`` of ``state_in.F`` into ``F_out`` (read by an incremental step in place
    of ``state_in.F``; ``state_in`` is only read)."""
    model.launches(
        kernels(model.scalar, model.fit_weight).rest_handback, model.particle_count,
        [state_in.F, model.particle_material, model.material_arrays()], [F_out], device=model.device,
    )


def start_fit(model, state, curved: bool = False, mats=None, rest_guard=None, rest=None) -> np.ndarray:
    """``rest_start_fit`` of ``state``: the ``(n, 3, 3)`` deformation gradients a rest step's fit
    takes at its positions (``mats``, ``rest_guard``, ``rest``: as in the launches here)."""
    rest_x, rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K = _rest_set(model, rest, rest_guard, curved)
    out = wp.empty_like(state.F, requires_grad=False)
    wp.launch(
        kernels(model.scalar, model.fit_weight).rest_start_fit, model.particle_count,
        [state.x, rest_x, model.particle_body, rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K,
         model.particle_material, model.material_arrays() if mats is None else mats, state.F, state.F_p,
         model.scalar(model.support_radius), int(curved)],
        [out], device=model.device, record_tape=False,
    )
    return out.numpy()


def launch_constitutive_update(model, state_in, state_out, dt, counters, mats=None, Fp_in=None):
    """``plasticity.launch_constitutive_update`` for models with a Fig. 8 comparison material
    (``mats``: the material struct the kernels read, default ``model.material_arrays()``;
    ``Fp_in``: the ``F_p`` read in place of ``state_in.F_p``, a hand-over's)."""
    model.launches(
        kernels(model.scalar, model.fit_weight).constitutive_update,
        model.particle_count,
        [state_in.F, state_in.alpha, state_in.F_p if Fp_in is None else Fp_in, model.particle_material,
         model.material_arrays() if mats is None else mats, model.scalar(dt)],
        [state_out.F_flowed, state_out.alpha, state_out.F_p, state_out.stress, state_out.F_inv, counters],
        device=model.device,
    )


@functools.cache
def adjoint_kernels(scalar, weight: str, fit: str) -> types.SimpleNamespace:
    """Hand-written adjoints of the rest model's kernels (``kernels``' ``update_deformation``
    and ``rest_variational_forces``) where every material is ``"rest"``, for the total fit
    ``fit`` ("linear" or "curvature_corrected"). Both read the rest moments ``A~^-1`` and
    ``K`` as their forwards do (``Model.rest_moments``): the rest positions are constant (no
    gradient), so only what the positions ``y``, the stress and ``F_p`` feed is taken back.
    The total fit ``G = I + sum_j w_j (u_j - u_i) o_j^T A~^-1`` (``u = y - X``, ``o_j = Xb_j -
    K^T q(Xb_j)``) is linear in ``y`` with the rest weights: ``adj u_j = w_j adj(G) A~^-T o_j``,
    the variational force's pair form (``curvature.variational_forces``, ``forces``' for the
    linear fit) with the map ``-adj(G) A~^-T``. The force's map ``M = V P* F_p^-T A~^-1``
    takes ``curvature``'s ``map_adjoint_sums`` and ``forces``' ``variational_map_adjoint``."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    cf = curvature.funcs(scalar, weight)
    fo = forces.funcs(scalar, weight)
    Materials = materials.struct(scalar)
    rest_total_fit = kernels(scalar, weight).rest_total_fit
    rest_elastic_part = kernels(scalar, weight).rest_elastic_part
    takes_rest_fit = kernels(scalar, weight).takes_rest_fit
    curved = 1 if fit == "curvature_corrected" else 0

    @wp.func
    def inverse_adjoint(M_inv: mat33, adj_M_inv: mat33) -> mat33:
        """Adjoint of ``M^-1`` in ``M``: ``-M^-T adj(M^-1) M^-T``."""
        T_inv = wp.transpose(M_inv)
        return -(T_inv * adj_M_inv * T_inv)

    @wp.kernel(enable_backward=False, module="unique")
    def update_deformation_adjoint(
        rest_x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        rest_guard: wp.array(dtype=wp.int32),
        rest_At_inv: wp.array(dtype=mat33),
        rest_K: wp.array(dtype=mat33),
        Fp: wp.array(dtype=mat33),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        h: scalar,
        adj_F_out: wp.array(dtype=mat33),
        adj_y: wp.array(dtype=vec3),
        adj_F_prev: wp.array(dtype=mat33),
        adj_Fp: wp.array(dtype=mat33),
    ):
        """Adjoint of the rest model's ``F = G(y) F_p^-1`` (``update_deformation`` with every
        deformation code "rest"): ``adj G = adj F F_p^-T``, to the positions as the variational
        force's pairs with ``M = -adj G A~^-T`` (``adjoint_kernels``; no guard fade: a guarded
        rest neighbourhood keeps its ``F`` whole, and all of ``adj F`` goes to the flowed
        ``F``, as where the forward does not take ``G F_p^-1``, ``takes_rest_fit``), and
        ``adj F_p^-1 = G^T adj F`` to ``F_p`` (``inverse_adjoint``)."""
        i = wp.tid()
        G = adj_F_out[i]
        if rest_guard[i] != 0:
            adj_F_prev[i] = adj_F_prev[i] + G
            return
        n = rest_count[i]
        At_inv = rest_At_inv[i]
        K = rest_K[i]
        fit = rest_total_fit(i, rest_x, y, body, rest_nbr, n, h, At_inv, K, wp.static(curved))
        Fp_inv = wp.inverse(Fp[i])
        if not takes_rest_fit(mat, material[i], wp.determinant(rest_elastic_part(fit, Fp[i]))):
            adj_F_prev[i] = adj_F_prev[i] + G
            return
        adj_Fp[i] = adj_Fp[i] + inverse_adjoint(Fp_inv, wp.transpose(fit) * G)
        M = -(G * wp.transpose(Fp_inv) * wp.transpose(At_inv))
        gy_i = vec3()
        if wp.static(curved != 0):
            gy_i = cf.variational_forces(i, rest_x, body, rest_nbr, n, M, K, h, adj_y)
        else:
            gy_i = fo.variational_forces(i, rest_x, body, rest_nbr, n, M, h, adj_y)
        wp.atomic_add(adj_y, i, gy_i)

    @wp.kernel(enable_backward=False, module="unique")
    def rest_variational_forces_adjoint(
        rest_x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        rest_nbr: wp.array2d(dtype=wp.int32),
        rest_count: wp.array(dtype=wp.int32),
        rest_guard: wp.array(dtype=wp.int32),
        rest_At_inv: wp.array(dtype=mat33),
        rest_K: wp.array(dtype=mat33),
        volume: wp.array(dtype=scalar),
        stress: wp.array(dtype=mat33),
        Fp: wp.array(dtype=mat33),
        h: scalar,
        adj_f: wp.array(dtype=vec3),
        adj_stress: wp.array(dtype=mat33),
        adj_Fp: wp.array(dtype=mat33),
    ):
        """Adjoint of ``rest_variational_forces``: its pairs' offsets are the rest ones, so only
        the map ``M = V P* F_p^-T A~^-1`` varies. With ``a_j = adj f_i - adj f_j``, ``adj M =
        S1 - S2 K`` (``curvature``'s ``map_adjoint_sums``; ``K = 0`` for the linear fit), then
        ``variational_map_adjoint`` to ``P*`` and ``F_p^-1``, and ``inverse_adjoint`` to ``F_p``."""
        i = wp.tid()
        m = material[i]
        if mat.deformation[m] != 1 or mat.elastic_force[m] != 1 or rest_guard[i] != 0:
            return
        n = rest_count[i]
        S1, S2 = cf.map_adjoint_sums(i, rest_x, body, rest_nbr, n, h, adj_f)
        Fp_inv = wp.inverse(Fp[i])
        adj_P, adj_Fp_inv, adj_At = fo.variational_map_adjoint(volume[i], stress[i], Fp_inv, rest_At_inv[i],
                                                               S1 - S2 * rest_K[i])
        adj_stress[i] = adj_stress[i] + adj_P
        adj_Fp[i] = adj_Fp[i] + inverse_adjoint(Fp_inv, adj_Fp_inv)

    return types.SimpleNamespace(update_deformation_adjoint=update_deformation_adjoint,
                                 rest_variational_forces_adjoint=rest_variational_forces_adjoint)


def launch_update_deformation(model, state_in, state_out, counters, curved: bool = False,
                              max_condition: float = deformation.guards.MAX_CONDITION,
                              min_neighbors: int = deformation.guards.MIN_NEIGHBORS, mats=None, rest_guard=None,
                              hand_adjoint: bool = True, rest=None):
    """``deformation.launch_update_deformation`` for models with a Fig. 8 comparison material
    (``curved``: the rest model's total fit is the curvature-corrected one; ``rest_guard``: the
    rest neighbourhoods' guard with the thresholds given, ``Model.rest_guard_for``, None: the
    default's; ``rest``: as in ``launch_rest_handover``). Under a ``wp.Tape``, where every
    material runs the rest model (``all_rest``), the backward runs ``adjoint_kernels``'
    ``update_deformation_adjoint`` (``hand_adjoint=False``, or a model mixing deformation
    models: Warp's generated adjoint)."""
    rest_x, rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K = _rest_set(model, rest, rest_guard, curved)
    mat_struct = model.material_arrays() if mats is None else mats
    inputs = [
        state_in.x, state_out.x, rest_x, model.particle_body, state_out.neighbors, state_out.neighbor_count,
        rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K, state_out.guard, model.particle_material,
        mat_struct, state_out.F_flowed,
        state_out.F_p, model.scalar(model.support_radius), int(min_neighbors), model.scalar(max_condition), int(curved),
    ]
    kernel = kernels(model.scalar, model.fit_weight).update_deformation
    tape = recording_tape()
    grads = (state_out.x, state_out.F_flowed, state_out.F_p, state_out.F)
    if tape is None or not hand_adjoint or not all_rest(model, mats) or any(a.grad is None for a in grads):
        model.launches(kernel, model.particle_count, inputs, [state_out.F, counters], device=model.device)
        return
    # Under a tape: the forward unrecorded, and the hand-written adjoint in its place.
    model.launches(kernel, model.particle_count, inputs, [state_out.F, counters], device=model.device, record_tape=False)
    fit = "curvature_corrected" if curved else "linear"

    def adjoint():
        y = state_out.x
        model.launches(
            adjoint_kernels(model.scalar, model.fit_weight, fit).update_deformation_adjoint, model.particle_count,
            [rest_x, y, model.particle_body, rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K, state_out.F_p,
             model.particle_material, mat_struct, model.scalar(model.support_radius), state_out.F.grad, y.grad, state_out.F_flowed.grad,
             state_out.F_p.grad],
            device=model.device, record_tape=False,
        )

    tape.record_func(adjoint, list(grads))


def launch_rest_variational_forces(model, state_out, curved: bool = False, mats=None, rest_guard=None,
                                   hand_adjoint: bool = True, rest=None):
    """``rest_variational_forces`` into ``state_out.force``, from the stress and ``F_p`` the
    constitutive update wrote (launched only when a material asks for it; ``curved``: of the
    curvature-corrected total fit; ``rest_guard``, ``rest``: as in ``launch_update_deformation``).
    Under a ``wp.Tape``, where every material runs the rest model (``all_rest``), the backward
    runs ``adjoint_kernels``' ``rest_variational_forces_adjoint`` (``hand_adjoint=False``, or a
    model mixing deformation models: Warp's generated adjoint)."""
    rest_x, rest_nbr, rest_count, rest_guard, rest_At_inv, rest_K = _rest_set(model, rest, rest_guard, curved)
    mat_struct = model.material_arrays() if mats is None else mats
    S = model.scalar
    inputs = [rest_x, model.particle_body, model.particle_material, mat_struct, rest_nbr, rest_count, rest_guard,
              rest_At_inv, rest_K, model.particle_volume, state_out.stress, state_out.F_p, S(model.support_radius),
              int(curved)]
    kernel = kernels(S, model.fit_weight).rest_variational_forces
    tape = recording_tape()
    grads = (state_out.stress, state_out.F_p, state_out.force)
    if tape is None or not hand_adjoint or not all_rest(model, mats) or any(a.grad is None for a in grads):
        with kept_through_backward(state_out.force):
            model.launches(kernel, model.particle_count, inputs, [state_out.force], device=model.device)
        return
    model.launches(kernel, model.particle_count, inputs, [state_out.force], device=model.device, record_tape=False)
    fit = "curvature_corrected" if curved else "linear"

    def adjoint():
        model.launches(
            adjoint_kernels(S, model.fit_weight, fit).rest_variational_forces_adjoint, model.particle_count,
            # The forward's inputs but the fit, which the adjoint kernel is built for.
            [*inputs[:-1], state_out.force.grad, state_out.stress.grad, state_out.F_p.grad],
            device=model.device, record_tape=False,
        )

    tape.record_func(adjoint, list(grads))


def all_rest(model, mats) -> bool:
    """Whether every material runs the rest model: the rest model switched on (``mats``, the
    rest codes' struct, ``Model.material_arrays(rest=True)``) or every material ``"rest"``.
    Only then do the rest kernels' hand-written adjoints stand in for the generated ones
    (``adjoint_kernels``; a model that mixes deformation models keeps the generated ones)."""
    return mats is not None or all(mt.deformation == "rest" for mt in model.materials)


def _rest_set(model, rest, rest_guard, curved):
    """``(X, neighbours, counts, guard, A~^-1, K)`` a launch reads: ``rest`` (a solver's own
    rest set, ``Solver.rest_set``) or the model's (``Model.rest_neighbors``), with ``rest_guard``
    or the model's default guard, and the moments of the same rest set (``Model.rest_moments``)."""
    rest_x, rest_nbr, rest_count = model.rest_neighbors() if rest is None else rest[:3]
    rest_guard = model.rest_guard if rest_guard is None else rest_guard
    return rest_x, rest_nbr, rest_count, rest_guard, *model.rest_moments(curved, rest)
