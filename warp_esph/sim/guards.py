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
from . import smoothing

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
#: ``sqrt(3) dx = 0.87 h``) count whole; beyond it the fit's weight is below 1 % of its peak
#: (the biweight's; poly6's below 0.1 %). A wider band (0.9) counted the axis neighbours of a body compressed by its
#: weight (at 1.8-1.9 dx) short, so that 60 % more particle-steps of Fig. 6's star lost
#: their fit than with the switch (docs/physics.md, "The few-neighbours guard fades").
COUNT_FADE = 0.95


@functools.cache
def guard_funcs(scalar) -> types.SimpleNamespace:
    """The guards on a moment matrix and a smooth neighbour count: ``count_weight`` (a
    partner's share of the count), ``guard`` (the switch, the fade and the fade's slopes in
    ``A`` and the count, for the hand-written adjoints, all at once), and its parts
    ``guard_code`` (the switch, for the neighbour pass) and ``guard_scale`` (the fade)."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    # Squared in Python (float64) and cast once: Warp evaluates arithmetic of Python constants
    # inside a kernel in float32, so ``scalar(COUNT_FADE * COUNT_FADE)`` put the float64
    # count's fade edge 2.6e-8 h^2 low.
    count_fade_sq = scalar(COUNT_FADE * COUNT_FADE)
    smoothstep = smoothing.funcs(scalar).smoothstep

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
        q0 = count_fade_sq * hh
        if r2 <= q0:
            c = scalar(1.0)
        elif r2 < hh:
            band = hh - q0
            t = (r2 - q0) / band
            st, dst = smoothstep(t)
            c = scalar(1.0) - st
            dc = -dst / band
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
            s, ds = smoothstep(t)
        return s, ds

    @wp.func
    def beyond_fade(lmin: scalar, lmax: scalar, max_condition: scalar) -> bool:
        """Whether the extreme eigenvalues put ``cond(A)`` beyond the fade's end, ``FADE *
        max_condition`` (or ``A`` is singular): the ill-conditioned switch."""
        return lmin <= scalar(0.0) or lmax > scalar(FADE) * max_condition * lmin

    @wp.func
    def guard(A: mat33, same: scalar, min_neighbors: int, max_condition: scalar):
        """Both guards of paper §4 at once, the bound and the eigen-decomposition of ``A``
        computed at most once: ``(code, s, ds/dA, ds/dsame)`` for the moment matrix ``A`` and
        the smooth count ``same`` of the same-body neighbours (``count_weight``).

        ``code`` (the switch): 1 too few neighbours (the count's fade is zero), 2 ``cond(A)``
        beyond the fade (``FADE * max_condition``), else 0. ``s``: the fade of the fit's
        increment and of the variational force, the count's (``count_scale``) times the
        condition number's (1 up to ``max_condition``, 0 from ``FADE`` times it, ``1 -
        smoothstep`` between); its slope in ``A`` is ``s_n s_c'(c) (q_max q_max^T - c q_min
        q_min^T) / l_min`` with ``c = cond(A)`` and ``q`` the eigenvectors of ``l_max``,
        ``l_min`` (``d lambda = q^T dA q``), in the count ``s_c s_n'``."""
        sn, dsn = count_scale(same, min_neighbors)
        code = int(0)
        s = scalar(0.0)
        G = mat33()
        dn = scalar(0.0)
        if sn <= scalar(0.0):
            code = 1
        elif well_conditioned(A, max_condition):
            s = sn
            dn = dsn
        else:
            lmin, lmax, qmin, qmax = extreme_eigen(A)
            if beyond_fade(lmin, lmax, max_condition):
                code = 2
            else:
                c = lmax / lmin
                band = (scalar(FADE) - scalar(1.0)) * max_condition
                t = (c - max_condition) / band
                sc = scalar(1.0)
                if t >= scalar(1.0):
                    sc = scalar(0.0)
                elif t > scalar(0.0):
                    st, dst = smoothstep(t)
                    sc = scalar(1.0) - st
                    dsc = -dst / band
                    G = (sn * dsc / lmin) * (wp.outer(qmax, qmax) - c * wp.outer(qmin, qmin))
                s = sc * sn
                dn = sc * dsn
        return code, s, G, dn

    @wp.func
    def guard_code(A: mat33, same: scalar, min_neighbors: int, max_condition: scalar) -> int:
        """The switch of ``guard`` alone (the neighbour pass's): 0 (the fit taken, faded by
        ``guard_scale``), 1 too few neighbours, 2 ill-conditioned. Its cheap bound is taken at
        the fade's end, so the eigen-decomposition runs only where ``cond(A)`` may pass it."""
        code = int(0)
        if same <= scalar(min_neighbors - 1):
            code = 1
        elif not well_conditioned(A, scalar(FADE) * max_condition):
            lmin, lmax, qmin, qmax = extreme_eigen(A)
            if beyond_fade(lmin, lmax, max_condition):
                code = 2
        return code

    @wp.func
    def guard_scale(A: mat33, same: scalar, min_neighbors: int, max_condition: scalar) -> scalar:
        """The fade of the fit's increment and of the variational force (``guard``)."""
        code, s, G, dn = guard(A, same, min_neighbors, max_condition)
        return s

    @wp.func
    def isotropic_conditioning(A: mat33) -> scalar:
        """``q = det A / (tr A / 3)^3`` of a moment matrix ``A = sum_j w_j d_j d_j^T``: 1 for an
        isotropic ``A``, 0 for neighbours on a plane or a line; 1 where ``tr A = 0`` (no
        neighbour). What the isotropic pressure's regularisation and the hourglass control's
        switch read (``pressure.isotropic_regularisation``, ``hourglass.residual_map``)."""
        q = scalar(1.0)
        tr = A[0, 0] + A[1, 1] + A[2, 2]
        if tr > scalar(0.0):
            a = tr / scalar(3.0)
            q = wp.determinant(A) / (a * a * a)
        return q

    return types.SimpleNamespace(guard=guard, guard_code=guard_code, guard_scale=guard_scale, count_weight=count_weight,
                                 count_scale=count_scale, isotropic_conditioning=isotropic_conditioning)
