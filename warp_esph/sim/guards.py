"""The neighbourhood guards of paper §4, as functions of a particle's fit moment matrix and
neighbour count.

Paper §4 skips the deformation update of a particle whose neighbourhood is too small (fewer
than ``min_neighbors`` same-body neighbours) or leaves a direction nearly unsampled (a
moment matrix ``A`` with a large condition number ``cond(A) = lmax / lmin``). As switches
both guards make the step jump, and a loss through the step with it: the first wherever a
neighbour crosses the support radius of a particle with ``min_neighbors`` of them, the
second wherever a condition number crosses the limit. So the fit's increment and the
variational force fade out instead (``guard_scale``), by the product of two smoothsteps
(continuous with their slopes at both ends):

- in the condition number: whole up to ``max_condition``, zero from ``FADE *
  max_condition``, differentiable through the eigenvalues of ``A`` (``d lambda = q^T dA q``);
- in a smooth neighbour count (``count_weight``: each neighbour counts 1 up to
  ``COUNT_FADE`` of the support radius and fades to 0 at it, where its fit weight ends):
  whole from ``min_neighbors``, zero at ``min_neighbors - 1`` and below.

The switches (``guard_code`` 1 and 2) hold only where the fade is already zero. A particle
whose neighbours all sit inside ``COUNT_FADE h`` with ``cond(A) <= max_condition`` is
unchanged, bit for bit (docs/method.md §2; docs/physics.md, "The fit's weight", the landing
loss, and "The few-neighbours guard fades").
"""

import functools
import types

import warp as wp

from .._types import type_set

#: Default ``min_neighbors`` (``Solver``): the fewest same-body neighbours whose fit is taken
#: whole (paper §4); with one fewer the fit's increment has faded to nothing.
MIN_NEIGHBORS = 6
#: Default ``max_condition`` (``Solver``): where the fade of an ill-conditioned fit starts.
#: A fit whose neighbours leave a direction nearly unsampled turns a small displacement of
#: the particle along it into a large ``dF`` (``dF - I`` grows as ``A^-1``), a local stiffness
#: far above the wave limit of ``Model.stable_dt``: plastic flow spreading a body into a thin
#: layer on the ground makes such fits (``cond`` 200-500 where the toothpaste preset without
#: viscosity blew up at 0.5 ``stable_dt``). Lattices (up to 2.05 at ``h = 2 dx``), lattices
#: jittered by 0.3 dx (5-7.4) and every preset's drop and the ``test_creep`` pile (at most
#: 9.9) stay below it (docs/method.md §2, docs/physics.md "The step bound of undamped fast
#: plastic flow").
MAX_CONDITION = 20.0
#: The fade ends, and the switch holds, at this multiple of ``max_condition``.
FADE = 2.0
#: A neighbour counts whole for the few-neighbours guard up to this fraction of the support
#: radius ``h`` and fades to nothing at ``h``. Lattice neighbours at ``h = 2 dx`` (at most
#: ``sqrt(3) dx = 0.87 h``) count whole; the fit's poly6 weight beyond it is below 0.7 % of
#: its peak.
COUNT_FADE = 0.9


