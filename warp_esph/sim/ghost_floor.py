"""A floor of ghosts (``SceneBuilder.add_particle_floor(ghost=True)``; docs/physics.md, "The
no-slip ghost floor"): a no-slip wall, or with ``slip=True`` a frictionless one.

The floor's particles stay pinned where they are for the neighbour search, the SPH
density, pressure and viscosity. In the incremental fit (eqs. 5-6) they are not material
but a continuation of it: floor particle ``k`` moves over the step by minus the material's
displacement at its mirror point ``p_k`` across the wall plane (halfway between the floor's
top layer and the body's lowest layer),

    y_k = x_k - sum_j s_kj u_j,     s_kj = W(|x_j - p_k|) / N(sum_j W),     (ghost_displacement)

a Shepard average over the body's free particles within ``GHOST_RADIUS`` spacings of
``p_k``, ``W`` the poly6 shape of eq. 7 normalised to 1 at ``p_k``. The motion the fits
near the floor see is then continued oddly across the plane, where it vanishes: a shear or
stretch that is zero on the plane is fitted next to the floor as in the interior (exactly
with a stencil of one spacing on a lattice, to about 1 % with the default). On a slip floor the
ghost moves by ``R sum_j s_kj u_j`` instead, ``R`` the mirror (``ghost_map``): the motion is
continued evenly along the plane and oddly across it, so the material slides freely on the
plane but does not cross it, and a motion with that symmetry (a lateral stretch, a
compression against the plane) is fitted next to the floor as in the interior.

``N`` (``stencil_normaliser``) is the stencil's total weight where it holds at least
``MIN_TOTAL + SWITCH`` (a particle's weight at ``p_k`` is 1), and switches smoothly (C1) to
``MIN_TOTAL`` below it, so a no-slip ghost that a spreading front reaches follows its few
particles in part and comes on gradually instead of at once. A slip ghost makes up the
tangential part it does not follow, ``1 - sum W / N`` (``stencil_fill``), with a Shepard
average of radius the support ``h`` around ``p_k`` (``f_kj = fill W_h / sum W_h``, the rows
``State.ghost_fill``):

    y_k = x_k + R sum_j s_kj u_j + P sum_j f_kj u_j,     P = diag(1, 0, 1),

so a ghost in any fit follows a slide along the plane whole (the fitting particle is within
``h`` of ``p_k``: the mirror point is nearer it than the ghost), and a body sliding on the
slip floor is fitted no shear at its rim, where the ghosts past it held still (docs/physics.md,
"The slip ghost floor"). The normal part, which vanishes on the plane, keeps the switch. Where
the stencil is full the fill is 0 and the ghost is as above.

The floor particles carry no energy (their ``Model.particle_volume`` is 0): only the free
particles' energies act, each also through its ghosts. Since ``y_k`` is linear in the free
particles' end positions, the force the energies put on ghost ``k`` goes to its stencil,
``f_j += s_kj M f_k`` with ``M`` the ghost's map (``-I``, or ``R`` on a slip floor; each its
own transpose; ``hand_over``), and on a slip floor ``f_j += f_kj P f_k``; floor particle
``k`` keeps the opposite, so every hand-over is a pair of equal and opposite forces and the
pinned floor's reaction (``tools``) is what the wall puts on the material.

Every step: ``StencilSearch.update`` (after the neighbour search; the candidates from a
hash grid, untaped integers, the weights differentiable), ``launch_hand_over`` (after the
elastic forces) and ``launch_fit_positions`` (before the deformation update, into
``State.ghost_y``: the fit reads those, so no state array is overwritten under a tape).
"""


import dataclasses
import functools
import types

import numpy as np
import warp as wp

from .._types import type_set
from . import neighbors, smoothing

#: The stencil's radius around the mirror point, in spacings (1: exact for affine motions
#: on a lattice whose layers mirror each other; 1.2 keeps a ghost's stencil from emptying
#: between lattice sites as the material shears; docs/physics.md).
GHOST_RADIUS = 1.2
#: Stencil rows per floor particle; a fuller stencil counts as a cut neighbour row.
STENCIL = 24
#: The least stencil weight normalised to 1, and the half-width of the smooth switch to it
#: (``stencil_normaliser``), in units of one particle's weight at the mirror point.
MIN_TOTAL = 0.5
SWITCH = 0.25


