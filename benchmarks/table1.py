"""The paper's Table 1 next to this project's seconds per frame, same particle counts and steps.

    python -m benchmarks.table1                       # every row, CPU, float32 (a few minutes)
    python -m benchmarks.table1 --rows "Fig. 5" --steps 50 --json t1.json
    python -m benchmarks.table1 --device cuda         # where Warp finds a GPU

Each row of the paper's Table 1 (``warp_esph.scenes.TABLE1``) is built from its figure
scene at scale 1 with only that run's bodies (``paper_run_scene``): the paper's particle
count (within 5 %) and time step. The run starts from the scene's initial state;
``--warmup`` steps run first (kernel loading, caches), then ``--steps`` steps are timed
(at least ``--min-seconds`` of them). Seconds per frame are **extrapolated**: seconds per
step times the steps in one frame at 30 frames per second (``(1/30) / dt``; the paper
does not give its frame rate, 30 fps is assumed), so they are comparable with the
paper's column whatever frame rate the scenes use (25 fps). Both the wall-clock time and
the process's CPU time are reported; the CPU time is steadier on a shared machine.
Warp runs each CPU kernel on one thread, so the CPU numbers are one core, like the paper's
(one core of a 2008 Xeon E5410, 2.33 GHz).

The timed steps are the first ones of the scene (bodies falling, not yet deformed); the
cost per step depends little on the motion (neighbour search and the per-particle
kernels dominate), which ``--warmup`` can check (e.g. 2000 steps: past the impact).
"""

import json
import os
import platform
import sys
import time

from benchmarks import _cli

FPS = 30.0
PROG = "python -m benchmarks.table1"


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def measure(run, device: str, dtype: str, warmup: int, steps: int, min_seconds: float) -> dict:
    """One Table 1 row timed; ``dtype``: ``"float32"`` or ``"float64"``."""
    import warp as wp

    from benchmarks.validation import _lab_dtype
    from warp_esph.scenes import paper_run_scene
    from warp_esph.sim.solver import Solver

    # Refused by name before the paper's scene is built: looked up in Warp, "double" was an
    # AttributeError and "float16" or "vec3" reached finalize after the build.
    scalar = _lab_dtype(wp, dtype)
    scene = paper_run_scene(run)
    model = scene.builder.finalize(device=device, dtype=scalar)
    solver = Solver(model)
    a, b = model.state(requires_grad=False), model.state(requires_grad=False)
    dt = scene.dt
    for _ in range(warmup):
        solver.step(a, b, dt)
        a, b = b, a
    wp.synchronize_device(model.device)
    done, wall, cpu = 0, 0.0, 0.0
    while done < steps or wall < min_seconds:
        w0, c0 = time.perf_counter(), time.process_time()
        for _ in range(10):
            solver.step(a, b, dt)
            a, b = b, a
        wp.synchronize_device(model.device)
        wall += time.perf_counter() - w0
        cpu += time.process_time() - c0
        done += 10
    steps_per_frame = (1.0 / FPS) / dt
    return {
        "label": run.label, "scene": run.scene, "bodies": list(run.bodies), "particles": model.particle_count,
        "paper_particles": run.particles, "dt": dt, "paper_dt": run.dt, "paper_seconds_per_frame": run.seconds_per_frame,
        "steps_timed": done, "wall_seconds_per_step": wall / done, "cpu_seconds_per_step": cpu / done,
        "wall_seconds_per_frame": wall / done * steps_per_frame, "cpu_seconds_per_frame": cpu / done * steps_per_frame,
        "steps_per_frame_at_30fps": steps_per_frame,
    }


def markdown(rows: list[dict], device: str) -> str:
    lines = [
        f"| figure | Δt (ms) | particles (paper) | particles (here) | s/frame paper, 1 core Xeon E5410 | "
        f"s/frame here, {device} CPU time (wall) | speed-up |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {1e3 * r['dt']:g} | {r['paper_particles']:,} | {r['particles']:,} | "
            f"{r['paper_seconds_per_frame']:.2f} | {r['cpu_seconds_per_frame']:.2f} ({r['wall_seconds_per_frame']:.2f}) | "
            f"{r['paper_seconds_per_frame'] / r['cpu_seconds_per_frame']:.0f}x |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    p = _cli.Parser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument("--rows", default=None, help="comma list of row labels or their prefixes, e.g. 'Fig. 1,Fig. 5' (default all)")
    p.add_argument("--device", default="cpu", help="Warp device (cpu, cuda, cuda:0, ...)")
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    p.add_argument("--warmup", type=_cli.nonnegative_int, default=5)
    p.add_argument("--steps", type=_cli.positive_int, default=20, help="at least this many timed steps (in blocks of 10)")
    p.add_argument("--min-seconds", type=_cli.nonnegative_float, default=2.0, help="and at least this much wall time")
    p.add_argument("--json", default=None, type=_cli.output_file, help="also write the measurements here")
    args = p.parse_args(argv)

    os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".warp_cache"))
    import warp as wp

    from warp_esph.startup import init_warp  # noqa: PLC0415 (log_level, no native CUDA note)

    init_warp()
    from warp_esph.scenes import TABLE1

    # Checked once Warp starts here (the kernel cache above): the device, and that every row asked for is one.
    problem = _cli.device_problem(args.device)
    if problem:
        p.error(f"--device = {args.device!r} is not allowed: {problem}")
    wanted = None if args.rows is None else [w.strip() for w in args.rows.split(",") if w.strip()]
    unknown = [w for w in wanted or () if not any(run.label.startswith(w) for run in TABLE1)]
    if wanted is not None and (unknown or not wanted):
        p.error(f"--rows = {args.rows!r} is not allowed: {repr(unknown[0]) + ' is' if unknown else 'it names'} no row "
                f"(nor a prefix of one) of Table 1; its rows: {', '.join(run.label for run in TABLE1)}")
    rows = []
    for run in TABLE1:
        if wanted is not None and not any(run.label.startswith(w) for w in wanted):
            continue
        r = measure(run, args.device, args.dtype, args.warmup, args.steps, args.min_seconds)
        rows.append(r)
        print(f"{r['label']:<24} {r['particles']:>6} particles  dt {1e3 * r['dt']:g} ms  "
              f"{1e3 * r['cpu_seconds_per_step']:.1f} ms/step CPU ({1e3 * r['wall_seconds_per_step']:.1f} wall)  "
              f"{r['cpu_seconds_per_frame']:.2f} s/frame at 30 fps  (paper {r['paper_seconds_per_frame']:.2f})", flush=True)
    print()
    print(markdown(rows, args.device))
    if args.json:
        info = {"cpu": _cpu_name(), "python": sys.version.split()[0], "warp": wp.__version__, "device": args.device,
                "dtype": args.dtype, "fps_assumed": FPS, "rows": rows}
        with open(args.json, "w") as fh:
            json.dump(info, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
