"""The near-yield column and the slump with the isotropic pressure force
(``Material.pressure_force = "isotropic"``, ``warp_esph.sim.pressure.launch_isotropic_pressure_forces``;
docs/physics.md, "Still open", the SPH pressure bullet), against the same case with the default
pair force: every ``Solver`` made inside ``isotropic_pressure()`` runs unfused, its model's
materials made ``isotropic`` (``energy_spiky``'s pressure and ``k_p``, each material keeping its
own: the step of a model built ``isotropic``, bit for bit).

    python -m benchmarks.isotropic_pressure column --resolution 4 --periods 60
    python -m benchmarks.isotropic_pressure column --resolution 6 --periods 72 --every 12
    python -m benchmarks.isotropic_pressure slump --S 0.2 --resolution 8 --duration 8
    (--baseline: the same run with the default pair force, unfused; --fit-weight biweight: the
    incremental fit's weight, ``validation``'s ``fit_weight``, refused there by name if unknown)
    python -m benchmarks.isotropic_pressure slump --S 0.3 --resolution 12 --duration 8 --save iso_S0.3.npz
    (--save: the slump's final particles, for comparing the two piles' shapes afterwards)
"""

import argparse
import contextlib
import json
import time

#: What a run prints of ``near_yield_column``'s and ``slump``'s rows.
COLUMN_KEYS = ("plastic_over_theory", "elastic_measured", "nearest_neighbour_min", "residual_rate_pct_per_s",
               "kinetic_over_weight", "highest_yielded_depth", "lean")


@contextlib.contextmanager
def column_history(every: float, resolution: int, periods: float, out=print):
    """Inside the block, ``validation.near_yield_column``'s run reports its state every
    ``every`` axial periods (the row has only its end), so a run to rest shows how it gets
    there and a run cut short still leaves its state: ``out(dict)`` gets the period, the
    shortening between the top and bottom layers' centres (m), the top's rate over the last
    tenth of the interval (% of the 1-D theory per s, the row's ``residual_rate_pct_per_s``),
    the kinetic energy over the weight's scale, the closest neighbours (dx, every particle, as
    the row's ``nearest_neighbour_min``), the lean (dx) and the highest initial depth (over L)
    of a free particle that reached the yield stress so far (sampled every 10 steps, as the
    row's ``highest_yielded_depth``). The returned list collects them; its plastic part over the
    theory needs the elastic reference, run after the plastic run
    (``plastic_over_theory``)."""
    import math

    import numpy as np

    from benchmarks import validation as v

    rows, seen = [], {}
    free_column, swap_run = v._free_column, v._swap_run

    def capture(we, mat, n, aspect, dx, **kw):
        r = free_column(we, mat, n, aspect, dx, **kw)
        # The first column made is the plastic run's; the elastic reference comes after it.
        if "model" not in seen:
            seen.update(mat=mat, dx=dx, model=r[0], H=r[1], x0=r[2], top=r[3], bottom=r[4], free=r[5], L0=r[6])
        return r

    def run(model, solver, a, c, dt, steps, after=None):
        if model is not seen.get("model"):
            return swap_run(model, solver, a, c, dt, steps, after)
        mat, dx, H, top, bottom, free, L0 = (seen[k] for k in ("mat", "dx", "H", "top", "bottom", "free", "L0"))
        x0 = seen["x0"]
        depth = (x0[:, 1].max() + 0.5 * dx - x0[:, 1]) / H
        per = steps / periods  # steps per axial period, as near_yield_column counted them
        stride = max(1, int(round(every * per)))
        scale = v.RHO * v.G * H * (H - dx) / (2.0 * 1.5e5) + v.near_yield_column_theory(0.8) * (H - dx)
        weight = float(model.particle_mass.numpy().sum()) * v.G * scale
        peak = np.zeros(model.particle_count)
        hist = []

        def watch(state, k):
            if k % 10 == 0:
                np.maximum(peak, v._deviatoric_norm(state.F.numpy(), mat.mu) / mat.yield_stress, out=peak)
            # A report within a tenth of the interval of the end is left to the end's, and the
            # end samples its own last tenth: a run ending a step after a report printed that
            # state twice, the second with one sample and a NaN rate.
            near_end = steps - k < 0.1 * stride
            report = k == steps or (k % stride == 0 and not near_end)
            if k % stride > stride - 0.1 * stride or report or near_end:
                x = state.x.numpy().astype(np.float64)
                hist.append((k * dt, L0 - (x[top, 1].mean() - x[bottom, 1].mean())))
            if report:
                h = np.array(hist)
                d2 = solver.scratch.neighbor_d2.numpy().astype(np.float64)
                cnt = state.neighbor_count.numpy()
                d2 = np.where(np.arange(d2.shape[1])[None, :] < cnt[:, None], d2, np.inf)
                yielded = (peak >= 0.99) & free
                x = state.x.numpy().astype(np.float64)
                row = {"period": k / per, "shortening": h[-1, 1],
                       "rate_pct_per_s": 100.0 * np.polyfit(h[:, 0], h[:, 1], 1)[0] / scale if len(h) > 1 else math.nan,
                       "kinetic_over_weight": v._kinetic(model, state) / weight,
                       "nearest_dx": math.sqrt(d2.min()) / dx, "lean_dx": v._lean(x, top, bottom) / dx,
                       "highest_yielded_depth": float(depth[yielded].min()) if yielded.any() else math.nan}
                rows.append(row)
                out(row)
                hist.clear()
            return None if after is None else after(state, k)

        return swap_run(model, solver, a, c, dt, steps, watch)

    v._free_column, v._swap_run = capture, run
    try:
        yield rows
    finally:
        v._free_column, v._swap_run = free_column, swap_run


