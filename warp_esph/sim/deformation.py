"""Incremental deformation gradient (paper eqs. 1-8, docs/method.md §2).

Over one step, with ``x`` the positions at its start and ``y`` at its end, the
weighted least-squares affine fit to the same-body neighbours is

    xb_j = x_j - x_i,  yb_j = y_j - y_i,  w_j = W_poly6(|xb_j|, h)     (eqs. 1, 7)
    A = sum_j w_j xb_j xb_j^T,  B = sum_j w_j yb_j xb_j^T,  dF = B A^-1  (eqs. 5-6)
    F_i <- dF F_i                                                       (eq. 8)

(``Model.fit_weight`` "biweight", the default: ``w_j`` is ``(h^2 - |xb_j|^2)^2`` instead,
``smoothing.fit_weight_funcs``; "poly6" is the paper's above.) Relative vectors make the fit translation invariant; it
reproduces any affine motion exactly, whatever the weights. The update is skipped (the old F kept, and counted) when the neighbourhood
guard of ``neighbors`` fired or the candidate has ``det <= 0`` (an inverted or
degenerate F: with the rotation-variant SVD that is exactly a signed singular value
``<= 0``).
"""

import functools
import types

import warp as wp

from .._types import type_set
from .. import checks
from . import guards, smoothing
from .replay import recording_tape
from .roundoff import compensated_sum

#: Indices into the solver's guard counters.
COUNT_FEW_NEIGHBORS = 0
COUNT_ILL_CONDITIONED = 1
COUNT_INVERTED = 2
#: Body ``b``'s particle-steps whose fit a guard of paper §4 skipped are counted at
#: ``COUNT_BODY + b`` (after the solver's ``GUARD_NAMES``), beside the guard's own count: the
#: run's warning names the bodies too coarse for the fit, not only the share of all of them.
COUNT_BODY = 6


@wp.func
def count_guarded(code: int, slot: int, counters: wp.array(dtype=wp.int32)):
    """Counts a particle-step whose fit a guard of paper §4 skipped (``code``: 1 too few
    neighbours, 2 too flat a neighbourhood; ``neighbors.GUARD_*``) under its guard and at its
    body's ``slot`` (``COUNT_BODY + body``): every fit that can be skipped counts it here."""
    if code == 1:
        wp.atomic_add(counters, COUNT_FEW_NEIGHBORS, 1)
    else:
        wp.atomic_add(counters, COUNT_ILL_CONDITIONED, 1)
    wp.atomic_add(counters, slot, 1)


@wp.func
def image_row_particle(i: int, k: int, n: int, nbr: wp.array2d(dtype=wp.int32)) -> int:
    """The particle whose floor image stands at slot ``k`` of particle ``i``'s image loop
    (``image_row_length`` slots): row neighbour ``nbr[i, k]`` for ``k < n``, ``i`` itself at
    slot ``n``, since a particle's own image counts like any other but ``i`` is not in its
    own row. ``nbr[i, n]`` is never read: a full row has no slot ``n``. Integers only, so
    nothing to differentiate; outside ``funcs`` because it has no scalar type, one function
    for both precisions' kernels."""
    j = i
    if k < n:
        j = nbr[i, k]
    return j


