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
        number of same-body neighbours (the guard's).

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
                w = sm.w_poly6_c(wp.dot(xb, xb), h, c6)
                A += w * wp.outer(xb, xb)
                B += w * wp.outer(yb, xb)
                same += 1
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
        moment_sums=moment_sums, affine_fit=affine_fit, step_gradient=step_gradient, unless_inverted=unless_inverted,
        deformation_update=deformation_update,
    )


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    fn = funcs(scalar)

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
        F_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        A, B, same = fn.moment_sums(i, x, y, body, nbr, count[i], h)
        F_out[i] = fn.deformation_update(A, B, guard[i], F_prev[i], counters)

    return types.SimpleNamespace(update_deformation=update_deformation)


def launch_update_deformation(model, state_in, state_out, counters):
    """Eqs. 1-8 over the step from ``state_in.x`` to ``state_out.x``, with the neighbourhood
    guards the neighbour search wrote to ``state_out.guard``."""
    wp.launch(
        kernels(model.scalar).update_deformation,
        model.particle_count,
        [
            state_in.x, state_out.x, model.particle_body, state_out.neighbors, state_out.neighbor_count, state_out.guard,
            state_out.F_flowed, model.scalar(model.support_radius),
        ],
        [state_out.F, counters],
        device=model.device,
    )