@functools.cache
def guard_funcs(scalar) -> types.SimpleNamespace:
    """The guards on a moment matrix and a smooth neighbour count: ``count_weight`` (a
    partner's share of the count), ``guard_code`` (the switch, shared by the neighbour pass and
    the fused step), ``guard_scale`` (the fade) and ``guard_scale_gradient`` (its slopes in
    ``A`` and the count, for the hand-written adjoints)."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33

    @wp.func
    def well_conditioned(A: mat33, limit: scalar) -> bool:
        """Whether ``cond(A) < limit / 2`` certainly: ``cond(A) <= tr(A)^3 / (4 det A)`` for a
        positive semi-definite ``A`` (``lmax <= tr``, ``l1 l2 <= (tr / 2)^2``), so the
        eigen-decomposition can be skipped."""
        tr = A[0, 0] + A[1, 1] + A[2, 2]
        det = wp.determinant(A)
        return det > scalar(0.0) and tr * tr * tr < scalar(2.0) * limit * det

    @wp.func
    def extreme_eigen(A: mat33):
        """The smallest and largest eigenvalue of the symmetric ``A`` and their eigenvectors
        ``(l_min, l_max, q_min, q_max)``."""
        Q = mat33()
        lam = vec3()
        wp.eig3(A, Q, lam)
        kmin = int(0)
        kmax = int(0)
        for k in range(1, 3):
            if lam[k] < lam[kmin]:
                kmin = k
            if lam[k] > lam[kmax]:
                kmax = k
        return (lam[kmin], lam[kmax], vec3(Q[0, kmin], Q[1, kmin], Q[2, kmin]),
                vec3(Q[0, kmax], Q[1, kmax], Q[2, kmax]))

    @wp.func
    def count_weight(r2: scalar, hh: scalar):
        """How much a same-body partner at squared distance ``r2`` counts for the
        few-neighbours guard (``hh = h^2``), and its slope in ``r2``: 1 up to ``COUNT_FADE
        h``, 0 from ``h`` (where its fit weight ends), ``1 - smoothstep`` in ``r2`` between."""
        c = scalar(0.0)
        dc = scalar(0.0)
        q0 = scalar(COUNT_FADE * COUNT_FADE) * hh
        if r2 <= q0:
            c = scalar(1.0)
        elif r2 < hh:
            band = hh - q0
            t = (r2 - q0) / band
            c = scalar(1.0) - t * t * (scalar(3.0) - scalar(2.0) * t)
            dc = -scalar(6.0) * t * (scalar(1.0) - t) / band
        return c, dc

    @wp.func
    def count_scale(same: scalar, min_neighbors: int):
        """The few-neighbours fade of a particle with the smooth count ``same``
        (``count_weight`` summed) and its slope: 1 from ``min_neighbors``, 0 at
        ``min_neighbors - 1`` and below, a smoothstep between."""
        t = same - scalar(min_neighbors - 1)
        s = scalar(1.0)
        ds = scalar(0.0)
        if t <= scalar(0.0):
            s = scalar(0.0)
        elif t < scalar(1.0):
            s = t * t * (scalar(3.0) - scalar(2.0) * t)
            ds = scalar(6.0) * t * (scalar(1.0) - t)
        return s, ds

    @wp.func
    def guard_code(A: mat33, same: scalar, min_neighbors: int, max_condition: scalar) -> int:
        """Guard of paper §4 from the moment matrix ``A`` and the smooth count ``same`` of the
        same-body neighbours (``count_weight``): 1 too few of them (the count's fade is zero),
        2 ``cond(A)`` beyond the fade (``FADE * max_condition``), else 0."""
        code = int(0)
        limit = scalar(FADE) * max_condition
        if same <= scalar(min_neighbors - 1):
            code = 1
        elif not well_conditioned(A, limit):
            lmin, lmax, qmin, qmax = extreme_eigen(A)
            if lmin <= scalar(0.0) or lmax > limit * lmin:
                code = 2
        return code

    @wp.func
    def condition_scale_gradient(A: mat33, max_condition: scalar):
        """``(s, ds/dA)``: the condition number's fade ``s`` of a fit with moment matrix ``A``
        (1 where ``cond(A) <= max_condition``, 0 from ``FADE`` times it, ``1 - smoothstep``
        between) and its slope, ``s'(c) (q_max q_max^T - c q_min q_min^T) / l_min`` with
        ``c = cond(A)`` and ``q`` the eigenvectors of ``l_max``, ``l_min``."""
        s = scalar(1.0)
        G = mat33()
        if not well_conditioned(A, max_condition):
            lmin, lmax, qmin, qmax = extreme_eigen(A)
            if lmin <= scalar(0.0):
                s = scalar(0.0)
            else:
                c = lmax / lmin
                band = (scalar(FADE) - scalar(1.0)) * max_condition
                t = (c - max_condition) / band
                if t >= scalar(1.0):
                    s = scalar(0.0)
                elif t > scalar(0.0):
                    s = scalar(1.0) - t * t * (scalar(3.0) - scalar(2.0) * t)
                    ds = -scalar(6.0) * t * (scalar(1.0) - t) / band
                    G = (ds / lmin) * (wp.outer(qmax, qmax) - c * wp.outer(qmin, qmin))
        return s, G

    @wp.func
    def guard_scale_gradient(A: mat33, same: scalar, min_neighbors: int, max_condition: scalar):
        """``(s, ds/dA, ds/dsame)``: the fade of the fit's increment and of the variational
        force, the condition number's (``condition_scale_gradient``) times the count's
        (``count_scale``), and its slopes in ``A`` and in the smooth count ``same``."""
        sn, dsn = count_scale(same, min_neighbors)
        s = scalar(0.0)
        G = mat33()
        if sn > scalar(0.0):
            sc, Gc = condition_scale_gradient(A, max_condition)
            s = sc * sn
            G = sn * Gc
            dsn = sc * dsn
        return s, G, dsn

    @wp.func
    def guard_scale(A: mat33, same: scalar, min_neighbors: int, max_condition: scalar) -> scalar:
        """The fade of the fit's increment and of the variational force (``guard_scale_gradient``)."""
        s, G, dn = guard_scale_gradient(A, same, min_neighbors, max_condition)
        return s

    return types.SimpleNamespace(guard_code=guard_code, guard_scale=guard_scale, guard_scale_gradient=guard_scale_gradient,
                                 count_weight=count_weight, count_scale=count_scale)