@dataclasses.dataclass
class GhostFloor:
    """A model's ghost floors (``Model.ghost_floor``): ``floor`` the floor particles'
    indices, ``slot`` each particle's row in them (-1: not a floor particle), the wall
    plane ``y = offset`` of each floor particle, whether it is a slip floor's (``slip``, 1),
    the stencil radius (m), the slip ghosts' fill radius (m, ``stencil_fill``: the support
    radius) and the stencil rows per floor particle."""

    floor: wp.array
    slot: wp.array
    offset: wp.array
    slip: wp.array
    radius: float
    reach: float
    rows: int

    @property
    def count(self) -> int:
        return self.floor.shape[0]


def build(model, ranges) -> "GhostFloor | None":
    """``GhostFloor`` of ``ranges``, a ``(start, stop, plane height, slip)`` per ghost floor."""
    if not ranges:
        return None
    idx = np.concatenate([np.arange(a, b, dtype=np.int32) for a, b, _, _ in ranges])
    off = np.concatenate([np.full(b - a, y) for a, b, y, _ in ranges]).astype(model.types.np_dtype)
    slip = np.concatenate([np.full(b - a, int(sl)) for a, b, _, sl in ranges]).astype(np.int32)
    slot = np.full(model.particle_count, -1, dtype=np.int32)
    slot[idx] = np.arange(len(idx), dtype=np.int32)
    dev = model.device
    # A slip ghost's fill reaches over a support radius, as many particles as a neighbour row.
    rows = max(STENCIL, model.max_neighbors) if slip.any() else STENCIL
    return GhostFloor(floor=wp.array(idx, dtype=wp.int32, device=dev), slot=wp.array(slot, dtype=wp.int32, device=dev),
                      offset=wp.array(off, dtype=model.scalar, device=dev),
                      slip=wp.array(slip, dtype=wp.int32, device=dev), radius=GHOST_RADIUS * model.spacing,
                      reach=float(model.support_radius), rows=int(rows))


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    sm = smoothing.funcs(scalar)

    @wp.func
    def mirror_point(x: vec3, offset: scalar) -> vec3:
        """``x`` mirrored across the wall plane ``y = offset``."""
        return vec3(x[0], scalar(2.0) * offset - x[1], x[2])

    @wp.func
    def ghost_map(u: vec3, slip: int) -> vec3:
        """How a ghost moves against the material's motion ``u`` at its mirror point: ``-u``
        (no slip: the motion vanishes on the plane), or on a slip floor ``R u``, the mirror of
        ``u`` (its normal part vanishes on the plane, its tangential part slides)."""
        out = -u
        if slip != 0:
            out = vec3(u[0], -u[1], u[2])
        return out

    @wp.func
    def stencil_weight(x: vec3, p: vec3, rs: scalar) -> scalar:
        """Eq. 7's poly6 shape around the mirror point ``p``, 1 at ``p`` and 0 from ``rs`` on
        with its slope."""
        return sm.w_poly6_c(wp.length_sq(x - p), rs, scalar(1.0) / wp.pow(rs, scalar(6.0)))

    @wp.func
    def stencil_normaliser(total: scalar) -> scalar:
        """``max(total, MIN_TOTAL)`` made C1: a quadratic over ``MIN_TOTAL +- SWITCH``."""
        m = scalar(MIN_TOTAL)
        d = scalar(SWITCH)
        out = total
        if total <= m - d:
            out = m
        elif total < m + d:
            e = total - m + d
            out = m + e * e / (scalar(4.0) * d)
        return out

    @wp.func
    def stencil_fill(total: scalar) -> scalar:
        """The part of a constant motion a ghost of stencil weight ``total`` does not follow,
        ``1 - total / N``: 0 on a full stencil, C1 through the switch, 1 on an empty one."""
        return scalar(1.0) - total / stencil_normaliser(total)

    @wp.func
    def stencil_total(t: int, x: wp.array(dtype=vec3), p: vec3, rs: scalar, cj: wp.array2d(dtype=wp.int32),
                      count: int) -> scalar:
        """The raw sum of the stencil's weights (a func of its own, so the caller's
        non-linear use of it is differentiated right: docs/method.md, Warp pitfall 1)."""
        total = scalar(0.0)
        for c in range(count):
            total += stencil_weight(x[cj[t, c]], p, rs)
        return total

    @wp.func
    def ghost_displacement(t: int, x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                           y_lo: wp.array(dtype=vec3), cj: wp.array2d(dtype=wp.int32), gw: wp.array2d(dtype=scalar),
                           gf: wp.array2d(dtype=scalar), count: int, slip: int) -> vec3:
        """``ghost_map(sum_j s_kj u_j) + P sum_j f_kj u_j``: the continuation of the
        material's displacement (``f_kj`` 0 off a slip floor)."""
        u = vec3()
        uf = vec3()
        for c in range(count):
            j = cj[t, c]
            d = (y[j] - x[j]) + (y_lo[j] - x_lo[j])
            u += gw[t, c] * d
            uf += gf[t, c] * d
        return ghost_map(u, slip) + vec3(uf[0], scalar(0.0), uf[2])

    return types.SimpleNamespace(mirror_point=mirror_point, ghost_map=ghost_map, stencil_weight=stencil_weight,
                                 stencil_normaliser=stencil_normaliser, stencil_fill=stencil_fill, stencil_total=stencil_total,
                                 ghost_displacement=ghost_displacement)


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    fn = funcs(scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def grid_points(x: wp.array(dtype=vec3), out: wp.array(dtype=wp.vec3f)):
        i = wp.tid()
        p = x[i]
        out[i] = wp.vec3f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))

    @wp.func
    def collect(grid: wp.uint64, x: wp.array(dtype=vec3), slot: wp.array(dtype=wp.int32), body: wp.array(dtype=wp.int32),
                k: int, t: int, p: vec3, r: scalar, rs: scalar, cj: wp.array2d(dtype=wp.int32)):
        """The free particles of ``k``'s body within ``r`` of ``p`` into row ``t``, the first
        as many as it holds, in the grid's order: how many it holds, how many there are and the
        raw sum of the stencil weights (``rs``) of those within ``rs``."""
        pf = wp.vec3f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))
        q = wp.hash_grid_query(grid, pf, neighbors.padded_query_radius(pf, wp.float32(r)))
        rows = cj.shape[1]
        j = int(0)
        c = int(0)
        n = int(0)
        total = scalar(0.0)
        while wp.hash_grid_query_next(q, j):
            if slot[j] < 0 and body[j] == body[k]:
                d2 = wp.length_sq(x[j] - p)
                if d2 < r * r:
                    n += 1
                    if d2 < rs * rs:
                        total += fn.stencil_weight(x[j], p, rs)
                    if c < rows:
                        cj[t, c] = j
                        c += 1
        return c, n, total

    @wp.func
    def keep_within(t: int, x: wp.array(dtype=vec3), p: vec3, r: scalar, cj: wp.array2d(dtype=wp.int32), count: int) -> int:
        """Row ``t``'s first ``count`` candidates compacted in place to those within ``r`` of
        ``p``, in their order; returns how many."""
        c = int(0)
        for i in range(count):
            j = cj[t, i]
            if wp.length_sq(x[j] - p) < r * r:
                cj[t, c] = j
                c += 1
        return c

    @wp.kernel(enable_backward=False, module="unique")
    def stencil_candidates(
        grid: wp.uint64,
        x: wp.array(dtype=vec3),
        floor: wp.array(dtype=wp.int32),
        offset: wp.array(dtype=scalar),
        slot: wp.array(dtype=wp.int32),
        body: wp.array(dtype=wp.int32),
        slip: wp.array(dtype=wp.int32),
        rs: scalar,
        reach: scalar,
        cj: wp.array2d(dtype=wp.int32),
        cc: wp.array(dtype=wp.int32),
        counters: wp.array(dtype=wp.int32),
        cut_index: int,
    ):
        """The free particles of floor particle ``floor[t]``'s body within ``rs`` of its mirror
        point, or within ``reach`` for a slip ghost whose stencil is not full (``stencil_fill``)
        (integers: the tape never sees the grid; docs/method.md, Warp pitfall 3). One query: a
        slip ghost collects within ``reach`` (> ``rs``: the support radius is at least 1.5
        spacings), summing the stencil's weight as it goes, and keeps those within ``rs`` where
        the stencil is full. A grid query visits the cells it shares with a narrower one in the
        same order, so the rows and the sum are a query's at ``rs`` to the bit. Only where the
        ``reach`` set overflows a full stencil's row (not seen: the rows are a neighbour row
        wide) is its own searched again, so a row is cut, and counted, where its own set
        does not fit, as before."""
        t = wp.tid()
        k = floor[t]
        p = fn.mirror_point(x[k], offset[t])
        r = rs
        if slip[t] != 0:
            r = reach
        c, n, total = collect(grid, x, slot, body, k, t, p, r, rs, cj)
        filled = fn.stencil_fill(total) > scalar(0.0)
        if slip[t] != 0 and not filled:
            if n <= cj.shape[1]:
                c = keep_within(t, x, p, rs, cj, c)
            else:
                c, n, total = collect(grid, x, slot, body, k, t, p, rs, rs, cj)
        cc[t] = c
        if n > cj.shape[1]:
            wp.atomic_add(counters, cut_index, 1)

    @wp.kernel(module="unique")
    def stencil_weights(
        x: wp.array(dtype=vec3),
        floor: wp.array(dtype=wp.int32),
        offset: wp.array(dtype=scalar),
        slip: wp.array(dtype=wp.int32),
        rs: scalar,
        reach: scalar,
        cj: wp.array2d(dtype=wp.int32),
        cc: wp.array(dtype=wp.int32),
        gw: wp.array2d(dtype=scalar),
        gf: wp.array2d(dtype=scalar),
    ):
        """``s_kj`` and a slip ghost's ``f_kj`` (module docstring)."""
        t = wp.tid()
        p = fn.mirror_point(x[floor[t]], offset[t])
        n = cc[t]
        total = fn.stencil_total(t, x, p, rs, cj, n)
        inv = scalar(1.0) / fn.stencil_normaliser(total)
        fill = scalar(0.0)
        if slip[t] != 0:
            wide = fn.stencil_total(t, x, p, reach, cj, n)
            if wide > scalar(0.0):
                fill = fn.stencil_fill(total) / wide
        for c in range(n):
            xj = x[cj[t, c]]
            gw[t, c] = fn.stencil_weight(xj, p, rs) * inv
            gf[t, c] = fn.stencil_weight(xj, p, reach) * fill

    @wp.kernel(module="unique")
    def fit_positions(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        slot: wp.array(dtype=wp.int32),
        slip: wp.array(dtype=wp.int32),
        cj: wp.array2d(dtype=wp.int32),
        cc: wp.array(dtype=wp.int32),
        gw: wp.array2d(dtype=scalar),
        gf: wp.array2d(dtype=scalar),
        y_fit: wp.array(dtype=vec3),
        y_fit_lo: wp.array(dtype=vec3),
    ):
        """The end positions the fit reads: the particles' own, the ghosts' ``y_k``."""
        i = wp.tid()
        t = slot[i]
        if t < 0:
            y_fit[i] = y[i]
            y_fit_lo[i] = y_lo[i]
        else:
            y_fit[i] = x[i] + fn.ghost_displacement(t, x, y, x_lo, y_lo, cj, gw, gf, cc[t], slip[t])
            y_fit_lo[i] = x_lo[i]

    @wp.kernel(module="unique")
    def copy_floor_forces(f: wp.array(dtype=vec3), floor: wp.array(dtype=wp.int32), gf: wp.array(dtype=vec3)):
        # A copy, so the hand-over's adjoint does not read forces the pressure adds later.
        t = wp.tid()
        gf[t] = f[floor[t]]

    @wp.kernel(module="unique")
    def hand_over(
        gf: wp.array(dtype=vec3),
        floor: wp.array(dtype=wp.int32),
        slip: wp.array(dtype=wp.int32),
        cj: wp.array2d(dtype=wp.int32),
        cc: wp.array(dtype=wp.int32),
        gw: wp.array2d(dtype=scalar),
        fw: wp.array2d(dtype=scalar),
        f: wp.array(dtype=vec3),
    ):
        """``f_j += s_kj M f_k + f_kj P f_k`` and the opposite on ``k``: equal and opposite."""
        t = wp.tid()
        fk = gf[t]
        mf = fn.ghost_map(fk, slip[t])
        pf = vec3(fk[0], scalar(0.0), fk[2])
        kept = vec3()
        for c in range(cc[t]):
            g = gw[t, c] * mf + fw[t, c] * pf
            wp.atomic_add(f, cj[t, c], g)
            kept -= g
        wp.atomic_add(f, floor[t], kept)

    return types.SimpleNamespace(grid_points=grid_points, stencil_candidates=stencil_candidates,
                                 stencil_weights=stencil_weights, fit_positions=fit_positions,
                                 copy_floor_forces=copy_floor_forces, hand_over=hand_over)


