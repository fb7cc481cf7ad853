"""Neighbour lists (paper §4, docs/method.md §1): the particles ``j != i`` with
``|x_j - x_i| < h sigma_max(F_i)`` (with ``F``; else ``< h``), the ``max_neighbors`` of
smallest key where there are more (the nearest; with ``F``, those nearest by the distance a
kernel weighs them by, ``weight_key``), stored as a fixed-width int32 row plus a count.

Rows reach ``h sigma_max(F_i)`` (an upper bound of it) where the paper's elastic kernel is
evaluated at ``F_i^-1 (x_j - x_i)`` (eq. 11): a pair then enters or leaves a row only
where every kernel of the step is zero, and the loss is continuous in the parameters.
Without that force every weight of the step ends at ``h`` and the solver asks for rows
within ``h`` (``Solver._stretch_rows``).
The default width (``default_max_neighbors``) leaves room for compression, so rows are
not cut in practice (a full stretched row drops only pairs no kernel weighs, or counts a
cut); a row that may be short of a weighted neighbour is counted
(``Solver.guard_counts()["neighbors_cut"]``). The paper's "up to 30 neighbours" is
``PAPER_MAX_NEIGHBORS``.

The lists are integers: they are recorded once per step and reused unchanged by the
backward pass, so the tape never queries a hash grid (docs/method.md, Warp pitfall 3). The
selection kernel can also evaluate the deformation-update guards of paper §4 that
depend only on the neighbourhood (too few neighbours, ill-conditioned moment matrix),
because they need an eigen-decomposition whose adjoint is not wanted, and the SPH
density of the forward-only step.

Two stages (a Verlet list with a skin):

1. ``build_candidates``: ``wp.HashGrid`` query of every particle within ``h s_i + skin``
   (``s_i`` the particle's stretch bound, ``candidate_stretch``), stored as an int32 row
   sorted by particle index, together with the positions it was built from. Only done
   when needed.
2. ``select_neighbors``, every step: the particles within ``h sigma_max(F_i)`` among the
   candidates; where there are more than the row width, the smallest keys
   ``(|x_j - x_i|², j)`` (nearest first, ties to the lower index; with ``F`` the distance
   is ``weight_key``'s). Rows are written in index order.

The candidates stay complete while every pair has moved by less than ``skin`` relative
to each other since they were built: ``NeighborSearch.update`` checks a bound on that
(from the bounding box of the displacements, so a body translating as a whole never
forces a rebuild) and that no stretch bound grew past its ``s_i``, and rebuilds otherwise. Since the selection and its order depend
only on the current positions (with ``F``: and ``F``, the rest positions) and indices, the lists are then exactly those of a
fresh search: the skin changes the cost, never the result (so a run resumed from a
checkpoint with a new solver is bit-identical). ``skin = 0`` searches afresh every
step.

Ties at a full row go to the lower index. (Before, rows were sorted by
distance with ties in hash-grid arrival order, which depended on the grid resolution
and device.)
"""

import functools
import math
import types

import numpy as np
import warp as wp

from .. import checks
from .._types import type_set
from . import deformation, guards, isotropic, materials, pressure, smoothing
from .replay import Launches

#: Guard codes written per particle (0 = the MLS update may run).
GUARD_OK = 0
GUARD_FEW_NEIGHBORS = 1
GUARD_ILL_CONDITIONED = 2

#: The displacement bound must stay below this fraction of the skin (margin for the
#: rounding of the distances the candidate test and the selection compute).
SKIN_SAFETY = 0.95
#: Hash-grid cell width as a fraction of the search radius h + skin (measured: 0.45 is
#: 15 % faster than 1 and leaves ~7 out-of-order entries per row to sort, not ~400).
CELL_FRACTION = 0.45
#: Candidate rows never grow beyond this many entries (a collapsed body).
MAX_CANDIDATES = 4096
#: The selection radius of a particle is ``h sigma_max(F)`` (``select_neighbors``): the
#: elastic kernel is evaluated at ``F^-1 (x_j - x_i)`` (eq. 11), so a pair closer than
#: ``h`` in the reference space can be up to ``sigma_max(F) h`` apart now, and a row cut
#: at ``h`` would drop it while its force is not zero (a jump in the loss). Each
#: particle's candidates are searched within ``h s_i + skin`` with ``s_i`` its stretch
#: bound at the build times STRETCH_SLACK (so a growing stretch does not rebuild every
#: step), at most MAX_STRETCH; they are rebuilt when a stretch bound exceeds its ``s_i``.
STRETCH_SLACK = 1.05
MAX_STRETCH = 2.0
#: Stretch assumed for the default row width (``default_max_neighbors``).
TYPICAL_STRETCH = 1.1
#: The interior lattice neighbour counts are scaled by this for the default row width
#: (``default_max_neighbors``): room for compression, so the cap never binds in practice.
DEFAULT_CAP_FACTOR = 3.0
#: The paper's neighbour count ("up to 30 neighbours", paper §4).
PAPER_MAX_NEIGHBORS = 30
#: Default ``Solver(max_condition=)``: where the fade of an ill-conditioned fit starts (``guards``).
MAX_CONDITION = guards.MAX_CONDITION
MIN_NEIGHBORS = guards.MIN_NEIGHBORS
#: The guards on a moment matrix (``guards.guard_funcs``), shared by the neighbour pass and the fused step.
guard_funcs = guards.guard_funcs


