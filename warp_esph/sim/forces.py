"""Stress (paper eq. 9, docs/method.md §5) and elastic pair forces (eqs. 10-13).

Stress, in the SVD frame ``F = U diag(sigma) V^T``:

    P^ = 2 mu (sigma - 1) + lam sum(sigma - 1)                    (eq. 9)
    P* = U diag(sigma o P^) V^T                                   (U F^ P^ V^T of eq. 10)

and the variants: a ``linear`` or ``non_newtonian`` material on the variational force that
cannot flow takes the corotated stress ``P = U diag(P^) V^T`` (``corotated_stress``: eq. 9
is the gradient of no energy beyond small strain, and that force must be one's);
``hyperelastic`` squares the singular values first (paper Fig. 5),
``P* = 2 mu (F F^T F - F) + lam (tr F^T F - 3) F`` (twice St. Venant-Kirchhoff), and
``stvk`` is half of that, whose small-strain stiffness equals the linear model's.

Pair forces, with ``r_ij = F_i^-1 (x_j - x_i)`` back-projected to reference space (eq. 11)
and ``grad W`` the gradient of Solenthaler's kernel (eqs. 12-13):

    g_ij = 2 V_i V_j P*_i grad W(r_ij),   f_j += ½ g_ij,   f_i -= ½ g_ij

The paper prints eq. 10 with a minus sign on ``y_j - y_i``, which pushes stretched
particles apart; this is the restoring sign (docs/method.md §5). Averaging ("equal and opposite")
makes linear momentum exact to round-off. Only particles of the same body interact
elastically; bodies meet through SPH pressure and colliders.

``Material(elastic_force="variational")`` replaces eqs. 10-13 by minus the gradient of the
elastic energy ``E = sum_i V_i psi(F_i)`` of the incremental fit (``deformation.py``):
within a step ``F_i = dF_i(y) F_i`` with ``dF_i = B_i A_i^-1`` linear in the end positions
``y``, so at the step's start (``dF = I``)

    M_i = V_i P*_i F_i^T A_i^-1,   g_ij = w_ij M_i xb_ij,   f_j -= g_ij,   f_i += g_ij

with ``w_ij`` and ``A_i`` the fit's own weights (``Model.fit_weight``) and moment matrix. Its linear
stiffness is ``sum_i V_i G_i^T C G_i`` (``G_i`` the fit's gradient operator): symmetric,
so an undamped body cannot gain energy by flutter, which eqs. 10-13 (a different weight
in the force than in the fit) allow. A particle whose fit is guarded (too few
neighbours, ill-conditioned ``A``) keeps its ``F`` whatever the positions do, so its
energy has no gradient and it applies no elastic force.
"""

import functools
import types

import warp as wp

from .._types import type_set
from .. import checks
from ..material import MODELS
from . import deformation, guards, isotropic, materials, neighbors, pressure, smoothing
from .replay import kept_through_backward, recording_tape


#: ``stress_model``'s code for ``corotated_stress``, past ``material.MODELS``' indices.
COROTATED = len(MODELS)


