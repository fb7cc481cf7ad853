"""Worlds benchmark: W worlds in one model against W separate runs of the same scenes.

Each world is a dough block of about ``--particles`` particles falling onto the ground,
world ``w`` with its own yield stress (a sensitivity sweep). The same W scenes are run

- as W separate models, one after another (what a sweep did before worlds), and
- as one model of W worlds (``SceneBuilder.finalize(worlds=W)``),

for ``--steps`` steps each, after a warm-up run (kernel loading, first neighbour
search). It reports the per-world cost ratio ``time(one model of W worlds) /
time(W separate runs)`` (below 1: worlds are cheaper), the best of ``--repeat`` timings
of each, and checks that every world's final positions equal its separate run's.
``--gradient`` also times a float64 ``Rollout`` forward + backward of a ``WorldLoss``
against W separate rollouts.

    python -m benchmarks.worlds_bench                      # 16 worlds of ~500 particles, 100 steps
    python -m benchmarks.worlds_bench --worlds 4 --steps 20 --gradient --json out.json

Not a test.
"""

import json
import os
import platform
import sys
import time

import numpy as np
import warp as wp

try:
    import warp_esph as we
except ImportError:  # run from a checkout without installing the package
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import warp_esph as we

from benchmarks import _cli
from benchmarks.blocks import block_builder
from warp_esph import losses
from warp_esph.rollout import Rollout


def yield_stresses(worlds: int) -> np.ndarray:
    base = we.Material.preset("dough").yield_stress
    return base * np.geomspace(0.5, 2.0, worlds)


def separate_models(particles, worlds, dtype, requires_grad=False, device="cpu"):
    out = []
    for ys in yield_stresses(worlds):
        m = block_builder(particles).finalize(device=device, dtype=dtype, requires_grad=requires_grad)
        m.set_material(0, m.materials[0].replace(yield_stress=float(ys)))
        out.append(m)
    return out


def world_model(particles, worlds, dtype, requires_grad=False, device="cpu"):
    m = block_builder(particles).finalize(device=device, dtype=dtype, requires_grad=requires_grad, worlds=worlds)
    for w, ys in enumerate(yield_stresses(worlds)):
        m.set_material(0, m.materials[m.world_materials(w).start].replace(yield_stress=float(ys)), world=w)
    return m


def run(model, steps, dt):
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    for _ in range(steps):
        solver.step(a, b, dt)
        a, b = b, a
    wp.synchronize_device(model.device)
    return a.x.numpy()


def timed_pair(fn_a, fn_b, repeat, cpu=None):
    """Best of ``repeat`` wall-clock timings of each, alternating a and b, so that a change
    in the machine's load (other processes) affects both alike. ``cpu`` (a dict) receives
    the best process CPU times too (``"a"``, ``"b"``): Warp runs CPU kernels on the calling
    thread, so that is the code's own cost without the time other processes took."""
    best = [float("inf"), float("inf")]
    best_cpu = [float("inf"), float("inf")]
    out = [None, None]
    for _ in range(repeat):
        for k, fn in enumerate((fn_a, fn_b)):
            t0, c0 = time.perf_counter(), time.process_time()
            out[k] = fn()
            best[k] = min(best[k], time.perf_counter() - t0)
            best_cpu[k] = min(best_cpu[k], time.process_time() - c0)
    if cpu is not None:
        cpu["a"], cpu["b"] = best_cpu
    return best[0], out[0], best[1], out[1]


def forward_case(particles, worlds, steps, dtype, repeat, device="cpu"):
    seps = separate_models(particles, worlds, dtype, device=device)
    multi = world_model(particles, worlds, dtype, device=device)
    dt = min(m.stable_dt() for m in seps)
    # Warm-up: kernels loaded, grids allocated in both set-ups.
    run(seps[0], 2, dt)
    run(multi, 2, dt)
    cpu = {}
    t_sep, xs_sep, t_multi, x_multi = timed_pair(
        lambda: [run(m, steps, dt) for m in seps], lambda: run(multi, steps, dt), repeat, cpu
    )
    diff = max(float(np.abs(x_multi[multi.world_particles(w)] - xs_sep[w]).max()) for w in range(worlds))
    return {
        "case": "forward", "device": device, "dtype": dtype.__name__, "worlds": worlds, "particles_per_world": seps[0].particle_count,
        "steps": steps, "dt": dt, "seconds_separate": t_sep, "seconds_worlds": t_multi,
        "per_world_cost_ratio": t_multi / t_sep, "cpu_seconds_separate": cpu["a"], "cpu_seconds_worlds": cpu["b"],
        "per_world_cpu_cost_ratio": cpu["b"] / cpu["a"], "max_position_difference": diff,
    }


