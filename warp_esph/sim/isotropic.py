"""Rotation-variant SVD (docs/method.md §3) and isotropic matrix maps with stable adjoints
(docs/method.md §9).

``wp.svd3`` returns proper rotations ``U, V`` (det +1) and lets the last singular value
go negative for an inverted ``F``: that is Irving et al.'s rotation-variant SVD.

Its built-in adjoint is wrong where singular values repeat, which is every particle at
rest (``F = I``). The functions here carry their own adjoints instead:

* ``singular_values(F)``: ``dsigma_i = u_i^T dF v_i``, exact everywhere.
* ``isotropic_map(F, g, d1) = U diag(g) V^T`` for ``g = f(sigma)`` computed by the caller
  with ordinary autodiff. The adjoint sends ``diag(U^T Gbar V)`` to ``g`` (and from there
  through ``f`` and ``singular_values`` to ``F`` and the material parameters) and adds
  the off-diagonal part ``M_ij = ½ D1 (C_ij + C_ji) + ½ D2 (C_ij - C_ji)`` directly to
  ``F``. ``D2 = (g_i + g_j)/(sigma_i + sigma_j)`` follows from ``g``; the divided
  difference ``D1 = (g_i - g_j)/(sigma_i - sigma_j)`` must be passed in as ``d1``
  (pairs 01, 02, 12) because only the caller knows its limit where ``sigma_i = sigma_j``.
* ``isotropic_change(F, g, d1) = U diag(g - sigma) V^T``, ``isotropic_map`` less ``F``: the
  plastic flow's change, added to ``F`` so that a small flow keeps ``F`` to the last bit.
"""

import functools
import types

import warp as wp