@functools.cache
def funcs(scalar, weight: str) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    iso = isotropic.funcs(scalar)
    sm = smoothing.funcs(scalar)
    fw = smoothing.fit_weight_funcs(scalar, weight)
    gf = guards.guard_funcs(scalar)
    floor_image = deformation.funcs(scalar, weight).floor_image
    scatter_partner_adjoint = deformation.funcs(scalar, weight).scatter_partner_adjoint
    image_row_length = deformation.funcs(scalar, weight).image_row_length
    image_slots = deformation.funcs(scalar, weight).image_slots
    image_row_particle = deformation.image_row_particle
    Materials = materials.struct(scalar)

    @wp.func
    def principal_strain_trace(s: vec3) -> scalar:
        """``sum(s - 1)``, the trace of ``F^ - I`` that eq. 9's ``lam`` term scales."""
        return s[0] + s[1] + s[2] - scalar(3.0)

    @wp.func
    def corotated_principal_stress(s: vec3, mu: scalar, lam: scalar) -> vec3:
        """The principal values ``P^ = 2 mu (s - 1) + lam sum(s - 1)`` of ``corotated_stress``:
        the gradient in ``s`` of ``psi = mu sum(s - 1)^2 + lam/2 (sum(s - 1))^2``; also eq. 9's
        ``P^``, which ``principal_stress`` scales by ``s``."""
        tr = principal_strain_trace(s)
        one = vec3(scalar(1.0), scalar(1.0), scalar(1.0))
        return scalar(2.0) * mu * (s - one) + lam * tr * one

    @wp.func
    def principal_stress(s: vec3, mu: scalar, lam: scalar) -> vec3:
        """Eq. 9 in the SVD frame: the principal values ``sigma o P^`` of ``P* = U F^ P^ V^T``,
        ``P^ = 2 mu (sigma - 1) + lam sum(sigma - 1)`` (``corotated_principal_stress``)."""
        return wp.cw_mul(s, corotated_principal_stress(s, mu, lam))

    @wp.func
    def principal_stress_differences(s: vec3, mu: scalar, lam: scalar) -> vec3:
        """Divided differences ``(f_i - f_j)/(s_i - s_j)`` of ``principal_stress`` (pairs
        01, 02, 12) for the adjoint of ``isotropic_map``: ``2 mu (s_i + s_j - 1) + lam tr``,
        exact, also at ``s_i = s_j``."""
        tr = principal_strain_trace(s)
        return vec3(
            scalar(2.0) * mu * (s[0] + s[1] - scalar(1.0)) + lam * tr,
            scalar(2.0) * mu * (s[0] + s[2] - scalar(1.0)) + lam * tr,
            scalar(2.0) * mu * (s[1] + s[2] - scalar(1.0)) + lam * tr,
        )

    @wp.func
    def corotated_stress(F: mat33, mu: scalar, lam: scalar) -> mat33:
        """``P = U diag(P^) V^T``, the gradient in ``F`` of the corotated energy
        ``psi = mu sum(s - 1)^2 + lam/2 (sum(s - 1))^2`` (``s`` the rotation-variant singular
        values, so ``psi`` is smooth and restoring through det ``F`` = 0; it has a crease, and
        ``P`` a jump, where an inverted ``F`` has two singular values of one size, ``s_j = -s_i``:
        docs/method.md, "Stable adjoints of the SVD maps"): the first Piola
        stress with eq. 9's small-strain limit that the variational force of a material that
        cannot flow takes (``stress_model``). Eq. 9's ``P* = U diag(s o P^) V^T`` is the gradient
        of no energy beyond small strain (``d(s_k P^_k)/ds_j = lam s_k`` is not symmetric),
        which let a conservative scheme gain energy. The divided differences of ``P^`` are
        ``2 mu`` for every pair, exact also at repeated singular values."""
        s = iso.singular_values(F)
        two_mu = scalar(2.0) * mu
        return iso.isotropic_map(F, corotated_principal_stress(s, mu, lam), vec3(two_mu, two_mu, two_mu))

    @wp.func
    def cannot_flow_variational(mat: Materials, m: int) -> bool:
        """Whether material ``m`` takes the variational force and cannot flow (``yield_stress
        = inf`` or ``flow_rate <= 0``): its elastic force is minus the gradient of an energy,
        so its stress must be one's (``stress_model``); the rest model that ``fit="auto"``
        runs, and whose inverted fit is taken (``comparison.continues_inverted``)."""
        return mat.elastic_force[m] == 1 and (mat.flow_rate[m] <= scalar(0.0) or wp.isinf(mat.yield_stress[m]))

    @wp.func
    def stress_model(mat: Materials, m: int) -> int:
        """The stress ``stress`` computes for material ``m``: its model (``material.MODELS``),
        but ``COROTATED`` for a linear or non-Newtonian one that ``cannot_flow_variational``
        (eq. 9's stress is no energy's gradient; ``corotated_stress``). Materials that can
        flow keep the paper's stress. The choice jumps where ``flow_rate`` leaves 0 or
        ``yield_stress`` leaves inf (by about the strain squared at finite strain), which no
        gradient sees: a fit of ``flow_rate`` started at 0 gets none from it."""
        k = mat.model[m]
        if k <= 1 and cannot_flow_variational(mat, m):
            k = COROTATED
        return k

    @wp.func
    def polynomial_stress(F: mat33, mu: scalar, lam: scalar, model: int) -> mat33:
        """Eq. 9 with squared singular values (paper Fig. 5), a polynomial in ``F``:
        ``2 mu (F F^T F - F) + lam (tr F^T F - 3) F`` for ``hyperelastic`` (model 2),
        half of it (St. Venant-Kirchhoff) for ``stvk`` (model 3)."""
        scale = wp.where(model == 2, scalar(1.0), scalar(0.5))
        C = wp.transpose(F) * F
        tr = C[0, 0] + C[1, 1] + C[2, 2]
        return scale * (scalar(2.0) * mu * (F * C - F) + lam * (tr - scalar(3.0)) * F)

    @wp.func
    def stress(F: mat33, mu: scalar, lam: scalar, model: int) -> mat33:
        """P* for material model ``model`` (index into ``material.MODELS``, or ``COROTATED``:
        ``stress_model``), differentiable: eq. 9 through ``isotropic_map`` (its adjoint stable
        at repeated singular values)."""
        if model == COROTATED:
            return corotated_stress(F, mu, lam)
        if model >= 2:
            return polynomial_stress(F, mu, lam, model)
        s = iso.singular_values(F)
        return iso.isotropic_map(F, principal_stress(s, mu, lam), principal_stress_differences(s, mu, lam))

    @wp.func
    def elastic_pair_force(VV: scalar, P: mat33, F_inv: mat33, d: vec3, h: scalar, c_el: scalar) -> vec3:
        """Eqs. 10-13: ``½ g_ij = V_i V_j P*_i grad W(F_i^-1 (x_j - x_i))`` for ``VV = V_i V_j``,
        ``d = x_j - x_i``, ``c_el = elastic_coef(h)``; it is added to ``j`` and taken from ``i``."""
        return VV * (P * sm.grad_w_elastic_c(F_inv * d, h, c_el))

    @wp.func
    def paper_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32),
                     n: int, volume: wp.array(dtype=scalar), P: mat33, F_inv: mat33, h: scalar,
                     f: wp.array(dtype=vec3)) -> vec3:
        """Eqs. 10-13 over particle ``i``'s row (``n`` neighbours, same body only): adds
        ``½ g_ij`` to ``f_j`` and returns ``i``'s share, ``-sum_j ½ g_ij``."""
        xi = x[i]
        bi = body[i]
        Vi = volume[i]
        c_el = sm.elastic_coef(h)
        fi = vec3()
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                g = elastic_pair_force(Vi * volume[j], P, F_inv, x[j] - xi, h, c_el)
                wp.atomic_add(f, j, g)
                fi -= g
        return fi

    @wp.func
    def elastic_pair_adjoint(VV: scalar, adj_g: vec3, P: mat33, F_inv: mat33, d: vec3, h: scalar, c_el: scalar):
        """Adjoint of ``elastic_pair_force`` (``g = VV P gradW(F^-1 d)``) given ``adj_g``: returns
        ``(adj P, adj F^-1, adj d)`` = ``(a gradW^T, adj_r d^T, F^-T adj_r)`` with ``a = VV adj_g``,
        ``adj_r = J^T P^T a`` (``smoothing.grad_w_elastic_adjoint``)."""
        a = VV * adj_g
        gw, ar = sm.grad_w_elastic_adjoint(F_inv * d, h, c_el, wp.transpose(P) * a)
        return wp.outer(a, gw), wp.outer(ar, d), wp.transpose(F_inv) * ar

    @wp.func
    def paper_image_count(xi: vec3, F: mat33, n: int, h: scalar, gn: vec3, goff: scalar, images: int) -> int:
        """How many of ``i``'s row (and ``i``) ``paper_image_forces`` visits: all ``n + 1`` where
        an image may be within the kernel's reach, ``|F^-1 d| < h`` (``|d| < h sigma_max(F)
        <= h |F|_F``; every image is at least as far from ``x_i`` as ``x_i`` is from the plane),
        else (or without an image plane, ``images`` 0) none."""
        # Kept apart from the other image loops' reach h: eqs. 10-13 weigh the
        # back-projected F^-1 d, so a stretched particle reaches images beyond h.
        return image_slots(xi, n, h * wp.sqrt(wp.ddot(F, F)), gn, goff, images)

    @wp.func
    def paper_image_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                           nbr: wp.array2d(dtype=wp.int32), n: int, volume: wp.array(dtype=scalar), P: mat33,
                           F: mat33, F_inv: mat33, h: scalar, gn: vec3, goff: scalar, gmin: scalar,
                           f: wp.array(dtype=vec3)) -> vec3:
        """Eqs. 10-13 with the floor images (``deformation.floor_image``), as a particle floor at
        the images whose particles carry their mirror particle's stress, ``F`` and volume
        (the variational force's ``floor_image_forces`` likewise): ``i``'s pairs with the
        images ``g_j`` of its row and of itself, ``-½ g(g_j - x_i)`` on ``i`` (the floor takes
        the other half), and the pairs of ``i``'s own image ``g_i`` (``i``'s stress and
        ``F^-1``), ``+½ g(x_r - g_i)`` on ``r`` in the row and on ``i``; returns ``i``'s share."""
        xi = x[i]
        bi = body[i]
        Vi = volume[i]
        c_el = sm.elastic_coef(h)
        gi = floor_image(xi, gn, goff, gmin)
        fi = vec3()
        for k in range(paper_image_count(xi, F, n, h, gn, goff, 1)):
            j = image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                VV = Vi * volume[j]
                fi -= elastic_pair_force(VV, P, F_inv, floor_image(xj, gn, goff, gmin) - xi, h, c_el)
                g = elastic_pair_force(VV, P, F_inv, xj - gi, h, c_el)
                if j == i:
                    fi += g
                else:
                    wp.atomic_add(f, j, g)
        return fi

    @wp.func
    def variational_map(volume: scalar, P: mat33, F: mat33, A_inv: mat33) -> mat33:
        """``M = V P* F^T A^-1`` (given ``A^-1``): the variational force on neighbour ``j``
        is ``-w_ij M xb_ij``."""
        return volume * (P * wp.transpose(F) * A_inv)

    @wp.func
    def variational_map_adjoint(volume: scalar, P: mat33, F: mat33, A_inv: mat33, adj_M: mat33):
        """Adjoint of ``variational_map``: ``adj P = V adj M A^-T F``, ``adj F = V A^-1 adj M^T P``,
        ``adj A = -A^-T (V F P^T adj M) A^-T``."""
        A_invT = wp.transpose(A_inv)
        return (volume * (adj_M * A_invT * F), volume * (A_inv * wp.transpose(adj_M) * P),
                -(A_invT * (volume * (F * wp.transpose(P) * adj_M)) * A_invT))

    @wp.func
    def variational_pair_force(M: mat33, d: vec3, h: scalar, c6: scalar) -> vec3:
        """``g_ij = w_ij M_i xb_ij`` (``d = xb_ij``, ``c6 = poly6_coef(h)``); taken from ``j``, added to ``i``."""
        return fw.w_c(wp.dot(d, d), h, c6) * (M * d)

    @wp.func
    def variational_pair_adjoint(M: mat33, adj_A: mat33, adj_A_sym: mat33, a: vec3, d: vec3, w: scalar, dw: scalar,
                                 adj_r2: scalar) -> vec3:
        """Adjoint in ``d = xb`` of one pair of the variational force: its force ``g = w M d``
        (``variational_pair_force``, against ``a = adj`` of the particle it is added to minus
        that of the one it is taken from), its term ``w d d^T`` in the moment matrix ``A``
        of ``M`` (``adj_A``, ``adj_A_sym = adj_A + adj_A^T``; ``dw = d w / d |d|^2``) and
        whatever else depends on ``|d|^2`` (``adj_r2``: the guard's count):
        ``w (M^T a + adj_A_sym d) + 2 (dw (a . M d + d . adj_A d) + adj_r2) d``."""
        return w * (wp.transpose(M) * a + adj_A_sym * d) + scalar(2.0) * (
            dw * (wp.dot(a, M * d) + wp.dot(d, adj_A * d)) + adj_r2) * d

    @wp.func
    def scatter_variational_pair_adjoint(M: mat33, adj_A: mat33, adj_A_sym: mat33, adj_same: scalar, a: vec3, d: vec3,
                                         hh: scalar, c6: scalar, adj_x: wp.array(dtype=vec3), j: int, xj: vec3,
                                         gn: vec3, goff: scalar, gmin: scalar, image: int) -> vec3:
        """``variational_pair_adjoint`` of the pair at ``d`` (0 at ``|d|^2 >= hh``, beyond the
        kernel's support; ``adj_same``: the adjoint of the guard's smooth count, which the
        pair enters by ``guards.count_weight``), added to ``adj x_j`` of the particle ``j`` at
        ``x_j`` whose position or, with ``image`` 1, floor image (through
        ``deformation.floor_image_jacobian``) is the pair's far end; returned, for the near end."""
        g = vec3()
        r2 = wp.dot(d, d)
        if r2 < hh:
            w, dw = fw.w_inside(r2, hh, c6)
            c, dc = gf.count_weight(r2, hh)
            g = variational_pair_adjoint(M, adj_A, adj_A_sym, a, d, w, dw, adj_same * dc)
            scatter_partner_adjoint(adj_x, j, xj, g, gn, goff, gmin, image)
        return g

    @wp.func
    def variational_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                           nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, h: scalar,
                           f: wp.array(dtype=vec3)) -> vec3:
        """The variational force over particle ``i``'s row: takes ``g_ij`` from ``f_j`` and
        returns ``i``'s share, ``sum_j g_ij``."""
        xi = x[i]
        bi = body[i]
        c6 = fw.coef(h)
        fi = vec3()
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                g = variational_pair_force(M, x[j] - xi, h, c6)
                wp.atomic_sub(f, j, g)
                fi += g
        return fi

    @wp.func
    def image_map(volume: scalar, P: mat33, F: mat33, A_image: mat33) -> mat33:
        """``M`` of a particle's floor image: ``variational_map`` with the particle's stress and
        the image's own moment matrix (``deformation.floor_image_moment``). The image carries
        its particle's stress, as a rough floor's top layer carries the shear it transmits to
        the layer above (docs/physics.md, "The ground collider's thin-layer strength")."""
        return variational_map(volume, P, F, wp.inverse(A_image))

    fit_sums = deformation.funcs(scalar, weight).fit_sums
    floor_image_moment = deformation.funcs(scalar, weight).floor_image_moment
    floor_image_jacobian = deformation.funcs(scalar, weight).floor_image_jacobian
    # R A R: a particle's F or stress as its mirror image carries it.
    mirror = deformation.funcs(scalar, weight).particle_f_for_image
    mirrored_motion_adjoint = deformation.funcs(scalar, weight).mirrored_motion_adjoint

    @wp.func
    def image_energy_share(xi: vec3, h: scalar, gn: vec3, goff: scalar, gmin: scalar, images: int):
        """The shares of a particle's energy and of its image's in the energy whose gradient the
        force is, and the image's share's slope and second slope in the particle's height ``d``:
        ``(1 - c, c, c', c'')``. Where the images move with their particles (``images`` 2) ``c``
        is ``1/2`` within ``h - gmin`` of the plane (``1/2 (E_i + E_g)``, the particle and its
        image as the two halves of one mirrored pair, docs/physics.md, "The frictionless imaged
        ground below half a spacing") and fades to 0 at ``h`` by the smoothstep ``c = t^2 (3 - 2
        t) / 2``, ``t = (h - d) / gmin``: beyond ``h`` the image carries its particle's F mirrored
        (``deformation.floor_image_share``), which its own F differs from where a partner was on
        the depth ramp, and a share that jumped there made the counted energy and the force jump
        as the particle crossed ``h`` (docs/physics.md, "Where a particle crosses ``h``"). ``c``
        and ``c'`` are continuous, ``c''`` jumps at both ends of the fade (read by the adjoints
        alone). Images at rest (1): ``(1, 1, 0, 0)``, the floor's own energy beside the
        particle's."""
        own = scalar(1.0)
        img = scalar(1.0)
        dc = scalar(0.0)
        ddc = scalar(0.0)
        if images == 2:
            img = scalar(0.0)
            d = wp.dot(gn, xi) - goff
            if d < h:
                t = (h - d) / gmin
                img = scalar(0.5)
                if t < scalar(1.0):
                    img = scalar(0.5) * t * t * (scalar(3.0) - scalar(2.0) * t)
                    dc = -(scalar(3.0) * t * (scalar(1.0) - t)) / gmin
                    ddc = scalar(3.0) * (scalar(1.0) - scalar(2.0) * t) / (gmin * gmin)
                own = scalar(1.0) - img
        return own, img, dc, ddc

    @wp.func
    def image_energy_difference(P: mat33, F: mat33, Pg: mat33, Fg: mat33, gn: vec3) -> scalar:
        """``psi(F_g) - psi(F)`` of a particle (stress ``P``) and its image (``Pg``), by the
        trapezoid rule along the straight path from the particle's mirror ``R F R`` to the
        image's ``F_g``: ``1/2 (P_g + R P R) : (F_g - R F R)`` (an isotropic ``psi`` is the
        same at ``F`` and ``R F R``, with stress ``R P R`` there). From the stresses the force
        has, for any stress model; exact for an energy quadratic in ``F``, its error third
        order in ``F_g - R F R`` otherwise. 0 where the image is its particle's mirror."""
        return scalar(0.5) * wp.ddot(Pg + mirror(P, gn, 2), Fg - mirror(F, gn, 2))

    @wp.func
    def image_share_force(volume: scalar, s: scalar, dc: scalar, P: mat33, F: mat33, Pg: mat33, Fg: mat33,
                          gn: vec3) -> vec3:
        """The force on a particle of its image's share's slope (``image_energy_share``): ``-s V
        c' (psi(F_g) - psi(F)) n`` (``image_energy_difference``), with the guards' fade ``s``
        of its fit (a guarded particle's energy applies no force)."""
        return -(s * volume * dc * image_energy_difference(P, F, Pg, Fg, gn)) * gn

    @wp.func
    def image_share_adjoint(volume: scalar, s: scalar, dc: scalar, ddc: scalar, P: mat33, F: mat33, Pg: mat33,
                            Fg: mat33, gn: vec3, ai: vec3, adj_c: scalar):
        """Adjoint of ``image_share_force`` against ``ai = adj f_i``, and of the share ``c`` given
        the adjoint ``adj_c`` of the maps it scales: ``(adj s, adj x_i, adj P, adj F, adj P_g,
        adj F_g)``, ``adj x_i`` through ``c'`` and ``c''`` along ``n``."""
        an = -volume * wp.dot(gn, ai)
        dpsi = image_energy_difference(P, F, Pg, Fg, gn)
        a = s * an * dc * scalar(0.5)
        dFm = Fg - mirror(F, gn, 2)
        Psum = Pg + mirror(P, gn, 2)
        return (an * dc * dpsi, (s * an * ddc * dpsi + dc * adj_c) * gn, mirror(a * dFm, gn, 2),
                -mirror(a * Psum, gn, 2), a * dFm, a * Psum)

    @wp.func
    def image_shares_adjoint(volume: scalar, s: scalar, img: scalar, dc: scalar, ddc: scalar, P: mat33, F: mat33,
                             Pg: mat33, Fg: mat33, gn: vec3, ai: vec3, adj_M0: scalar, adj_Mg: mat33, Mg0: mat33,
                             images: int, adj_s: scalar, adj_P: mat33, adj_F: mat33, adj_Pg: mat33, adj_Fg: mat33):
        """The image's share in either fit's adjoint (``adj_M0 = adj M : M0``, ``adj_Mg`` of
        ``Mg = s c Mg0``): ``c adj Mg : Mg0`` added to ``adj s``, and where the images move with
        their particles (``images`` 2) ``image_share_adjoint``'s terms added to ``adj s``, ``adj
        P``, ``adj F``, ``adj P_g``, ``adj F_g``; returns them with ``adj x_i``."""
        adj_Mg0 = wp.ddot(adj_Mg, Mg0)
        adj_s = adj_s + img * adj_Mg0
        ax = vec3()
        if images == 2:
            as_, ax_, aP, aF, aPg, aFg = image_share_adjoint(volume, s, dc, ddc, P, F, Pg, Fg, gn, ai,
                                                             s * (adj_Mg0 - adj_M0))
            adj_s = adj_s + as_
            adj_P = adj_P + aP
            adj_F = adj_F + aF
            adj_Pg = adj_Pg + aPg
            adj_Fg = adj_Fg + aFg
            ax = ax_
        return adj_s, ax, adj_P, adj_F, adj_Pg, adj_Fg

    @wp.func
    def image_pair_force(M: mat33, gb: vec3, pb: vec3, h: scalar, c6: scalar) -> vec3:
        """The pair force of an image's energy on another image, ``w(|pb|^2) M gb``
        (``gb = g_r - g_i``), weighed as its particles' pair ``pb = x_r - x_i``
        (``deformation.floor_image_moment``)."""
        return fw.w_c(wp.dot(pb, pb), h, c6) * (M * gb)

    @wp.func
    def moving_image_pair_reactions(i: int, j: int, Jj: mat33, g: vec3, gr: vec3, gg: vec3,
                                    f: wp.array(dtype=vec3)):
        """One pair of a row of images moving with their particles (``moving_image_pair_forces``,
        either fit's), given its pair forces: ``g`` on ``x_i`` from ``g_j`` (``i``'s energy),
        ``gr`` on ``g_i`` from ``x_j`` and ``gg`` on ``g_i`` from ``g_j`` (its image's; unread
        for ``j == i``). Each reaction on an image reaches its particle through ``J`` (the image's
        chain rule): ``-J_j (g + gg) - gr`` on ``j``, added to ``f`` (to ``i``'s own for ``j ==
        i``). Returns what the pair adds to the force on ``x_i`` and to the one on ``g_i``
        (``image_force_on_particle`` sends that to ``i``)."""
        fi = g
        fg = gr
        fj = -(Jj * g) - gr
        if j != i:
            fg = fg + gg
            wp.atomic_add(f, j, fj - Jj * gg)
        else:
            fi = fi + fj
        return fi, fg

    @wp.func
    def image_force_on_particle(fi: vec3, fg: vec3, xi: vec3, gn: vec3, goff: scalar, gmin: scalar) -> vec3:
        """The force on a particle ``fi`` with the one on its image moving with it, ``fg``,
        sent through ``J(x_i)``: applied to the pairs' loop's sums by its caller, not in the
        loop's function, whose sum Warp's generated adjoint would not replay (it lost ``J``'s
        slope: docs/method.md, Warp pitfall 1)."""
        return fi + floor_image_jacobian(xi, gn, goff, gmin) * fg

    @wp.func
    def moving_image_pair_slopes(j: int, xi: vec3, xj: vec3, ai: vec3, aj: vec3, g: vec3, gr: vec3, gg: vec3,
                                 gn: vec3, goff: scalar, gmin: scalar, adj_x: wp.array(dtype=vec3)) -> vec3:
        """Adjoint of ``J``'s slope in one pair's reactions (``moving_image_pair_reactions``, either
        fit's pair forces ``g``, ``gr``, ``gg``; ``gg`` 0 for ``j == i``) against ``ai = adj f_i``,
        ``aj = adj f_j``: of ``-J_j (g + gg)`` on ``j``, taken from ``adj x_j``, and of the pair's
        ``J_i (gr + gg)`` on ``i`` (``image_force_on_particle`` applies ``J_i`` to the pairs'
        sum, linear in it: the sum of each pair's), returned for ``adj x_i``
        (``deformation.mirrored_motion_adjoint``)."""
        sj, uj = mirrored_motion_adjoint(xj, g + gg, aj, gn, goff, gmin)
        wp.atomic_sub(adj_x, j, sj)
        si, ui = mirrored_motion_adjoint(xi, gr + gg, ai, gn, goff, gmin)
        return si

    @wp.func
    def moving_image_pair_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                                 nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, Mg: mat33, h: scalar,
                                 gn: vec3, goff: scalar, gmin: scalar, f: wp.array(dtype=vec3)):
        """The pairs of ``moving_image_forces``: on ``i``, ``w M (g_j - x_i)`` of each image in
        its fit, its reaction ``-J_j`` of it on ``j``, returned; of its own image's energy
        (``Mg``), the pairs with its real partners (``w Mg (x_r - g_i)``, taken from ``r``) and
        with their images (``image_pair_force``, taken from ``r`` through ``J_r``), their sum
        on ``g_i`` returned."""
        xi = x[i]
        bi = body[i]
        c6 = fw.coef(h)
        gi = floor_image(xi, gn, goff, gmin)
        fi = vec3()
        fg = vec3()
        for k in range(image_row_length(xi, n, h, gn, goff)):
            j = image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                gj = floor_image(xj, gn, goff, gmin)
                dfi, dfg = moving_image_pair_reactions(
                    i, j, floor_image_jacobian(xj, gn, goff, gmin), variational_pair_force(M, gj - xi, h, c6),
                    variational_pair_force(Mg, xj - gi, h, c6), image_pair_force(Mg, gj - gi, xj - xi, h, c6), f)
                fi += dfi
                fg += dfg
        return fi, fg

    @wp.func
    def moving_image_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                            nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, Mg: mat33, h: scalar,
                            gn: vec3, goff: scalar, gmin: scalar, f: wp.array(dtype=vec3)) -> vec3:
        """``floor_image_forces`` of images moving with their particles (``g(x)``, Jacobian
        ``J``): every pair's reaction on an image goes to the image's particle through ``J``
        (symmetric), so the force is minus the gradient of the energy the images store
        (``moving_image_pair_forces``, ``moving_image_pair_reactions``; the force on ``g_i``
        reaches ``i`` by ``image_force_on_particle``)."""
        fi, fg = moving_image_pair_forces(i, x, body, nbr, n, M, Mg, h, gn, goff, gmin, f)
        return image_force_on_particle(fi, fg, x[i], gn, goff, gmin)

    @wp.func
    def floor_image_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                           nbr: wp.array2d(dtype=wp.int32), n: int, M: mat33, Mg: mat33, h: scalar,
                           gn: vec3, goff: scalar, gmin: scalar, images: int, f: wp.array(dtype=vec3)) -> vec3:
        """The variational force of the floor images (``deformation.fit_pair_sums``), those
        at rest (``images`` 1): through ``i``'s own energy (``M``), ``w M (g_j - x_i)`` for each
        image ``g_j`` in its fit (the floor takes the reaction), returned; and through the
        energy of ``i``'s own image ``g_i`` (``Mg = image_map``), ``-w Mg (x_r - g_i)`` on ``i``
        and on each same-body neighbour ``r`` within ``h`` of it. Those moving with their
        particles (2): ``moving_image_forces``."""
        fi = vec3()
        if images == 2:
            fi = moving_image_forces(i, x, body, nbr, n, M, Mg, h, gn, goff, gmin, f)
        else:
            xi = x[i]
            bi = body[i]
            c6 = fw.coef(h)
            gi = floor_image(xi, gn, goff, gmin)
            for k in range(image_row_length(xi, n, h, gn, goff)):
                j = image_row_particle(i, k, n, nbr)
                if body[j] == bi:
                    xj = x[j]
                    fi += variational_pair_force(M, floor_image(xj, gn, goff, gmin) - xi, h, c6)
                    gr = variational_pair_force(Mg, xj - gi, h, c6)
                    if j == i:
                        fi -= gr
                    else:
                        wp.atomic_sub(f, j, gr)
        return fi

    @wp.func
    def image_pair_adjoint_vectors(ai: vec3, aj: vec3, xi: vec3, xj: vec3, gn: vec3, goff: scalar, gmin: scalar,
                                   images: int):
        """What an image row's pairs of ``floor_image_forces`` are weighed against in its
        adjoint (``ai``, ``aj``: the adjoints of ``f_i``, ``f_j``): of ``i``'s pair with ``g_j``,
        of ``g_i``'s with ``x_j`` and of ``g_i``'s with ``g_j``. Images at rest (``images`` 1)
        give their reactions to the floor: ``(ai, -aj, 0)``; images moving with their particles
        (2) give them through ``J``: ``(ai - J_j aj, J_i ai - aj, J_i ai - J_j aj)``."""
        a1 = ai
        ar = -aj
        ag = vec3()
        if images == 2:
            Jai = floor_image_jacobian(xi, gn, goff, gmin) * ai
            Jaj = floor_image_jacobian(xj, gn, goff, gmin) * aj
            a1 = ai - Jaj
            ar = Jai - aj
            ag = Jai - Jaj
        return a1, ar, ag

    @wp.func
    def fit_variational_forces(i: int, x: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                               nbr: wp.array2d(dtype=wp.int32), n: int, volume: scalar, P: mat33, F: mat33, Pg: mat33,
                               Fg: mat33, h: scalar, min_neighbors: int, max_condition: scalar, gn: vec3, goff: scalar,
                               gmin: scalar, images: int, f: wp.array(dtype=vec3)) -> vec3:
        """The variational force of particle ``i``'s energy (stress ``P``, ``F``) over its row,
        taken from its neighbours and returned for ``i``, faded where ``cond(A)`` passes
        ``max_condition`` or the count falls towards ``min_neighbors - 1``
        (``guards.guard_scale``); with ``images`` its floor images' terms and its own image's
        energy (stress ``Pg``, ``Fg``: ``State.F_image``, where its work is stored), each
        counted by ``image_energy_share``. The elastic kernels' side of the linear fit;
        ``curvature.funcs`` has the corrected one's."""
        # The moments of x alone (y = x and the same round-off: B - A = 0), from their own
        # function: an inverse must not see a loop accumulator (docs/method.md, Warp pitfall 1).
        A, B, same = fit_sums(i, x, x, x, x, body, nbr, n, h, gn, goff, gmin, images)
        A_inv = wp.inverse(A)
        s = gf.guard_scale(A, same, min_neighbors, max_condition)
        own, img, dc, ddc = image_energy_share(x[i], h, gn, goff, gmin, images)
        M = (s * own) * variational_map(volume, P, F, A_inv)
        fi = variational_forces(i, x, body, nbr, n, M, h, f)
        if images != 0:
            Mg = (s * img) * image_map(volume, Pg, Fg, floor_image_moment(i, x, body, nbr, n, h, gn, goff, gmin))
            fi += floor_image_forces(i, x, body, nbr, n, M, Mg, h, gn, goff, gmin, images, f)
            if images == 2:
                fi += image_share_force(volume, s, dc, P, F, Pg, Fg, gn)
        return fi

    return types.SimpleNamespace(
        fit_variational_forces=fit_variational_forces,
        image_map=image_map, floor_image_forces=floor_image_forces, image_energy_share=image_energy_share,
        image_share_force=image_share_force, image_share_adjoint=image_share_adjoint,
        image_shares_adjoint=image_shares_adjoint,
        image_energy_difference=image_energy_difference,
        image_pair_force=image_pair_force, image_pair_adjoint_vectors=image_pair_adjoint_vectors,
        moving_image_pair_reactions=moving_image_pair_reactions, image_force_on_particle=image_force_on_particle,
        moving_image_pair_slopes=moving_image_pair_slopes,
        stress=stress, principal_stress=principal_stress, principal_stress_differences=principal_stress_differences,
        corotated_principal_stress=corotated_principal_stress, corotated_stress=corotated_stress,
        principal_strain_trace=principal_strain_trace,
        cannot_flow_variational=cannot_flow_variational, stress_model=stress_model,
        polynomial_stress=polynomial_stress, elastic_pair_force=elastic_pair_force, paper_forces=paper_forces,
        elastic_pair_adjoint=elastic_pair_adjoint, paper_image_count=paper_image_count,
        scatter_image_pair_adjoint=deformation.funcs(scalar, weight).scatter_image_pair_adjoint,
        paper_image_forces=paper_image_forces,
        variational_map=variational_map, variational_map_adjoint=variational_map_adjoint,
        variational_pair_force=variational_pair_force, variational_forces=variational_forces,
        variational_pair_adjoint=variational_pair_adjoint,
        scatter_variational_pair_adjoint=scatter_variational_pair_adjoint,
    )