class StencilSearch:
    """The hash grid of the ghosts' stencils (one per solver, kept alive while a tape may
    replay the step: docs/method.md, Warp pitfall 3)."""

    def __init__(self, model):
        self.model = model
        self.points = wp.zeros(model.particle_count, dtype=wp.vec3f, device=model.device)
        self.grid = None

    def update(self, state_in, state_out, counters, cut_index: int):
        m, g = self.model, self.model.ghost_floor
        k = kernels(m.scalar)
        if self.grid is None:
            x0 = m.particle_x0
            cell = max(g.radius, g.reach) if g.rows > STENCIL else g.radius
            dims = [int(min(128, max(1, np.ceil((x0[:, a].max() - x0[:, a].min()) / cell) + 8))) for a in range(3)]
            self.grid = wp.HashGrid(*dims, device=m.device)
        m.launches(k.grid_points, m.particle_count, [state_in.x], [self.points], device=m.device, record_tape=False)
        self.grid.build(self.points, max(g.radius, g.reach) if g.rows > STENCIL else g.radius)
        m.launches(k.stencil_candidates, g.count,
                   [self.grid.id, state_in.x, g.floor, g.offset, g.slot, m.particle_body, g.slip, m.scalar(g.radius),
                    m.scalar(g.reach)],
                   [state_out.ghost_rows, state_out.ghost_count, counters, cut_index], device=m.device, record_tape=False)
        m.launches(k.stencil_weights, g.count,
                   [state_in.x, g.floor, g.offset, g.slip, m.scalar(g.radius), m.scalar(g.reach), state_out.ghost_rows,
                    state_out.ghost_count],
                   [state_out.ghost_weights, state_out.ghost_fill], device=m.device)