from .._types import type_set


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33

    @wp.func
    def strained(sk: scalar, v0: scalar, v1: scalar, v2: scalar, E: mat33) -> scalar:
        """``svd``'s singular value ``sk`` of right singular vector ``v`` taken from the strain
        ``E = F^T F - I``: ``1 + v^T E v / (1 + sk)``; an inverted one (``sk <= 0``) as given."""
        v = vec3(v0, v1, v2)
        return wp.where(sk > scalar(0.0), scalar(1.0) + wp.dot(v, E * v) / (scalar(1.0) + sk), sk)

    @wp.func
    def svd(F: mat33):
        """``(U, sigma, V)`` of ``wp.svd3(F)`` with each ``sigma_k`` taken again from ``F``'s
        strain, ``1 + v_k^T (F^T F - I) v_k / (1 + sigma_k)`` (``= sigma_k`` exactly), the strain
        formed from ``F - I`` before any product, where every ``sigma_k`` is within 0.4 of 1
        (farther, ``wp.svd3``'s own: docs/method.md §3). ``wp.svd3`` rotates even a
        diagonal ``F`` and returns ``F = I``'s singular values 1 to 5 units in the last place
        below 1 in float32, so the stress at rest was not 0 (0.076 Pa at mu = 58 kPa) and a
        body at rest felt forces of up to 0.015 m/s^2 (docs/physics.md, "The held
        cantilever's float32 late growth"). Here ``F = I`` gives 1 exactly, and near ``I``
        within half a unit of float64 (docs/method.md §3). Every SVD the stress and the flow
        read is this one."""
        U = mat33()
        s = vec3()
        V = mat33()
        wp.svd3(F, U, s, V)
        one = scalar(1.0)
        # Near I only: the strain's round-off grows as sigma_max^2 and the Rayleigh quotient's
        # as svd3's error in V squared times the gap, so far from I it is worse than svd3's QR
        # (float32, F = R diag(3, 1, 0.3) Q^T: 1.3e-3 of a sigma against 2.4e-4).
        if wp.max(wp.max(wp.abs(s[0] - one), wp.abs(s[1] - one)), wp.abs(s[2] - one)) < scalar(0.4):
            H = F - wp.identity(n=3, dtype=scalar)
            E = H + wp.transpose(H) + wp.transpose(H) * H
            s = vec3(strained(s[0], V[0, 0], V[1, 0], V[2, 0], E), strained(s[1], V[0, 1], V[1, 1], V[2, 1], E),
                     strained(s[2], V[0, 2], V[1, 2], V[2, 2], E))
        # In order where round-off would swap repeated values by a unit (wp.svd3's own do too).
        s1 = wp.min(s[1], s[0])
        return U, vec3(s[0], s1, wp.where(s[2] > scalar(0.0), wp.min(s[2], s1), s[2])), V

    @wp.func
    def singular_values(F: mat33) -> vec3:
        U, s, V = svd(F)
        return s

    @wp.func_grad(singular_values)
    def adj_singular_values(F: mat33, adj_ret: vec3):
        U, s, V = svd(F)
        wp.adjoint[F] += U * wp.diag(adj_ret) * wp.transpose(V)

    @wp.func
    def from_principal(U: mat33, g: vec3, V: mat33) -> mat33:
        """``U diag(g) V^T``: the isotropic function with principal values ``g`` in the
        frame of ``F = U diag(sigma) V^T`` (forward only; ``isotropic_map`` for gradients)."""
        return U * wp.diag(g) * wp.transpose(V)

    @wp.func
    def isotropic_map(F: mat33, g: vec3, d1: vec3) -> mat33:
        U, s, V = svd(F)
        return from_principal(U, g, V)

    @wp.func
    def skew_coefficient(gi: scalar, gj: scalar, si: scalar, sj: scalar) -> scalar:
        """``(g_i + g_j) / (sigma_i + sigma_j)``: the skew part's factor of the map's derivative
        for the singular-value pair ``(i, j)`` (module doc)."""
        den = si + sj
        # sigma_i + sigma_j >= 0 with the rotation-variant ordering; it reaches 0 for a
        # degenerate F, and for an inverted one whose two singular values are equal in size
        # (sigma_j = -sigma_i: diag(a, b, -b)). There a map of the signed singular values (the
        # corotated stress, the inverted fit's) jumps, by more than its size (docs/method.md),
        # and no derivative exists; near it the derivative is this quotient, large but true.
        eps = scalar(1.0e-6)
        if wp.abs(den) < eps:
            den = wp.where(den < scalar(0.0), -eps, eps)
        return (gi + gj) / den

    @wp.func
    def pair_skew_coefficients(g: vec3, s: vec3) -> vec3:
        """``skew_coefficient`` of the pairs (0, 1), (0, 2), (1, 2)."""
        return vec3(skew_coefficient(g[0], g[1], s[0], s[1]), skew_coefficient(g[0], g[2], s[0], s[2]),
                    skew_coefficient(g[1], g[2], s[1], s[2]))

    @wp.func
    def off_diagonal(C: mat33, d1: vec3, d2: vec3) -> mat33:
        """The off-diagonal part ``M`` of the map's adjoint in the SVD frame (``C = U^T adj
        V``): ``M_ij = d1 (C_ij + C_ji) / 2 +- d2 (C_ij - C_ji) / 2`` for the pairs 01, 02, 12
        (``d1``: the symmetric part's factors, ``d2``: ``pair_skew_coefficients``)."""
        M = mat33()
        sym = scalar(0.5) * (C[0, 1] + C[1, 0])
        skw = scalar(0.5) * (C[0, 1] - C[1, 0])
        M[0, 1] = d1[0] * sym + d2[0] * skw
        M[1, 0] = d1[0] * sym - d2[0] * skw
        sym = scalar(0.5) * (C[0, 2] + C[2, 0])
        skw = scalar(0.5) * (C[0, 2] - C[2, 0])
        M[0, 2] = d1[1] * sym + d2[1] * skw
        M[2, 0] = d1[1] * sym - d2[1] * skw
        sym = scalar(0.5) * (C[1, 2] + C[2, 1])
        skw = scalar(0.5) * (C[1, 2] - C[2, 1])
        M[1, 2] = d1[2] * sym + d2[2] * skw
        M[2, 1] = d1[2] * sym - d2[2] * skw
        return M

    @wp.func
    def isotropic_map_adjoint(F: mat33, g: vec3, d1: vec3, adj_ret: mat33):
        """The adjoints ``(adj F, adj g)`` of ``isotropic_map`` (module doc)."""
        U, s, V = svd(F)
        C = wp.transpose(U) * adj_ret * V
        M = off_diagonal(C, d1, pair_skew_coefficients(g, s))
        return U * M * wp.transpose(V), vec3(C[0, 0], C[1, 1], C[2, 2])

    @wp.func_grad(isotropic_map)
    def adj_isotropic_map(F: mat33, g: vec3, d1: vec3, adj_ret: mat33):
        aF, ag = isotropic_map_adjoint(F, g, d1, adj_ret)
        wp.adjoint[F] += aF
        wp.adjoint[g] += ag

    @wp.func
    def isotropic_change(F: mat33, g: vec3, d1: vec3) -> mat33:
        """``isotropic_map(F, g, d1) - F = U diag(g - sigma) V^T``: where ``g`` is close to
        ``sigma`` (a small plastic flow) the change alone, added to ``F`` by the caller, keeps
        ``F`` to the last bit, where ``U diag(g) V^T`` rebuilds ``F`` with the SVD's error,
        units in the last place every step (docs/physics.md, the float32 creep floor). Its
        adjoint is ``isotropic_map``'s less the identity."""
        U, s, V = svd(F)
        return from_principal(U, g - s, V)

    @wp.func_grad(isotropic_change)
    def adj_isotropic_change(F: mat33, g: vec3, d1: vec3, adj_ret: mat33):
        aF, ag = isotropic_map_adjoint(F, g, d1, adj_ret)
        wp.adjoint[F] += aF - adj_ret
        wp.adjoint[g] += ag


    return types.SimpleNamespace(svd=svd, singular_values=singular_values, isotropic_map=isotropic_map,
                                 isotropic_change=isotropic_change, from_principal=from_principal,
                                 skew_coefficient=skew_coefficient, pair_skew_coefficients=pair_skew_coefficients,
                                 off_diagonal=off_diagonal)
