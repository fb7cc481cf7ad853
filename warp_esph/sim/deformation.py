"""Incremental deformation gradient (paper eqs. 1-8, docs/method.md §2).

Over one step, with ``x`` the positions at its start and ``y`` at its end, the
weighted least-squares affine fit to the same-body neighbours is

    xb_j = x_j - x_i,  yb_j = y_j - y_i,  w_j = W_poly6(|xb_j|, h)     (eqs. 1, 7)
    A = sum_j w_j xb_j xb_j^T,  B = sum_j w_j yb_j xb_j^T,  dF = B A^-1  (eqs. 5-6)
    F_i <- dF F_i                                                       (eq. 8)

Relative vectors make the fit translation invariant; it reproduces any affine motion
exactly. The update is skipped (the old F kept, and counted) when the neighbourhood
guard of ``neighbors`` fired or the candidate has ``det <= 0`` (an inverted or
degenerate F: with the rotation-variant SVD that is exactly a signed singular value
``<= 0``).
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import smoothing

#: Indices into the solver's guard counters.
COUNT_FEW_NEIGHBORS = 0
COUNT_ILL_CONDITIONED = 1
COUNT_INVERTED = 2


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    sm = smoothing.funcs(scalar)

    @wp.func
    def moment_sums(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
    ):
        """Eqs. 5-7: the fit's moments ``A = sum w xb xb^T``, ``B = sum w yb xb^T`` and the
        number of same-body neighbours closer than ``h`` (the guard's).

        Only the raw sums live in this loop: the caller's inverse must not see a loop
        accumulator, whose adjoint Warp would not replay (docs/method.md, Warp pitfall 1).
        (Summing only A's six distinct entries measured 9 % slower: the matrix form vectorises.)"""
        A = mat33()
        B = mat33()
        xi = x[i]
        yi = y[i]
        bi = body[i]
        c6 = sm.poly6_coef(h)
        same = int(0)
        for k in range(n):
            j = nbr[i, k]
            if body[j] == bi:
                xb = x[j] - xi
                yb = y[j] - yi
                r2 = wp.dot(xb, xb)
                w = sm.w_poly6_c(r2, h, c6)
                A += w * wp.outer(xb, xb)
                B += w * wp.outer(yb, xb)
                # Rows may reach beyond h (neighbors.select_neighbors): only neighbours
                # of non-zero weight count for the guard.
                same += wp.where(r2 < h * h, 1, 0)
        return A, B, same

    @wp.func
    def floor_image(x: vec3, n: vec3, offset: scalar, min_depth: scalar) -> vec3:
        """The image of ``x`` in the rough floor ``dot(n, x) = offset``: below its foot on the
        plane, as deep as ``x`` is high but at least ``min_depth`` (half a spacing: the
        floor's top layer of a floor of particles), so that a particle pressed towards the
        plane closes on its image as on a floor particle (docs/physics.md, "The ground
        collider's thin-layer strength")."""
        d = wp.dot(n, x) - offset
        return x - (d + wp.max(d, min_depth)) * n

    @wp.func
    def floor_image_sums(
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
    ):
        """Eqs. 5-7 over the floor's images ``g_j = floor_image(x_j)`` of ``i`` and of its
        same-body neighbours: ``A = sum w xb xb^T``, ``B = sum w yb xb^T`` with ``xb = g_j - x_i``,
        ``yb = g_j - y_i`` (the floor is at rest: an image does not move over the step), and
        how many are closer than ``h``. An image is at least as far from ``x_i`` as its
        particle, so the row holds every image within ``h``."""
        A = mat33()
        B = mat33()
        xi = x[i]
        yi = y[i]
        bi = body[i]
        c6 = sm.poly6_coef(h)
        same = int(0)
        # Every image is at least as far from x_i as x_i is from the plane.
        for k in range(wp.where(wp.dot(gn, xi) - goff < h, n + 1, 0)):
            j = i
            if k < n:
                j = nbr[i, k]
            if body[j] == bi:
                g = floor_image(x[j], gn, goff, gmin)
                xb = g - xi
                yb = g - yi
                r2 = wp.dot(xb, xb)
                w = sm.w_poly6_c(r2, h, c6)
                A += w * wp.outer(xb, xb)
                B += w * wp.outer(yb, xb)
                same += wp.where(r2 < h * h, 1, 0)
        return A, B, same

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
        (the mirror ``R A_i R`` of ``i``'s where every image is a mirror)."""
        A = mat33()
        xi = x[i]
        bi = body[i]
        gi = floor_image(xi, gn, goff, gmin)
        c6 = sm.poly6_coef(h)
        for k in range(wp.where(wp.dot(gn, xi) - goff < h, n + 1, 0)):
            j = i
            if k < n:
                j = nbr[i, k]
            if body[j] == bi:
                xb = x[j] - gi
                A += sm.w_poly6_c(wp.dot(xb, xb), h, c6) * wp.outer(xb, xb)
                if j != i:
                    gb = floor_image(x[j], gn, goff, gmin) - gi
                    A += sm.w_poly6_c(wp.dot(gb, gb), h, c6) * wp.outer(gb, gb)
        return A

    @wp.func
    def fit_sums(
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
    ):
        """``moment_sums``, plus ``floor_image_sums`` where the model has an image plane."""
        A, B, same = moment_sums(i, x, y, body, nbr, n, h)
        if images != 0:
            Ag, Bg, sg = floor_image_sums(i, x, y, body, nbr, n, h, gn, goff, gmin)
            A = A + Ag
            B = B + Bg
            same = same + sg
        return A, B, same

    @wp.func
    def affine_fit(A: mat33, B: mat33) -> mat33:
        """Eqs. 5-6: the least-squares affine map ``B A^-1`` of the weighted moments."""
        return B * wp.inverse(A)

    @wp.func
    def step_gradient(A: mat33, B: mat33, code: int, counters: wp.array(dtype=wp.int32)) -> mat33:
        """This step's ``dF = B A^-1`` (eqs. 4-6); ``I``, counted, where a guard of paper §4
        holds (``code``: ``neighbors.GUARD_*``)."""
        dF = wp.identity(n=3, dtype=scalar)
        if code == 1:
            wp.atomic_add(counters, COUNT_FEW_NEIGHBORS, 1)
        elif code == 2:
            wp.atomic_add(counters, COUNT_ILL_CONDITIONED, 1)
        else:
            dF = affine_fit(A, B)
        return dF

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
    def deformation_update(A: mat33, B: mat33, code: int, F: mat33, counters: wp.array(dtype=wp.int32)) -> mat33:
        """Eq. 8 with the guards of paper §4: ``F <- dF F`` unless guarded or inverted."""
        # A guarded particle gets dF = I: I F = F exactly, and det F > 0 always holds.
        return unless_inverted(step_gradient(A, B, code, counters) * F, F, counters)

    return types.SimpleNamespace(
        moment_sums=moment_sums, floor_image=floor_image, floor_image_sums=floor_image_sums, fit_sums=fit_sums,
        floor_image_moment=floor_image_moment,
        affine_fit=affine_fit, step_gradient=step_gradient, unless_inverted=unless_inverted,
        deformation_update=deformation_update,
    )


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    fn = funcs(scalar)
    sm = smoothing.funcs(scalar)

    @wp.kernel
    def update_deformation(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        F_prev: wp.array(dtype=mat33),
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        F_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        A, B, same = fn.fit_sums(i, x, y, body, nbr, count[i], h, gn, goff, gmin, images)
        F_out[i] = fn.deformation_update(A, B, guard[i], F_prev[i], counters)

    @wp.kernel(enable_backward=False)
    def update_deformation_adjoint(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        F_prev: wp.array(dtype=mat33),
        h: scalar,
        adj_F_out: wp.array(dtype=mat33),
        adj_x: wp.array(dtype=vec3),
        adj_y: wp.array(dtype=vec3),
        adj_F_prev: wp.array(dtype=mat33),
    ):
        """Hand-written adjoint of ``update_deformation`` (eqs. 5-8 differentiated): the
        tape's generated one spends 15-20x the forward on per-neighbour matrix selects and
        zeroing; this one recomputes the sums once and scatters one vector per pair.

        With ``dF = B A^-1`` and ``F_out = dF F``: ``adj F = dF^T G``, ``adj dF = G F^T``,
        ``adj B = adj dF A^-T``, ``adj A = -dF^T adj B``; per pair, ``A`` and ``B`` depend on
        ``xb`` through ``w(|xb|^2) xb xb^T`` and ``w yb xb^T``. Guarded or inverted
        particles keep ``F``: all of ``G`` goes to ``F``."""
        i = wp.tid()
        G = adj_F_out[i]
        Fp = F_prev[i]
        code = guard[i]
        A, B, same = fn.moment_sums(i, x, y, body, nbr, count[i], h)
        if code == 1 or code == 2:
            adj_F_prev[i] = adj_F_prev[i] + G
            return
        Ainv = wp.inverse(A)
        dF = B * Ainv
        if wp.determinant(dF * Fp) <= scalar(0.0):
            adj_F_prev[i] = adj_F_prev[i] + G
            return
        adj_F_prev[i] = adj_F_prev[i] + wp.transpose(dF) * G
        adj_B = G * wp.transpose(Fp) * wp.transpose(Ainv)
        adj_A = -(wp.transpose(dF) * adj_B)
        adj_A_sym = adj_A + wp.transpose(adj_A)
        xi = x[i]
        yi = y[i]
        bi = body[i]
        c6 = sm.poly6_coef(h)
        hh = h * h
        gx_i = vec3()
        gy_i = vec3()
        for k in range(count[i]):
            j = nbr[i, k]
            if body[j] == bi:
                xb = x[j] - xi
                r2 = wp.dot(xb, xb)
                if r2 < hh:
                    yb = y[j] - yi
                    w, dw = sm.w_poly6_inside(r2, hh, c6)
                    Bx = adj_B * xb
                    s = wp.dot(xb, adj_A * xb) + wp.dot(yb, Bx)
                    gx = w * (adj_A_sym * xb + wp.transpose(adj_B) * yb) + scalar(2.0) * dw * s * xb
                    gy = w * Bx
                    wp.atomic_add(adj_x, j, gx)
                    wp.atomic_add(adj_y, j, gy)
                    gx_i -= gx
                    gy_i -= gy
        wp.atomic_add(adj_x, i, gx_i)
        wp.atomic_add(adj_y, i, gy_i)

    return types.SimpleNamespace(update_deformation=update_deformation, update_deformation_adjoint=update_deformation_adjoint)


def recording_tape():
    """The ``wp.Tape`` recording launches now, or None."""
    runtime = getattr(getattr(getattr(wp, "_src", None), "context", None), "runtime", None)
    if runtime is None:  # pragma: no cover (older layout)
        runtime = wp.context.runtime
    return getattr(runtime, "tape", None)


def launch_update_deformation(model, state_in, state_out, counters, hand_adjoint: bool = True):
    """Eqs. 1-8 over the step from ``state_in.x`` to ``state_out.x``, with the neighbourhood
    guards the neighbour search wrote to ``state_out.guard``. Under a ``wp.Tape`` the
    backward runs ``update_deformation_adjoint`` (``hand_adjoint=False``: Warp's generated
    adjoint, which tests compare it against)."""
    k = kernels(model.scalar)
    inputs = [
        state_in.x, state_out.x, model.particle_body, state_out.neighbors, state_out.neighbor_count, state_out.guard,
        state_out.F_flowed, model.scalar(model.support_radius), *model.image_args(),
    ]
    tape = recording_tape()
    grads = (state_in.x, state_out.x, state_out.F_flowed, state_out.F)
    if tape is None or not hand_adjoint or any(a.grad is None for a in grads):
        wp.launch(k.update_deformation, model.particle_count, inputs, [state_out.F, counters], device=model.device)
        return
    # Under a tape: the forward unrecorded, and the hand-written adjoint in its place.
    wp.launch(k.update_deformation, model.particle_count, inputs, [state_out.F, counters], device=model.device,
              record_tape=False)

    tape.record_func(lambda: launch_update_deformation_adjoint(model, state_in, state_out), list(grads))


def launch_update_deformation_adjoint(model, state_in, state_out):
    """``update_deformation_adjoint``: ``state_out.F.grad`` into the gradients of ``state_in.x``,
    ``state_out.x`` and ``state_out.F_flowed``, with the guards in ``state_out.guard``."""
    wp.launch(
        kernels(model.scalar).update_deformation_adjoint, model.particle_count,
        [
            state_in.x, state_out.x, model.particle_body, state_out.neighbors, state_out.neighbor_count, state_out.guard,
            state_out.F_flowed, model.scalar(model.support_radius), state_out.F.grad, state_in.x.grad, state_out.x.grad,
            state_out.F_flowed.grad,
        ],
        device=model.device, record_tape=False,
    )