@functools.cache
def funcs(scalar, weight: str) -> types.SimpleNamespace:
    """The fit's functions for ``scalar`` and the fit ``weight`` (``smoothing.FIT_WEIGHTS``)."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    fw = smoothing.fit_weight_funcs(scalar, weight)
    gf = guards.guard_funcs(scalar)

    @wp.func
    def displacement(x: vec3, y: vec3, x_lo: vec3, y_lo: vec3) -> vec3:
        """A particle's displacement over the step from ``x + x_lo`` to ``y + y_lo``
        (``fit_pair_sums``): ``y - x`` is exact, the round-offs' difference added to it."""
        return (y - x) + (y_lo - x_lo)

    @wp.func
    def image_depth(d: scalar, min_depth: scalar):
        """How deep under the plane the floor image of a point ``d`` above it lies, and its
        slope in ``d`` and that slope's own: ``d`` from ``min_depth`` up, ``min_depth`` below ``min_depth - w``
        (``w = min_depth / 2``), and between them the cubic ``min_depth + w t^2 (t - 1)``,
        ``t = 1 + (d - min_depth) / w``, which joins the two with value and slope continuous
        (a plain ``max(d, min_depth)`` has a kink, and a loss through contact jumps in its slope
        where a particle crosses it; docs/physics.md, "The imaged ground's contact is smooth").
        The cubic dips at most ``4 w / 27`` below ``min_depth``; the image's own depth ``d + s``
        still grows with ``d`` (slope >= 2/3). The second slope, ``(6 t - 2) / w`` on the cubic
        and 0 off it (it jumps at the cubic's ends), is what the adjoint of an image moving with
        its particle reads (``mirrored_motion_adjoint``)."""
        s = d
        ds = scalar(1.0)
        dds = scalar(0.0)
        if d < min_depth:
            w = scalar(0.5) * min_depth
            t = wp.max(scalar(1.0) + (d - min_depth) / w, scalar(0.0))
            s = min_depth + w * t * t * (t - scalar(1.0))
            ds = t * (scalar(3.0) * t - scalar(2.0))
            if t > scalar(0.0):
                dds = (scalar(6.0) * t - scalar(2.0)) / w
        return s, ds, dds

    @wp.func
    def floor_image(x: vec3, n: vec3, offset: scalar, min_depth: scalar) -> vec3:
        """The image of ``x`` in the rough floor ``dot(n, x) = offset``: below its foot on the
        plane, as deep as ``x`` is high but at least ``min_depth`` (half a spacing: the
        floor's top layer of a floor of particles; ``image_depth``), so that a particle
        pressed towards the plane closes on its image as on a floor particle (docs/physics.md,
        "The ground collider's thin-layer strength")."""
        d = wp.dot(n, x) - offset
        s, ds, dds = image_depth(d, min_depth)
        return x - (d + s) * n

    @wp.func
    def floor_image_jacobian(x: vec3, n: vec3, offset: scalar, min_depth: scalar) -> mat33:
        """``d floor_image / d x`` (symmetric): ``I - (1 + s') n n^T`` for the slope ``s'`` of
        ``image_depth``: the mirror ``R = I - 2 n n^T`` while ``x`` is higher than
        ``min_depth``, the tangential projector ``I - n n^T`` below ``min_depth - w``, where the
        image stays at ``min_depth`` under the plane, and between them a blend of the two."""
        s, ds, dds = image_depth(wp.dot(n, x) - offset, min_depth)
        return wp.identity(n=3, dtype=scalar) - (scalar(1.0) + ds) * wp.outer(n, n)

    @wp.func
    def mirrored_motion(x: vec3, u: vec3, n: vec3, offset: scalar, min_depth: scalar) -> vec3:
        """The motion of the floor image of a particle at ``x`` moving by ``u`` (a displacement
        over the step, or a velocity), to first order: ``floor_image_jacobian(x) u``, its
        tangential part kept and its normal part reversed while ``x`` is higher than
        ``min_depth`` (the mirror). Images that move so (``model.IMAGES_MOVING``) follow a
        body sliding over them: a frictionless imaged ground (docs/physics.md, "The imaged
        ground is rough whatever its friction")."""
        return floor_image_jacobian(x, n, offset, min_depth) * u

    @wp.func
    def mirrored_motion_adjoint(x: vec3, u: vec3, g: vec3, n: vec3, offset: scalar, min_depth: scalar):
        """Adjoint of ``mirrored_motion`` given the gradient ``g`` of its output: ``(adj x, adj
        u)``, ``adj u = J g`` (``J`` symmetric) and ``adj x = -(n . u)(n . g) s'' n`` through the
        Jacobian's depth slope (``image_depth``'s second slope ``s''``: 0 but on its cubic)."""
        s, ds, dds = image_depth(wp.dot(n, x) - offset, min_depth)
        return -(dds * wp.dot(n, u) * wp.dot(n, g)) * n, floor_image_jacobian(x, n, offset, min_depth) * g

    @wp.func
    def partner_displacement(j: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                             y_lo: wp.array(dtype=vec3), given: int, gn: vec3, goff: scalar, gmin: scalar,
                             image: int) -> vec3:
        """The displacement over the step of the far end of a fit pair whose partner is particle
        ``j`` (``pair_partner``): ``image`` 0, ``j``'s own (``displacement``; ``given`` 1: ``y``
        holds it); 1, its floor image's at rest: 0; 2, its image's moving with it,
        ``mirrored_motion`` of ``j``'s. Every fit's image pair takes its displacement here: the
        pair's ``ub`` is this minus the near end's."""
        u = vec3()
        if image != 1:
            u = y[j]
            if given == 0:
                u = displacement(x[j], u, x_lo[j], y_lo[j])
            if image == 2:
                u = mirrored_motion(x[j], u, gn, goff, gmin)
        return u

    @wp.func
    def image_row_length(x: vec3, n: int, reach: scalar, gn: vec3, goff: scalar) -> int:
        """How many slots the floor-image loop of a particle at ``x`` with ``n`` row
        neighbours visits (``image_row_particle``): all ``n + 1`` (the row and the particle
        itself) while ``x`` is less than ``reach`` above the plane ``dot(gn, x) = goff``, else
        none. Every image lies under the plane, so it is at least as far from ``x`` as ``x``
        is from the plane: at ``reach`` or higher no image is within the kernel's reach and
        the loop can be skipped whole. ``reach`` is ``h`` for the fit, the variational force
        and SPH; eqs. 10-13 back-project by ``F^-1`` and pass a wider one
        (``forces.paper_image_count``)."""
        return wp.where(wp.dot(gn, x) - goff < reach, n + 1, 0)

    @wp.func
    def image_slots(x: vec3, n: int, reach: scalar, gn: vec3, goff: scalar, images: int) -> int:
        """``image_row_length`` where the model has an image plane (``images``), else 0."""
        slots = int(0)
        if images != 0:
            slots = image_row_length(x, n, reach, gn, goff)
        return slots

    @wp.func
    def pair_slots(xi: vec3, n: int, h: scalar, gn: vec3, goff: scalar, image: int) -> int:
        """How many slots a loop over ``i``'s pairs visits (``pair_partner``): the ``n`` row
        neighbours, or for the floor images (``image`` 1) ``image_row_length``'s."""
        slots = n
        if image != 0:
            slots = image_slots(xi, n, h, gn, goff, image)
        return slots

    @wp.func
    def pair_partner(i: int, k: int, n: int, nbr: wp.array2d(dtype=wp.int32), x: wp.array(dtype=vec3), gn: vec3,
                     goff: scalar, gmin: scalar, image: int):
        """Slot ``k`` of ``i``'s pairs (``pair_slots``): the particle ``j`` (``image_row_particle``)
        and the position the pair weighs, ``x_j``, or its ``floor_image`` ``g_j`` (``image`` 1)."""
        j = image_row_particle(i, k, n, nbr)
        p = x[j]
        if image != 0:
            p = floor_image(p, gn, goff, gmin)
        return j, p

    @wp.func
    def pair_ends(i: int, k: int, n: int, nbr: wp.array2d(dtype=wp.int32), x: wp.array(dtype=vec3),
                  y: wp.array(dtype=vec3), gn: vec3, goff: scalar, gmin: scalar, image: int):
        """``pair_partner`` with the partner's position at the step's end: ``(j, x_j, y_j)``, or
        for a floor image ``(j, g_j, g_j)`` at rest over the step (``image`` 1) or ``(j, g_j, g_j +
        mirrored_motion(x_j, y_j - x_j))`` moving with ``j`` (``image`` 2;
        ``partner_displacement``)."""
        j, p = pair_partner(i, k, n, nbr, x, gn, goff, gmin, image)
        q = p
        if image == 0:
            q = y[j]
        elif image == 2:
            q = p + mirrored_motion(x[j], y[j] - x[j], gn, goff, gmin)
        return j, p, q

    @wp.func
    def moment_term(xb: vec3, h: scalar, c6: scalar):
        """Eq. 5's term of one pair at ``xb``: ``(|xb|^2, w, w xb xb^T)`` with the fit's weight
        ``w = w(|xb|^2)`` (eqs. 1, 7; ``c6 = fw.coef(h)``). Every sum of the linear fit's moment
        matrix adds this one product, so sums of the same pairs in the same order are the same
        bits (``position_moments`` and the variational force's adjoint rely on that)."""
        r2 = wp.dot(xb, xb)
        w = fw.w_c(r2, h, c6)
        return r2, w, w * wp.outer(xb, xb)

    @wp.func
    def moment_pair_terms(xb: vec3, h: scalar, c6: scalar, hh: scalar):
        """``moment_term`` of a same-body row pair and what it adds to the few-neighbours
        guard's smooth count (``guards.count_weight``, ``hh = h^2``): ``(w, w xb xb^T, c)``.
        Rows may reach beyond ``h`` (``neighbors.select_neighbors``): only partners of non-zero
        weight count."""
        r2, w, dA = moment_term(xb, h, c6)
        c, dc = gf.count_weight(r2, hh)
        return w, dA, c

    @wp.func
    def fit_pair_sums(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        given: int,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        image: int,
    ):
        """Eqs. 5-7: the fit's moments ``A = sum w xb xb^T``, ``B - A = sum w ub xb^T`` (returned
        as ``B``; ``ub = yb - xb``, the step's relative displacement) and the smooth count of
        same-body partners (the guard's, ``guards.count_weight``), over ``i``'s row neighbours
        (``image`` 0: ``xb = x_j - x_i``, ``ub = u_j - u_i``) or over the floor's images ``g_j``
        of ``i`` and of its same-body neighbours (``image`` 1: ``xb = g_j - x_i``, ``ub = -u_i``:
        the floor is at rest, an image does not move over the step; ``image`` 2: ``ub =
        J(x_j) u_j - u_i``, the image moving with its particle, ``partner_displacement``; an
        image is at least as far from ``x_i`` as its particle, so the row holds every image
        within ``h``).

        ``ub`` from each particle's displacement ``u = (y - x) + (y_lo - x_lo)`` (``x_lo``,
        ``y_lo``: the positions' round-off, ``State.x_lo``) rather than ``y_j - y_i``: ``y - x``
        is exact in floating point (the two positions are close), so the fit's increment
        ``dF - I`` is exactly 0 at rest and otherwise as precise as the motion, where
        ``B A^-1`` minus ``I`` would carry the round-off of the absolute positions and of the
        inverse, units in the last place of ``F`` every step (docs/physics.md, the float32
        creep floor).

        Only the raw sums live in this loop: the caller's inverse must not see a loop
        accumulator, whose adjoint Warp would not replay (docs/method.md, Warp pitfall 1).
        (Summing only A's six distinct entries measured 9 % slower: the matrix form vectorises.)

        ``given`` 1: ``y`` holds each particle's ``displacement`` already (``x_lo``, ``y_lo``
        unread; the fused step's, one load per neighbour instead of three)."""
        A = mat33()
        B = mat33()
        xi = x[i]
        ui = y[i]
        if given == 0:
            ui = displacement(xi, y[i], x_lo[i], y_lo[i])
        bi = body[i]
        c6 = fw.coef(h)
        hh = h * h
        same = scalar(0.0)
        for k in range(pair_slots(xi, n, h, gn, goff, image)):
            j, p = pair_partner(i, k, n, nbr, x, gn, goff, gmin, image)
            if body[j] == bi:
                xb = p - xi
                ub = partner_displacement(j, x, y, x_lo, y_lo, given, gn, goff, gmin, image) - ui
                w, dA, c = moment_pair_terms(xb, h, c6, hh)
                A += dA
                B += w * wp.outer(ub, xb)
                same += c
        return A, B, same

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
        """``fit_sums`` on ``x`` alone (``y = x``, so ``B - A = 0``) without its ``B``: the
        moment matrix ``A`` and the smooth count ``same``, the same terms in the same order
        (the same bits). A force that needs only ``A`` at the step's start (the variational
        force of the fused step) then skips a second outer product and the displacement's
        three loads per neighbour (measured: the compiler does not drop them)."""
        A = mat33()
        same = scalar(0.0)
        xi = x[i]
        bi = body[i]
        c6 = fw.coef(h)
        hh = h * h
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                w, dA, c = moment_pair_terms(x[j] - xi, h, c6, hh)
                A += dA
                same += c
        if images != 0:
            Ag, Bg, sg = fit_pair_sums(i, x, x, x, x, body, nbr, n, h, 0, gn, goff, gmin, 1)
            A = A + Ag
            same = same + sg
        return A, same

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
        """Eqs. 5-7 from the positions at the step's start and end over ``i``'s row neighbours
        (``fit_pair_sums``)."""
        A, B, same = fit_pair_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, 0, vec3(), scalar(0.0), scalar(0.0), 0)
        return A, B, same

    @wp.func
    def scatter_partner_adjoint(adj_x: wp.array(dtype=vec3), j: int, xj: vec3, g: vec3, gn: vec3, goff: scalar,
                                gmin: scalar, image: int):
        """Adds the adjoint ``g`` of a pair's far end to its particle ``j``: to ``x_j``, or where
        the far end is ``j``'s floor image (``image`` 1) by the chain rule through ``g_j(x_j)``,
        ``floor_image_jacobian(x_j) g`` (symmetric)."""
        if image != 0:
            wp.atomic_add(adj_x, j, floor_image_jacobian(xj, gn, goff, gmin) * g)
        else:
            wp.atomic_add(adj_x, j, g)

    @wp.func
    def scatter_own_adjoint(adj_x: wp.array(dtype=vec3), i: int, xi: vec3, gx: vec3, gg: vec3, gn: vec3, goff: scalar,
                            gmin: scalar):
        """Adds to ``adj x_i`` the adjoint ``gx`` of ``x_i`` itself and ``gg`` of its floor image
        ``g_i``, by the chain rule through ``g_i(x_i)``: ``gx + floor_image_jacobian(x_i) gg``
        (one add: the image terms of a particle's loops summed first)."""
        wp.atomic_add(adj_x, i, gx + floor_image_jacobian(xi, gn, goff, gmin) * gg)

    @wp.func
    def scatter_moving_image_adjoint(adj_x: wp.array(dtype=vec3), adj_y: wp.array(dtype=vec3), j: int, xj: vec3,
                                     yj: vec3, gg: vec3, gp: vec3, gu: vec3, gn: vec3, goff: scalar, gmin: scalar):
        """Adds to particle ``j`` the adjoints of its floor image ``g_j`` (``gg``, through
        ``floor_image_jacobian``), of ``x_j`` itself (``gp``) and of its image's displacement
        ``mirrored_motion(x_j, y_j - x_j)`` (``gu``, ``mirrored_motion_adjoint``): the far end of a
        pair with an image moving with its particle (``model.IMAGES_MOVING``)."""
        ax, au = mirrored_motion_adjoint(xj, yj - xj, gu, gn, goff, gmin)
        wp.atomic_add(adj_x, j, floor_image_jacobian(xj, gn, goff, gmin) * gg + gp + ax - au)
        wp.atomic_add(adj_y, j, au)

    @wp.func
    def fit_pair_adjoint(w: scalar, dw: scalar, xb: vec3, yb: vec3, adj_A: mat33, adj_A_sym: mat33, adj_B: mat33,
                         adj_r2: scalar):
        """Adjoint of one pair's terms ``w(|xb|^2) xb xb^T`` in ``A`` and ``w yb xb^T`` in ``B``
        (eqs. 5-7; ``dw = d w / d |xb|^2``, ``adj_A_sym = adj_A + adj_A^T``) and of whatever
        else depends on ``|xb|^2`` (``adj_r2``: the guard's count): returns
        ``(adj xb, adj yb)``."""
        Bx = adj_B * xb
        s = wp.dot(xb, adj_A * xb) + wp.dot(yb, Bx)
        return w * (adj_A_sym * xb + wp.transpose(adj_B) * yb) + scalar(2.0) * (dw * s + adj_r2) * xb, w * Bx

    @wp.func
    def scatter_pair_adjoint(adj_x: wp.array(dtype=vec3), adj_y: wp.array(dtype=vec3), j: int, xj: vec3, yj: vec3,
                             gx: vec3, gy: vec3, gn: vec3, goff: scalar, gmin: scalar, image: int):
        """Adds a fit pair's ``(adj xb, adj yb)`` to its partner ``j`` (``pair_ends``): to ``x_j``
        and ``y_j``; for a floor image at rest (``image`` 1), which stands at ``g_j`` at the
        step's start and end, their sum to ``x_j`` through ``floor_image_jacobian``; for one
        moving with ``j`` (``image`` 2), ending at ``g_j + J(x_j) (y_j - x_j)``, ``J gx`` to
        ``x_j``, ``J gy`` to ``y_j`` and the Jacobian's own slope to ``x_j``
        (``mirrored_motion_adjoint``)."""
        if image == 0:
            wp.atomic_add(adj_x, j, gx)
            wp.atomic_add(adj_y, j, gy)
        elif image == 1:
            wp.atomic_add(adj_x, j, floor_image_jacobian(xj, gn, goff, gmin) * (gx + gy))
        else:
            scatter_moving_image_adjoint(adj_x, adj_y, j, xj, yj, gx + gy, vec3(), gy, gn, goff, gmin)

    @wp.func
    def fit_pairs_adjoint(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                          nbr: wp.array2d(dtype=wp.int32), n: int, h: scalar, gn: vec3, goff: scalar, gmin: scalar,
                          image: int, adj_A: mat33, adj_A_sym: mat33, adj_B: mat33, adj_same: scalar,
                          adj_x: wp.array(dtype=vec3), adj_y: wp.array(dtype=vec3), gx_i: vec3, gy_i: vec3):
        """Adjoint of ``fit_pair_sums``' pairs (``image`` as there; ``yb = q - y_i`` with the far
        end ``q`` at the step's end, ``pair_ends``) given ``adj A``, ``adj B`` and ``adj same`` (the smooth
        count's, ``guards.count_weight``): each pair's
        ``fit_pair_adjoint`` scattered to its partner (``scatter_pair_adjoint``) and taken from
        ``i``'s, ``gx_i``, ``gy_i``, which it returns."""
        xi = x[i]
        yi = y[i]
        bi = body[i]
        c6 = fw.coef(h)
        hh = h * h
        for k in range(pair_slots(xi, n, h, gn, goff, image)):
            j, p, q = pair_ends(i, k, n, nbr, x, y, gn, goff, gmin, image)
            if body[j] == bi:
                xb = p - xi
                r2 = wp.dot(xb, xb)
                if r2 < hh:
                    w, dw = fw.w_inside(r2, hh, c6)
                    c, dc = gf.count_weight(r2, hh)
                    gx, gy = fit_pair_adjoint(w, dw, xb, q - yi, adj_A, adj_A_sym, adj_B, adj_same * dc)
                    scatter_pair_adjoint(adj_x, adj_y, j, x[j], y[j], gx, gy, gn, goff, gmin, image)
                    gx_i -= gx
                    gy_i -= gy
        return gx_i, gy_i

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
    ) -> mat33:
        """Eq. 5 of particle ``i``'s own image ``g_i``: ``A = sum w xb xb^T`` over ``i`` and its
        same-body neighbours, ``xb = x_r - g_i``, and over their images, ``xb = g_r - g_i``
        (the mirror ``R A_i R`` of ``i``'s where every image is a mirror). An image pair weighs
        as its particles' pair, ``w(|x_r - x_i|)``: the row holds every ``r`` within ``h`` of
        ``x_i``, but near the plane, where the images are held half a spacing deep, ``g_r`` may
        be within ``h`` of ``g_i`` while ``x_r`` is not, and such a pair would enter and leave
        the sum at a non-zero weight as ``r`` crosses the row's edge (a jump of the step;
        docs/physics.md, "The imaged ground's contact is smooth")."""
        A = mat33()
        xi = x[i]
        bi = body[i]
        gi = floor_image(xi, gn, goff, gmin)
        c6 = fw.coef(h)
        for k in range(image_row_length(xi, n, h, gn, goff)):
            j = image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                r2, w, dA = moment_term(x[j] - gi, h, c6)
                A += dA
                if j != i:
                    gb = floor_image(x[j], gn, goff, gmin) - gi
                    pb = x[j] - xi
                    A += fw.w_c(wp.dot(pb, pb), h, c6) * wp.outer(gb, gb)
        return A

    @wp.func
    def scatter_image_pair_adjoint(adj_A: mat33, adj_A_sym: mat33, M: mat33, a: vec3, gb: vec3, pb: vec3, hh: scalar,
                                   c6: scalar, adj_x: wp.array(dtype=vec3), j: int, xj: vec3, gn: vec3, goff: scalar,
                                   gmin: scalar):
        """Adjoint of an image-image term ``w(|pb|^2) gb gb^T`` of an image's moment matrix
        (``floor_image_moment``: ``gb = g_j - g_i``, weighed as its particles' pair
        ``pb = x_j - x_i``) and of the pair's force ``w M gb`` against ``a``
        (``forces.image_pair_force``; ``M`` 0 where the images rest and the pair has no
        force): ``adj gb = w (adj_A_sym gb + M^T a)``, ``adj pb = 2 dw (gb . adj_A gb + a . M
        gb) pb``, added to ``j`` (``gb``'s through ``floor_image_jacobian``); returned for
        ``i``: ``(adj g_i, adj x_i)``."""
        gg = vec3()
        gp = vec3()
        r2 = wp.dot(pb, pb)
        if r2 < hh:
            w, dw = fw.w_inside(r2, hh, c6)
            gg = w * (adj_A_sym * gb + wp.transpose(M) * a)
            gp = scalar(2.0) * dw * (wp.dot(gb, adj_A * gb) + wp.dot(a, M * gb)) * pb
            wp.atomic_add(adj_x, j, floor_image_jacobian(xj, gn, goff, gmin) * gg + gp)
        return gg, gp

    @wp.func
    def moving_image_pair_adjoint(adj_B: mat33, gb: vec3, pb: vec3, ub: vec3, hh: scalar, c6: scalar):
        """Adjoint of an image-image term ``w(|pb|^2) ub gb^T`` of a moving image's displacement
        moment (``floor_image_displacement_sums``, ``images`` 2): ``(adj gb, adj pb, adj ub)`` =
        ``(w adj_B^T ub, 2 dw (ub . adj_B gb) pb, w adj_B gb)``."""
        gg = vec3()
        gp = vec3()
        gu = vec3()
        r2 = wp.dot(pb, pb)
        if r2 < hh:
            w, dw = fw.w_inside(r2, hh, c6)
            Bg = adj_B * gb
            gg = w * (wp.transpose(adj_B) * ub)
            gp = scalar(2.0) * dw * wp.dot(ub, Bg) * pb
            gu = w * Bg
        return gg, gp, gu

    @wp.struct
    class ImageSums:
        """The sums of a floor image's own fit that move with the particles
        (``floor_image_displacement_sums``): ``B - A`` and the pairs' weight sum."""
        Bu: mat33

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
        """Eq. 6 of particle ``i``'s own image ``g_i``: ``B - A = sum w ub xb^T`` over ``i`` and
        its same-body neighbours, ``xb = x_r - g_i``, ``ub = u_r - u_g`` (their displacements,
        ``displacement``, less the image's own, ``partner_displacement``: 0 for images at rest,
        ``images`` 1, whose image pairs do not move either); for images moving with their
        particles (``images`` 2) also over the neighbours' images, ``xb = g_r - g_i`` weighed
        as their particles' pair (``floor_image_moment``), ``ub = J(x_r) u_r - u_g``. Also the sum
        of the particle pairs' weights: 0 where no particle is within ``h`` of the image."""
        B = mat33()
        xi = x[i]
        bi = body[i]
        gi = floor_image(xi, gn, goff, gmin)
        ug = partner_displacement(i, x, y, x_lo, y_lo, 0, gn, goff, gmin, images)
        c6 = fw.coef(h)
        for k in range(image_row_length(xi, n, h, gn, goff)):
            j = image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xb = x[j] - gi
                w = fw.w_c(wp.dot(xb, xb), h, c6)
                B += w * wp.outer(displacement(x[j], y[j], x_lo[j], y_lo[j]) - ug, xb)
                if images == 2 and j != i:
                    pb = x[j] - xi
                    B += fw.w_c(wp.dot(pb, pb), h, c6) * wp.outer(
                        partner_displacement(j, x, y, x_lo, y_lo, 0, gn, goff, gmin, images) - ug,
                        floor_image(x[j], gn, goff, gmin) - gi)
        sums = ImageSums()
        sums.Bu = B
        return sums

    @wp.func
    def floor_image_share(near: int, images: int) -> scalar:
        """How much of a floor image's F is its own (``floor_image_update``): 1 wherever its
        own fit runs (its particle within ``h`` of the plane, ``near``) and for images at rest
        (``images`` 1) everywhere: a floor at rest keeps its own F, as a particle floor's pinned
        particles do, and an image with no particle near it keeps it unchanged (its fit sees no
        motion). An image moving with its particle (2) beyond ``h`` carries its particle's new
        F mirrored (0). Blended towards its particle's F (a share below 1 inside ``h``), the
        image stored a share of a work its force did not do, and an undamped block gained energy
        (docs/physics.md, "Where the imaged ground's images store no energy", "The frictionless
        imaged ground below half a spacing"). Where its particle crosses ``h`` the image's own F
        is its particle's mirrored while every partner in its row is over half a spacing up
        (its fit then sees only its mirror's); with a partner below that, held on the depth
        ramp, the two differ, and the image's share of the energy fades to 0 at ``h``
        (``forces.image_energy_share``) so that neither the energy nor the force jumps as the
        particle leaves (docs/physics.md, "Where a particle crosses ``h``")."""
        c = scalar(1.0)
        if images == 2 and near == 0:
            c = scalar(0.0)
        return c

    @wp.func
    def uncompensated_update(F: mat33, inc: mat33, scale: scalar):
        """Eq. 8 faded and without ``F``'s round-off carried (``carried_update`` carries it):
        ``F + (scale inc) F``, ``inc = dF - I`` unfaded, and 1; or ``F`` and 0 where that would
        invert (det <= 0, paper §4). A floor image's own update is this (``State.F_image``
        carries no round-off), and the adjoints recompute with it what the update took."""
        out = F
        applied = int(0)
        cand = F + (scale * inc) * F
        if wp.determinant(cand) > scalar(0.0):
            out = cand
            applied = 1
        return out, applied

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
        """The image's own eq. 8 (``image_update_funcs``): ``Fg + scale B_g A_g^-1 Fg`` and 1,
        or ``Fg`` and 0 where its fit is empty, ``i``'s is guarded (``code``) or the update
        would invert."""
        out = Fg
        applied = int(0)
        if code == 0 and image_row_length(x[i], n, h, gn, goff) > 0:
            Ag = floor_image_moment(i, x, body, nbr, n, h, gn, goff, gmin)
            out, applied = uncompensated_update(Fg, affine_fit(Ag, sums.Bu), scale)
        return out, applied

    @wp.func
    def particle_f_for_image(F: mat33, n: vec3, images: int) -> mat33:
        """A particle's ``F`` as its floor image carries it where the image's own fit does not
        run (``floor_image_select``): ``F`` itself for images at rest (``images`` 1, whose
        share is 1: unread), its mirror ``R F R`` (``R = I - 2 n n^T``) for images moving
        with their particles (``images`` 2): there the image is the particle's mirror, whose own
        fit gives ``R dF R`` to its particle's ``dF``; carrying ``F`` unmirrored, an undamped
        elastic block floating on the frictionless imaged ground gained sideways momentum and
        energy (docs/physics.md, "The imaged ground is rough whatever its friction"). Linear and
        self-adjoint in ``F``: its adjoint is itself."""
        out = F
        if images == 2:
            R = wp.identity(n=3, dtype=scalar) - scalar(2.0) * wp.outer(n, n)
            out = R * F * R
        return out

    @wp.func
    def floor_image_select(own: mat33, F_new: mat33, near: int, images: int):
        """The image's new F, its own updated ``own`` or its particle's new ``F_new`` as
        ``floor_image_share`` (of ``near``, the image loop's length) has it, and that share."""
        c = floor_image_share(near, images)
        out = own
        if c < scalar(1.0):
            out = F_new
        return out, c

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
        """Adjoint of ``floor_image_own_update`` where the image's own fit applied (``sums``,
        ``Ag`` its sums at ``x``, ``y``; ``Gg`` the gradient of its output): scatters the pairs'
        adjoints (``B``'s ``w u xb^T`` with ``u = y_r - x_r - u_g``, ``xb = x_r - g_i``, and
        ``floor_image_moment``'s two kinds of term) to ``x`` and ``y``, ``g_i``'s to ``x_i``
        through ``floor_image_jacobian``; for moving images (``images`` 2) the image pairs'
        ``B`` terms too (``moving_image_pair_adjoint``) and the image's own displacement
        ``u_g``'s (``scatter_moving_image_adjoint``); returns ``(adj Fg, adj scale)``."""
        Ag_inv = wp.inverse(floor_image_moment(i, x, body, nbr, n, h, gn, goff, gmin))
        D0 = sums.Bu * Ag_inv
        adj_B = scale * (Gg * wp.transpose(Fg)) * Ag_inv
        adj_A = -(wp.transpose(D0) * adj_B)
        adj_A_sym = adj_A + wp.transpose(adj_A)
        xi = x[i]
        bi = body[i]
        gi = floor_image(xi, gn, goff, gmin)
        c6 = fw.coef(h)
        hh = h * h
        gg_i = vec3()
        gx_i = vec3()
        gu_i = vec3()
        # The image's own displacement (the round-off arrays are not differentiated: x for both).
        ug = partner_displacement(i, x, y, x, x, 0, gn, goff, gmin, images)
        for k in range(image_row_length(xi, n, h, gn, goff)):
            j = image_row_particle(i, k, n, nbr)
            if body[j] == bi:
                xj = x[j]
                xb = xj - gi
                r2 = wp.dot(xb, xb)
                if r2 < hh:
                    w, dw = fw.w_inside(r2, hh, c6)
                    u = y[j] - xj - ug
                    Bx = adj_B * xb
                    adj_u = w * Bx
                    adj_xb = (w * (adj_A_sym * xb + wp.transpose(adj_B) * u)
                              + scalar(2.0) * dw * (wp.dot(xb, adj_A * xb) + wp.dot(u, Bx)) * xb)
                    wp.atomic_add(adj_y, j, adj_u)
                    wp.atomic_add(adj_x, j, adj_xb - adj_u)
                    gg_i -= adj_xb
                    gu_i -= adj_u
                if j != i:
                    gb = floor_image(xj, gn, goff, gmin) - gi
                    gg, gp = scatter_image_pair_adjoint(adj_A, adj_A_sym, mat33(), vec3(), gb, xj - xi, hh, c6, adj_x, j,
                                                        xj, gn, goff, gmin)
                    gg_i -= gg
                    gx_i -= gp
                    if images == 2:
                        yj = y[j]
                        gg, gp, gu = moving_image_pair_adjoint(adj_B, gb, xj - xi,
                                                               mirrored_motion(xj, yj - xj, gn, goff, gmin) - ug, hh, c6)
                        scatter_moving_image_adjoint(adj_x, adj_y, j, xj, yj, gg, gp, gu, gn, goff, gmin)
                        gg_i -= gg
                        gx_i -= gp
                        gu_i -= gu
        if images == 2:
            scatter_moving_image_adjoint(adj_x, adj_y, i, xi, y[i], vec3(), vec3(), gu_i, gn, goff, gmin)
        scatter_own_adjoint(adj_x, i, xi, gx_i, gg_i, gn, goff, gmin)
        adj_Fg = wp.transpose(wp.identity(n=3, dtype=scalar) + scale * D0) * Gg
        return adj_Fg, wp.ddot(Gg * wp.transpose(Fg), D0)

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
        """``moment_sums``, plus ``fit_pair_sums`` over the floor's images where the model has
        an image plane (``images``)."""
        A, B, same = moment_sums(i, x, y, x_lo, y_lo, body, nbr, n, h)
        if images != 0:
            Ag, Bg, sg = fit_pair_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, 0, gn, goff, gmin, images)
            A = A + Ag
            B = B + Bg
            same = same + sg
        return A, B, same

    @wp.func
    def affine_fit(A: mat33, B: mat33) -> mat33:
        """Eqs. 5-6: the least-squares affine map ``B A^-1`` of the weighted moments; of the
        displacement moment ``B - A`` (``moment_sums``) it is ``dF - I``."""
        return B * wp.inverse(A)

    @wp.func
    def step_increment(A: mat33, Bu: mat33, code: int, scale: scalar, slot: int,
                       counters: wp.array(dtype=wp.int32)) -> mat33:
        """This step's ``dF - I`` (eqs. 4-6) times the guards' fade ``scale``
        (``guards.guard_scale``: below 1 where ``cond(A)`` passes ``max_condition`` or the smooth
        neighbour count falls towards ``min_neighbors - 1``); 0, counted, where a guard of
        paper §4 holds (``code``: ``neighbors.GUARD_*``), at its body's ``slot`` too (``COUNT_BODY``)."""
        D = mat33()
        if code == 1 or code == 2:
            count_guarded(code, slot, counters)
        else:
            D = scale * affine_fit(A, Bu)
        return D

    @wp.func
    def step_gradient(A: mat33, Bu: mat33, code: int, scale: scalar, slot: int,
                      counters: wp.array(dtype=wp.int32)) -> mat33:
        """This step's ``dF = B A^-1`` (eqs. 4-6, ``step_increment``); ``I``, counted, where a
        guard of paper §4 holds (``code``: ``neighbors.GUARD_*``)."""
        return wp.identity(n=3, dtype=scalar) + step_increment(A, Bu, code, scale, slot, counters)

    @wp.func
    def unless_inverted(candidate: mat33, F: mat33, counters: wp.array(dtype=wp.int32)) -> mat33:
        """``candidate`` unless it inverts (det <= 0, paper §4): then ``F``, counted."""
        out = F
        if wp.determinant(candidate) > scalar(0.0):
            out = candidate
        else:
            wp.atomic_add(counters, COUNT_INVERTED, 1)
        return out

    @wp.func
    def carried_update(D: mat33, F: mat33, F_lo: mat33, counters: wp.array(dtype=wp.int32)):
        """Eq. 8 of this step's ``D = dF - I`` (of either fit): ``F <- dF F`` of the compensated
        ``F + F_lo`` (``State.F_lo``) unless it inverts; returns the new ``(F, F_lo)``."""
        # As F + (dF - I) F with F's round-off carried: the step's increment, a few units in
        # F's last place near rest, is not rounded away (docs/physics.md, the float32 creep
        # floor). A guarded particle gets dF - I = 0 and keeps F + F_lo, whose det > 0.
        F_new, F_new_lo = compensated_sum(F, F_lo + D * F)
        out = F
        out_lo = F_lo
        if wp.determinant(F_new) > scalar(0.0):
            out = F_new
            out_lo = F_new_lo
        else:
            wp.atomic_add(counters, COUNT_INVERTED, 1)
        return out, out_lo

    @wp.func
    def deformation_update(A: mat33, Bu: mat33, code: int, scale: scalar, F: mat33, F_lo: mat33, slot: int,
                           counters: wp.array(dtype=wp.int32)):
        """Eq. 8 with the guards of paper §4 (``code``, and their fade ``scale``): ``F <- dF F``
        unless guarded or inverted, of the compensated ``F + F_lo``; returns the new ``(F, F_lo)``."""
        return carried_update(step_increment(A, Bu, code, scale, slot, counters), F, F_lo, counters)

    # The fit's side of the update kernels (``update_kernels``); ``curvature.funcs`` has the
    # same four for the corrected fit.
    @wp.func
    def fit_increment(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                      y_lo: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32), n: int,
                      h: scalar, gn: vec3, goff: scalar, gmin: scalar, images: int, code: int, min_neighbors: int,
                      max_condition: scalar, counters: wp.array(dtype=wp.int32)):
        """This step's guarded ``dF - I`` (``step_increment``) of ``i``'s fit and the guards'
        fade ``scale`` it carries (``guards.guard_scale``)."""
        A, B, same = fit_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
        scale = gf.guard_scale(A, same, min_neighbors, max_condition)
        return step_increment(A, B, code, scale, COUNT_BODY + body[i], counters), scale

    @wp.struct
    class FitMoments:
        """One particle's sums of ``fit_sums``: the moment matrix ``A``, the displacement
        moment ``B - A`` and the smooth same-body count."""
        A: mat33
        Bu: mat33
        same: scalar

    @wp.func
    def fit_moments(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                    y_lo: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32), n: int,
                    h: scalar, gn: vec3, goff: scalar, gmin: scalar, images: int) -> FitMoments:
        """``fit_sums`` as one value, for the adjoint kernel."""
        A, Bu, same = fit_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
        m = FitMoments()
        m.A = A
        m.Bu = Bu
        m.same = same
        return m

    @wp.func
    def moments_increment(m: FitMoments) -> mat33:
        """The unguarded ``dF - I`` of the moments (``affine_fit``)."""
        return affine_fit(m.A, m.Bu)

    @wp.func
    def moments_adjoint(i: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                        nbr: wp.array2d(dtype=wp.int32), n: int, h: scalar, gn: vec3, goff: scalar, gmin: scalar,
                        images: int, m: FitMoments, inc0: mat33, adj_inc0: mat33, adj_A_fade: mat33, adj_same: scalar,
                        adj_x: wp.array(dtype=vec3), adj_y: wp.array(dtype=vec3)):
        """Adjoint of ``moments_increment`` (``inc0 = Bu A^-1``) and of the sums, given the
        gradient of ``inc0`` and the fade's own ``adj A`` and ``adj same``: ``adj Bu = adj inc0
        A^-T``, ``adj A = -(I + inc0)^T adj Bu`` (``B = Bu + A``, the same function of the
        positions) plus the fade's, scattered over the row's pairs and the floor's images
        (``fit_pairs_adjoint``). Returns what goes to ``x_i``, ``y_i``."""
        adj_B = adj_inc0 * wp.transpose(wp.inverse(m.A))
        adj_A = -((wp.identity(n=3, dtype=scalar) + wp.transpose(inc0)) * adj_B) + adj_A_fade
        adj_A_sym = adj_A + wp.transpose(adj_A)
        gx_i, gy_i = fit_pairs_adjoint(i, x, y, body, nbr, n, h, gn, goff, gmin, 0, adj_A, adj_A_sym, adj_B, adj_same,
                                       adj_x, adj_y, vec3(), vec3())
        if images != 0:
            gx_i, gy_i = fit_pairs_adjoint(i, x, y, body, nbr, n, h, gn, goff, gmin, images, adj_A, adj_A_sym, adj_B,
                                           adj_same, adj_x, adj_y, gx_i, gy_i)
        return gx_i, gy_i

    return types.SimpleNamespace(
        displacement=displacement, pair_slots=pair_slots, pair_partner=pair_partner, pair_ends=pair_ends,
        moment_term=moment_term, moment_pair_terms=moment_pair_terms, fit_pair_sums=fit_pair_sums,
        moment_sums=moment_sums, position_moments=position_moments, floor_image=floor_image,
        image_row_length=image_row_length, image_slots=image_slots, image_row_particle=image_row_particle,
        fit_sums=fit_sums,
        floor_image_jacobian=floor_image_jacobian, fit_pair_adjoint=fit_pair_adjoint,
        mirrored_motion=mirrored_motion, mirrored_motion_adjoint=mirrored_motion_adjoint,
        partner_displacement=partner_displacement, scatter_moving_image_adjoint=scatter_moving_image_adjoint,
        moving_image_pair_adjoint=moving_image_pair_adjoint,
        scatter_partner_adjoint=scatter_partner_adjoint, scatter_own_adjoint=scatter_own_adjoint,
        scatter_pair_adjoint=scatter_pair_adjoint, fit_pairs_adjoint=fit_pairs_adjoint,
        floor_image_moment=floor_image_moment, scatter_image_pair_adjoint=scatter_image_pair_adjoint,
        floor_image_displacement_sums=floor_image_displacement_sums, floor_image_share=floor_image_share,
        ImageSums=ImageSums, floor_image_own_update=floor_image_own_update,
        floor_image_select=floor_image_select,
        particle_f_for_image=particle_f_for_image,
        floor_image_own_update_adjoint=floor_image_own_update_adjoint, affine_fit=affine_fit, step_increment=step_increment,
        uncompensated_update=uncompensated_update,
        step_gradient=step_gradient, unless_inverted=unless_inverted,
        carried_update=carried_update, deformation_update=deformation_update, fit_increment=fit_increment,
        FitMoments=FitMoments, fit_moments=fit_moments, moments_increment=moments_increment, moments_adjoint=moments_adjoint,
    )


