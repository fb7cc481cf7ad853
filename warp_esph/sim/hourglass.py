"""Control of the zero-energy (hourglass) modes of the affine fit (``Solver(hourglass=c)``;
on by default, at ``model.AUTO_HOURGLASS``, where ``fit="auto"`` chose the curvature-corrected
fit; docs/physics.md, "Hourglass modes"). Not in the paper.

The fit of eqs. 5-6 sees a neighbourhood only through its weighted moments: on a regular
lattice a displacement that alternates from one particle layer to the next (``(-1)^j``)
leaves every interior particle's ``B`` unchanged, so it costs no elastic energy. A
concentrated load (a sphere pressed into a block) drives such a pattern: the particle
layers under the load slide between their neighbours and the load-bearing column gives
way. The control penalises the part of each neighbour's offset that no affine map of the
rest neighbourhood explains,

    E_i = c mu_i V_i / (2 S_i) min_G sum_j w_ij |x_ij - G X_ij|^2,  S_i = sum_j w_ij |X_ij|^2

(``X``: rest positions, ``w_ij`` the poly6 weight of the rest distance, same-body neighbours
of the current list). The minimiser is ``G_i = B_i A_i^-1``, ``A_i = sum_j w_ij X_ij X_ij^T``,
``B_i = sum_j w_ij x_ij X_ij^T``, and since ``dE_i/dG_i = 0`` there, the force is the
derivative at fixed ``G_i``: ``f_j -= g_ij``, ``f_i += g_ij``, ``g_ij = c mu_i V_i w_ij
(x_ij - G_i X_ij) / S_i``, equal and opposite. An affine motion has a zero residual: no
force. The kernel forms the residual of the displacements ``u = x - X``, ``u_ij - (G_i - I)
X_ij`` with ``G_i - I = (sum_j w_ij u_ij X_ij^T) A_i^-1``, the same in exact arithmetic, so a
body at rest has none to the bit. ``E = sum_i E_i`` is a function of the positions alone (for a fixed neighbour list),
so the control is conservative and its stiffness symmetric. (Its first form used the stored
``F_i`` in place of ``G_i``: with the linear fit, whose ``F`` is nearly that minimiser, the
same; with the curvature-corrected fit, whose ``F`` is not, a non-symmetric stiffness, and an
undamped breathing cube gained 25 % kinetic energy in 1.5 s, measured.) Where ``A_i`` is
singular (a sheet or a line of neighbours: ``det A_i`` below ``MIN_DET (tr A_i / 3)^3``) the
particle has no control. It is measured against the rest positions, so it is for elastic
solids: after plastic flow the rest neighbourhood is no longer the material's and the control
would pull the body back towards its rest shape.

Stable step (``stable_dt``, in ``Model.stable_dt(hourglass=c)``). The energy at the minimising
``G_i`` is at most its value at any fixed map, so the stiffness is bounded by that of the
control at fixed ``G_i``, a set of zero-length springs: ``g_ij`` is linear in ``x_j - x_i`` with the
isotropic stiffness ``k_ij = c mu_i V_i w_ij / S_i``, and ``j`` pulls back on ``i`` with
``k_ji``. Its stiffness matrix is the graph Laplacian of the weights ``k_ij + k_ji`` (times
the 3 x 3 identity), whose largest eigenvalue (Gershgorin) is at most twice the largest
diagonal entry, ``2 sum_j (k_ij + k_ji)``. On a regular lattice every particle has the same
``W / S`` (``W_i = sum_j w_ij``), so with ``V / m = 1 / rho``

    omega^2 <= 4 c (mu / rho) W / S,

and the symplectic Euler step of such a spring system is stable for ``dt omega <= 2``:
``dt <= sqrt(rho S / (c mu W))``. The lattice's highest hourglass mode, the checkerboard
``(-1)^(i+j+k)``, is at 0.8 of that bound (its same-parity neighbours, the edge diagonals,
do not move relative to it), so the bound keeps a factor 1.25.
"""

import functools
import math
import types

import numpy as np
import warp as wp

from .._types import type_set
from . import guards, materials, smoothing

