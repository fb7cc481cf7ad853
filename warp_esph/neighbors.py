"""Neighbour lists (paper §4, SPEC §1.1): the up-to-30 nearest particles ``j != i`` with
``|x_j - x_i| < h``, found with ``wp.HashGrid`` and stored as a fixed-width int32 row
plus a count.

The lists are integers: they are recorded once per step and reused unchanged by the
backward pass, so the tape never queries a hash grid (WARP_NOTES trap 3). The same
kernel evaluates the deformation-update guards of paper §4 that depend only on the
neighbourhood (too few neighbours, ill-conditioned moment matrix), because they need
an eigen-decomposition whose adjoint is not wanted.
"""

import functools
import math
import types

import numpy as np
import warp as wp

from ._types import type_set
from . import smoothing

#: Guard codes written per particle (0 = the MLS update may run).
GUARD_OK = 0
GUARD_FEW_NEIGHBORS = 1
GUARD_ILL_CONDITIONED = 2


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    w_poly6 = smoothing.funcs(scalar).w_poly6

    @wp.kernel(enable_backward=False)
    def to_float32(x: wp.array(dtype=vec3), out: wp.array(dtype=wp.vec3f)):
        i = wp.tid()
        p = x[i]
        out[i] = wp.vec3f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))

    @wp.kernel(enable_backward=False)
    def find_neighbors(
        grid: wp.uint64,
        grid_points: wp.array(dtype=wp.vec3f),
        x: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        nbr: wp.array2d(dtype=wp.int32),
        nbr_d2: wp.array2d(dtype=scalar),
        count: wp.array(dtype=wp.int32),
        guard: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        xi = x[i]
        kmax = nbr.shape[1]
        h2 = h * h
        n = int(0)
        query = wp.hash_grid_query(grid, grid_points[i], wp.float32(h))
        j = int(0)
        while wp.hash_grid_query_next(query, j):
            if j == i:
                continue
            d = x[j] - xi
            d2 = wp.dot(d, d)
            if d2 >= h2:
                continue
            pos = int(0)
            if n < kmax:
                pos = n
                n += 1
            elif d2 < nbr_d2[i, kmax - 1]:
                pos = kmax - 1
            else:
                continue
            # Insertion keeps the row sorted by distance, ties by arrival order.
            while pos > 0 and nbr_d2[i, pos - 1] > d2:
                nbr[i, pos] = nbr[i, pos - 1]
                nbr_d2[i, pos] = nbr_d2[i, pos - 1]
                pos -= 1
            nbr[i, pos] = j
            nbr_d2[i, pos] = d2
        count[i] = n

        # Guards of paper §4 on the same-body neighbourhood used by the MLS fit.
        A = mat33()
        same = int(0)
        for k in range(n):
            jj = nbr[i, k]
            if body[jj] == body[i]:
                d = x[jj] - xi
                A += w_poly6(wp.dot(d, d), h) * wp.outer(d, d)
                same += 1
        code = int(0)
        if same < min_neighbors:
            code = 1
        else:
            Q = mat33()
            lam = vec3()
            wp.eig3(A, Q, lam)
            lmin = wp.min(wp.min(lam[0], lam[1]), lam[2])
            lmax = wp.max(wp.max(lam[0], lam[1]), lam[2])
            if lmin <= scalar(0.0) or lmax > max_condition * lmin:
                code = 2
        guard[i] = code

    return types.SimpleNamespace(to_float32=to_float32, find_neighbors=find_neighbors)


class NeighborSearch:
    """Owns the hash grid; ``build`` fills a state's neighbour arrays from its positions.

    The grid is periodic, so its resolution is chosen from the domain extent at each
    build: cells of width ``h`` covering the bounding box (WARP_NOTES: HashGrid).
    """

    def __init__(self, particle_count: int, scalar, device, h: float, *, min_neighbors: int = 6, max_condition: float = 1.0e3):
        self.scalar = scalar
        self.device = device
        self.h = float(h)
        self.min_neighbors = int(min_neighbors)
        self.max_condition = float(max_condition)
        self.kernels = kernels(scalar)
        self._grid_dims = None
        self.grid = None
        self._points = None if scalar is wp.float32 else wp.zeros(particle_count, dtype=wp.vec3f, device=device)

    def _ensure_grid(self, x: wp.array):
        # Grid dimensions only grow, and only when the body's extent outgrows them, so the
        # grid is reallocated rarely; cell aliasing of a periodic grid costs time, not
        # correctness (every candidate is distance-filtered).
        if self._grid_dims is None:
            dims = 128 if x.shape[0] > 50_000 else 64
            self._grid_dims = (dims, dims, dims)
            self.grid = wp.HashGrid(*self._grid_dims, device=self.device)

    def build(self, x: wp.array, body: wp.array, nbr, nbr_d2, count, guard):
        self._ensure_grid(x)
        n = x.shape[0]
        if self._points is None:
            points = x
        else:
            wp.launch(self.kernels.to_float32, n, [x], [self._points], device=self.device, record_tape=False)
            points = self._points
        self.grid.build(points, self.h)
        wp.launch(
            self.kernels.find_neighbors,
            n,
            [self.grid.id, points, x, body, self.scalar(self.h), self.min_neighbors, self.scalar(self.max_condition)],
            [nbr, nbr_d2, count, guard],
            device=self.device,
            record_tape=False,
        )
