"""The near-yield column and the slump with the isotropic pressure force
(``Material.pressure_force = "isotropic"``, ``warp_esph.sim.pressure.launch_isotropic_pressure_forces``;
docs/physics.md, "Still open", the SPH pressure bullet), against the same case with the default
pair force: every ``Solver`` made inside ``isotropic_pressure()`` runs unfused, its model's
materials made ``isotropic`` (``energy_spiky``'s pressure and ``k_p``: the experimental
``Solver._isotropic_pressure`` flag's step on the default force, bit for bit).

    python -m benchmarks.isotropic_pressure column --resolution 4 --periods 60
    python -m benchmarks.isotropic_pressure slump --S 0.2 --resolution 8 --duration 8
    (--baseline: the same run with the default pair force, unfused)
"""

import argparse
import contextlib
import json
import time

#: What a run prints of ``near_yield_column``'s and ``slump``'s rows.
COLUMN_KEYS = ("plastic_over_theory", "elastic_measured", "nearest_neighbour_min", "residual_rate_pct_per_s",
               "kinetic_over_weight", "highest_yielded_depth", "lean")


@contextlib.contextmanager
def isotropic_pressure(on: bool = True):
    """Every ``warp_esph.Solver`` made in the block runs unfused (the isotropic force's path)
    and, with ``on``, on a model whose every material is ``pressure_force = "isotropic"``
    (``Model.set_materials``, each keeping its ``k_p``); ``on=False`` is the baseline on the same
    path."""
    import warp_esph as we

    init = we.Solver.__init__

    def patched(self, model, *args, **kwargs):
        kwargs["fused"] = False
        if on and any(mat.pressure_force != "isotropic" for mat in model.materials):
            # Together: every material is isotropic or none (one at a time was refused).
            model.set_materials([mat.replace(pressure_force="isotropic", pressure_stiffness=mat.pressure_stiffness)
                                 for mat in model.materials])
        init(self, model, *args, **kwargs)

    we.Solver.__init__ = patched
    try:
        yield
    finally:
        we.Solver.__init__ = init


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=("column", "slump"))
    ap.add_argument("--resolution", type=int, default=4)
    ap.add_argument("--periods", type=float, default=60.0)
    ap.add_argument("--S", type=float, default=0.2)
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--baseline", action="store_true")
    a = ap.parse_args(argv)
    from benchmarks import validation

    t = time.time()
    with isotropic_pressure(not a.baseline):
        if a.case == "column":
            row = validation.near_yield_column(resolution=a.resolution, width=0.04, floor="slip_ghost_particles",
                                               periods=a.periods)
        else:
            row = validation.slump(a.S, resolution=a.resolution, duration=a.duration)
    out = {k: v for k, v in row.items() if not isinstance(v, list)}
    out["isotropic_pressure"] = not a.baseline
    out["wall_s"] = time.time() - t
    print(json.dumps(out, default=str, indent=0))


if __name__ == "__main__":
    main()