@functools.cache
def elastic_kernels(scalar, weight: str, fit: str) -> types.SimpleNamespace:
    """The elastic pair forces of every particle (eqs. 10-13, or the variational force of
    ``fit``: "linear", this module's ``fit_variational_forces``, or "curvature_corrected",
    ``curvature.funcs``' of the same name). A particle of a comparison deformation model
    (``Material.deformation`` other than "incremental") gets none here: its variational
    force is ``comparison.py``'s, and the solver runs the corrected fit without them."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    fo = funcs(scalar, weight)
    checks.choice("fit", fit, ("linear", "curvature_corrected"))  # "auto" is resolved before (Model.solver_choice)
    if fit == "linear":
        fn = fo
    else:
        from . import curvature  # imports this module

        fn = curvature.funcs(scalar, weight)
    Materials = materials.struct(scalar)

    @wp.kernel(module="unique")
    def elastic_forces(
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        volume: wp.array(dtype=scalar),
        stress: wp.array(dtype=mat33),
        F: wp.array(dtype=mat33),
        F_inv: wp.array(dtype=mat33),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        image_stress: wp.array(dtype=mat33),
        F_image: wp.array(dtype=mat33),
        f: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        fi = vec3()
        if mat.elastic_force[material[i]] == 0:
            fi = fo.paper_forces(i, x, body, nbr, count[i], volume, stress[i], F_inv[i], h, f)
            if images != 0:
                fi += fo.paper_image_forces(i, x, body, nbr, count[i], volume, stress[i], F[i], F_inv[i], h, gn, goff,
                                            gmin, f)
        elif guard[i] == 0 and mat.deformation[material[i]] == 0:
            # (A rest-configuration material's variational force is comparison.py's.)
            fi = fn.fit_variational_forces(i, x, body, nbr, count[i], volume[i], stress[i], F[i], image_stress[i],
                                           F_image[i], h, min_neighbors, max_condition, gn, goff, gmin, images, f)
        wp.atomic_add(f, i, fi)

    return types.SimpleNamespace(elastic_forces=elastic_forces)


def launch_elastic_forces(model, state_in, state_out, hand_adjoint: bool = True,
                          max_condition: float = neighbors.MAX_CONDITION, min_neighbors: int = neighbors.MIN_NEIGHBORS):
    """Elastic pair forces (eqs. 10-13, or the variational force) into ``state_out.force``,
    from the stress, ``F`` and ``F^-1`` the constitutive update wrote to ``state_out``.
    Under a ``wp.Tape``, when every material uses eqs. 10-13, the backward runs
    ``elastic_forces_adjoint`` (``hand_adjoint=False``: Warp's generated adjoint)."""
    kernel = elastic_kernels(model.scalar, model.fit_weight, "linear").elastic_forces
    inputs = elastic_force_inputs(model, state_in, state_out, max_condition, min_neighbors)
    tape = recording_tape()
    grads = (state_in.x, state_out.stress, state_out.F_inv, state_out.force)
    if (tape is None or not hand_adjoint or any(a.grad is None for a in grads)
            or model.material_elastic_force.numpy().any()):  # 0: eqs. 10-13 ("paper")
        with kept_through_backward(state_out.force):
            model.launches(kernel, model.particle_count, inputs, [state_out.force], device=model.device)
        return
    model.launches(kernel, model.particle_count, inputs, [state_out.force], device=model.device, record_tape=False)

    tape.record_func(lambda: launch_elastic_forces_adjoint(model, state_in, state_out), list(grads))


def elastic_force_inputs(model, state_in, state_out, max_condition: float, min_neighbors: int) -> list:
    """``elastic_kernels``' inputs, the same for either fit (``launch_elastic_forces`` here
    and in ``curvature.py``), so the two launchers cannot drift from the kernel's signature."""
    S = model.scalar
    return [
        state_in.x, model.particle_body, model.particle_material, model.material_arrays(), state_out.neighbors,
        state_out.neighbor_count, state_out.guard, model.particle_volume, state_out.stress, state_out.F_flowed,
        state_out.F_inv, S(model.support_radius), int(min_neighbors), S(max_condition), *model.image_args(),
        *image_constitutive(model, state_out),
    ]


def image_constitutive(model, state_out):
    """The images' stress and flowed F the variational force reads (``State.image_stress``,
    ``State.F_image_flowed``, written by ``plasticity.launch_image_constitutive_update``);
    without an image plane, arrays of the right shape that it does not read."""
    if model.image_plane is None:
        return state_out.stress, state_out.F_flowed
    return state_out.image_stress, state_out.F_image_flowed


@functools.cache
def kernels(scalar, weight: str) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    sm = smoothing.funcs(scalar)
    fw = smoothing.fit_weight_funcs(scalar, weight)
    fn = funcs(scalar, weight)
    fit_pair_sums = deformation.funcs(scalar, weight).fit_pair_sums
    image_moment = deformation.funcs(scalar, weight).floor_image_moment
    floor_image = deformation.funcs(scalar, weight).floor_image
    image_slots = deformation.funcs(scalar, weight).image_slots
    image_row_particle = deformation.image_row_particle
    scatter_partner_adjoint = deformation.funcs(scalar, weight).scatter_partner_adjoint
    scatter_own_adjoint = deformation.funcs(scalar, weight).scatter_own_adjoint

    @wp.kernel(enable_backward=False, module="unique")
    def elastic_forces_adjoint(
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        elastic_force: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        volume: wp.array(dtype=scalar),
        stress: wp.array(dtype=mat33),
        F: wp.array(dtype=mat33),
        F_inv: wp.array(dtype=mat33),
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        adj_f: wp.array(dtype=vec3),
        adj_x: wp.array(dtype=vec3),
        adj_stress: wp.array(dtype=mat33),
        adj_F_inv: wp.array(dtype=mat33),
    ):
        """Hand-written adjoint of ``elastic_forces`` for eqs. 10-13 (every material
        ``elastic_force="paper"``): per pair, with ``a = adj f_j - adj f_i``, ``r = F_i^-1 d``
        and ``g = V_i V_j P_i gradW(r)``: ``adj P_i += V_i V_j a gradW^T``,
        ``adj r = J^T V_i V_j P_i^T a``, ``adj F_i^-1 += adj r d^T``, ``adj d = F_i^-T adj r``
        (``elastic_pair_adjoint``). With ``images`` (``paper_image_forces``) the image pairs
        likewise, ``a = -adj f_i`` for ``i``'s own (``d = g_j - x_i``), ``a = adj f_r`` for its
        image's (``d = x_r - g_i``), an image's ``adj`` going to its particle through
        ``deformation.floor_image_jacobian``. Particles of the variational force are
        ``variational_forces_adjoint``'s."""
        i = wp.tid()
        if elastic_force[material[i]] != 0:
            return
        xi = x[i]
        bi = body[i]
        P = stress[i]
        Vi = volume[i]
        Finv = F_inv[i]
        ai = adj_f[i]
        c_el = sm.elastic_coef(h)
        n = count[i]
        aP = mat33()
        aFinv = mat33()
        gx_i = vec3()
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                d = x[j] - xi
                dP, dFinv, ad = fn.elastic_pair_adjoint(Vi * volume[j], adj_f[j] - ai, P, Finv, d, h, c_el)
                aP += dP
                aFinv += dFinv
                wp.atomic_add(adj_x, j, ad)
                gx_i -= ad
        n_img = fn.paper_image_count(xi, F[i], n, h, gn, goff, images)
        gi = floor_image(xi, gn, goff, gmin)
        gg_i = vec3()
        for k in range(n_img):
            j = image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                VV = Vi * volume[j]
                dP, dFinv, ad = fn.elastic_pair_adjoint(VV, -ai, P, Finv, floor_image(xj, gn, goff, gmin) - xi, h, c_el)
                aP += dP
                aFinv += dFinv
                scatter_partner_adjoint(adj_x, j, xj, ad, gn, goff, gmin, 1)
                gx_i -= ad
                dP, dFinv, ad = fn.elastic_pair_adjoint(VV, adj_f[j], P, Finv, xj - gi, h, c_el)
                aP += dP
                aFinv += dFinv
                wp.atomic_add(adj_x, j, ad)
                gg_i -= ad
        scatter_own_adjoint(adj_x, i, xi, gx_i, gg_i, gn, goff, gmin)
        adj_stress[i] = adj_stress[i] + aP
        adj_F_inv[i] = adj_F_inv[i] + aFinv

    guard_state = neighbors.guard_funcs(scalar).guard
    moment_pair_terms = deformation.funcs(scalar, weight).moment_pair_terms
    Materials = materials.struct(scalar)
    sph_adjoint = pressure.kernels(scalar)
    sph_pair_adjoint = sph_adjoint.pressure_pair_adjoint
    sph_particle_terms = sph_adjoint.pressure_particle_terms
    sph_particle_adjoint = sph_adjoint.pressure_particle_adjoint

    @wp.func
    def row_moments_and_adjoint_map(
        i: int,
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        adj_f: wp.array(dtype=vec3),
    ):
        """Over ``i``'s row neighbours: the fit's moment matrix ``A = sum w xb xb^T`` and smooth
        count ``same`` as ``deformation.moment_sums`` sums them on ``x`` alone (its pair terms,
        ``deformation.moment_pair_terms``, in the same order, so the same bits), and ``adj M = sum w (adj f_i - adj f_j) xb^T``
        (``variational_forces_adjoint``), in one pass: both weigh the pair by the same ``w``."""
        A = mat33()
        adj_M = mat33()
        same = scalar(0.0)
        xi = x[i]
        ai = adj_f[i]
        bi = body[i]
        c6 = fw.coef(h)
        hh = h * h
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                xb = x[j] - xi
                w, dA, c = moment_pair_terms(xb, h, c6, hh)
                A += dA
                same += c
                adj_M += w * wp.outer(ai - adj_f[j], xb)
        return A, same, adj_M

    @wp.func
    def variational_adjoint_maps(
        i: int,
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        volume: wp.array(dtype=scalar),
        stress: wp.array(dtype=mat33),
        F: wp.array(dtype=mat33),
        min_neighbors: int,
        max_condition: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        image_stress: wp.array(dtype=mat33),
        F_image: wp.array(dtype=mat33),
        adj_f: wp.array(dtype=vec3),
        adj_stress: wp.array(dtype=mat33),
        adj_F: wp.array(dtype=mat33),
        adj_image_stress: wp.array(dtype=mat33),
        adj_F_image: wp.array(dtype=mat33),
        adj_x: wp.array(dtype=vec3),
    ):
        """The part of ``variational_forces_adjoint`` before its scatter pass: ``adj M`` (and
        ``adj Mg``), the maps' adjoints into ``adj P``, ``adj F`` (and the image's), and what
        the scatter needs: ``(applied, M, adj A, adj A + adj A^T, adj same, Mg, adj A_g, adj A_g +
        adj A_g^T, image slots, g_i)``; ``applied`` 0 where the guard stops the force (then
        nothing is written)."""
        xi = x[i]
        bi = body[i]
        ai = adj_f[i]
        c6 = fw.coef(h)
        # The fit's moment matrix and guard as the forward's (images included: fit_sums'
        # image part added as it adds it), with adj M, which does not depend on A, summed in
        # the same pass over the row (one pass instead of two; the same bits).
        A, same, adj_M = row_moments_and_adjoint_map(i, x, body, nbr, n, h, adj_f)
        if images != 0:
            Ag, Bg, sg = fit_pair_sums(i, x, x, x, x, body, nbr, n, h, 0, gn, goff, gmin, 1)
            A = A + Ag
            same = same + sg
        # The guards and the fade s(A, same) of both maps (guards.guard): M = s M0, Mg = s Mg0.
        code, s, ds_dA, ds_dn = guard_state(A, same, min_neighbors, max_condition)
        if code != 0:
            return 0, mat33(), mat33(), mat33(), scalar(0.0), mat33(), mat33(), mat33(), 0, vec3()
        # With images, their part of adj M and adj Mg (image_pair_adjoint_vectors).
        n_img = image_slots(xi, n, h, gn, goff, images)
        gi = floor_image(xi, gn, goff, gmin)
        adj_Mg = mat33()
        for k in range(n_img):
            j = image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                gj = floor_image(xj, gn, goff, gmin)
                a1, ar, ag = fn.image_pair_adjoint_vectors(ai, adj_f[j], xi, xj, gn, goff, gmin, images)
                d = gj - xi
                adj_M += fw.w_c(wp.dot(d, d), h, c6) * wp.outer(a1, d)
                dr = xj - gi
                adj_Mg += fw.w_c(wp.dot(dr, dr), h, c6) * wp.outer(ar, dr)
                if images == 2 and j != i:
                    pb = xj - xi
                    adj_Mg += fw.w_c(wp.dot(pb, pb), h, c6) * wp.outer(ag, gj - gi)
        # The energies' shares (image_energy_share) scale the maps with the fade: M = s (1 - c) M0,
        # Mg = s c Mg0.
        own, img, dc, ddc = fn.image_energy_share(xi, h, gn, goff, gmin, images)
        so = s * own
        Vi = volume[i]
        P = stress[i]
        Fi = F[i]
        Ainv = wp.inverse(A)
        M0 = fn.variational_map(Vi, P, Fi, Ainv)
        M = so * M0
        adj_P, adj_Fi, adj_A = fn.variational_map_adjoint(Vi, P, Fi, Ainv, so * adj_M)
        adj_M0 = wp.ddot(adj_M, M0)
        adj_s = own * adj_M0
        Mg = mat33()
        adj_Ag = mat33()
        if n_img > 0:
            sg = s * img
            Ag_inv = wp.inverse(image_moment(i, x, body, nbr, n, h, gn, goff, gmin))
            Pg = image_stress[i]
            Fg = F_image[i]
            Mg0 = fn.variational_map(Vi, Pg, Fg, Ag_inv)
            Mg = sg * Mg0
            adj_Pg_, adj_Fg_, adj_Ag_ = fn.variational_map_adjoint(Vi, Pg, Fg, Ag_inv, sg * adj_Mg)
            adj_s, ax, adj_P, adj_Fi, adj_Pg, adj_Fg = fn.image_shares_adjoint(
                Vi, s, img, dc, ddc, P, Fi, Pg, Fg, gn, ai, adj_M0, adj_Mg, Mg0, images, adj_s, adj_P, adj_Fi, adj_Pg_,
                adj_Fg_)
            if images == 2:
                wp.atomic_add(adj_x, i, ax)
            adj_image_stress[i] = adj_image_stress[i] + adj_Pg
            adj_F_image[i] = adj_F_image[i] + adj_Fg
            adj_Ag = adj_Ag_
        adj_A = adj_A + adj_s * ds_dA
        adj_A_sym = adj_A + wp.transpose(adj_A)
        adj_Ag_sym = adj_Ag + wp.transpose(adj_Ag)
        adj_same = adj_s * ds_dn
        adj_stress[i] = adj_stress[i] + adj_P
        adj_F[i] = adj_F[i] + adj_Fi
        return 1, M, adj_A, adj_A_sym, adj_same, Mg, adj_Ag, adj_Ag_sym, n_img, gi

    @wp.kernel(enable_backward=False, module="unique")
    def variational_forces_adjoint(
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        elastic_force: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
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
        sph: int,
        v: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        mat: Materials,
        adj_f: wp.array(dtype=vec3),
        adj_x: wp.array(dtype=vec3),
        adj_stress: wp.array(dtype=mat33),
        adj_F: wp.array(dtype=mat33),
        adj_image_stress: wp.array(dtype=mat33),
        adj_F_image: wp.array(dtype=mat33),
        adj_v: wp.array(dtype=vec3),
        adj_rho: wp.array(dtype=scalar),
        adj_rho_p: wp.array(dtype=scalar),
        adj_k: wp.array(dtype=scalar),
        adj_visc: wp.array(dtype=scalar),
    ):
        """Hand-written adjoint of the variational elastic force (``variational_map``,
        ``variational_pair_force``) as the fused step applies it: the guard evaluated on the
        moment matrix ``A`` at the step's start (a guarded particle applies no force).

        With ``a_j = adj f_i - adj f_j`` (``g_j = w_j M xb_j`` is added to ``i``, taken from
        ``j``) and ``M = V P F^T A^-1``: ``adj M = sum_j w_j a_j xb_j^T``;
        ``adj P = V adj M A^-T F``, ``adj F = V A^-1 adj M^T P``,
        ``adj A = -A^-T (V F P^T adj M) A^-T`` (``variational_map_adjoint``); per pair
        ``adj xb_j`` is ``variational_pair_adjoint``, scattered to ``j`` and taken from ``i``.
        Recomputes ``A`` and ``M`` (two passes over the row: ``A`` with ``adj M``
        (``variational_adjoint_maps``), then the scatter) instead of storing them.

        With ``images`` (``floor_image_forces``): the image pairs of ``i``'s fit, ``xb = g_j -
        x_i`` with ``a = adj f_i`` (the floor takes the reaction); the energy of ``i``'s own
        image, ``Mg = image_map`` on the image's moment matrix ``A_g``
        (``deformation.floor_image_moment``), its pairs ``d = x_r - g_i`` with ``a = -adj f_r``
        and the image-image terms ``d = g_r - g_i`` of ``A_g``, weighed by their particles' pair
        (``scatter_image_pair_adjoint``); an image's ``adj`` goes to its particle through
        ``deformation.floor_image_jacobian``. Images moving with their particles (``images`` 2,
        ``moving_image_forces``) weigh each pair against ``image_pair_adjoint_vectors`` (their
        reactions reach the particles through ``J``), their image-image pairs' forces too, both
        maps scaled by ``image_energy_share``, and ``J``'s slope (``moving_image_pair_slopes``)
        on the particles whose ``J`` carries a reaction.

        With ``sph`` 1 the scatter pass also takes every particle's SPH pressure and viscosity
        pairs (``pressure.pressure_forces_adjoint``'s, ``pressure_pair_adjoint``), as the fused
        forward applies both forces in one loop: one pass over the pairs instead of two
        launches' one each (the floor images' pressure stays with the generated adjoint,
        ``pressure.launch_pressure_image_forces_adjoint``)."""
        i = wp.tid()
        n = count[i]
        applied = int(0)
        M = mat33()
        adj_A = mat33()
        adj_A_sym = mat33()
        adj_same = scalar(0.0)
        Mg = mat33()
        adj_Ag = mat33()
        adj_Ag_sym = mat33()
        n_img = int(0)
        gi = vec3()
        if elastic_force[material[i]] == 1:
            applied, M, adj_A, adj_A_sym, adj_same, Mg, adj_Ag, adj_Ag_sym, n_img, gi = variational_adjoint_maps(
                i, x, body, nbr, n, h, volume, stress, F, min_neighbors, max_condition, gn, goff, gmin, images,
                image_stress, F_image, adj_f, adj_stress, adj_F, adj_image_stress, adj_F_image, adj_x)
        if applied == 0 and sph == 0:
            return
        xi = x[i]
        bi = body[i]
        ai = adj_f[i]
        c6 = fw.coef(h)
        hh = h * h
        # The pressure's terms of i (pressure_forces_adjoint).
        mi = int(0)
        vi = vec3()
        rho_i = scalar(0.0)
        Vi = scalar(0.0)
        rp_i = scalar(0.0)
        k_i = scalar(0.0)
        pi = scalar(0.0)
        visc_i = scalar(0.0)
        form = int(0)
        if sph != 0:
            mi, vi, rho_i, Vi, rp_i, k_i, pi, visc_i, form = sph_particle_terms(i, v, mass, rho, rho_p, rest_density,
                                                                                 material, mat)
        c_sph = sm.poly6_coef(h)
        c_spiky = sm.spiky_coef(h)
        c_visc = sm.viscosity_coef(h)
        adj_pi = scalar(0.0)
        adj_Ai = scalar(0.0)
        adj_rho_i = scalar(0.0)
        adj_visc_i = scalar(0.0)
        gp_i = vec3()
        gv_i = vec3()
        gx_i = vec3()
        for k in range(n):
            j = nbr[i, k]
            xj = x[j]
            if applied != 0 and body[j] == bi:
                gx_i -= fn.scatter_variational_pair_adjoint(M, adj_A, adj_A_sym, adj_same, ai - adj_f[j], xj - xi, hh, c6,
                                                            adj_x, j, xj, gn, goff, gmin, 0)
            if sph != 0:
                r = xi - xj
                r2 = wp.dot(r, r)
                if r2 < hh:
                    adj_pi, adj_Ai, adj_rho_i, adj_visc_i, gp_i, gv_i = sph_pair_adjoint(
                        i, j, r, r2, h, hh, c_sph, c_spiky, c_visc, ai, vi, Vi, rho_i, pi, rp_i, visc_i, form, v, mass,
                        rho, rho_p, rest_density, material, mat, adj_f, adj_x, adj_v, adj_rho, adj_rho_p, adj_k,
                        adj_visc, adj_pi, adj_Ai, adj_rho_i, adj_visc_i, gp_i, gv_i)
        if applied != 0:
            # Through g_i (summed, then by d g_i / d x_i).
            gg_i = vec3()
            for k in range(n_img):
                j = image_row_particle(i, k, n, nbr)
                if body[j] == bi:
                    xj = x[j]
                    aj = adj_f[j]
                    gj = floor_image(xj, gn, goff, gmin)
                    a1, ar, ag = fn.image_pair_adjoint_vectors(ai, aj, xi, xj, gn, goff, gmin, images)
                    gx_i -= fn.scatter_variational_pair_adjoint(M, adj_A, adj_A_sym, adj_same, a1, gj - xi, hh, c6, adj_x,
                                                                j, xj, gn, goff, gmin, 1)
                    # (The own image's moments are not the fit's: they do not count.)
                    gg_i -= fn.scatter_variational_pair_adjoint(Mg, adj_Ag, adj_Ag_sym, scalar(0.0), ar, xj - gi,
                                                                hh, c6, adj_x, j, xj, gn, goff, gmin, 0)
                    Mp = mat33()  # the image-image pair's force map: moving images' alone
                    if images == 2:
                        Mp = Mg
                    if j != i:
                        gg, gp = fn.scatter_image_pair_adjoint(adj_Ag, adj_Ag_sym, Mp, ag, gj - gi, xj - xi, hh, c6,
                                                               adj_x, j, xj, gn, goff, gmin)
                        gg_i -= gg
                        gx_i -= gp
                    if images == 2:
                        gg = vec3()
                        if j != i:
                            gg = fn.image_pair_force(Mg, gj - gi, xj - xi, h, c6)
                        g = fn.variational_pair_force(M, gj - xi, h, c6)
                        gr = fn.variational_pair_force(Mg, xj - gi, h, c6)
                        gx_i += fn.moving_image_pair_slopes(j, xi, xj, ai, aj, g, gr, gg, gn, goff, gmin, adj_x)
            scatter_own_adjoint(adj_x, i, xi, gx_i, gg_i, gn, goff, gmin)
        if sph != 0:
            wp.atomic_add(adj_x, i, gp_i)
            sph_particle_adjoint(i, mi, rp_i, k_i, pi, rest_density, mat, adj_pi, adj_Ai, adj_rho_i, adj_visc_i, gv_i,
                                 adj_v, adj_rho, adj_rho_p, adj_k, adj_visc)

    return types.SimpleNamespace(elastic_forces_adjoint=elastic_forces_adjoint,
                                 variational_forces_adjoint=variational_forces_adjoint)


def launch_elastic_forces_adjoint(model, state_in, state_out):
    """``elastic_forces_adjoint``: ``state_out.force.grad`` into the gradients of ``state_in.x``,
    ``state_out.stress`` and ``state_out.F_inv`` (eqs. 10-13 only)."""
    S = model.scalar
    model.launches(
        kernels(S, model.fit_weight).elastic_forces_adjoint, model.particle_count,
        [state_in.x, model.particle_body, model.particle_material, model.material_elastic_force, state_out.neighbors,
         state_out.neighbor_count, model.particle_volume, state_out.stress, state_out.F_flowed, state_out.F_inv,
         S(model.support_radius), *model.image_args(), state_out.force.grad, state_in.x.grad, state_out.stress.grad,
         state_out.F_inv.grad],
        device=model.device, record_tape=False,
    )


def launch_variational_forces_adjoint(model, state_in, state_out, min_neighbors: int, max_condition: float,
                                      sph: bool = False):
    """``variational_forces_adjoint``: ``state_out.force.grad`` into the gradients of
    ``state_in.x``, ``state_out.stress`` and ``state_out.F_flowed`` (the particles of the
    variational force only; the guard as the fused step evaluates it). With ``sph``, in the
    same pass, ``pressure.launch_pressure_forces_adjoint``'s pairs (every particle's): into
    those of ``state_in.x, v``, the densities and ``pressure_stiffness``, ``viscosity``; its
    floor images' part is not taken (``pressure.launch_pressure_image_forces_adjoint``)."""
    S = model.scalar
    rho_p = pressure.pressure_density(model, state_out)
    model.launches(
        kernels(S, model.fit_weight).variational_forces_adjoint, model.particle_count,
        [state_in.x, model.particle_body, model.particle_material, model.material_elastic_force, state_out.neighbors,
         state_out.neighbor_count, model.particle_volume, state_out.stress, state_out.F_flowed, S(model.support_radius),
         int(min_neighbors), S(max_condition), *model.image_args(), *image_constitutive(model, state_out), int(sph),
         state_in.v, model.particle_mass, state_out.density, rho_p, model.particle_rest_density, model.material_arrays(),
         state_out.force.grad, state_in.x.grad, state_out.stress.grad, state_out.F_flowed.grad,
         *(a.grad for a in image_constitutive(model, state_out)),
         # Without sph these are not read: arrays of the right types.
         *((state_in.v.grad, state_out.density.grad, rho_p.grad, model.pressure_stiffness.grad, model.viscosity.grad)
           if sph else (state_in.x.grad, state_out.density, state_out.density, model.particle_mass, model.particle_mass))],
        device=model.device, record_tape=False,
    )