def fit_funcs(scalar, weight: str, fit: str) -> types.SimpleNamespace:
    """The functions of ``fit`` ("linear": this module's ``funcs``; "curvature_corrected":
    ``curvature.funcs``, whose functions build on these; "auto" is resolved before,
    ``Model.solver_choice``)."""
    checks.choice("fit", fit, ("linear", "curvature_corrected"))
    if fit == "linear":
        return funcs(scalar, weight)
    from . import curvature  # imports this module

    return curvature.funcs(scalar, weight)


@functools.cache
def image_update_funcs(scalar, weight: str, fit: str) -> types.SimpleNamespace:
    """Eq. 8 of a floor image (``State.F_image``) and its adjoint, written once for both
    fits: ``fit`` (``fit_funcs``) supplies the image's own sums
    (``floor_image_displacement_sums``, its ``ImageSums``), its own update and that
    update's adjoint; the share is this module's."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    df = funcs(scalar, weight)
    fn = fit_funcs(scalar, weight, fit)

    @wp.func
    def floor_image_update(
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
        code: int,
        scale: scalar,
        Fg: mat33,
        F_new: mat33,
    ):
        """Eq. 8 of particle ``i``'s floor image (``State.F_image``). The image is a floor
        particle, at rest over the step or moving with ``i`` (``images``,
        ``floor_image_displacement_sums``): its own fit over the particles near it (the fit's
        ``floor_image_displacement_sums`` and ``floor_image_moment``), faded as ``i``'s
        (``scale``), updates its own flowed ``Fg``, so that the work of its energy (the
        fit's ``image_map``) is stored as a particle's is (docs/physics.md, "The floor
        images' energy is not stored"). An image at rest keeps its own F wherever it is (a
        floor at rest); an image moving with ``i`` keeps its own while ``i`` is within ``h`` of
        the plane (its energy counted there, ``forces.image_energy_share``) and carries its
        particle's new F, ``F_new``, mirrored beyond (``floor_image_share``; the two agree
        where ``i`` crosses ``h`` while every image in its row is its particle's mirror, its
        particle over half a spacing up). Returns the image's new F and that share (``State.image_share``: the image's
        hardening is chosen by it too, ``plasticity.image_hardening_update``)."""
        sums = fn.floor_image_displacement_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
        own, applied = fn.floor_image_own_update(i, x, body, nbr, n, h, gn, goff, gmin, code, scale, sums, Fg)
        return df.floor_image_select(own, df.particle_f_for_image(F_new, gn, images),
                                     df.image_row_length(x[i], n, h, gn, goff), images)

    @wp.func
    def floor_image_update_adjoint(
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
        code: int,
        scale: scalar,
        Fg: mat33,
        Gg: mat33,
        adj_x: wp.array(dtype=vec3),
        adj_y: wp.array(dtype=vec3),
    ):
        """Adjoint of ``floor_image_update`` inside ``update_kernels``' adjoint (``Gg`` the
        gradient of the image's new F; its share is constant where it is smooth, so the share's
        gradient goes nowhere): the pairs' adjoints scattered to ``x`` and ``y``
        (the fit's ``floor_image_own_update_adjoint``); returns the share of ``Gg`` that joins
        the gradient of the particle's new F, and the adjoints of the image's flowed F and of
        the fade ``scale``."""
        sums = fn.floor_image_displacement_sums(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
        own, applied = fn.floor_image_own_update(i, x, body, nbr, n, h, gn, goff, gmin, code, scale, sums, Fg)
        c = df.floor_image_share(df.image_row_length(x[i], n, h, gn, goff), images)
        adj_Fg = c * Gg
        adj_s = scalar(0.0)
        if applied != 0:
            adj_Fg, adj_s = fn.floor_image_own_update_adjoint(i, x, y, body, nbr, n, h, gn, goff, gmin, images, scale, sums,
                                                              Fg, c * Gg, adj_x, adj_y)
        return df.particle_f_for_image((scalar(1.0) - c) * Gg, gn, images), adj_Fg, adj_s

    return types.SimpleNamespace(floor_image_update=floor_image_update,
                                 floor_image_update_adjoint=floor_image_update_adjoint)


@functools.cache
def kernels(scalar, weight: str) -> types.SimpleNamespace:
    """The update kernels of the linear fit (``update_kernels``)."""
    return update_kernels(scalar, weight, "linear")


@functools.cache
def update_kernels(scalar, weight: str, fit: str) -> types.SimpleNamespace:
    """Eq. 8's update and its hand-written adjoint for ``fit`` ("linear": this module's
    ``funcs``; "curvature_corrected": ``curvature.funcs``, whose functions build on these),
    whose functions supply
    ``fit_increment``, ``fit_moments``, ``moments_increment``, ``moments_adjoint`` and eq.
    8's ``carried_update`` (the same for both, as are the guards); the floor image's update
    and its adjoint are ``image_update_funcs``'."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    gf = guards.guard_funcs(scalar)
    df = funcs(scalar, weight)
    fn = fit_funcs(scalar, weight, fit)
    fi = image_update_funcs(scalar, weight, fit)

    @wp.kernel(module="unique")
    def update_deformation(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        F_prev: wp.array(dtype=mat33),
        F_prev_lo: wp.array(dtype=mat33),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        Fg_prev: wp.array(dtype=mat33),
        F_out: wp.array(dtype=mat33),
        F_out_lo: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
        Fg_out: wp.array(dtype=mat33),
        share_out: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        inc, scale = fn.fit_increment(i, x, y, x_lo, y_lo, body, nbr, count[i], h, gn, goff, gmin, images, guard[i],
                                      min_neighbors, max_condition, counters)
        F_new, F_new_lo = fn.carried_update(inc, F_prev[i], F_prev_lo[i], counters)
        F_out[i] = F_new
        F_out_lo[i] = F_new_lo
        # The floor image's own F (State.F_image) and its share; without images, its particle's.
        Fg_new = F_new
        c = scalar(0.0)
        if images != 0:
            Fg_new, c = fi.floor_image_update(i, x, y, x_lo, y_lo, body, nbr, count[i], h, gn, goff, gmin, images,
                                              guard[i], scale, Fg_prev[i], F_new)
        Fg_out[i] = Fg_new
        share_out[i] = c

    @wp.kernel(enable_backward=False, module="unique")
    def update_deformation_adjoint(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        F_prev: wp.array(dtype=mat33),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        Fg_prev: wp.array(dtype=mat33),
        adj_F_out: wp.array(dtype=mat33),
        adj_Fg_out: wp.array(dtype=mat33),
        adj_x: wp.array(dtype=vec3),
        adj_y: wp.array(dtype=vec3),
        adj_F_prev: wp.array(dtype=mat33),
        adj_Fg_prev: wp.array(dtype=mat33),
    ):
        """Hand-written adjoint of ``update_deformation`` (eqs. 5-8 differentiated): the
        tape's generated one spends 15-20x the forward on per-neighbour matrix selects and
        zeroing; this one recomputes the sums once and scatters one vector per pair.

        With ``inc0`` the fit's unguarded ``dF - I`` (``moments_increment``), ``dF = I + s
        inc0`` and ``F_out = dF F``: ``adj F = dF^T G``, ``adj inc0 = s G F^T``, and the fit
        takes it back to its moments and their pairs (``moments_adjoint``: for the linear fit
        ``adj B = adj inc0 A^-T``, ``adj A = -dF0^T adj B``, per pair ``A`` and ``B`` depend on
        ``xb`` through ``w(|xb|^2) xb xb^T`` and ``w yb xb^T``; with ``images`` the floor's
        image pairs likewise, scattered to ``x_j`` through ``floor_image_jacobian``). Guarded
        or inverted particles keep ``F``: all of ``G`` goes to ``F``. The fade ``s(A, same)``
        (``guards.guard``) adds ``(adj dF : inc0) ds/dA`` to ``adj A`` and gives the smooth
        count ``same`` its adjoint ``(adj dF : inc0) ds/dsame``, spread over the pairs by the
        slope of ``guards.count_weight``.

        With ``images`` the image's own update (``floor_image_update``) too
        (``floor_image_update_adjoint``): its share of the gradient of ``F_new`` joins ``G``,
        the rest goes to the image's flowed F and, through its fit, to the positions, and its
        fade's share joins ``adj s``."""
        i = wp.tid()
        G = adj_F_out[i]
        Fp = F_prev[i]
        code = guard[i]
        n = count[i]
        # The round-off arrays enter the sums but are not differentiated (roundoff.py).
        m = fn.fit_moments(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin, images)
        inc0 = fn.moments_increment(m)
        # The fade s(A, same) on the plain moment matrix (guards.guard): inc = s inc0.
        code_, s, ds_dA, ds_dn = gf.guard(m.A, m.same, min_neighbors, max_condition)
        # The image's update (floor_image_update): its share of the gradient of F_new joins G.
        adj_s = scalar(0.0)
        if images != 0:
            G_share, adj_Fg, adj_sg = fi.floor_image_update_adjoint(i, x, y, x_lo, y_lo, body, nbr, n, h, gn, goff, gmin,
                                                                    images, code, s, Fg_prev[i], adj_Fg_out[i], adj_x,
                                                                    adj_y)
            G = G + G_share
            adj_Fg_prev[i] = adj_Fg_prev[i] + adj_Fg
            adj_s = adj_sg
        if code == 1 or code == 2:
            adj_F_prev[i] = adj_F_prev[i] + G
            return
        dF = wp.identity(n=3, dtype=scalar) + s * inc0
        F_new, applied = df.uncompensated_update(Fp, inc0, s)
        if applied == 0:
            # F is kept; the image's fade (adj s) still reaches A through the guard.
            adj_F_prev[i] = adj_F_prev[i] + G
            if adj_s == scalar(0.0):
                return
            G = mat33()
        else:
            adj_F_prev[i] = adj_F_prev[i] + wp.transpose(dF) * G
        adj_inc = G * wp.transpose(Fp)
        adj_s += wp.ddot(adj_inc, inc0)
        gx_i, gy_i = fn.moments_adjoint(i, x, y, body, nbr, n, h, gn, goff, gmin, images, m, inc0, s * adj_inc,
                                        adj_s * ds_dA, adj_s * ds_dn, adj_x, adj_y)
        wp.atomic_add(adj_x, i, gx_i)
        wp.atomic_add(adj_y, i, gy_i)

    return types.SimpleNamespace(update_deformation=update_deformation, update_deformation_adjoint=update_deformation_adjoint)


def image_F_flowed(model, state_out):
    """The images' flowed F the update reads (``State.F_image_flowed``); without an image
    plane, an array of the right shape that it does not read."""
    return state_out.F_image_flowed if model.image_plane is not None else state_out.F_flowed


def fit_kernels(model, fit: str = "linear") -> types.SimpleNamespace:
    """The update kernels of ``fit`` ("linear" or "curvature_corrected": a fit the solver
    resolved, ``Model.solver_choice``) for the model's precision and fit weight."""
    return update_kernels(model.scalar, model.fit_weight, fit)


def launch_update_deformation(model, state_in, state_out, counters, hand_adjoint: bool = True, y=None, y_lo=None,
                              max_condition: float = guards.MAX_CONDITION, min_neighbors: int = guards.MIN_NEIGHBORS,
                              fit: str = "linear"):
    """Eqs. 1-8 over the step from ``state_in.x`` to ``state_out.x`` (or to ``y``, ``y_lo``
    where given: a ghost floor's fit positions, ``ghost_floor.launch_fit_positions``), with
    the neighbourhood guards the neighbour search wrote to ``state_out.guard`` and the fades
    from ``max_condition`` and ``min_neighbors`` (the solver's; ``guards``), by the linear
    fit or the curvature-corrected one (``fit``, ``fit_kernels``). Under a ``wp.Tape`` the
    backward runs ``update_deformation_adjoint`` (``hand_adjoint=False``: Warp's generated
    adjoint, which tests compare it against)."""
    k = fit_kernels(model, fit)
    y = state_out.x if y is None else y
    y_lo = state_out.x_lo if y_lo is None else y_lo
    inputs = [
        state_in.x, y, state_in.x_lo, y_lo, model.particle_body, state_out.neighbors,
        state_out.neighbor_count, state_out.guard, state_out.F_flowed, state_out.F_flowed_lo,
        model.scalar(model.support_radius), int(min_neighbors), model.scalar(max_condition), *model.image_args(),
        image_F_flowed(model, state_out),
    ]
    outputs = [state_out.F, state_out.F_lo, counters, state_out.F_image, state_out.image_share]
    tape = recording_tape()
    grads = (state_in.x, y, state_out.F_flowed, state_out.F)
    if model.image_plane is not None:
        grads += (state_out.F_image_flowed, state_out.F_image, state_out.image_share)
    if tape is None or not hand_adjoint or any(a.grad is None for a in grads):
        model.launches(k.update_deformation, model.particle_count, inputs, outputs, device=model.device)
        return
    # Under a tape: the forward unrecorded, and the hand-written adjoint in its place.
    model.launches(k.update_deformation, model.particle_count, inputs, outputs, device=model.device, record_tape=False)

    tape.record_func(lambda: launch_update_deformation_adjoint(model, state_in, state_out, y, y_lo, max_condition,
                                                               min_neighbors, fit),
                     list(grads))


def launch_update_deformation_adjoint(model, state_in, state_out, y=None, y_lo=None,
                                      max_condition: float = guards.MAX_CONDITION,
                                      min_neighbors: int = guards.MIN_NEIGHBORS, fit: str = "linear"):
    """``update_deformation_adjoint`` of ``fit``: ``state_out.F.grad`` (and ``F_image.grad``)
    into the gradients of ``state_in.x``, ``state_out.x`` (or ``y``) and
    ``state_out.F_flowed`` (and ``F_image_flowed``), with the guards in ``state_out.guard``."""
    y = state_out.x if y is None else y
    y_lo = state_out.x_lo if y_lo is None else y_lo
    images = model.image_plane is not None
    model.launches(
        fit_kernels(model, fit).update_deformation_adjoint, model.particle_count,
        [
            state_in.x, y, state_in.x_lo, y_lo, model.particle_body, state_out.neighbors,
            state_out.neighbor_count, state_out.guard, state_out.F_flowed, model.scalar(model.support_radius),
            int(min_neighbors), model.scalar(max_condition),
            *model.image_args(), image_F_flowed(model, state_out), state_out.F.grad,
            state_out.F_image.grad if images else state_out.F.grad, state_in.x.grad,
            y.grad, state_out.F_flowed.grad, state_out.F_image_flowed.grad if images else state_out.F_flowed.grad,
        ],
        device=model.device, record_tape=False,
    )
