"""What replaying the step's launches saves (``warp_esph/sim/replay.py``): the forward step
with the replayed launches against every launch through ``wp.launch``, and against replayed
launches that go through ``cmd.launch()`` (which fills the kernel's argument struct again at
every call, where the replay keeps it filled), timed in the same run on the same states, in
interleaved blocks (the ratio, not the seconds, is the result: these machines are shared).

    python -m benchmarks.launches                         # 216, 1000, 8000 particles
    python -m benchmarks.launches --sizes 512,4096 --json out.json

Three scenes per size: an elastoplastic cube dropped on the ground collider (the plain
integrator), the same cube on a pinned particle floor (the tool integrator, as the
validation slumps run), and that cube under a keyframed press in float64 run as a fit runs
it, a ``Rollout`` forward on a ``wp.Tape`` (every step into new states; the replayed
launches are recorded on the tape). Not a test.
"""

import json
import platform

from benchmarks import _cli

PROG = "python -m benchmarks.launches"


def _scene(n: int, floor: bool, press: bool = False):
    import warp as wp

    import warp_esph as we
    from warp_esph import tools

    side = max(2, round(n ** (1.0 / 3.0)))
    dx = 0.01
    b = we.SceneBuilder(spacing=dx, support_radius=2.0 * dx)
    mat = we.Material(mu=2e4, lam=3e4, density=1000.0, yield_stress=300.0, flow_rate=50.0, viscosity=1.0)
    body = b.add_box(center=(0.0, 0.5 * side * dx + 0.5 * dx, 0.0), size=(side * dx,) * 3, material=mat)
    if floor:
        b.add_particle_floor(body, margin=0.5 * side * dx)
    else:
        b.add_ground(friction=0.5)
    if press:
        top = (side + 1) * dx
        b.add_tool("box", half_extents=(side * dx, 0.5 * dx, side * dx), name="press",
                   motion=tools.Keyframes([0.0, 1.0], [(0.0, top, 0.0), (0.0, top - 0.2 * side * dx, 0.0)]))
        return b.finalize(dtype=wp.float64, requires_grad=True)
    return b.finalize()


def measure(n: int, floor: bool, steps: int, blocks: int, warmup: int) -> dict:
    import warp_esph as we
    from benchmarks.step import time_block

    model = _scene(n, floor)
    solver = we.Solver(model)
    states = [model.state(), model.state()]
    dt = 0.5 * model.stable_dt()
    owners = (model.launches, solver.search.launches)
    for _ in range(warmup // 3):
        for setting in SETTINGS:
            _set(owners, setting)
            time_block(solver, states, 2, model.device, dt)
    times = {setting: [] for setting in SETTINGS}
    for _ in range(blocks):
        for setting in SETTINGS:
            _set(owners, setting)
            times[setting].append(time_block(solver, states, steps, model.device, dt)[0])
    _set(owners, "replayed")
    return _row(model, "particle floor" if floor else "ground", times)


#: Replayed (the default), replayed with the struct filled again at every call, ``wp.launch``.
SETTINGS = ("replayed", "rebuilt", "plain")


def _set(owners, setting: str):
    for o in owners:
        o.enabled = setting != "plain"
        o.keep_struct = setting == "replayed"


def _row(model, scene: str, times: dict) -> dict:
    replayed, rebuilt, plain = (min(times[s]) for s in SETTINGS)
    return {"particles": model.particle_count, "scene": scene, "plain_ms": 1e3 * plain, "rebuilt_ms": 1e3 * rebuilt,
            "replayed_ms": 1e3 * replayed, "speedup": plain / replayed, "kept_struct_speedup": rebuilt / replayed}


def measure_taped(n: int, steps: int, blocks: int) -> dict:
    """ms per step of ``Rollout.forward`` (taped) over ``steps`` steps, replay on and off."""
    import time

    from warp_esph.rollout import Rollout

    model = _scene(n, True, press=True)
    rollout = Rollout(model, steps, 0.5 * model.stable_dt())
    owners = (model.launches, rollout.solver.search.launches)
    times = {setting: [] for setting in SETTINGS}
    for k in range(blocks + 1):
        for setting in SETTINGS:
            _set(owners, setting)
            t0 = time.perf_counter()
            rollout.forward()
            if k > 0:  # the first block loads the kernels and makes the states
                times[setting].append((time.perf_counter() - t0) / steps)
    _set(owners, "replayed")
    return _row(model, "taped press (float64)", times)


def main(argv=None):
    p = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="216,1000,8000", type=_cli.positive_int_list,
                   help="particle counts of the cube (rounded to a cube)")
    p.add_argument("--steps", type=_cli.positive_int, default=40, help="steps per timed block")
    p.add_argument("--blocks", type=_cli.positive_int, default=5, help="timed blocks per setting, interleaved; the best is kept")
    p.add_argument("--warmup", type=_cli.nonnegative_int, default=20, help="untimed steps first (kernel loading)")
    p.add_argument("--json", default=None, type=_cli.output_file, help="also write the rows here")
    args = p.parse_args(argv)
    from warp_esph.startup import init_warp

    init_warp()
    rows = []
    for n in args.sizes:
        for floor in (False, True, "taped"):
            r = (measure_taped(n, args.steps, args.blocks) if floor == "taped"
                 else measure(n, floor, args.steps, args.blocks, args.warmup))
            rows.append(r)
            print(f"{r['particles']:>7d}  {r['scene']:<22s} wp.launch {r['plain_ms']:8.2f} ms/step   "
                  f"struct refilled {r['rebuilt_ms']:8.2f}   replayed {r['replayed_ms']:8.2f} ms/step   "
                  f"{r['speedup']:.2f} x ({r['kept_struct_speedup']:.2f} x of it the kept struct)", flush=True)
    report = {"machine": platform.processor() or platform.machine(), "rows": rows}
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=1)
    return report


if __name__ == "__main__":
    _cli.run(main, PROG)
