"""What each floor costs: the step on the slump scene (``validation.slump_model``) on every
floor of ``validation.FLOORS``, as a ratio to the plain particle floor's default (fused) step
timed in the same run.

    python -m benchmarks.floors                          # S = 0.2, 12 across, float32 forward
    python -m benchmarks.floors --resolution 8 --taped --json out.json

Each floor's forward step is timed over ``--steps`` steps after ``--warmup`` (kernel
loading, the pile starting to fall), the best of ``--repeat``; the particle floor also
with the non-fused kernels, which a ghost floor (``add_particle_floor(ghost=True)``) runs.
``--taped`` also times a float64 taped window of ``--taped-steps`` steps, forward and
backward, for the particle and ghost floors. ``--reach`` also times the particle floor's
step with its floor particles out of every free particle's reach run as every other
(``ToolSet.still_particles`` hidden; the fused step leaves out their neighbour passes,
``fused.out_of_reach``), interleaved with the default, and counts those it leaves out at the
end of the timed steps. Not a test.
"""

import json
import platform
import sys
import time

import numpy as np

from benchmarks import _cli

PROG = "python -m benchmarks.floors"


def _forward(floor: str, fused: bool, resolution: int, steps: int, warmup: int, reach: bool = True):
    """Seconds per forward step, the particle count and the particles the last step left out
    of its neighbour passes (``reach`` False: none, every one run)."""
    import warp_esph as we
    from benchmarks import validation as V
    from benchmarks.step import time_block

    model, _, _, _ = V.slump_model(0.2, resolution, floor=floor)
    if not reach:
        model.tools.still_particles = lambda: None
    solver = we.Solver(model, fused=fused)
    states = [model.state(), model.state()]
    dt = 0.5 * model.stable_dt()
    time_block(solver, states, warmup, model.device, dt)
    t = time_block(solver, states, steps, model.device, dt)[0]
    return t, model.particle_count, int(solver.scratch.far.numpy().sum())


def _taped(floor: str, resolution: int, steps: int) -> tuple[float, float]:
    import warp as wp

    import warp_esph as we
    from benchmarks import validation as V

    model, _, _, _ = V.slump_model(0.2, resolution, floor=floor, dtype=wp.float64, requires_grad=True)
    solver = we.Solver(model)
    states = [model.state() for _ in range(steps + 1)]
    dt = 0.5 * model.stable_dt()
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    weights = wp.array(np.random.default_rng(0).normal(size=(model.particle_count, 3)), dtype=wp.vec3d)

    @wp.kernel(module="unique")
    def dot(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.float64)):
        i = wp.tid()
        wp.atomic_add(out, 0, wp.dot(x[i], w[i]))

    tape = wp.Tape()
    t0 = time.perf_counter()
    with tape:
        for a, b in zip(states[:-1], states[1:]):
            solver.step(a, b, dt)
        wp.launch(dot, model.particle_count, [states[-1].x, weights], [loss])
    wp.synchronize()
    t1 = time.perf_counter()
    tape.backward(loss)
    wp.synchronize()
    return (t1 - t0) / steps, (time.perf_counter() - t1) / steps


def main(argv=None) -> dict:
    p = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--resolution", type=_cli.positive_int, default=12, help="particles across the slump's cylinder")
    p.add_argument("--steps", type=_cli.positive_int, default=60)
    p.add_argument("--warmup", type=_cli.positive_int, default=5)
    p.add_argument("--repeat", type=_cli.positive_int, default=2)
    p.add_argument("--taped", action="store_true", help="also time a float64 taped window, forward and backward")
    p.add_argument("--taped-steps", type=_cli.positive_int, default=3)
    p.add_argument("--reach", action="store_true",
                   help="also time the particle floor with its floor particles out of reach run as every other")
    p.add_argument("--json", default=None, type=_cli.output_file, help="where the results go")
    args = p.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from benchmarks import validation as V

    runs = [(f, True, True) for f in V.FLOORS] + [("particles", False, True)]
    if args.reach:
        runs.append(("particles", True, False))
    best: dict[str, float] = {}
    counts: dict[str, int] = {}
    left: dict[str, int] = {}
    for _ in range(args.repeat):  # interleaved, so a slow spell of the machine hits every floor
        for floor, fused, reach in runs:
            key = floor + ("" if fused else " (non-fused)") + ("" if reach else " (every pass)")
            t, n, far = _forward(floor, fused, args.resolution, args.steps, args.warmup, reach)
            best[key] = min(best.get(key, np.inf), t)
            counts[key], left[key] = n, far
    base = best["particles"]
    out = {"resolution": args.resolution, "steps": args.steps, "machine": platform.machine(),
           "forward": {k: {"s_per_step": v, "ratio": v / base, "particles": counts[k], "left_out": left[k]}
                       for k, v in best.items()}}
    for k, v in out["forward"].items():
        print(f"{k:28s} {v['particles']:6d} particles  {1e3 * v['s_per_step']:8.2f} ms/step  {v['ratio']:.2f} x"
              f"  ({v['left_out']} left out of the neighbour passes)", flush=True)
    if args.taped:
        floors = ("particles", "ghost_particles")
        for f in floors:  # kernel loading (float64, taped) before any timing
            _taped(f, args.resolution, 1)
        taped = {f: _taped(f, args.resolution, args.taped_steps) for f in floors}
        fb = taped["particles"]
        out["taped"] = {f: {"forward_ratio": t[0] / fb[0], "backward_ratio": t[1] / fb[1]} for f, t in taped.items()}
        for f, t in out["taped"].items():
            print(f"taped float64 {f:16s} forward {t['forward_ratio']:.2f} x  backward {t['backward_ratio']:.2f} x", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return out


if __name__ == "__main__":
    sys.exit(0 if _cli.run(main, PROG) else 1)