def lattice_neighbor_count(radius_over_spacing: float) -> int:
    """Other points of a cubic lattice closer than ``radius_over_spacing`` lattice spacings
    to a point (26 below 2, 80 below 2.5)."""
    r = float(radius_over_spacing)
    k = int(math.ceil(r))
    g = np.arange(-k, k + 1)
    d2 = g[:, None, None] ** 2 + g[None, :, None] ** 2 + g[None, None, :] ** 2
    return int((d2 < r * r).sum()) - 1


def default_max_neighbors(support_over_spacing: float) -> int:
    """Default row width: ``DEFAULT_CAP_FACTOR`` times the lattice count within the largest
    selection radius ``TYPICAL_STRETCH h``, rounded up to 8 (96 at h = 2 dx, 240 at 2.5 dx)."""
    n = DEFAULT_CAP_FACTOR * lattice_neighbor_count(TYPICAL_STRETCH * float(support_over_spacing))
    return int(8 * math.ceil(n / 8))


@wp.func
def padded_query_radius(p: wp.vec3f, radius: wp.float32) -> wp.float32:
    """The radius of a float32 hash-grid query around ``p`` that misses no point within
    ``radius``: padded by more than the float32 rounding of the (possibly world-shifted)
    grid points; an exact test of each point returned decides."""
    big = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.abs(p[2])) + radius
    return radius * wp.float32(1.0001) + wp.float32(5.0e-7) * big