def gradient_case(particles, worlds, steps, repeat, device="cpu"):
    dtype = wp.float64
    seps = separate_models(particles, worlds, dtype, requires_grad=True, device=device)
    multi = world_model(particles, worlds, dtype, requires_grad=True, device=device)
    dt = min(m.stable_dt() for m in seps)
    targets = [m.particle_x0 + np.array([0.0, -0.05, 0.0]) for m in seps]
    rollouts = [Rollout(m, steps, dt) for m in seps]
    sep_losses = [losses.PositionLoss(t, frames=[steps]) for t in targets]
    multi_rollout = Rollout(multi, steps, dt)
    world_loss = losses.WorldLoss(multi, [losses.PositionLoss(t, frames=[steps]) for t in targets])

    def separate():
        return [r.value_and_grad(loss)[1]["yield_stress"][0] for r, loss in zip(rollouts, sep_losses)]

    def together():
        return multi_rollout.value_and_grad(world_loss)[1]["yield_stress"]

    separate()
    together()
    cpu = {}
    t_sep, g_sep, t_multi, g_multi = timed_pair(separate, together, repeat, cpu)
    # Forward and backward apart (the backward of the last forward, re-run each time).
    t_fs, _, t_fm, _ = timed_pair(lambda: [r.forward() for r in rollouts], multi_rollout.forward, repeat)
    for r in rollouts:
        r.forward()
    multi_rollout.forward()
    t_bs, _, t_bm, _ = timed_pair(lambda: [r.backward(loss) for r, loss in zip(rollouts, sep_losses)],
                                  lambda: multi_rollout.backward(world_loss), repeat)
    rel = float(np.max(np.abs(np.asarray(g_multi) - np.asarray(g_sep)) / np.maximum(np.abs(g_sep), 1e-300)))
    return {
        "case": "gradient", "device": device, "dtype": "float64", "worlds": worlds, "particles_per_world": seps[0].particle_count,
        "steps": steps, "dt": dt, "seconds_separate": t_sep, "seconds_worlds": t_multi,
        "per_world_cost_ratio": t_multi / t_sep, "cpu_seconds_separate": cpu["a"], "cpu_seconds_worlds": cpu["b"],
        "per_world_cpu_cost_ratio": cpu["b"] / cpu["a"], "forward_ratio": t_fm / t_fs, "backward_ratio": t_bm / t_bs,
        "max_yield_stress_gradient_rel_difference": rel,
    }


PROG = "python -m benchmarks.worlds_bench"


def main(argv=None):
    ap = _cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    ap.add_argument("--worlds", type=_cli.positive_int, default=16)
    ap.add_argument("--particles", type=_cli.positive_int, default=500, help="particles per world (about)")
    ap.add_argument("--steps", type=_cli.positive_int, default=100)
    ap.add_argument("--repeat", type=_cli.positive_int, default=5)
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ap.add_argument("--gradient", action="store_true", help="also time Rollout forward + backward (float64)")
    ap.add_argument("--gradient-steps", type=_cli.positive_int, default=10)
    ap.add_argument("--device", default="cpu", type=_cli.device, help="Warp device, e.g. cuda:0")
    ap.add_argument("--json", default="worlds_bench.json", type=_cli.output_file)
    args = ap.parse_args(argv)
    from warp_esph.startup import init_warp  # noqa: PLC0415 (log_level, no native CUDA note)

    init_warp()
    results = [forward_case(args.particles, args.worlds, args.steps, getattr(wp, args.dtype), args.repeat, args.device)]
    if args.gradient:
        results.append(gradient_case(args.particles, args.worlds, args.gradient_steps, args.repeat, args.device))
    for r in results:
        print(
            f"{r['case']:8s} {r['dtype']:7s} {r['worlds']} worlds x {r['particles_per_world']} particles, {r['steps']} steps: "
            f"separate {r['seconds_separate']:.3f} s, worlds {r['seconds_worlds']:.3f} s, "
            f"per-world cost ratio {r['per_world_cost_ratio']:.3f} (CPU time: {r['per_world_cpu_cost_ratio']:.3f})"
            + (f"; forward {r['forward_ratio']:.3f}, backward {r['backward_ratio']:.3f}" if "forward_ratio" in r else "")
        )
    meta = {"machine": platform.machine(), "python": platform.python_version(), "warp": wp.__version__,
            "device": str(wp.get_device(args.device)), "load_average": os.getloadavg()}
    with open(args.json, "w") as f:
        json.dump({"meta": meta, "results": results}, f, indent=2)


if __name__ == "__main__":
    _cli.run(main, PROG)
