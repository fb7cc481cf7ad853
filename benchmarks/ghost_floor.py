"""An experiment outside the solver: a no-slip particle floor made of odd ghosts.

    python -m benchmarks.ghost_floor slump --S 0.2 --res 8 --duration 5
    python -m benchmarks.ghost_floor incline --load 1.3
    python -m benchmarks.ghost_floor slump --S 0.2 --res 8 --duration 5 --ghost-energy   # the variant that doubles the wall

It answers one question of docs/physics.md ("The floor's plasticity"): what does a floor do
that makes the material's velocity vanish on a plane between the floor and the material,
without holding a layer of material as the elastic floor does? It is not part of
``warp_esph``: it swaps two of the solver's stage launchers while a ``with ghost_floor():``
block runs, forward only (no tape), with the non-fused kernels.

**Method.** The pinned floor particles of ``SceneBuilder.add_particle_floor`` stay where they
are for the neighbour search and the SPH pressure. In the incremental fit (eqs. 5-6) each
floor particle ``k`` takes the displacement ``-u(p_k)``: minus the Shepard average
(``sum_j s_kj u_j``, poly6 weights of radius ``rs`` spacings) of the free particles'
displacements at its mirror point ``p_k`` across the plane halfway between the floor's top
layer and the body's lowest layer. The weights are divided by their sum or by ``min_total``
(half the weight of a particle at the mirror point), whichever is larger: where a spreading
front reaches a floor particle its ghost then switches on with the front's weight, not at
once (a lone particle's weight normalised to 1 gave the S = 0.3 pile a late rearrangement). So the fits near the floor see the odd
continuation of the material's motion, which vanishes on that plane: an affine motion that
is zero on the plane is reproduced exactly by every fit next to the floor
(``tests/test_validation_suite.py``), where the plain particle floor's static particles leave
the first layer's fitted shear at 0.75 of it. Float32 models only (Warp's hash grid). The floor particles are then a kinematic extension of
the material, not material: their stress is set to zero before the elastic forces, so only
the free particles' energies act, each of them also through its ghosts. Since
``y_k = x_k - sum_j s_kj (y_j - x_j)``, the force that those energies put on a floor particle
is handed to the free particles of its stencil, ``f_j -= s_kj f_k``. ``ghost_energy=True``
keeps the floor particles' own stress as well (it counts the mirrored material twice: the
wall then carries twice the first layer's stress).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json

import numpy as np

#: Ghost stencil rows per floor particle.
STENCIL = 16


@functools.lru_cache(maxsize=None)
def _kernels():
    import warp as wp

    stencil_rows = wp.constant(STENCIL)

    @wp.kernel
    def stencil(x: wp.array(dtype=wp.vec3), grid: wp.uint64, floor_idx: wp.array(dtype=wp.int32), n_free: int,
                plane: float, rs: float, min_total: float, gj: wp.array2d(dtype=wp.int32), gw: wp.array2d(dtype=float),
                gc: wp.array(dtype=wp.int32)):
        # The normalised poly6 weights of the free particles around floor particle k's mirror point.
        t = wp.tid()
        xk = x[floor_idx[t]]
        p = wp.vec3(xk[0], 2.0 * plane - xk[1], xk[2])
        q = wp.hash_grid_query(grid, p, rs)
        j = int(0)
        c = int(0)
        total = float(0.0)
        while wp.hash_grid_query_next(q, j):
            if j < n_free and c < stencil_rows:
                d2 = wp.length_sq(x[j] - p)
                if d2 < rs * rs:
                    a = 1.0 - d2 / (rs * rs)
                    gj[t, c] = j
                    gw[t, c] = a * a * a
                    total += a * a * a
                    c += 1
        # Normalised (Shepard) where the stencil holds at least min_total of weight; below it
        # (at a spreading front) the ghost follows its few particles only in part.
        total = wp.max(total, min_total)
        for m in range(c):
            gw[t, m] = gw[t, m] / total
        gc[t] = c

    @wp.kernel
    def set_ghosts(x_in: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3), floor_idx: wp.array(dtype=wp.int32),
                   gj: wp.array2d(dtype=wp.int32), gw: wp.array2d(dtype=float), gc: wp.array(dtype=wp.int32)):
        t = wp.tid()
        u = wp.vec3()
        for m in range(gc[t]):
            j = gj[t, m]
            u += gw[t, m] * (y[j] - x_in[j])
        k = floor_idx[t]
        y[k] = x_in[k] - u

    @wp.kernel
    def restore(x_in: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3), floor_idx: wp.array(dtype=wp.int32)):
        k = floor_idx[wp.tid()]
        y[k] = x_in[k]

    @wp.kernel
    def zero_stress(stress: wp.array(dtype=wp.mat33), floor_idx: wp.array(dtype=wp.int32)):
        stress[floor_idx[wp.tid()]] = wp.mat33()

    @wp.kernel
    def transfer(f: wp.array(dtype=wp.vec3), floor_idx: wp.array(dtype=wp.int32), gj: wp.array2d(dtype=wp.int32),
                 gw: wp.array2d(dtype=float), gc: wp.array(dtype=wp.int32)):
        t = wp.tid()
        fk = f[floor_idx[t]]
        for m in range(gc[t]):
            wp.atomic_add(f, gj[t, m], -gw[t, m] * fk)

    return stencil, set_ghosts, restore, zero_stress, transfer


class _Ghosts:
    """Per model: the floor (particles whose rest height is below ``below``; the free ones
    must come first, as ``add_particle_floor`` appends the floor), the mirror plane and the
    stencil arrays."""

    def __init__(self, model, rs: float, below: float, min_total: float):
        import warp as wp

        if model.scalar is not wp.float32:
            raise ValueError(f"ghost_floor needs a float32 model, not {model.scalar.__name__}: its stencil uses Warp's hash grid")
        x0 = model.particle_x0.astype(np.float64)
        free = x0[:, 1] > below
        n_free = int(free.sum())
        if n_free == 0 or n_free == len(x0) or not free[:n_free].all():
            raise ValueError("ghost_floor needs the free particles first and a particle floor below y = %g" % below)
        top, low = x0[~free, 1].max(), x0[free, 1].min()
        self.plane = 0.5 * (top + low)
        self.rs = rs * model.spacing
        self.min_total = min_total
        self.n_free = n_free
        self.floor = wp.array(np.arange(n_free, len(x0), dtype=np.int32), dtype=wp.int32, device=model.device)
        nf = len(x0) - n_free
        self.nf = nf
        self.gj = wp.zeros((nf, STENCIL), dtype=wp.int32, device=model.device)
        self.gw = wp.zeros((nf, STENCIL), dtype=float, device=model.device)
        self.gc = wp.zeros(nf, dtype=wp.int32, device=model.device)
        self.grid = wp.HashGrid(64, 64, 64, device=model.device)

    def weights(self, x):
        import warp as wp

        stencil = _kernels()[0]
        self.grid.build(x, self.rs)
        self.gc.zero_()
        wp.launch(stencil, self.nf, [x, self.grid.id, self.floor, self.n_free, float(self.plane), float(self.rs),
                                     float(self.min_total), self.gj, self.gw, self.gc], device=x.device)


@contextlib.contextmanager
def ghost_floor(rs: float = 1.2, ghost_energy: bool = False, below: float = 0.0, min_total: float = 0.5):
    """While it runs, every ``Solver`` built runs the non-fused kernels and every model's
    particle floor (the particles whose rest height is below ``below``) acts as odd ghosts
    (module docstring). ``rs``: the ghosts' stencil radius in spacings; ``min_total``: the
    least stencil weight that is normalised to 1 (0: every non-empty stencil, a partner
    with the weight of one at its mirror point is 1)."""
    import warp as wp

    import warp_esph as we
    from warp_esph.sim import deformation, forces

    _, set_ghosts, restore, zero_stress, transfer = _kernels()
    per_model = {}
    orig_init, orig_forces, orig_def = we.Solver.__init__, forces.launch_elastic_forces, deformation.launch_update_deformation

    def ghosts(model):
        if id(model) not in per_model:
            per_model[id(model)] = (model, _Ghosts(model, rs, below, min_total))
        return per_model[id(model)][1]

    def init(self, model, *args, **kw):
        kw["fused"] = False
        orig_init(self, model, *args, **kw)

    def elastic_forces(model, state_in, state_out, hand_adjoint=True):
        if deformation.recording_tape() is not None:
            raise RuntimeError("ghost_floor is forward only: no wp.Tape")
        g = ghosts(model)
        if not ghost_energy:
            wp.launch(zero_stress, g.nf, [state_out.stress, g.floor], device=model.device)
        orig_forces(model, state_in, state_out, hand_adjoint)
        g.weights(state_in.x)
        wp.launch(transfer, g.nf, [state_out.force, g.floor, g.gj, g.gw, g.gc], device=model.device)

    def update_deformation(model, state_in, state_out, counters, hand_adjoint=True):
        g = ghosts(model)
        wp.launch(set_ghosts, g.nf, [state_in.x, state_out.x, g.floor, g.gj, g.gw, g.gc], device=model.device)
        orig_def(model, state_in, state_out, counters, hand_adjoint)
        wp.launch(restore, g.nf, [state_in.x, state_out.x, g.floor], device=model.device)

    we.Solver.__init__, forces.launch_elastic_forces, deformation.launch_update_deformation = init, elastic_forces, update_deformation
    try:
        yield per_model
    finally:
        we.Solver.__init__, forces.launch_elastic_forces, deformation.launch_update_deformation = orig_init, orig_forces, orig_def


SLUMP_KEYS = ("S", "resolution", "thickness_over_H0", "h_over_H0", "theory_h_over_H0", "at_rest", "radius_over_R0",
              "kinetic_last_quarter_over_MgH0", "thickness_rate_pct_H0_per_s", "top_rate_pct_H0_per_s", "wall_s")
INCLINE_KEYS = ("load", "layers", "top_speed", "top_speed_two_thirds", "bingham_surface_speed", "top_height_ratio", "wall_s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case", choices=("slump", "incline"))
    ap.add_argument("--S", type=float, default=0.2)
    ap.add_argument("--res", type=int, default=8)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--load", type=float, default=1.3)
    ap.add_argument("--layers", type=int, default=3)
    ap.add_argument("--rs", type=float, default=1.2, help="the ghosts' stencil radius, in spacings")
    ap.add_argument("--ghost-energy", action="store_true", help="keep the floor particles' own stress too")
    ap.add_argument("--min-total", type=float, default=0.5, help="the least stencil weight normalised to 1")
    args = ap.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from . import validation as V

    with ghost_floor(rs=args.rs, ghost_energy=args.ghost_energy, min_total=args.min_total):
        if args.case == "slump":
            r = V.slump(args.S, args.res, duration=args.duration or 5.0)
            out = {k: r[k] for k in SLUMP_KEYS}
            out["thickness_vs_1d_pct"] = 100.0 * (r["thickness_over_H0"] / r["theory_h_over_H0"] - 1.0)
            # Every 20th sample (of 200): time, centre thickness / H0, kinetic energy / (M g H0).
            t, th, ke = r["height_history"], r["thickness_history"], r["ke_history"]  # "height_history" holds the times
            out["history"] = [[round(t[i], 3), round(th[i], 5), float("%.2e" % ke[i])] for i in range(0, len(t), 20)]
        else:
            r = V.incline(layers=args.layers, load=args.load, floor="particles", duration=args.duration or 0.6,
                          walls="centres")
            out = {k: r[k] for k in INCLINE_KEYS}
    out.update(case=args.case, floor="ghost", rs=args.rs, ghost_energy=args.ghost_energy, min_total=args.min_total)
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