#: ``residual_map``'s least ``det A_i / (tr A_i / 3)^3`` (1 for a symmetric neighbourhood; on a
#: 6^3 lattice cube at least 0.88 / 0.79 / 0.72 at h = 2 / 2.5 / 3 dx, its corners; 0 for a sheet).
MIN_DET = 1.0e-4


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    sm = smoothing.funcs(scalar)
    gf = guards.guard_funcs(scalar)
    Materials = materials.struct(scalar)

    @wp.func
    def rest_fit_sums(i: int, x: wp.array(dtype=vec3), rest: wp.array(dtype=vec3), body: wp.array(dtype=wp.int32),
                      nbr: wp.array2d(dtype=wp.int32), n: int, h: scalar, c6: scalar):
        """``S_i = sum_j w_ij |X_ij|^2`` and the moments ``A_i = sum_j w_ij X_ij X_ij^T``,
        ``B_i = sum_j w_ij u_ij X_ij^T`` of the best affine map of the displacements ``u = x -
        X`` over the same-body neighbours (poly6 weights of the rest distances). Only the raw
        sums live in this loop: the caller's inverse must not see a loop accumulator
        (docs/method.md, Warp pitfall 1)."""
        s = scalar(0.0)
        A = mat33()
        B = mat33()
        ui = x[i] - rest[i]
        Xi = rest[i]
        for k in range(n):
            j = nbr[i, k]
            if body[j] == body[i]:
                d = rest[j] - Xi
                r2 = wp.dot(d, d)
                w = sm.w_poly6_c(r2, h, c6)
                s += w * r2
                A += w * wp.outer(d, d)
                B += w * wp.outer((x[j] - rest[j]) - ui, d)
        return s, A, B

    @wp.func
    def residual_map(s: scalar, A: mat33, B: mat33):
        """The affine map ``G_i = B_i A_i^-1`` that minimises ``E_i`` (module doc; of the
        displacements, with ``rest_fit_sums``' ``B_i``: ``I + G_i`` the positions'), and whether
        it is defined: ``det A_i`` above ``MIN_DET`` of ``(tr A_i / 3)^3``
        (``guards.isotropic_conditioning``; a sheet or a line of neighbours samples a direction
        with zero weight; there the particle has no control)."""
        ok = s > scalar(0.0)
        G = mat33()
        if ok:
            ok = gf.isotropic_conditioning(A) > scalar(MIN_DET)
            if ok:
                G = B * wp.inverse(A)
        return G, ok

    @wp.func
    def hourglass_pair_force(coef: scalar, G: mat33, ub: vec3, Xb: vec3, h: scalar, c6: scalar):
        """``g_ij = coef w(|X_ij|) (u_ij - G_i X_ij)``, ``coef = c mu_i V_i / S_i``, ``u`` the
        displacement and ``G_i`` its map (``x_ij - (I + G_i) X_ij``): minus the gradient of
        ``E_i`` with respect to ``x_j`` (at the minimising ``G_i``, where the derivative through
        ``G_i`` vanishes)."""
        return coef * sm.w_poly6_c(wp.dot(Xb, Xb), h, c6) * (ub - G * Xb)

    @wp.kernel(module="unique")
    def hourglass_forces(
        x: wp.array(dtype=vec3),
        rest: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        volume: wp.array(dtype=scalar),
        h: scalar,
        c: scalar,
        f: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        n = count[i]
        c6 = sm.poly6_coef(h)
        s, A, B = rest_fit_sums(i, x, rest, body, nbr, n, h, c6)
        G, ok = residual_map(s, A, B)
        if ok:
            coef = c * mat.mu[material[i]] * volume[i] / s
            # Displacements, not positions: x_j - x_i and B A^-1 = I + round-off left a force of
            # 1.2e-5 m/s^2 on a float32 body at rest (docs/physics.md, "The held cantilever's
            # float32 late growth").
            ui = x[i] - rest[i]
            Xi = rest[i]
            for k in range(n):
                j = nbr[i, k]
                if body[j] == body[i]:
                    g = hourglass_pair_force(coef, G, (x[j] - rest[j]) - ui, rest[j] - Xi, h, c6)
                    wp.atomic_sub(f, j, g)
                    wp.atomic_add(f, i, g)

    return types.SimpleNamespace(hourglass_forces=hourglass_forces, hourglass_pair_force=hourglass_pair_force)


def launch_hourglass_forces(model, state_in, state_out, rest, c: float):
    """Add the control's forces (module doc) into ``state_out.force``; ``rest``: the rest
    positions as a device array."""
    S = model.scalar
    model.launches(
        kernels(S).hourglass_forces, model.particle_count,
        [state_in.x, rest, model.particle_body, model.particle_material, model.material_arrays(), state_out.neighbors,
         state_out.neighbor_count, model.particle_volume, S(model.support_radius), S(c)],
        [state_out.force], device=model.device,
    )


@functools.cache
def lattice_weight_ratio(k: float) -> float:
    """``W / S`` of an interior particle of the cubic lattice (``S`` in units of the spacing
    squared) for a support radius of ``k`` spacings: ``sum_j w_ij / sum_j w_ij |X_ij|^2`` over
    the lattice offsets within ``k`` (poly6 weights; their constant cancels)."""
    n = int(math.ceil(k))
    r = np.arange(-n, n + 1, dtype=np.float64)
    r2 = (r[:, None, None] ** 2 + r[None, :, None] ** 2 + r[None, None, :] ** 2).ravel()
    r2 = r2[(r2 > 0.0) & (r2 < k * k)]
    w = (k * k - r2) ** 3
    return float(w.sum() / (w * r2).sum())


def stable_dt(c: float, mu_over_rho: float, spacing: float, support_radius: float) -> float:
    """The step limit ``2 / omega`` of the control alone at strength ``c`` (module doc):
    ``sqrt(rho S / (c mu W))`` with ``W / S`` of the lattice of ``spacing`` and
    ``support_radius``; ``inf`` where ``c mu = 0``."""
    stiffness = 4.0 * c * mu_over_rho * lattice_weight_ratio(support_radius / spacing) / spacing**2
    return 2.0 / math.sqrt(stiffness) if stiffness > 0.0 else math.inf
