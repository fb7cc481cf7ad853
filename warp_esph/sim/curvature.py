"""Curvature-corrected incremental fit (opt-in: ``Solver(model, fit="curvature_corrected")``;
docs/physics.md, "Bending stiffness"; docs/method.md §2).

Where the neighbourhood is one-sided (within h of a free surface) a curved motion leaks
into the linear fit of eqs. 5-6 (``deformation.py``): with ``yb = G xb + (quadratic in xb)``,
the quadratic part's third moments ``sum w xb_x^2 yb`` no longer vanish, and the fit
returns the gradient at the neighbourhood's centroid, inside the body, instead of at the
particle; a bent beam's surface fibres then report too little strain and the beam is too
soft (1.16 x the Timoshenko deflection at 6 particles thick, float64). This fit carries,
besides ``G``, the three mixed quadratic terms ``q(xb) = (xb_x xb_y, xb_x xb_z, xb_y xb_z) / h``
and keeps only ``G``. By the Schur complement it is the paper's fit with ``xb`` replaced
by its part orthogonal to ``q``:

    C = sum_j w_j xb_j q_j^T,  D = sum_j w_j q_j q_j^T,  E = sum_j w_j yb_j q_j^T
    K = (D + eps I)^-1 C^T,  eps = 1e-4 tr(A) / 3
    A~ = A - C K,  B~ = B - E K,  dF = B~ A~^-1

In a neighbourhood symmetric about the particle (the interior of a lattice) ``C = E = 0``:
exactly the paper's fit. Affine motions are still reproduced exactly. ``eps`` keeps ``D``
invertible where a mixed term vanishes on every neighbour (a one-particle-thick sheet).
The correction is dropped (``K = 0``, the paper's fit) where it would leave ``det A~``
below ``CURVATURE_DET_RATIO det A`` (sharp, jittered tips, where ``A~`` is near singular).
The three mixed terms are those of the world axes: a bend in a coordinate plane is
corrected fully, one about a tilted axis in part (the full quadratic basis, which is
rotation invariant, makes ``A~`` singular at every lattice edge at h = 2 dx).

The variational elastic force (``forces.py``) follows the same operator:
``M_i = V_i P*_i F_i^T A~_i^-1``, ``g_ij = w_ij M_i (xb_ij - K_i^T q(xb_ij))``.

The deformation update is ``deformation.update_kernels`` on this module's functions
(``fit_increment``, ``fit_moments``, ``moments_increment``, ``moments_adjoint``): one
kernel and one adjoint for both fits, so the guards, the carried composition and the
floor images' share are written once. The solver runs the corrected fit, non-fused, only
when the option is on. Under a tape both have hand-written adjoints: the deformation
update's ``update_deformation_adjoint``, the variational force's
``variational_forces_adjoint`` (eqs. 10-13's particles use
``forces.elastic_forces_adjoint``); ``Solver.hand_adjoints = False`` runs Warp's generated
ones, which the tests compare them with in float64.

With ``SceneBuilder.add_ground(images=True)`` the floor's images enter the moments as the
linear fit's do (``moment_pair_sums``) and each image's energy is that of its own corrected
fit (``floor_image_moment``, ``image_map``, ``floor_image_forces``; docs/physics.md, "The
ground collider's thin-layer strength").
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import deformation, forces, guards, smoothing
from .replay import kept_through_backward, recording_tape

#: The curvature correction is dropped (the paper's fit kept) where it would leave
#: ``det A~`` below this fraction of ``det A`` (on a lattice it is above 0.4 everywhere).
CURVATURE_DET_RATIO = 0.1

#: The ridge ``eps`` of ``curvature_projection``, relative to ``tr(A) / 3``.
CURVATURE_RIDGE = 1.0e-4

COUNT_FEW_NEIGHBORS = deformation.COUNT_FEW_NEIGHBORS
COUNT_ILL_CONDITIONED = deformation.COUNT_ILL_CONDITIONED
COUNT_BODY = deformation.COUNT_BODY


@functools.cache
def funcs(scalar, weight: str) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    # Divided in Python (float64) and cast once: Warp evaluates arithmetic of Python constants
    # inside a kernel in float32, which a float64 model's ridge would inherit.
    ridge_third = scalar(CURVATURE_RIDGE / 3.0)
    fw = smoothing.fit_weight_funcs(scalar, weight)
    df = deformation.funcs(scalar, weight)
    gf = guards.guard_funcs(scalar)
    variational_map = forces.funcs(scalar, weight).variational_map
    image_energy_share = forces.funcs(scalar, weight).image_energy_share
    image_share_force = forces.funcs(scalar, weight).image_share_force
    moving_image_pair_reactions = forces.funcs(scalar, weight).moving_image_pair_reactions
    image_force_on_particle = forces.funcs(scalar, weight).image_force_on_particle

    @wp.func
    def curvature_basis(d: vec3, h: scalar) -> vec3:
        """``q(xb) = (xb_x xb_y, xb_x xb_z, xb_y xb_z) / h``: the mixed quadratic terms the fit
        carries beside the gradient (module docstring)."""
        return vec3(d[0] * d[1], d[0] * d[2], d[1] * d[2]) / h

    @wp.func
    def pair_moments(xb: vec3, yb: vec3, w: scalar, h: scalar):
        """One pair's terms of ``moment_sums``: ``w xb xb^T``, ``w yb xb^T``, ``w xb q^T``,
        ``w q q^T``, ``w yb q^T`` (``q = curvature_basis(xb)``)."""
        q = curvature_basis(xb, h)
        wxb = w * xb
        wq = w * q
        return wp.outer(wxb, xb), wp.outer(yb, wxb), wp.outer(wxb, q), wp.outer(wq, q), wp.outer(yb, wq)

    @wp.func
    def moment_pair_terms(xb: vec3, yb: vec3, h: scalar, c6: scalar, hh: scalar):
        """One same-body row pair's ``pair_moments`` at the fit's weight ``w(|xb|^2)`` (eqs. 1,
        7; ``c6 = fw.coef(h)``) and what it adds to the few-neighbours guard's smooth count
        (``guards.count_weight``, ``hh = h^2``; rows may reach beyond ``h``: only partners of
        non-zero weight count): ``(w xb xb^T, w yb xb^T, w xb q^T, w q q^T, w yb q^T, c)``.
        Every row sum of the corrected fit adds these, so its sums of the same pairs in the
        same order are the same bits."""
        r2 = wp.dot(xb, xb)
        dA, dB, dC, dD, dE = pair_moments(xb, yb, fw.w_c(r2, h, c6), h)
        c, dc = gf.count_weight(r2, hh)
        return dA, dB, dC, dD, dE, c

    @wp.func
    def moment_pair_sums(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        image: int,
    ):
        """Eqs. 5-7 with the curvature terms: ``A = sum w xb xb^T``, ``C = sum w xb q^T``,
        ``D = sum w q q^T``, the displacement moments ``B - A = sum w ub xb^T`` and ``E - C =
        sum w ub q^T`` and the smooth count of same-body partners (the guard's,
        ``guards.count_weight``), over ``i``'s
        row neighbours (``image`` 0: ``xb = x_j - x_i``, ``ub = u_j - u_i``, ``u = (y - x) +
        (y_lo - x_lo)`` with the positions' round-off, as ``deformation.fit_pair_sums``: exact
        at rest, docs/physics.md, the float32 creep floor) or over the floor's images ``g_j``
        of ``i`` and of its same-body neighbours (``image`` 1: ``xb = g_j - x_i``, ``ub =
        -u_i``, the floor at rest over the step; ``image`` 2: ``ub = J(x_j) u_j - u_i``, the
        images moving with their particles; ``deformation.partner_displacement``). Only the raw sums live in this loop: the
        caller's inverse must not see a loop accumulator (docs/method.md, Warp pitfall 1)."""
        A = mat33()
        B = mat33()
        C = mat33()
        D = mat33()
        E = mat33()
        xi = x[i]
        ui = df.displacement(xi, y[i], x_lo[i], y_lo[i])
        bi = body[i]
        c6 = fw.coef(h)
        hh = h * h
        same = scalar(0.0)
        for k in range(df.pair_slots(xi, n, h, gn, goff, image)):
            j, p = df.pair_partner(i, k, n, nbr, x, gn, goff, gmin, image)
            if body[j] == bi:
                ub = df.partner_displacement(j, x, y, x_lo, y_lo, 0, gn, goff, gmin, image) - ui
                dA, dB, dC, dD, dE, c = moment_pair_terms(p - xi, ub, h, c6, hh)
                A += dA
                B += dB
                C += dC
                D += dD
                E += dE
                same += c
        return A, B, C, D, E, same

    @wp.func
    def moment_sums(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
    ):
        """``moment_pair_sums`` over ``i``'s row neighbours."""
        A, B, C, D, E, same = moment_pair_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, vec3(), scalar(0.0), scalar(0.0),
                                               0)
        return A, B, C, D, E, same

    @wp.func
    def fit_sums(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
    ):
        """``moment_sums``, plus ``moment_pair_sums`` over the floor's images where the model
        has an image plane (``images``)."""
        A, B, C, D, E, same = moment_sums(i, x, y, x_lo, y_lo, body, nbr, n, h)
        if images != 0:
            Ag, Bg, Cg, Dg, Eg, sg = moment_pair_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
            A = A + Ag
            B = B + Bg
            C = C + Cg
            D = D + Dg
            E = E + Eg
            same = same + sg
        return A, B, C, D, E, same

    @wp.func
    def position_moments(
        i: int,
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
    ):
        """``fit_sums`` on ``x`` alone (``y = x``: ``B - A`` and ``E - C`` are 0) without those
        two: ``A``, ``C``, ``D`` and the smooth count, the same terms in the same order (the
        same bits), for the variational force and its adjoint, which read no displacement
        moment: two sums and the displacement's three loads per neighbour fewer
        (docs/performance.md, a few percent of the corrected fit's step)."""
        A = mat33()
        C = mat33()
        D = mat33()
        xi = x[i]
        bi = body[i]
        c6 = fw.coef(h)
        hh = h * h
        same = scalar(0.0)
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                # (The displacement terms, of a zero yb here, are not summed.)
                dA, dB, dC, dD, dE, c = moment_pair_terms(x[j] - xi, vec3(), h, c6, hh)
                A += dA
                C += dC
                D += dD
                same += c
        if images != 0:
            Ag, Bg, Cg, Dg, Eg, sg = moment_pair_sums(i, x, x, x, x, body, nbr, n, h, gn, goff, gmin, 1)
            A = A + Ag
            C = C + Cg
            D = D + Dg
            same = same + sg
        return A, C, D, same

    @wp.func
    def floor_image_moment(
        i: int,
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
    ):
        """``deformation.floor_image_moment`` with the curvature terms: ``A``, ``C``, ``D`` of
        ``i``'s own image ``g_i`` over ``i`` and its same-body neighbours (``xb = x_r - g_i``)
        and their images (``xb = g_r - g_i``)."""
        A = mat33()
        C = mat33()
        D = mat33()
        xi = x[i]
        bi = body[i]
        gi = df.floor_image(xi, gn, goff, gmin)
        c6 = fw.coef(h)
        zero = vec3()
        for k in range(df.image_row_length(xi, n, h, gn, goff)):
            j = df.image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xb = x[j] - gi
                dA, dB, dC, dD, dE = pair_moments(xb, zero, fw.w_c(wp.dot(xb, xb), h, c6), h)
                A += dA
                C += dC
                D += dD
                if j != i:
                    gb = df.floor_image(x[j], gn, goff, gmin) - gi
                    pb = x[j] - xi  # weighed as its particles' pair (deformation.floor_image_moment)
                    dA, dB, dC, dD, dE = pair_moments(gb, zero, fw.w_c(wp.dot(pb, pb), h, c6), h)
                    A += dA
                    C += dC
                    D += dD
        return A, C, D

    @wp.struct
    class ImageSums:
        """``deformation``'s ``ImageSums`` with the curvature term: ``B - A`` and ``E - C``."""
        Bu: mat33
        Eu: mat33

    @wp.func
    def floor_image_displacement_sums(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
    ) -> ImageSums:
        """``deformation.floor_image_displacement_sums`` with the curvature terms: ``Bu = sum
        w ub xb^T``, ``Eu = sum w ub q^T`` of ``i``'s own image ``g_i`` over ``i`` and its
        same-body neighbours (``xb = x_r - g_i``, ``ub = u_r - u_g``: ``u_g`` 0 at rest), for
        moving images (``images`` 2) over their images too (``xb = g_r - g_i``, ``ub = J(x_r) u_r
        - u_g``)."""
        B = mat33()
        E = mat33()
        xi = x[i]
        bi = body[i]
        gi = df.floor_image(xi, gn, goff, gmin)
        ug = df.partner_displacement(i, x, y, x_lo, y_lo, 0, gn, goff, gmin, images)
        c6 = fw.coef(h)
        for k in range(df.image_row_length(xi, n, h, gn, goff)):
            j = df.image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xb = x[j] - gi
                w = fw.w_c(wp.dot(xb, xb), h, c6)
                wu = w * (df.displacement(x[j], y[j], x_lo[j], y_lo[j]) - ug)
                B += wp.outer(wu, xb)
                E += wp.outer(wu, curvature_basis(xb, h))
                if images == 2 and j != i:
                    gb = df.floor_image(x[j], gn, goff, gmin) - gi
                    pb = x[j] - xi
                    wu = fw.w_c(wp.dot(pb, pb), h, c6) * (
                        df.partner_displacement(j, x, y, x_lo, y_lo, 0, gn, goff, gmin, images) - ug)
                    B += wp.outer(wu, gb)
                    E += wp.outer(wu, curvature_basis(gb, h))
        sums = ImageSums()
        sums.Bu = B
        sums.Eu = E
        return sums

    @wp.func
    def floor_image_own_update(
        i: int,
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        code: int,
        scale: scalar,
        sums: ImageSums,
        Fg: mat33,
    ):
        """The image's own eq. 8 by its corrected fit (``deformation.floor_image_own_update``
        with ``corrected_increment`` of its moments ``floor_image_moment`` and displacement
        moments ``sums``): ``Fg + scale inc Fg`` and 1, or ``Fg`` and 0."""
        out = Fg
        applied = int(0)
        if code == 0 and df.image_row_length(x[i], n, h, gn, goff) > 0:
            Ag, Cg, Dg = floor_image_moment(i, x, body, nbr, n, h, gn, goff, gmin)
            out, applied = df.uncompensated_update(Fg, corrected_increment(Ag, sums.Bu, Cg, Dg, sums.Eu), scale)
        return out, applied

    @wp.func
    def curvature_kept(A: mat33, C: mat33, K: mat33) -> bool:
        """Whether the correction ``K`` is kept: where the curvature terms nearly repeat the
        linear ones (few, one-sided neighbours: a sharp tip), ``A~ = A - C K`` is near
        singular, and the paper's fit is used there (``K = 0``)."""
        return wp.determinant(A - C * K) > scalar(CURVATURE_DET_RATIO) * wp.determinant(A)

    @wp.func
    def curvature_basis_adjoint(d: vec3, adj_q: vec3, h: scalar) -> vec3:
        """Adjoint of ``curvature_basis``: ``(dq / d xb)^T adj q``."""
        return vec3(d[1] * adj_q[0] + d[2] * adj_q[1], d[0] * adj_q[0] + d[2] * adj_q[2],
                    d[0] * adj_q[1] + d[1] * adj_q[2]) / h

    @wp.func
    def ridge_inverse(A: mat33, D: mat33) -> mat33:
        """``(D + eps I)^-1``, ``eps = 1e-4 tr(A) / 3`` (``CURVATURE_RIDGE``)."""
        eps = ridge_third * (A[0, 0] + A[1, 1] + A[2, 2])
        return wp.inverse(D + eps * wp.identity(n=3, dtype=scalar))

    @wp.func
    def projection_terms(A: mat33, C: mat33, D: mat33):
        """``curvature_projection``'s ``K``, with ``(D + eps I)^-1`` and whether ``K`` is kept
        (1 or 0), which its adjoint (``projection_adjoint``) needs."""
        D_inv = ridge_inverse(A, D)
        K = D_inv * wp.transpose(C)
        kept = scalar(1.0)
        if not curvature_kept(A, C, K):
            K = mat33()
            kept = scalar(0.0)
        return K, D_inv, kept

    @wp.func
    def curvature_projection(A: mat33, C: mat33, D: mat33) -> mat33:
        """``K = (D + eps I)^-1 C^T``, ``eps = 1e-4 tr(A) / 3``: the curvature terms' share of
        ``xb`` (``xb - K^T q(xb)`` is orthogonal to them in the fit's weights)."""
        K, D_inv, kept = projection_terms(A, C, D)
        return K

    @wp.func
    def projection_adjoint(adj_At: mat33, adj_K: mat33, C: mat33, K: mat33, D_inv: mat33, kept: scalar):
        """Adjoint of ``A~ = A - C K``, ``K = (D + eps I)^-1 C^T`` (``projection_terms``), from
        ``adj A~`` and ``adj K``'s other terms: with ``adj K -= C^T adj A~``,
        ``adj C = -adj A~ K^T + adj K^T Dr^-1``, ``adj D = -Dr^-T adj K K^T`` (``Dr = D + eps I``),
        ``adj A = adj A~ + (eps / tr(A)) tr(adj D) I``. Where the correction is dropped
        (``kept = 0``), ``K = 0`` depends on neither ``C`` nor ``D``. Returns ``adj A, adj C, adj D``."""
        KT = wp.transpose(K)
        adj_K_all = adj_K - wp.transpose(C) * adj_At
        adj_C = -(adj_At * KT) + kept * (wp.transpose(adj_K_all) * D_inv)
        adj_D = -(kept * (wp.transpose(D_inv) * adj_K_all * KT))
        adj_A = adj_At + ridge_third * (adj_D[0, 0] + adj_D[1, 1] + adj_D[2, 2]) * wp.identity(
            n=3, dtype=scalar)
        return adj_A, adj_C, adj_D

    @wp.func
    def corrected_moment(M: mat33, N: mat33, K: mat33) -> mat33:
        """A moment of eqs. 5-6 with the curvature terms projected out (Schur complement):
        ``M - N K`` (``A~ = A - C K``, ``B~ = B - E K``)."""
        return M - N * K

    @wp.func
    def corrected_offset(K: mat33, d: vec3, h: scalar) -> vec3:
        """``xb - K^T q(xb)``: the relative position the corrected fit weighs ``yb`` with
        (``dF = sum_j w_j yb_j (xb_j - K^T q_j)^T A~^-1``)."""
        return d - wp.transpose(K) * curvature_basis(d, h)

    @wp.func
    def corrected_increment(A: mat33, Bu: mat33, C: mat33, D: mat33, Eu: mat33) -> mat33:
        """Eqs. 5-6 with the curvature correction, of the displacement moments ``Bu = B - A``,
        ``Eu = E - C`` (``moment_sums``): ``B~ A~^-1 - I = (Bu - Eu K) A~^-1``."""
        K = curvature_projection(A, C, D)
        return df.affine_fit(corrected_moment(A, C, K), corrected_moment(Bu, Eu, K))

    @wp.func
    def corrected_fit(A: mat33, Bu: mat33, C: mat33, D: mat33, Eu: mat33) -> mat33:
        """Eqs. 5-6 with the curvature correction: ``B~ A~^-1``."""
        return wp.identity(n=3, dtype=scalar) + corrected_increment(A, Bu, C, D, Eu)

    @wp.func
    def step_increment(A: mat33, Bu: mat33, C: mat33, D: mat33, Eu: mat33, code: int, scale: scalar, slot: int,
                       counters: wp.array(dtype=wp.int32)) -> mat33:
        """This step's ``dF - I = B~ A~^-1 - I`` times the guards' fade ``scale``
        (``guards.guard_scale``, on the plain moment matrix ``A`` the guard reads); 0, counted,
        where a guard of paper §4 holds (``code``: ``neighbors.GUARD_*``)."""
        inc = mat33()
        if code == 1 or code == 2:
            deformation.count_guarded(code, slot, counters)
        else:
            inc = scale * corrected_increment(A, Bu, C, D, Eu)
        return inc

    @wp.func
    def variational_pair_force(M: mat33, K: mat33, d: vec3, h: scalar, c6: scalar) -> vec3:
        """``g_ij = w_ij M_i (xb_ij - K_i^T q(xb_ij))`` (``d = xb_ij``, ``M = V P* F^T A~^-1``);
        taken from ``j``, added to ``i``."""
        return fw.w_c(wp.dot(d, d), h, c6) * (M * corrected_offset(K, d, h))

    @wp.func
    def variational_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                           nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, K: mat33, h: scalar,
                           f: wp.array(dtype=vec3)) -> vec3:
        """``forces.variational_forces`` with the corrected fit's pair force."""
        xi = x[i]
        bi = body[i]
        c6 = fw.coef(h)
        fi = vec3()
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                g = variational_pair_force(M, K, x[j] - xi, h, c6)
                wp.atomic_sub(f, j, g)
                fi += g
        return fi

    @wp.func
    def map_adjoint_sums(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                         nbr: wp.array2d(dtype=wp.int32), n: int, h: scalar, adj_f: wp.array(dtype=vec3)):
        """``S1 = sum_j w_j a_j xb_j^T`` and ``S2 = sum_j w_j a_j q_j^T`` over ``i``'s row
        (``a_j = adj f_i - adj f_j``: ``variational_forces`` adds each pair's force to ``i`` and
        takes it from ``j``): the adjoint of its map is ``adj M = S1 - S2 K``, and ``adj K``
        has ``-S2^T M`` (``K = 0``: the linear fit's, ``S1``)."""
        xi = x[i]
        bi = body[i]
        ai = adj_f[i]
        c6 = fw.coef(h)
        S1 = mat33()
        S2 = mat33()
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                d = x[j] - xi
                wa = fw.w_c(wp.dot(d, d), h, c6) * (ai - adj_f[j])
                S1 += wp.outer(wa, d)
                S2 += wp.outer(wa, curvature_basis(d, h))
        return S1, S2

    @wp.func
    def image_map(volume: scalar, P: mat33, F: mat33, A: mat33, C: mat33, D: mat33):
        """``forces.image_map`` of the corrected fit: ``M_g = V P F^T A~_g^-1`` and ``K_g`` of the
        image's own moments (``floor_image_moment``)."""
        K = curvature_projection(A, C, D)
        return variational_map(volume, P, F, wp.inverse(corrected_moment(A, C, K))), K

    @wp.func
    def image_pair_force(M: mat33, K: mat33, gb: vec3, pb: vec3, h: scalar, c6: scalar) -> vec3:
        """``forces.image_pair_force`` with the corrected fit's offset: ``w(|pb|^2) M o(gb)``."""
        return fw.w_c(wp.dot(pb, pb), h, c6) * (M * corrected_offset(K, gb, h))

    @wp.func
    def moving_image_pair_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                                 nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, K: mat33, Mg: mat33, Kg: mat33,
                                 h: scalar, gn: vec3, goff: scalar, gmin: scalar, f: wp.array(dtype=vec3)):
        """``forces.moving_image_pair_forces`` with the corrected fit's pair force (``o = xb -
        K^T q(xb)``; an image-image pair weighed as its particles' pair, ``floor_image_moment``),
        its pairs' reactions routed by ``forces.moving_image_pair_reactions``."""
        xi = x[i]
        bi = body[i]
        c6 = fw.coef(h)
        gi = df.floor_image(xi, gn, goff, gmin)
        fi = vec3()
        fg = vec3()
        for k in range(df.image_row_length(xi, n, h, gn, goff)):
            j = df.image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                gj = df.floor_image(xj, gn, goff, gmin)
                dfi, dfg = moving_image_pair_reactions(
                    i, j, df.floor_image_jacobian(xj, gn, goff, gmin), variational_pair_force(M, K, gj - xi, h, c6),
                    variational_pair_force(Mg, Kg, xj - gi, h, c6), image_pair_force(Mg, Kg, gj - gi, xj - xi, h, c6),
                    f)
                fi += dfi
                fg += dfg
        return fi, fg

    @wp.func
    def moving_image_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                            nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, K: mat33, Mg: mat33, Kg: mat33,
                            h: scalar, gn: vec3, goff: scalar, gmin: scalar, f: wp.array(dtype=vec3)) -> vec3:
        """``forces.moving_image_forces`` with the corrected fit's pair force."""
        fi, fg = moving_image_pair_forces(i, x, body, nbr, n, M, K, Mg, Kg, h, gn, goff, gmin, f)
        return image_force_on_particle(fi, fg, x[i], gn, goff, gmin)

    @wp.func
    def floor_image_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                           nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, K: mat33, Mg: mat33, Kg: mat33,
                           h: scalar, gn: vec3, goff: scalar, gmin: scalar, images: int,
                           f: wp.array(dtype=vec3)) -> vec3:
        """``forces.floor_image_forces`` with the corrected fit's pair force: for images at rest
        (``images`` 1) ``w M o(g_j - x_i)`` on ``i`` for each image in its fit, and ``-w Mg
        o_g(x_r - g_i)`` of its own image's energy on ``i`` and on each same-body neighbour ``r``
        (``o = xb - K^T q(xb)``); for images moving with their particles (2),
        ``moving_image_forces``."""
        fi = vec3()
        if images == 2:
            fi = moving_image_forces(i, x, body, nbr, n, M, K, Mg, Kg, h, gn, goff, gmin, f)
        else:
            xi = x[i]
            bi = body[i]
            c6 = fw.coef(h)
            gi = df.floor_image(xi, gn, goff, gmin)
            for k in range(df.image_row_length(xi, n, h, gn, goff)):
                j = df.image_row_particle(i, k, n, nbr)
                if body[j] == bi:
                    xj = x[j]
                    fi += variational_pair_force(M, K, df.floor_image(xj, gn, goff, gmin) - xi, h, c6)
                    gr = variational_pair_force(Mg, Kg, xj - gi, h, c6)
                    if j == i:
                        fi -= gr
                    else:
                        wp.atomic_sub(f, j, gr)
        return fi

    @wp.func
    def moment_pair_adjoint(xb: vec3, yb: vec3, w: scalar, dw: scalar, h: scalar, adj_A: mat33, adj_A_sym: mat33,
                            adj_B: mat33, adj_C: mat33, adj_D: mat33, adj_D_sym: mat33, adj_E: mat33, adj_r2: scalar):
        """Adjoint of one pair's ``pair_moments`` given the moments' adjoints
        (``adj_A_sym = adj_A + adj_A^T``, likewise ``D``) and of whatever else depends on
        ``|xb|^2`` (``adj_r2``: the guard's count): returns ``(adj xb, adj yb)``; the
        pair depends on ``xb`` through ``w(|xb|^2)`` (``dw = dw / d|xb|^2``), ``xb`` and ``q(xb)``,
        on ``yb`` linearly."""
        q = curvature_basis(xb, h)
        Bx = adj_B * xb
        Eq = adj_E * q
        Cq = adj_C * q
        s = wp.dot(xb, adj_A * xb) + wp.dot(yb, Bx) + wp.dot(xb, Cq) + wp.dot(q, adj_D * q) + wp.dot(yb, Eq)
        # d s / d q (through C, D, E), carried back through q(xb) = (xy, xz, yz) / h.
        aq = wp.transpose(adj_C) * xb + adj_D_sym * q + wp.transpose(adj_E) * yb
        jq = curvature_basis_adjoint(xb, aq, h)
        gx = w * (adj_A_sym * xb + wp.transpose(adj_B) * yb + Cq + jq) + scalar(2.0) * (dw * s + adj_r2) * xb
        return gx, w * (Bx + Eq)

    @wp.func
    def moment_pairs_adjoint(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                             nbr: wp.array2d(dtype=wp.int32), n: int, h: scalar, gn: vec3, goff: scalar, gmin: scalar,
                             image: int, adj_A: mat33, adj_A_sym: mat33, adj_B: mat33, adj_C: mat33, adj_D: mat33,
                             adj_D_sym: mat33, adj_E: mat33, adj_same: scalar, adj_x: wp.array(dtype=vec3),
                             adj_y: wp.array(dtype=vec3), gx_i: vec3, gy_i: vec3):
        """Adjoint of ``moment_pair_sums``' pairs (``image`` as there; ``yb = q - y_i`` with the
        far end ``q`` at the step's end, ``deformation.pair_ends``) given the moments' adjoints and the smooth count's
        (``adj_same``, ``guards.count_weight``): each pair's
        ``moment_pair_adjoint`` scattered to its partner (``deformation.scatter_pair_adjoint``)
        and taken from ``i``'s, ``gx_i``, ``gy_i``, which it returns."""
        xi = x[i]
        yi = y[i]
        bi = body[i]
        c6 = fw.coef(h)
        hh = h * h
        for k in range(df.pair_slots(xi, n, h, gn, goff, image)):
            j, p, q = df.pair_ends(i, k, n, nbr, x, y, gn, goff, gmin, image)
            if body[j] == bi:
                xb = p - xi
                r2 = wp.dot(xb, xb)
                if r2 < hh:
                    w, dw = fw.w_inside(r2, hh, c6)
                    c, dc = gf.count_weight(r2, hh)
                    gx, gy = moment_pair_adjoint(xb, q - yi, w, dw, h, adj_A, adj_A_sym, adj_B, adj_C, adj_D, adj_D_sym,
                                                 adj_E, adj_same * dc)
                    df.scatter_pair_adjoint(adj_x, adj_y, j, x[j], y[j], gx, gy, gn, goff, gmin, image)
                    gx_i -= gx
                    gy_i -= gy
        return gx_i, gy_i

    @wp.func
    def variational_pair_adjoint(d: vec3, a: vec3, w: scalar, dw: scalar, h: scalar, M: mat33, K: mat33,
                                 adj_A: mat33, adj_A_sym: mat33, adj_C: mat33, adj_D: mat33, adj_D_sym: mat33,
                                 adj_r2: scalar) -> vec3:
        """Adjoint in ``d = xb`` of one pair of the corrected variational force: its force
        ``w M o``, ``o = d - K^T q(d)`` (against ``a``, as ``forces.variational_pair_adjoint``),
        its terms in ``A``, ``C``, ``D`` (``adj_A``, ``adj_C``, ``adj_D``; ``a = 0``: the
        moments only) and whatever else depends on ``|d|^2`` (``adj_r2``: the guard's count)."""
        q = curvature_basis(d, h)
        o = d - wp.transpose(K) * q
        adj_o = w * (wp.transpose(M) * a)
        Cq = adj_C * q
        s = wp.dot(d, adj_A * d) + wp.dot(d, Cq) + wp.dot(q, adj_D * q) + wp.dot(a, M * o)
        # d / d q (the moments C, D and the offset o), carried back through q(xb).
        aq = w * (wp.transpose(adj_C) * d + adj_D_sym * q) - K * adj_o
        jq = curvature_basis_adjoint(d, aq, h)
        return w * (adj_A_sym * d + Cq) + jq + adj_o + scalar(2.0) * (dw * s + adj_r2) * d

    @wp.func
    def scatter_variational_pair_adjoint(d: vec3, a: vec3, hh: scalar, c6: scalar, h: scalar, M: mat33, K: mat33,
                                         adj_A: mat33, adj_A_sym: mat33, adj_C: mat33, adj_D: mat33, adj_D_sym: mat33,
                                         adj_same: scalar, adj_x: wp.array(dtype=vec3), j: int, xj: vec3, gn: vec3,
                                         goff: scalar, gmin: scalar, image: int) -> vec3:
        """``variational_pair_adjoint`` of the pair at ``d`` (0 at ``|d|^2 >= hh``, beyond the
        kernel's support; ``adj_same`` the guard's smooth count's, ``guards.count_weight``),
        added to ``adj x_j`` as ``forces.scatter_variational_pair_adjoint``
        (``image`` 1: through ``deformation.floor_image_jacobian``); returned, for the near end."""
        g = vec3()
        r2 = wp.dot(d, d)
        if r2 < hh:
            w, dw = fw.w_inside(r2, hh, c6)
            c, dc = gf.count_weight(r2, hh)
            g = variational_pair_adjoint(d, a, w, dw, h, M, K, adj_A, adj_A_sym, adj_C, adj_D, adj_D_sym, adj_same * dc)
            df.scatter_partner_adjoint(adj_x, j, xj, g, gn, goff, gmin, image)
        return g

    @wp.func
    def scatter_image_pair_adjoint(gb: vec3, pb: vec3, hh: scalar, c6: scalar, h: scalar, M: mat33, a: vec3, K: mat33,
                                   adj_A: mat33, adj_A_sym: mat33, adj_C: mat33, adj_D: mat33, adj_D_sym: mat33,
                                   adj_x: wp.array(dtype=vec3), j: int, xj: vec3, gn: vec3, goff: scalar,
                                   gmin: scalar):
        """Adjoint of an image-image pair's terms in an image's moments (``floor_image_moment``:
        ``gb = g_j - g_i`` weighed by ``w(|pb|^2)``, ``pb = x_j - x_i``) and of its force
        ``image_pair_force`` against ``a`` (``M`` 0 where it has none), as
        ``deformation.scatter_image_pair_adjoint`` with the ``C``, ``D`` terms; returned for
        ``i``: ``(adj g_i, adj x_i)``."""
        gg = vec3()
        gp = vec3()
        r2 = wp.dot(pb, pb)
        if r2 < hh:
            w, dw = fw.w_inside(r2, hh, c6)
            q = curvature_basis(gb, h)
            gg = variational_pair_adjoint(gb, a, w, scalar(0.0), h, M, K, adj_A, adj_A_sym, adj_C, adj_D,
                                          adj_D_sym, scalar(0.0))
            s = (wp.dot(gb, adj_A * gb) + wp.dot(gb, adj_C * q) + wp.dot(q, adj_D * q)
                 + wp.dot(a, M * corrected_offset(K, gb, h)))
            gp = scalar(2.0) * dw * s * pb
            wp.atomic_add(adj_x, j, df.floor_image_jacobian(xj, gn, goff, gmin) * gg + gp)
        return gg, gp

    @wp.func
    def moving_image_pair_adjoint(adj_B: mat33, adj_E: mat33, gb: vec3, pb: vec3, ub: vec3, hh: scalar, c6: scalar,
                                  h: scalar):
        """``deformation``'s ``moving_image_pair_adjoint`` with the curvature term: the adjoint of
        an image-image pair's ``w(|pb|^2) ub gb^T`` in ``Bu`` and ``w ub q(gb)^T`` in ``Eu``
        (``floor_image_displacement_sums``, ``images`` 2): ``(adj gb, adj pb, adj ub)``, the
        second term's as the first's with ``q`` for ``gb``, carried back through ``q(gb)``."""
        gg, gp, gu = df.moving_image_pair_adjoint(adj_B, gb, pb, ub, hh, c6)
        gq, gpq, guq = df.moving_image_pair_adjoint(adj_E, curvature_basis(gb, h), pb, ub, hh, c6)
        return gg + curvature_basis_adjoint(gb, gq, h), gp + gpq, gu + guq

    @wp.func
    def floor_image_own_update_adjoint(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        scale: scalar,
        sums: ImageSums,
        Fg: mat33,
        Gg: mat33,
        adj_x: wp.array(dtype=vec3),
        adj_y: wp.array(dtype=vec3),
    ):
        """Adjoint of ``floor_image_own_update`` where it applied (``Gg`` the gradient of its
        output), as ``deformation.floor_image_own_update_adjoint`` for the corrected fit:
        ``inc0 = (Bu - Eu K) A~^-1`` back into the image's moments (``projection_adjoint``), each pair's
        ``moment_pair_adjoint`` (``xb = x_r - g_i``, ``yb = u_r - u_g``) scattered to ``x``, ``y``,
        the image pairs' ``scatter_image_pair_adjoint`` (and for moving images, ``images`` 2,
        their ``moving_image_pair_adjoint`` and ``u_g``'s), ``g_i``'s to ``x_i`` through
        ``deformation.floor_image_jacobian``; returns ``(adj Fg, adj scale)``."""
        Ag, Cg, Dg = floor_image_moment(i, x, body, nbr, n, h, gn, goff, gmin)
        K, D_inv, kept = projection_terms(Ag, Cg, Dg)
        At_inv = wp.inverse(corrected_moment(Ag, Cg, K))
        inc0 = corrected_moment(sums.Bu, sums.Eu, K) * At_inv
        adj_Bt = scale * (Gg * wp.transpose(Fg)) * wp.transpose(At_inv)
        adj_Bu = adj_Bt
        adj_Eu = -(adj_Bt * wp.transpose(K))
        adj_A, adj_C, adj_D = projection_adjoint(-(wp.transpose(inc0) * adj_Bt), -(wp.transpose(sums.Eu) * adj_Bt), Cg,
                                                 K, D_inv, kept)
        adj_A_sym = adj_A + wp.transpose(adj_A)
        adj_D_sym = adj_D + wp.transpose(adj_D)
        xi = x[i]
        bi = body[i]
        gi = df.floor_image(xi, gn, goff, gmin)
        c6 = fw.coef(h)
        hh = h * h
        gg_i = vec3()
        gx_i = vec3()
        gu_i = vec3()
        # The image's own displacement (the round-off arrays are not differentiated: x for both).
        ug = df.partner_displacement(i, x, y, x, x, 0, gn, goff, gmin, images)
        for k in range(df.image_row_length(xi, n, h, gn, goff)):
            j = df.image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                xb = xj - gi
                r2 = wp.dot(xb, xb)
                if r2 < hh:
                    w, dw = fw.w_inside(r2, hh, c6)
                    gx, gu = moment_pair_adjoint(xb, y[j] - xj - ug, w, dw, h, adj_A, adj_A_sym, adj_Bu, adj_C, adj_D,
                                                 adj_D_sym, adj_Eu, scalar(0.0))
                    wp.atomic_add(adj_y, j, gu)
                    wp.atomic_add(adj_x, j, gx - gu)
                    gg_i -= gx
                    gu_i -= gu
                if j != i:
                    gb = df.floor_image(xj, gn, goff, gmin) - gi
                    gg, gp = scatter_image_pair_adjoint(gb, xj - xi, hh, c6, h, mat33(), vec3(), K, adj_A, adj_A_sym,
                                                        adj_C, adj_D, adj_D_sym, adj_x, j, xj, gn, goff, gmin)
                    gg_i -= gg
                    gx_i -= gp
                    if images == 2:
                        yj = y[j]
                        gg, gp, gu = moving_image_pair_adjoint(adj_Bu, adj_Eu, gb, xj - xi,
                                                               df.mirrored_motion(xj, yj - xj, gn, goff, gmin) - ug,
                                                               hh, c6, h)
                        df.scatter_moving_image_adjoint(adj_x, adj_y, j, xj, yj, gg, gp, gu, gn, goff, gmin)
                        gg_i -= gg
                        gx_i -= gp
                        gu_i -= gu
        if images == 2:
            df.scatter_moving_image_adjoint(adj_x, adj_y, i, xi, y[i], vec3(), vec3(), gu_i, gn, goff, gmin)
        df.scatter_own_adjoint(adj_x, i, xi, gx_i, gg_i, gn, goff, gmin)
        adj_Fg = wp.transpose(wp.identity(n=3, dtype=scalar) + scale * inc0) * Gg
        return adj_Fg, wp.ddot(Gg * wp.transpose(Fg), inc0)

    @wp.func
    def fit_variational_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                               nbr: wp.array2d(dtype=wp.int32), n: int, volume: scalar, P: mat33, F: mat33, Pg: mat33,
                               Fg: mat33, h: scalar, min_neighbors: int, max_condition: scalar, gn: vec3, goff: scalar,
                               gmin: scalar, images: int, f: wp.array(dtype=vec3)) -> vec3:
        """``forces.fit_variational_forces`` with the corrected fit: ``M = V P F^T A~^-1``,
        ``g_ij = w_ij M (xb_ij - K^T q(xb_ij))``; with ``images`` the floor images' terms of the
        corrected fit and its own image's energy (``Mg``, ``Kg`` of ``floor_image_moment``)."""
        # The moments from their own function: the inverses must not see a loop
        # accumulator (docs/method.md, Warp pitfall 1).
        A, C, D, same = position_moments(i, x, body, nbr, n, h, gn, goff, gmin, images)
        K = curvature_projection(A, C, D)
        s = gf.guard_scale(A, same, min_neighbors, max_condition)
        own, img, dc, ddc = image_energy_share(x[i], h, gn, goff, gmin, images)
        M = (s * own) * variational_map(volume, P, F, wp.inverse(corrected_moment(A, C, K)))
        fi = variational_forces(i, x, body, nbr, n, M, K, h, f)
        if images != 0:
            Ag, Cg, Dg = floor_image_moment(i, x, body, nbr, n, h, gn, goff, gmin)
            Mg0, Kg = image_map(volume, Pg, Fg, Ag, Cg, Dg)
            Mg = (s * img) * Mg0
            fi += floor_image_forces(i, x, body, nbr, n, M, K, Mg, Kg, h, gn, goff, gmin, images, f)
            if images == 2:
                fi += image_share_force(volume, s, dc, P, F, Pg, Fg, gn)
        return fi

    # The fit's side of the update kernels (``deformation.update_kernels``), as
    # ``deformation.funcs`` has them for the linear fit.
    @wp.func
    def fit_increment(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                      y_lo: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32), n: int,
                      h: scalar, gn: vec3, goff: scalar, gmin: scalar, images: int, code: int, min_neighbors: int,
                      max_condition: scalar, counters: wp.array(dtype=wp.int32)):
        """This step's guarded ``dF - I = B~ A~^-1 - I`` (``step_increment``) of ``i``'s fit and
        the guards' fade ``scale`` it carries (``guards.guard_scale``, on the plain ``A``)."""
        A, Bu, C, D, Eu, same = fit_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
        scale = gf.guard_scale(A, same, min_neighbors, max_condition)
        return step_increment(A, Bu, C, D, Eu, code, scale, COUNT_BODY + body[i], counters), scale

    @wp.struct
    class FitMoments:
        """One particle's sums of ``fit_sums``: ``A``, ``B - A``, ``C``, ``D``, ``E - C`` and
        the smooth same-body count."""
        A: mat33
        Bu: mat33
        C: mat33
        D: mat33
        Eu: mat33
        same: scalar

    @wp.func
    def fit_moments(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                    y_lo: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32), n: int,
                    h: scalar, gn: vec3, goff: scalar, gmin: scalar, images: int) -> FitMoments:
        """``fit_sums`` as one value, for the adjoint kernel."""
        A, Bu, C, D, Eu, same = fit_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
        m = FitMoments()
        m.A = A
        m.Bu = Bu
        m.C = C
        m.D = D
        m.Eu = Eu
        m.same = same
        return m

    @wp.func
    def moments_increment(m: FitMoments) -> mat33:
        """The unguarded ``dF - I`` of the moments (``corrected_increment``)."""
        return corrected_increment(m.A, m.Bu, m.C, m.D, m.Eu)

    @wp.func
    def moments_adjoint(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                        nbr: wp.array2d(dtype=wp.int32), n: int, h: scalar, gn: vec3, goff: scalar, gmin: scalar,
                        images: int, m: FitMoments, inc0: mat33, adj_inc0: mat33, adj_A_fade: mat33, adj_same: scalar,
                        adj_x: wp.array(dtype=vec3), adj_y: wp.array(dtype=vec3)):
        """Adjoint of ``moments_increment`` and of the sums, given the gradient of ``inc0``
        and the fade's own ``adj A`` and ``adj same``. With ``K = (D + eps I)^-1 C^T``, ``A~ =
        A - C K``, ``B~ = B - E K``: ``adj B~ = adj inc0 A~^-T``, ``adj A~ = -(I + inc0)^T
        adj B~``; ``adj B = adj B~``, ``adj E = -adj B~ K^T``, and ``projection_adjoint`` takes
        ``adj A~`` and ``adj K = -E^T adj B~`` to ``adj A``, ``adj C``, ``adj D`` (``B = Bu +
        A``, ``E = Eu + C``, the same functions of the positions). Per pair the sums depend on
        ``xb`` through ``w(|xb|^2)``, ``xb`` and ``q(xb)``, and on ``yb`` linearly
        (``moment_pairs_adjoint``), over the row and the floor's images. Returns what goes to
        ``x_i``, ``y_i``."""
        K, D_inv, kept = projection_terms(m.A, m.C, m.D)
        At = corrected_moment(m.A, m.C, K)
        E = m.Eu + m.C
        adj_Bt = adj_inc0 * wp.transpose(wp.inverse(At))
        adj_At = -((wp.identity(n=3, dtype=scalar) + wp.transpose(inc0)) * adj_Bt)
        adj_B = adj_Bt
        adj_E = -(adj_Bt * wp.transpose(K))
        adj_A, adj_C, adj_D = projection_adjoint(adj_At, -(wp.transpose(E) * adj_Bt), m.C, K, D_inv, kept)
        adj_A = adj_A + adj_A_fade
        adj_A_sym = adj_A + wp.transpose(adj_A)
        adj_D_sym = adj_D + wp.transpose(adj_D)
        gx_i, gy_i = moment_pairs_adjoint(i, x, y, body, nbr, n, h, gn, goff, gmin, 0, adj_A, adj_A_sym, adj_B, adj_C,
                                          adj_D, adj_D_sym, adj_E, adj_same, adj_x, adj_y, vec3(), vec3())
        if images != 0:
            gx_i, gy_i = moment_pairs_adjoint(i, x, y, body, nbr, n, h, gn, goff, gmin, images, adj_A, adj_A_sym, adj_B,
                                              adj_C, adj_D, adj_D_sym, adj_E, adj_same, adj_x, adj_y, gx_i, gy_i)
        return gx_i, gy_i

    return types.SimpleNamespace(
        pair_moments=pair_moments, moment_pair_terms=moment_pair_terms, moment_pair_sums=moment_pair_sums, fit_sums=fit_sums,
        position_moments=position_moments,
        fit_variational_forces=fit_variational_forces, fit_increment=fit_increment, FitMoments=FitMoments, fit_moments=fit_moments, moments_increment=moments_increment,
        moments_adjoint=moments_adjoint, carried_update=df.carried_update,
        ImageSums=ImageSums, floor_image_displacement_sums=floor_image_displacement_sums,
        floor_image_own_update=floor_image_own_update, floor_image_own_update_adjoint=floor_image_own_update_adjoint,
        scatter_image_pair_adjoint=scatter_image_pair_adjoint,
        moment_pairs_adjoint=moment_pairs_adjoint,
        floor_image_moment=floor_image_moment, image_map=image_map, floor_image_forces=floor_image_forces,
        image_pair_force=image_pair_force,
        moment_pair_adjoint=moment_pair_adjoint, variational_pair_adjoint=variational_pair_adjoint,
        scatter_variational_pair_adjoint=scatter_variational_pair_adjoint,
        curvature_basis=curvature_basis, curvature_basis_adjoint=curvature_basis_adjoint, moment_sums=moment_sums,
        map_adjoint_sums=map_adjoint_sums,
        curvature_kept=curvature_kept, ridge_inverse=ridge_inverse, projection_terms=projection_terms,
        curvature_projection=curvature_projection, projection_adjoint=projection_adjoint,
        corrected_moment=corrected_moment, corrected_offset=corrected_offset, corrected_increment=corrected_increment,
        corrected_fit=corrected_fit, step_increment=step_increment, variational_pair_force=variational_pair_force,
        variational_forces=variational_forces,
    )