@contextlib.contextmanager
def final_slump_state(path: str):
    """Inside the block, ``validation.slump``'s run writes its final particles to the .npz
    ``path`` (the row keeps only summaries, and the two piles' shapes are compared afterwards,
    e.g. each particle's Voronoi volume against its det F): every particle's ``x0``, ``x``,
    ``F``, ``alpha`` and ``volume`` (rest), the mask ``free`` of the non-floor ones, and the
    scene's ``spacing``, ``mu`` and ``Y``. The run itself is left as it was."""
    import numpy as np

    from benchmarks import validation as v

    seen = {}
    slump_model, swap_run = v.slump_model, v._swap_run

    def capture(*args, **kw):
        r = slump_model(*args, **kw)
        seen.update(model=r[0], free=r[1], mu=r[2], Y=r[3])
        return r

    def run(model, solver, a, c, dt, steps, after=None):
        a, c = swap_run(model, solver, a, c, dt, steps, after)
        if model is seen.get("model"):
            np.savez_compressed(path, x0=model.particle_x0, x=a.x.numpy(), F=a.F.numpy(), alpha=a.alpha.numpy(),
                                volume=model.particle_volume.numpy(), free=seen["free"], spacing=model.spacing,
                                mu=seen["mu"], Y=seen["Y"])
        return a, c

    v.slump_model, v._swap_run = capture, run
    try:
        yield
    finally:
        v.slump_model, v._swap_run = slump_model, swap_run


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
    from benchmarks import _cli

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=("column", "slump"))
    ap.add_argument("--resolution", type=int, default=4)
    ap.add_argument("--periods", type=float, default=60.0)
    ap.add_argument("--S", type=float, default=0.2)
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--baseline", action="store_true")
    # Not argparse choices: validation refuses an unknown weight with the allowed ones named.
    ap.add_argument("--fit-weight", default="poly6", help="the incremental fit's weight (validation's fit_weight; default poly6, the weight "
                         "of the runs docs/physics.md records)")
    ap.add_argument("--every", type=float, default=0.0,
                    help="column: print its state every this many axial periods (0: the end only)")
    ap.add_argument("--save", type=lambda t: _cli.check_output_file(t, "--save"),
                    help="slump: write the final particles (x0, x, F, alpha, ...) to this .npz")
    a = ap.parse_args(argv)
    if a.save and a.case != "slump":
        ap.error(f"--save = {a.save!r} is not allowed with the {a.case} case: it saves the slump's final particles")
    from benchmarks import validation

    t = time.time()
    history = column_history(a.every, a.resolution, a.periods, lambda r: print(json.dumps(r), flush=True)) \
        if a.case == "column" and a.every > 0 else contextlib.nullcontext([])
    saving = final_slump_state(a.save) if a.save else contextlib.nullcontext()
    with isotropic_pressure(not a.baseline), history as rows, saving:
        if a.case == "column":
            row = validation.near_yield_column(resolution=a.resolution, width=0.04, floor="slip_ghost_particles",
                                               periods=a.periods, fit_weight=a.fit_weight)
        else:
            row = validation.slump(a.S, resolution=a.resolution, duration=a.duration, fit_weight=a.fit_weight)
    out = {k: v for k, v in row.items() if not isinstance(v, list)}
    out["isotropic_pressure"] = not a.baseline
    out["wall_s"] = time.time() - t
    if rows:
        # The plastic part at each report, against the elastic reference run after the plastic run.
        out["plastic_over_theory_history"] = [
            [r["period"], (r["shortening"] - row["elastic_measured"]) / row["theory_plastic"]] for r in rows]
    print(json.dumps(out, default=str, indent=0))


if __name__ == "__main__":
    main()