def launch_hand_over(model, state_out):
    """The elastic forces on the ghosts handed to their stencils (after the elastic forces,
    before anything else adds to ``state_out.force``)."""
    g, k = model.ghost_floor, kernels(model.scalar)
    model.launches(k.copy_floor_forces, g.count, [state_out.force, g.floor], [state_out.ghost_force], device=model.device)
    model.launches(k.hand_over, g.count, [state_out.ghost_force, g.floor, g.slip, state_out.ghost_rows,
                                          state_out.ghost_count, state_out.ghost_weights, state_out.ghost_fill], [state_out.force],
                   device=model.device)


def launch_fit_positions(model, state_in, state_out):
    """``State.ghost_y``: what the deformation update fits to (after the integration)."""
    g, k = model.ghost_floor, kernels(model.scalar)
    model.launches(k.fit_positions, model.particle_count,
                   [state_in.x, state_out.x, state_in.x_lo, state_out.x_lo, g.slot, g.slip, state_out.ghost_rows,
                    state_out.ghost_count, state_out.ghost_weights, state_out.ghost_fill], [state_out.ghost_y, state_out.ghost_y_lo],
                   device=model.device)


def allocate_state(model, state, requires_grad: bool):
    """A state's ghost arrays (written by the step that produces it); None without a ghost floor."""
    g = model.ghost_floor
    if g is None:
        state.ghost_y = state.ghost_y_lo = state.ghost_weights = state.ghost_rows = state.ghost_count = None
        state.ghost_fill = state.ghost_force = None
        return
    T, dev, n, nf = model.types, model.device, model.particle_count, g.count
    state.ghost_y = wp.zeros(n, dtype=T.vec3, device=dev, requires_grad=requires_grad)
    state.ghost_y_lo = wp.zeros(n, dtype=T.vec3, device=dev)
    state.ghost_weights = wp.zeros((nf, g.rows), dtype=T.scalar, device=dev, requires_grad=requires_grad)
    state.ghost_fill = wp.zeros((nf, g.rows), dtype=T.scalar, device=dev, requires_grad=requires_grad)
    state.ghost_rows = wp.zeros((nf, g.rows), dtype=wp.int32, device=dev)
    state.ghost_count = wp.zeros(nf, dtype=wp.int32, device=dev)
    state.ghost_force = wp.zeros(nf, dtype=T.vec3, device=dev, requires_grad=requires_grad)