@functools.cache
def kernels(scalar, weight: str) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    fw = smoothing.fit_weight_funcs(scalar, weight)
    df = deformation.funcs(scalar, weight)
    fo = forces.funcs(scalar, weight)
    fn = funcs(scalar, weight)
    gf = guards.guard_funcs(scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def variational_forces_adjoint(
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        elastic_force: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        volume: wp.array(dtype=scalar),
        stress: wp.array(dtype=mat33),
        F: wp.array(dtype=mat33),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        image_stress: wp.array(dtype=mat33),
        F_image: wp.array(dtype=mat33),
        adj_f: wp.array(dtype=vec3),
        adj_x: wp.array(dtype=vec3),
        adj_stress: wp.array(dtype=mat33),
        adj_F: wp.array(dtype=mat33),
        adj_image_stress: wp.array(dtype=mat33),
        adj_F_image: wp.array(dtype=mat33),
    ):
        """Hand-written adjoint of ``elastic_forces``' variational force (as
        ``forces.variational_forces_adjoint`` for the linear fit; eqs. 10-13's particles are
        ``forces.elastic_forces_adjoint``'s).

        With ``a_j = adj f_i - adj f_j`` (``g_j = w_j M o_j``, ``o_j = xb_j - K^T q_j``, added
        to ``i``, taken from ``j``) and ``M = V P F^T A~^-1``: ``adj M = sum_j w_j a_j o_j^T``,
        ``adj o_j = w_j M^T a_j``, ``adj K = -sum_j q_j adj o_j^T``; ``adj P = V adj M A~^-T F``,
        ``adj F = V A~^-1 adj M^T P``, ``adj A~ = -A~^-T (V F P^T adj M) A~^-T``; then through
        ``A~ = A - C K`` and ``K = (D + eps I)^-1 C^T`` as ``update_deformation_adjoint``.
        Per pair ``A``, ``C``, ``D`` depend on ``xb`` through ``w(|xb|^2)``, ``xb`` and
        ``q(xb)``; ``o_j`` through ``xb`` and ``q`` (``variational_pair_adjoint``). Guarded
        particles apply no force. With ``images`` (``floor_image_forces``) as the linear fit's
        (``forces.variational_forces_adjoint``): the image pairs of the fit with ``a = adj f_i``,
        the own image's energy (``Mg``, ``Kg`` of ``floor_image_moment``) with ``a = -adj f_r``
        on ``d = x_r - g_i`` and the image-image terms ``d = g_r - g_i``, weighed by their
        particles' pair (``scatter_image_pair_adjoint``); for moving images as the linear fit's
        (``forces.image_pair_adjoint_vectors``, the image-image pairs' forces, the energies'
        share and ``J``'s slope)."""
        i = wp.tid()
        if elastic_force[material[i]] != 1 or guard[i] != 0:
            return
        xi = x[i]
        bi = body[i]
        ai = adj_f[i]
        n = count[i]
        c6 = fw.coef(h)
        hh = h * h
        A, C, D, same = fn.position_moments(i, x, body, nbr, n, h, gn, goff, gmin, images)
        # adj M = S1 - S2 K and adj K = -S2^T M (which need K and M); the same for the own
        # image's Mg, Kg (S1g, S2g).
        S1, S2 = fn.map_adjoint_sums(i, x, body, nbr, n, h, adj_f)
        n_img = df.image_slots(xi, n, h, gn, goff, images)
        gi = df.floor_image(xi, gn, goff, gmin)
        S1g = mat33()
        S2g = mat33()
        for k in range(n_img):
            j = df.image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                gj = df.floor_image(xj, gn, goff, gmin)
                a1, ar, ag = fo.image_pair_adjoint_vectors(ai, adj_f[j], xi, xj, gn, goff, gmin, images)
                d = gj - xi
                wa = fw.w_c(wp.dot(d, d), h, c6) * a1
                S1 += wp.outer(wa, d)
                S2 += wp.outer(wa, fn.curvature_basis(d, h))
                d = xj - gi
                wa = fw.w_c(wp.dot(d, d), h, c6) * ar
                S1g += wp.outer(wa, d)
                S2g += wp.outer(wa, fn.curvature_basis(d, h))
                if images == 2 and j != i:
                    d = gj - gi
                    pb = xj - xi
                    wa = fw.w_c(wp.dot(pb, pb), h, c6) * ag
                    S1g += wp.outer(wa, d)
                    S2g += wp.outer(wa, fn.curvature_basis(d, h))
        K, D_inv, kept = fn.projection_terms(A, C, D)
        Ainv = wp.inverse(fn.corrected_moment(A, C, K))
        Vi = volume[i]
        P = stress[i]
        Fi = F[i]
        # The fade s(A, same) of both maps (guards.guard) and the energies' shares
        # (forces.image_energy_share): M = s (1 - c) M0, Mg = s c Mg0.
        code_, s, ds_dA, ds_dn = gf.guard(A, same, min_neighbors, max_condition)
        own, img, dc, ddc = fo.image_energy_share(xi, h, gn, goff, gmin, images)
        so = s * own
        M0 = fo.variational_map(Vi, P, Fi, Ainv)
        M = so * M0
        adj_M = S1 - S2 * K
        adj_P, adj_Fi, adj_At = fo.variational_map_adjoint(Vi, P, Fi, Ainv, so * adj_M)
        adj_M0 = wp.ddot(adj_M, M0)
        adj_s = own * adj_M0
        adj_A, adj_C, adj_D = fn.projection_adjoint(adj_At, -(wp.transpose(S2) * M), C, K, D_inv, kept)
        adj_D_sym = adj_D + wp.transpose(adj_D)
        Mg = mat33()
        Kg = mat33()
        adj_Ag = mat33()
        adj_Cg = mat33()
        adj_Dg = mat33()
        gx_i = vec3()
        if n_img > 0:
            sg = s * img
            Ag, Cg, Dg = fn.floor_image_moment(i, x, body, nbr, n, h, gn, goff, gmin)
            Kg_, Dg_inv, kept_g = fn.projection_terms(Ag, Cg, Dg)
            Ag_inv = wp.inverse(fn.corrected_moment(Ag, Cg, Kg_))
            Pg = image_stress[i]
            Fg = F_image[i]
            Mg0 = fo.variational_map(Vi, Pg, Fg, Ag_inv)
            Mg_ = sg * Mg0
            adj_Mg = S1g - S2g * Kg_
            adj_Pg_, adj_Fg_, adj_Agt = fo.variational_map_adjoint(Vi, Pg, Fg, Ag_inv, sg * adj_Mg)
            adj_s, gx_i, adj_P, adj_Fi, adj_Pg, adj_Fg = fo.image_shares_adjoint(
                Vi, s, img, dc, ddc, P, Fi, Pg, Fg, gn, ai, adj_M0, adj_Mg, Mg0, images, adj_s, adj_P, adj_Fi, adj_Pg_,
                adj_Fg_)
            adj_image_stress[i] = adj_image_stress[i] + adj_Pg
            adj_F_image[i] = adj_F_image[i] + adj_Fg
            adj_Ag_, adj_Cg_, adj_Dg_ = fn.projection_adjoint(adj_Agt, -(wp.transpose(S2g) * Mg_), Cg, Kg_, Dg_inv,
                                                              kept_g)
            Mg = Mg_
            Kg = Kg_
            adj_Ag = adj_Ag_
            adj_Cg = adj_Cg_
            adj_Dg = adj_Dg_
        adj_A = adj_A + adj_s * ds_dA
        adj_A_sym = adj_A + wp.transpose(adj_A)
        adj_Ag_sym = adj_Ag + wp.transpose(adj_Ag)
        adj_Dg_sym = adj_Dg + wp.transpose(adj_Dg)
        adj_same = adj_s * ds_dn
        adj_stress[i] = adj_stress[i] + adj_P
        adj_F[i] = adj_F[i] + adj_Fi
        # The scatter to the positions.
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                xj = x[j]
                gx_i -= fn.scatter_variational_pair_adjoint(xj - xi, ai - adj_f[j], hh, c6, h, M, K, adj_A, adj_A_sym,
                                                            adj_C, adj_D, adj_D_sym, adj_same, adj_x, j, xj, gn, goff,
                                                            gmin, 0)
        # Through g_i (summed, then by d g_i / d x_i).
        gg_i = vec3()
        for k in range(n_img):
            j = df.image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                aj = adj_f[j]
                gj = df.floor_image(xj, gn, goff, gmin)
                a1, ar, ag = fo.image_pair_adjoint_vectors(ai, aj, xi, xj, gn, goff, gmin, images)
                gx_i -= fn.scatter_variational_pair_adjoint(gj - xi, a1, hh, c6, h, M, K, adj_A, adj_A_sym, adj_C,
                                                            adj_D, adj_D_sym, adj_same, adj_x, j, xj, gn, goff, gmin, 1)
                # (The own image's moments are not the fit's: they do not count.)
                gg_i -= fn.scatter_variational_pair_adjoint(xj - gi, ar, hh, c6, h, Mg, Kg, adj_Ag, adj_Ag_sym,
                                                            adj_Cg, adj_Dg, adj_Dg_sym, scalar(0.0), adj_x, j, xj, gn,
                                                            goff, gmin, 0)
                Mp = mat33()  # the image-image pair's force map: moving images' alone
                if images == 2:
                    Mp = Mg
                if j != i:
                    gg, gp = fn.scatter_image_pair_adjoint(gj - gi, xj - xi, hh, c6, h, Mp, ag, Kg, adj_Ag, adj_Ag_sym,
                                                           adj_Cg, adj_Dg, adj_Dg_sym, adj_x, j, xj, gn, goff, gmin)
                    gg_i -= gg
                    gx_i -= gp
                if images == 2:
                    gg = vec3()
                    if j != i:
                        gg = fn.image_pair_force(Mg, Kg, gj - gi, xj - xi, h, c6)
                    g = fn.variational_pair_force(M, K, gj - xi, h, c6)
                    gr = fn.variational_pair_force(Mg, Kg, xj - gi, h, c6)
                    gx_i += fo.moving_image_pair_slopes(j, xi, xj, ai, aj, g, gr, gg, gn, goff, gmin, adj_x)
        df.scatter_own_adjoint(adj_x, i, xi, gx_i, gg_i, gn, goff, gmin)

    # Eq. 8's update and its adjoint are the linear fit's kernels on this fit's functions
    # (as the elastic forces are: forces.elastic_kernels).
    update = deformation.update_kernels(scalar, weight, "curvature_corrected")
    return types.SimpleNamespace(update_deformation=update.update_deformation,
                                 update_deformation_adjoint=update.update_deformation_adjoint,
                                 variational_forces_adjoint=variational_forces_adjoint)


def launch_elastic_forces(model, state_in, state_out, hand_adjoint: bool = True,
                          max_condition: float = guards.MAX_CONDITION, min_neighbors: int = guards.MIN_NEIGHBORS):
    """``forces.launch_elastic_forces`` with the corrected fit's variational force. Under a
    tape the backward runs ``variational_forces_adjoint`` and, for the particles of eqs.
    10-13, ``forces.elastic_forces_adjoint`` (``hand_adjoint=False``: Warp's generated one)."""
    S = model.scalar
    kernel = forces.elastic_kernels(S, model.fit_weight, "curvature_corrected").elastic_forces
    inputs = forces.elastic_force_inputs(model, state_in, state_out, max_condition, min_neighbors)
    tape = recording_tape()
    grads = (state_in.x, state_out.stress, state_out.F_flowed, state_out.F_inv, state_out.force)
    if model.image_plane is not None:
        grads += (state_out.image_stress, state_out.F_image_flowed)
    if tape is None or not hand_adjoint or any(a.grad is None for a in grads):
        with kept_through_backward(state_out.force):
            model.launches(kernel, model.particle_count, inputs, [state_out.force], device=model.device)
        return
    model.launches(kernel, model.particle_count, inputs, [state_out.force], device=model.device, record_tape=False)

    def adjoint():
        model.launches(
            kernels(S, model.fit_weight).variational_forces_adjoint, model.particle_count,
            [state_in.x, model.particle_body, model.particle_material, model.material_elastic_force,
             state_out.neighbors, state_out.neighbor_count, state_out.guard, model.particle_volume, state_out.stress,
             state_out.F_flowed, S(model.support_radius), int(min_neighbors), S(max_condition), *model.image_args(),
             *forces.image_constitutive(model, state_out), state_out.force.grad, state_in.x.grad,
             state_out.stress.grad, state_out.F_flowed.grad,
             *(a.grad for a in forces.image_constitutive(model, state_out))],
            device=model.device, record_tape=False,
        )
        forces.launch_elastic_forces_adjoint(model, state_in, state_out)

    tape.record_func(adjoint, list(grads))