@functools.cache
def kernels(scalar, weight: str) -> types.SimpleNamespace:
    """The neighbour search's kernels; ``weight`` (``smoothing.FIT_WEIGHTS``) the fit's, which
    the guard's moment matrix sums (the SPH density sums poly6)."""
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    sm = smoothing.funcs(scalar)
    fw = smoothing.fit_weight_funcs(scalar, weight)
    pressure_of = pressure.funcs(scalar).pressure
    density_weight = pressure.funcs(scalar).density_weight
    image_density = pressure.funcs(scalar).image_density
    fit_pair_sums = deformation.funcs(scalar, weight).fit_pair_sums
    guard_code = guard_funcs(scalar).guard_code
    count_weight = guard_funcs(scalar).count_weight
    Materials = materials.struct(scalar)
    floor_image = deformation.funcs(scalar, "poly6").floor_image
    svd = isotropic.funcs(scalar).svd
    # The volume range the plastic flow keeps (flow_inverse_bound); imported here, plasticity
    # imports the modules that import this one.
    from .plasticity import VOLUME_PRESERVING_RANGE  # noqa: PLC0415
    j_lo, j_hi = scalar(VOLUME_PRESERVING_RANGE[0]), scalar(VOLUME_PRESERVING_RANGE[1])
    # Divided in Python (float64) and cast once: Warp evaluates ``1.0 / 3.0`` inside a kernel in
    # float32, whatever the scalar it is cast to.
    third = scalar(1.0 / 3.0)

    @wp.func
    def stretch_bound2(F: mat33) -> scalar:
        """An upper bound of sigma_max(F)^2 = lambda_max(F^T F): the largest absolute row
        sum of F^T F (Gershgorin), tight for a small strain."""
        C = wp.transpose(F) * F
        g = scalar(0.0)
        for row in range(3):
            g = wp.max(g, wp.abs(C[row, 0]) + wp.abs(C[row, 1]) + wp.abs(C[row, 2]))
        return g

    @wp.func
    def candidate_stretch(F: mat33, with_stretch: int, slack: scalar, max_stretch: scalar) -> scalar:
        """The stretch ``s_i`` a particle's candidates cover (1 without ``with_stretch``)."""
        st = scalar(1.0)
        if with_stretch != 0:
            st = wp.min(max_stretch, wp.max(scalar(1.0), wp.sqrt(stretch_bound2(F))) * slack)
        return st

    @wp.func
    def key_greater(da: scalar, ja: int, db: scalar, jb: int) -> bool:
        return da > db or (da == db and ja > jb)

    @wp.func
    def sift_down(nbr: wp.array2d(dtype=wp.int32), nbr_d2: wp.array2d(dtype=scalar), i: int, start: int, n: int):
        # Max-heap on the key (d2, j) over nbr[i, :n], restored below position ``start``.
        pos = start
        child = 2 * pos + 1
        while child < n:
            if child + 1 < n and key_greater(nbr_d2[i, child + 1], nbr[i, child + 1], nbr_d2[i, child], nbr[i, child]):
                child += 1
            if key_greater(nbr_d2[i, child], nbr[i, child], nbr_d2[i, pos], nbr[i, pos]):
                tj = nbr[i, pos]
                td = nbr_d2[i, pos]
                nbr[i, pos] = nbr[i, child]
                nbr_d2[i, pos] = nbr_d2[i, child]
                nbr[i, child] = tj
                nbr_d2[i, child] = td
                pos = child
                child = 2 * pos + 1
            else:
                child = n

    @wp.kernel(enable_backward=False, module="unique")
    def grid_points(x: wp.array(dtype=vec3), world: wp.array(dtype=wp.int32), stride: wp.float32, out: wp.array(dtype=wp.vec3f)):
        """float32 points for the hash grid with x and z swapped: its query visits cells
        with the first coordinate fastest, so bodies sampled in lattice order (z fastest,
        ``meshes.lattice_points``) come out nearly sorted by index. With worlds
        (``stride > 0``), world ``w`` is shifted by ``w * stride`` along the slowest grid
        axis: worlds placed at the same spot then fill different cells, so a query does
        not visit (and reject) the other worlds' particles."""
        i = wp.tid()
        p = x[i]
        shift = wp.float32(0.0)
        if stride > wp.float32(0.0):
            shift = wp.float32(world[i]) * stride
        out[i] = wp.vec3f(wp.float32(p[2]), wp.float32(p[1]), wp.float32(p[0]) + shift)

    @wp.kernel(enable_backward=False, module="unique")
    def build_candidates(
        grid: wp.uint64,
        grid_points: wp.array(dtype=wp.vec3f),
        x: wp.array(dtype=vec3),
        h: scalar,
        skin: scalar,
        F: wp.array(dtype=mat33),
        with_stretch: int,
        slack: scalar,
        max_stretch: scalar,
        group: wp.array(dtype=wp.int32),
        same_group: int,
        cand: wp.array2d(dtype=wp.int32),
        cand_count: wp.array(dtype=wp.int32),
        overflow: wp.array(dtype=wp.int32),
        x_ref: wp.array(dtype=vec3),
        cand_stretch: wp.array(dtype=scalar),
        cand_found: wp.array(dtype=wp.int32),
    ):
        """Every ``j != i`` with ``|x_j - x_i| < h s_i + skin`` (of ``i``'s group only, with
        ``same_group``: its body without body interaction, its world with worlds), sorted by
        index; ``s_i`` (``candidate_stretch``) goes to ``cand_stretch``, the count before the
        row's cap to ``cand_found`` (which names the particles past ``MAX_CANDIDATES``)."""
        i = wp.tid()
        xi = x[i]
        bi = group[i]
        cap = cand.shape[1]
        st = scalar(1.0)
        if with_stretch != 0:
            st = candidate_stretch(F[i], with_stretch, slack, max_stretch)
        cand_stretch[i] = st
        radius = h * st + skin
        r2 = radius * radius
        n = int(0)
        # The float32 query box is padded (the exact test below decides).
        gp = grid_points[i]
        query = wp.hash_grid_query(grid, gp, padded_query_radius(gp, wp.float32(radius)))
        j = int(0)
        while wp.hash_grid_query_next(query, j):
            if j == i or (same_group != 0 and group[j] != bi):
                continue
            d = x[j] - xi
            if wp.dot(d, d) >= r2:
                continue
            if n < cap:
                cand[i, n] = j
            n += 1
        cand_found[i] = n
        if n > cap:
            wp.atomic_max(overflow, 0, n)
            n = cap
        cand_count[i] = n
        # Sort by index (insertion sort: the query returns ascending runs, one per cell;
        # sorting after the query costs 40 % less than inserting during it).
        for a in range(1, n):
            v = cand[i, a]
            b = a
            while b > 0 and cand[i, b - 1] > v:
                cand[i, b] = cand[i, b - 1]
                b -= 1
            cand[i, b] = v
        x_ref[i] = xi

    @wp.kernel(enable_backward=False, module="unique")
    def displacement_bounds(
        x: wp.array(dtype=vec3),
        x_ref: wp.array(dtype=vec3),
        c: vec3,
        F: wp.array(dtype=mat33),
        with_stretch: int,
        max_stretch: scalar,
        cand_stretch: wp.array(dtype=scalar),
        out: wp.array(dtype=scalar),
    ):
        """For the displacements d = x - x_ref: out[k] = max d_k, out[k + 3] = max -d_k,
        out[6] = max |d - c|^2 for a given centre c; with ``with_stretch``, out[7] = 1
        where a stretch bound exceeds what the particle's candidates cover; out[8] = 1 where
        a position is not finite (a NaN fails every comparison below, so the maxima miss it)."""
        i = wp.tid()
        if with_stretch != 0:
            st = cand_stretch[i]
            if st < max_stretch and stretch_bound2(F[i]) > st * st:
                out[7] = scalar(1.0)
        d = x[i] - x_ref[i]
        if not (wp.isfinite(d[0]) and wp.isfinite(d[1]) and wp.isfinite(d[2])):
            out[8] = scalar(1.0)
        for k in range(3):
            if d[k] > out[k]:
                wp.atomic_max(out, k, d[k])
            if -d[k] > out[k + 3]:
                wp.atomic_max(out, k + 3, -d[k])
        e = d - c
        e2 = wp.dot(e, e)
        if e2 > out[6]:
            wp.atomic_max(out, 6, e2)

    @wp.func
    def weight_key(xi: vec3, xj: vec3, d2: scalar, Finv: mat33, gi: vec3, rest_i: vec3, rest: wp.array(dtype=vec3),
                   j: int, slack2: scalar, with_rest: int, images: int, gn: vec3, goff: scalar, gmin: scalar) -> scalar:
        """The key a full stretched row keeps the smallest of: the least of the distances some
        kernel of the step may weigh the pair by, each scaled so that ``h^2`` is where its
        weight ends: ``|x_j - x_i|^2`` (the fit, SPH, the variational force),
        ``|F_i^-1 (x_j - x_i)|^2 / slack^2`` (the paper's elastic kernel, eq. 11, and with
        ``images`` its floor images, whose pairs ``g_j - x_i`` and ``x_j - g_i`` the fit, the
        variational force and SPH also weigh at their current distance; ``slack``: the force reads the ``F`` this step makes; for
        a material that flows ``Finv`` is ``flow_inverse_bound``'s, the flowed ``F`` being
        read), and
        with ``with_rest`` the rest distance (the hourglass control). Below ``h^2``: weighed."""
        k = d2
        e = Finv * (xj - xi)
        k = wp.min(k, wp.dot(e, e) / slack2)
        if images != 0:
            g = floor_image(xj, gn, goff, gmin) - xi
            k = wp.min(k, wp.dot(g, g))
            e = Finv * g
            k = wp.min(k, wp.dot(e, e) / slack2)
            g = xj - gi
            k = wp.min(k, wp.dot(g, g))
            e = Finv * g
            k = wp.min(k, wp.dot(e, e) / slack2)
        if with_rest != 0:
            e = rest[j] - rest_i
            k = wp.min(k, wp.dot(e, e))
        return k

    @wp.func
    def flow_inverse_bound(F: mat33, det: scalar) -> mat33:
        """``G`` with ``|G d| <= |F'^-1 d|`` for every ``d`` and every ``F'`` this step's plastic
        flow may make of ``F`` (``det F > 0``): the flow keeps ``F``'s singular vectors and
        moves each singular value to ``sigma_k^(1 - gamma) t^gamma``, ``gamma`` in [0, 1],
        ``t = clamp(J, 0.8, 1.25)^(1/3)`` (``plasticity.flow_step``), never past
        ``max(sigma_k, t)``: ``G = V diag(1 / max(sigma_k, t)) U^T``. Of the flow's own SVD
        (``isotropic.svd``), whose ``sigma_k`` are the very values the flow moves: one formula
        for them (``wp.svd3``'s, which this read before, differ near ``F = I`` by units in the
        last place, and moved ``G`` by at most 9 units of float32; the bound holds to the same
        round-off either way, tests/test_shared_formulas.py)."""
        U, sg, V = svd(F)
        t = wp.pow(wp.min(wp.max(det, j_lo), j_hi), third)
        inv = vec3(scalar(1.0) / wp.max(wp.abs(sg[0]), t), scalar(1.0) / wp.max(wp.abs(sg[1]), t),
                   scalar(1.0) / wp.max(wp.abs(sg[2]), t))
        return V * wp.diag(inv) * wp.transpose(U)

    @wp.kernel(enable_backward=False, module="unique")
    def select_neighbors(
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        mass: wp.array(dtype=scalar),
        cand: wp.array2d(dtype=wp.int32),
        cand_count: wp.array(dtype=wp.int32),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        with_guard: int,
        with_density: int,
        material: wp.array(dtype=wp.int32),
        rest_density: wp.array(dtype=scalar),
        mat: Materials,
        F: wp.array(dtype=mat33),
        with_stretch: int,
        cand_stretch: wp.array(dtype=scalar),
        slack: scalar,
        rest: wp.array(dtype=vec3),
        with_rest: int,
        with_flow: int,
        cut_index: int,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        nbr: wp.array2d(dtype=wp.int32),
        nbr_d2: wp.array2d(dtype=scalar),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
        rho: wp.array(dtype=scalar),
        p: wp.array(dtype=scalar),
        vol: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        vol_p: wp.array(dtype=scalar),
        counters: wp.array(dtype=wp.int32),
    ):
        """The neighbour rows at ``x``; with ``with_guard`` the guards of paper §4; with
        ``with_density`` the SPH density ``rho`` (poly6), volume ``m / rho`` and pressure
        ``p``, of ``rho`` (``with_density`` 1) or (2) of each material's pressure density
        ``rho_p`` (``pressure.density``), written with its ``vol_p = m / rho_p``.

        With ``with_stretch`` the rows hold every particle within ``h sigma_max(F_i)``
        (at most ``cand_stretch[i] h``, the candidates' reach), so a pair enters or leaves a row only where every
        kernel of the step, the elastic one at ``F_i^-1 (x_j - x_i)`` included, is zero.
        A particle whose row may lack a neighbour of non-zero weight is counted in
        ``counters[cut_index]``: a stretch beyond the margin, or a full row that dropped a
        candidate some kernel of the step may weigh (its ``weight_key`` below ``h^2``; an
        ``F_i`` that is not invertible: any candidate). ``rest``
        (``with_rest``): the rest positions, whose distances the hourglass control weighs;
        ``with_flow``: ``material`` and ``mat`` say which particles' ``F`` flows this step."""
        i = wp.tid()
        xi = x[i]
        bi = body[i]
        kmax = nbr.shape[1]
        h_fit2 = h * h
        h2 = h_fit2
        cut = int(0)
        if with_stretch != 0:
            g = stretch_bound2(F[i])
            m2 = cand_stretch[i] * cand_stretch[i]
            if g > m2:
                cut = 1
                g = m2
            h2 = h_fit2 * wp.max(g, scalar(1.0))
        # keyed: a full stretched row keeps the smallest weight_key, not the nearest; what it
        # reads (F_i^-1) is made only when a row overflows, which the default width makes rare.
        keyed = int(0)
        Finv = mat33()
        gi = xi
        rest_i = xi
        slack2 = slack * slack
        nc = cand_count[i]
        # Pass 1: the candidates within the selection radius in index order while the row
        # has room. A row that overflows becomes a max-heap on the key (k, j), k the squared
        # distance (keyed: weight_key, so that the pairs a kernel weighs are kept before
        # those of the ball of radius h sigma_max(F_i) no kernel weighs: squashed to
        # diag(1.3, 1.3, 0.33), a landing ball's lowest particles, the ball held ~100, more
        # than a row, of which ~58 are weighed); a smaller key replaces its root, so the row
        # ends with the kmax smallest keys. Candidates come in index order, so a new one is
        # below the root exactly when its k is.
        n_in = int(0)
        c = int(0)
        # Branch-free while the row has room (whether a candidate is within h is hard to
        # predict in a deformed body): write every candidate at the next free slot and
        # advance only past those within h.
        while c < nc and n_in < kmax:
            j = cand[i, c]
            d = x[j] - xi
            d2 = wp.dot(d, d)
            nbr[i, n_in] = j
            nbr_d2[i, n_in] = d2
            n_in += wp.where(d2 < h2, 1, 0)
            c += 1
        while c < nc:
            j = cand[i, c]
            d = x[j] - xi
            d2 = wp.dot(d, d)
            if d2 < h2:
                if n_in == kmax and with_stretch != 0:
                    Fi = F[i]
                    det = wp.determinant(Fi)
                    if det > scalar(0.0) and det < scalar(1.0e30):
                        keyed = 1
                        Finv = wp.inverse(Fi)
                        if with_flow != 0:
                            if mat.flow_rate[material[i]] > scalar(0.0):
                                Finv = flow_inverse_bound(Fi, det)
                        if images != 0:
                            gi = floor_image(xi, gn, goff, gmin)
                        if with_rest != 0:
                            rest_i = rest[i]
                k = d2
                if keyed != 0:
                    k = weight_key(xi, x[j], d2, Finv, gi, rest_i, rest, j, slack2, with_rest, images, gn, goff, gmin)
                if n_in == kmax:
                    if keyed != 0:
                        for q in range(kmax):
                            jq = nbr[i, q]
                            nbr_d2[i, q] = weight_key(xi, x[jq], nbr_d2[i, q], Finv, gi, rest_i, rest, jq, slack2,
                                                      with_rest, images, gn, goff, gmin)
                    for q in range(kmax // 2):
                        sift_down(nbr, nbr_d2, i, kmax // 2 - 1 - q, kmax)
                if k < nbr_d2[i, 0]:
                    nbr[i, 0] = j
                    nbr_d2[i, 0] = k
                    sift_down(nbr, nbr_d2, i, 0, kmax)
                n_in += 1
            c += 1
        max_k = nbr_d2[i, 0]
        max_j = nbr[i, 0]
        n = n_in
        if n_in > kmax:
            # Pass 2: rewrite the row in index order, every key up to the largest kept.
            # Branch-free as above; it stops at the kmax-th kept key.
            n = int(0)
            c = int(0)
            while c < nc and n < kmax:
                j = cand[i, c]
                d = x[j] - xi
                d2 = wp.dot(d, d)
                k = d2
                if keyed != 0:
                    k = weight_key(xi, x[j], d2, Finv, gi, rest_i, rest, j, slack2, with_rest, images, gn, goff, gmin)
                nbr[i, n] = j
                nbr_d2[i, n] = d2
                n += wp.where(d2 < h2 and (k < max_k or (k == max_k and j <= max_j)), 1, 0)
                c += 1
            if keyed == 0:
                cut = 1
            elif max_k < h_fit2:
                # Short only if a dropped candidate (a key above the largest kept) is weighed.
                c = int(0)
                while c < nc and cut == 0:
                    j = cand[i, c]
                    d = x[j] - xi
                    d2 = wp.dot(d, d)
                    if d2 < h2:
                        k = weight_key(xi, x[j], d2, Finv, gi, rest_i, rest, j, slack2, with_rest, images, gn, goff, gmin)
                        if k < h_fit2 and key_greater(k, j, max_k, max_j):
                            cut = 1
                    c += 1
        count[i] = n
        if cut != 0:
            wp.atomic_add(counters, cut_index, 1)

        # SPH density (pressure.density) and the guards of paper §4 on the same-body
        # neighbourhood used by the MLS fit.
        c6 = sm.poly6_coef(h)
        cf = fw.coef(h)
        c_ws = sm.w_spiky_coef(h)
        r = scalar(0.0)
        rp = scalar(0.0)
        # Whether the pressure density is a sum of its own (else it is the poly6 one).
        form = int(0)
        if with_density != 0:
            r = mass[i] * sm.w_poly6_c(scalar(0.0), h, c6)
            if with_density == 2:
                form = mat.pressure_force[material[i]]
                rp = mass[i] * density_weight(scalar(0.0), h, c6, c_ws, form)
        A = mat33()
        same = scalar(0.0)
        for k in range(n):
            j = nbr[i, k]
            w = sm.w_poly6_c(nbr_d2[i, k], h, c6)
            if with_density != 0:
                r += mass[j] * w
                if form >= 2:
                    rp += mass[j] * density_weight(nbr_d2[i, k], h, c6, c_ws, form)
            if with_guard != 0:
                # Only neighbours of non-zero weight count for the guard (rows reach
                # beyond h with with_stretch).
                if body[j] == bi and nbr_d2[i, k] < h_fit2:
                    d = x[j] - xi
                    if wp.static(weight != "poly6"):
                        w = fw.w_c(nbr_d2[i, k], h, cf)  # the fit's weight (the density's w otherwise)
                    A += w * wp.outer(d, d)
                    cw, dcw = count_weight(nbr_d2[i, k], h_fit2)
                    same += cw
        if with_density != 0:
            if images != 0:
                # The floor images enter both densities, each with its own kernel.
                r += image_density(i, x, mass, nbr, n, h, c6, c_ws, 0, gn, goff, gmin)
                if form >= 2:
                    rp += image_density(i, x, mass, nbr, n, h, c6, c_ws, form, gn, goff, gmin)
            rho[i] = r
            vol[i] = mass[i] / r
            if with_density == 2:
                if form < 2:
                    rp = r
                rho_p[i] = rp
                vol_p[i] = mass[i] / rp
            else:
                rp = r
            m = material[i]
            p[i] = pressure_of(rp, rest_density[i], mat.pressure_stiffness[m], mat.clamp_pressure[m])
        if with_guard != 0:
            if images != 0:
                # The floor images are partners of the fit (deformation.fit_sums): the guard
                # counts them, as the fused step's guard on the fit's own moments does (a
                # layer one particle thick on the imaged ground is a full neighbourhood).
                # Only A and the count are read; the displacements passed are not used.
                Ag, Bg, sg = fit_pair_sums(i, x, x, x, x, body, nbr, n, h, 1, gn, goff, gmin, 1)
                A = A + Ag
                same = same + sg
            guard[i] = guard_code(A, same, min_neighbors, max_condition)

    return types.SimpleNamespace(
        grid_points=grid_points,
        build_candidates=build_candidates,
        displacement_bounds=displacement_bounds,
        select_neighbors=select_neighbors,
        guard_code=guard_code,
        flow_inverse_bound=flow_inverse_bound,
    )


class NeighborOverflow(checks.Rebuilt, RuntimeError):
    """A candidate row past ``MAX_CANDIDATES``: a body crushed together, or a blow-up whose
    stretch widened the search radius over the whole body. ``particles``: the indices of
    those past it (a model of worlds: the worlds that blew up, ``fit`` failing their starts
    alone); ``need``: the largest row."""

    def __init__(self, message: str, *, particles, need: int):
        super().__init__(message)
        self.particles = np.asarray(particles, dtype=np.int64)
        self.need = need


class NeighborSearch:
    """Owns the hash grid and the candidate lists; fills a state's neighbour arrays.

    ``skin`` (a length, >= 0) is the Verlet margin of the candidate lists; ``build``
    always searches afresh, ``update`` reuses the candidates while they are complete.
    ``rebuilds`` counts the candidate builds. ``fit_weight`` (``smoothing.FIT_WEIGHTS``): the
    weights of the guard's moment matrix, the fit's.
    """

    def __init__(
        self,
        particle_count: int,
        scalar,
        device,
        h: float,
        *,
        min_neighbors: int = MIN_NEIGHBORS,
        max_condition: float = MAX_CONDITION,
        skin: float = 0.0,
        spacing: float | None = None,
        bodies_interact: bool = True,
        group: wp.array | None = None,
        world: wp.array | None = None,
        fit_weight: str = smoothing.DEFAULT_FIT_WEIGHT,
    ):
        self.scalar = scalar
        self.bodies_interact = bool(bodies_interact)
        # ``group``: per-particle ids that never see each other across (overrides the
        # body filter of ``bodies_interact=False``; ``Model.neighbor_group``). ``world``:
        # per-particle world ids, only used to spread the worlds over the hash grid.
        self.group = group
        self.world = world
        self._world_stride = 0.0
        self.device = device
        self.launches = Launches()
        self.h = float(h)
        #: The kernels' image-plane arguments (``Model.image_args``) for the density the
        #: selection sums; None: no image plane.
        self.image_args = None
        self.skin = float(skin)
        self.min_neighbors = int(min_neighbors)
        self.max_condition = float(max_condition)
        self.kernels = kernels(scalar, fit_weight)
        self.particle_count = int(particle_count)
        self._grid_dims = None
        self.grid = None
        self._points = wp.zeros(particle_count, dtype=wp.vec3f, device=device)
        # Candidate capacity from the lattice count inside h + skin, with room for compression.
        dx = float(spacing) if spacing else self.h / 2.0
        ball = 4.0 / 3.0 * math.pi * ((self.h * TYPICAL_STRETCH + self.skin) / dx) ** 3
        self._capacity = int(8 * math.ceil((1.5 * ball + 16) / 8))
        self.candidates = None
        self.candidate_count = wp.zeros(particle_count, dtype=wp.int32, device=device)
        self._x_ref = wp.zeros(particle_count, dtype=type_set(scalar).vec3, device=device)
        self._overflow = wp.zeros(1, dtype=wp.int32, device=device)
        self._bounds = wp.zeros(9, dtype=scalar, device=device)
        #: Whether the last ``candidates_valid`` found a non-finite position: read with the
        #: displacement bounds the check reads anyway, so the solver can say so without a read
        #: of its own (``Solver.step``).
        self.found_non_finite = False
        self._bounds_view = self._bounds.numpy() if self._bounds.device.is_cpu else None
        self._centre = (0.0, 0.0, 0.0)
        self._have_candidates = False
        # Per particle: the stretch its candidates cover (candidate_stretch).
        self._cand_stretch = wp.ones(particle_count, dtype=scalar, device=device)
        self._cand_found = wp.zeros(particle_count, dtype=wp.int32, device=device)
        self._cand_with_stretch = False
        self.rebuilds = 0
        self.updates = 0

    @property
    def capacity(self) -> int:
        return self._capacity


    def _ensure_grid(self, x: wp.array):
        # Cells of a bit under half the search radius: about one particle each, so a
        # query visits few points outside the ball and returns rows nearly in index order
        # (grid_points). Dimensions are fixed at the first build from the extent then
        # (with room to spread); cell aliasing of the periodic grid later costs time,
        # not correctness (every candidate is distance-filtered).
        if self._grid_dims is None:
            self.cell_width = CELL_FRACTION * (self.h + self.skin)
            xs = x.numpy()
            if self.world is not None and len(xs):
                # Worlds side by side along x, a search radius apart, as grid_points
                # places them (their extent then counts for the dimensions).
                w = self.world.numpy()
                width = 0.0
                for k in np.unique(w):
                    xk = xs[w == k, 0]
                    xk = xk[np.isfinite(xk)]
                    if len(xk):
                        width = max(width, float(xk.max() - xk.min()))
                self._world_stride = width + 2.0 * (self.h + self.skin)
                xs = xs.copy()
                xs[:, 0] += w * self._world_stride
            extent = xs.max(axis=0) - xs.min(axis=0) if len(xs) else np.zeros(3)
            extent = np.where(np.isfinite(extent), extent, 0.0)
            dims = [int(min(256, max(32, 2 * math.ceil(e / self.cell_width) + 8))) for e in extent[::-1]]
            # At most ~16 cells (two int32 each) per particle: a sparse scene aliases more.
            limit = max(16 * x.shape[0], 64**3)
            while dims[0] * dims[1] * dims[2] > limit and max(dims) > 32:
                k = dims.index(max(dims))
                dims[k] = max(32, dims[k] // 2)
            self._grid_dims = tuple(dims)
            self.grid = wp.HashGrid(*self._grid_dims, device=self.device)

    def _build_candidates(self, x: wp.array, body: wp.array, F=None):
        self._ensure_grid(x)
        n = x.shape[0]
        world = self.world if self.world is not None else self._dummy_arrays()["i"]
        self.launches(
            self.kernels.grid_points, n, [x, world, wp.float32(self._world_stride)], [self._points],
            device=self.device, record_tape=False,
        )
        points = self._points
        self.grid.build(points, self.cell_width)
        while True:
            if self.candidates is None or self.candidates.shape[1] != self._capacity:
                self.candidates = wp.empty((n, self._capacity), dtype=wp.int32, device=self.device)
            self._overflow.zero_()
            args = [
                self.grid.id, points, x, self.scalar(self.h), self.scalar(self.skin),
                self._dummy_arrays()["F"] if F is None else F, int(F is not None), self.scalar(STRETCH_SLACK),
                self.scalar(MAX_STRETCH), body if self.group is None else self.group,
                int(self.group is not None or not self.bodies_interact),
            ]
            self.launches(
                self.kernels.build_candidates,
                n,
                args,
                [self.candidates, self.candidate_count, self._overflow, self._x_ref, self._cand_stretch,
                 self._cand_found],
                device=self.device,
                record_tape=False,
            )
            need = int(self._overflow.numpy()[0])
            if need == 0:
                break
            if need > MAX_CANDIDATES:
                over = np.flatnonzero(self._cand_found.numpy() > MAX_CANDIDATES)
                raise NeighborOverflow(
                    f"a particle has {need} particles within h s + skin = {self.h:g} s + {self.skin:g}: more than {MAX_CANDIDATES}; "
                    "the body has collapsed (reduce dt)", particles=over, need=need)
            self._capacity = int(8 * math.ceil(1.25 * need / 8))
        self._have_candidates = True
        self._cand_with_stretch = F is not None
        self._centre = (0.0, 0.0, 0.0)
        self.rebuilds += 1

    def candidates_valid(self, x: wp.array, F=None) -> bool:
        """Whether the candidates built earlier still hold every pair within the selection
        radius at ``x`` (``h``; with ``F``, ``h sigma_max(F)``).

        Two particles moved relative to each other by at most ``D``, the smaller of the
        diagonal of the displacements' bounding box and twice their largest distance from
        any fixed point ``c`` (the box centre at the previous check): a pair not among the
        candidates (``>= h s_i + skin`` apart when they were built) is still beyond the
        selection radius ``h sigma_max(F_i) <= h s_i`` while ``D < skin``."""
        self.found_non_finite = False
        if not self._have_candidates or self.skin <= 0.0 or x.shape[0] != self.particle_count:
            return False
        if F is not None and not self._cand_with_stretch:
            return False
        # On the CPU through one kept view of the bounds' memory: numpy() and fill_() each
        # cost about as much as the check's kernel at small particle counts.
        view = self._bounds_view
        if view is not None:
            view[...] = -np.inf
        else:
            self._bounds.fill_(-np.inf)
        c = self._centre
        self.launches(
            self.kernels.displacement_bounds, x.shape[0],
            [
                x, self._x_ref, type_set(self.scalar).vec3(*c), self._dummy_arrays()["F"] if F is None else F,
                int(F is not None), self.scalar(MAX_STRETCH), self._cand_stretch,
            ],
            [self._bounds], device=self.device, record_tape=False,
        )
        # Nine numbers: Python floats cost less than numpy's calls on them.
        b = (view if view is not None else self._bounds.numpy()).tolist()
        # Only said: the lists are judged as before (a NaN position passes every test).
        self.found_non_finite = b[8] > 0.0
        if b[7] > 0.0:
            return False
        if not all(math.isfinite(v) for v in b[:7]):
            return False
        width = [b[k] + b[3 + k] for k in range(3)]
        diag = math.sqrt(width[0] * width[0] + width[1] * width[1] + width[2] * width[2])
        spread = min(diag, 2.0 * math.sqrt(max(b[6], 0.0)))
        self._centre = tuple(0.5 * (b[k] - b[3 + k]) for k in range(3))
        return spread < SKIN_SAFETY * self.skin

    def _select(self, x, body, nbr, nbr_d2, count, guard, sph=None, F=None, counters=None, cut_index=0, rest=None,
                flow=None):
        """``sph``: None, or (mass, material, rest_density, materials, rho, p, vol, rho_p, vol_p)
        (``rho_p``, ``vol_p`` None: the pressure reads ``rho``); ``F``:
        None (rows within h) or the deformation gradients the rows must cover
        (``select_neighbors``); ``counters[cut_index]`` counts the rows that may be short,
        ``rest`` (None: no term weighs rest distances) the rest positions they are judged by too,
        ``flow`` (None, or (particle material, materials struct)) which particles' ``F`` may flow
        before the force reads it."""
        d = self._dummy_arrays()
        if sph is None:
            mass, material, rest_density, mats, rho, p, vol = d["s"], d["i"], d["s"], d["mat"], d["s"], d["s"], d["s"]
            rho_p = vol_p = None
        else:
            mass, material, rest_density, mats, rho, p, vol, rho_p, vol_p = sph
        with_density = 0 if sph is None else (1 if rho_p is None else 2)
        if flow is not None:
            material, mats = flow
        with_guard = guard is not None
        self.launches(
            self.kernels.select_neighbors,
            x.shape[0],
            [
                x, body, mass, self.candidates, self.candidate_count, self.scalar(self.h), self.min_neighbors,
                self.scalar(self.max_condition), int(with_guard), with_density, material, rest_density, mats,
                d["F"] if F is None else F, int(F is not None), self._cand_stretch, self.scalar(STRETCH_SLACK),
                d["v"] if rest is None else rest, int(rest is not None), int(flow is not None), int(cut_index),
                *(self.image_args if self.image_args is not None else
                  (type_set(self.scalar).vec3(0.0, 1.0, 0.0), self.scalar(0.0), self.scalar(0.0), 0)),
            ],
            [nbr, nbr_d2, count, guard if with_guard else d["i"], rho, p, vol, d["s"] if rho_p is None else rho_p,
             d["s"] if vol_p is None else vol_p, d["c"] if counters is None else counters],
            device=self.device,
            record_tape=False,
        )

    def _dummy_arrays(self):
        # Typed one-element placeholders for arguments a launch does not read.
        if getattr(self, "_dummies", None) is None:
            self._dummies = {
                "s": wp.zeros(1, dtype=self.scalar, device=self.device),
                "i": wp.zeros(1, dtype=wp.int32, device=self.device),
                "mat": materials.make(self.scalar, self.device),
                "F": wp.zeros(1, dtype=type_set(self.scalar).mat33, device=self.device),
                "c": wp.zeros(1, dtype=wp.int32, device=self.device),
                "v": wp.zeros(1, dtype=type_set(self.scalar).vec3, device=self.device),
            }
        return self._dummies

    def build(self, x: wp.array, body: wp.array, nbr, nbr_d2, count, guard, sph=None, **stretch):
        """A fresh search at ``x`` (the candidates are rebuilt). ``guard`` may be None
        (not evaluated); ``sph`` and ``stretch``, see ``update``."""
        self._build_candidates(x, body, stretch.get("F"))
        self._select(x, body, nbr, nbr_d2, count, guard, sph, **stretch)

    def update(self, x: wp.array, body: wp.array, nbr, nbr_d2, count, guard, sph=None, **stretch):
        """The same lists as ``build``, reusing the candidates while they are complete.

        With ``sph = (mass, material, rest_density, materials, rho, p, vol, rho_p, vol_p)``
        (``materials``: the ``sim.materials`` struct), also writes the SPH density ``rho`` over
        the new lists, the volume ``vol = mass / rho``, the pressure density ``rho_p`` and its
        ``vol_p = mass / rho_p`` (both None: the pressure reads ``rho``) and the pressure ``p``
        (not recorded on a tape). With ``F=`` (the
        deformation gradients at ``x``) the rows reach ``h sigma_max(F)``; with
        ``counters=, cut_index=`` rows that may be short are counted (``select_neighbors``;
        ``rest=``: the rest positions where a term weighs their distances; ``flow=``: the
        materials, whose plastic flow changes the ``F`` the force reads)."""
        self.updates += 1
        F = stretch.get("F")
        if not self.candidates_valid(x, F):
            self._build_candidates(x, body, F)
        self._select(x, body, nbr, nbr_d2, count, guard, sph, **stretch)
