"""Incremental deformation gradient (paper eqs. 1-8, SPEC §2).

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
def kernels(scalar) -> types.SimpleNamespace:
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
        """The fit's moments ``A, B`` and the number of same-body neighbours (the guard's).

        Only the raw sums live in this loop: the caller's inverse must not see a loop
        accumulator, whose adjoint Warp would not replay (WARP_NOTES trap 1). (Summing
        only A's six distinct entries measured 9 % slower: the matrix form vectorises.)"""
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
    def incremental_gradient(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
    ) -> mat33:
        A, B, same = moment_sums(i, x, y, body, nbr, n, h)
        return B * wp.inverse(A)

    @wp.func
    def step_gradient(
        i: int,
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        n: int,
        h: scalar,
        code: int,
        counters: wp.array(dtype=wp.int32),
    ) -> mat33:
        """This step's ``dF`` (eq. 4); ``I``, counted, where a guard of paper §4 holds."""
        dF = wp.identity(n=3, dtype=scalar)
        if code == 1:
            wp.atomic_add(counters, 0, 1)
        elif code == 2:
            wp.atomic_add(counters, 1, 1)
        else:
            dF = incremental_gradient(i, x, y, body, nbr, n, h)
        return dF

    @wp.func
    def unless_inverted(candidate: mat33, F: mat33, counters: wp.array(dtype=wp.int32)) -> mat33:
        """``candidate`` unless it inverts (det <= 0, paper §4): then ``F``, counted."""
        out = F
        if wp.determinant(candidate) > scalar(0.0):
            out = candidate
        else:
            wp.atomic_add(counters, 2, 1)
        return out

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
        F = F_prev[i]
        # A guarded particle gets dF = I: I F = F exactly, and det F > 0 always holds.
        dF = step_gradient(i, x, y, body, nbr, count[i], h, guard[i], counters)
        F_out[i] = unless_inverted(dF * F, F, counters)

    return types.SimpleNamespace(
        update_deformation=update_deformation, incremental_gradient=incremental_gradient, moment_sums=moment_sums,
        step_gradient=step_gradient, unless_inverted=unless_inverted,
    )
