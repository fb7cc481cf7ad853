"""The fused step at rest with and without ``fused.KeptFits``, in one process.

    python -m benchmarks.kept_fits                 # 8 ABBA rounds of 60-step blocks
    python -m benchmarks.kept_fits --rounds 2      # a quick look

Scene: ``benchmarks.validation``'s 8-across S = 0.2 slump on its 3.2 R0 particle floor
(float32, 1464 particles, 1048 pinned), run 600 steps (dt 0.9 of ``stable_dt``) so that
most of the floor is out of the cylinder's reach. Two solvers then step two copies of that
state, blocks alternated A B B A: A with the kept fits switched off (``keep_fits`` called
with ``keep`` False: the floor's far particles found by ``out_of_reach`` every step, as the
parent of the change did), B as the package runs. Each block's thread CPU time per step;
medians and best blocks, and the ratio A / B. The two runs' positions must be the same bits.
"""

import time

import numpy as np

from benchmarks import _cli

PROG = "python -m benchmarks.kept_fits"


def slump_after(steps: int, resolution: int, floor_radius: float):
    """``benchmarks.validation``'s S = 0.2 slump (``resolution`` across, its pinned floor
    ``floor_radius`` R0) after ``steps`` fused float32 steps of 0.9 ``stable_dt``:
    ``(model, free, dt, solver, state)``."""
    from benchmarks import validation

    model, free, _, _ = validation.slump_model(0.2, resolution, floor_radius=floor_radius)
    dt = 0.9 * model.stable_dt()
    s = validation._solver(model)
    a, c = model.state(), model.state()
    for _ in range(steps):
        s.step(a, c, dt)
        a, c = c, a
    return model, free, dt, s, a


def measure(rounds: int, block_steps: int) -> dict:
    """The A / B blocks of the module's docstring: per-step thread CPU seconds of each block,
    the particles far and kept; refuses (RuntimeError) where the two runs' positions differ."""
    from benchmarks import validation
    from warp_esph.sim import fused

    model, free, dt, _, a = slump_after(600, 8, 3.2)
    keep_fits = fused.keep_fits

    def off(m, state_in, scratch, search, keep):
        return keep_fits(m, state_in, scratch, search, False)

    runs = {name: (validation._solver(model), [model.state(), model.state()]) for name in "AB"}
    for _, pair in runs.values():
        pair[0].assign(a)

    def block(name):
        solver, pair = runs[name]
        fused.keep_fits = off if name == "A" else keep_fits
        try:
            t = time.thread_time()
            for _ in range(block_steps):
                solver.step(pair[0], pair[1], dt)
                pair.reverse()
            return (time.thread_time() - t) / block_steps
        finally:
            fused.keep_fits = keep_fits  # the package as it was, whatever happened

    block("A")  # compiled
    block("B")  # the marks made, the fits kept
    times = {"A": [], "B": []}
    for _ in range(rounds):
        for name in "ABBA":
            times[name].append(block(name))
    if not np.array_equal(runs["A"][1][0].x.numpy(), runs["B"][1][0].x.numpy()):
        raise RuntimeError("the runs with and without the kept fits reached different positions")
    scratch = runs["B"][0].scratch
    return {"particles": model.particle_count, "pinned": int((~free).sum()), "far": int(scratch.far.numpy().sum()),
            "kept": int((scratch.kept_fits.kept.numpy() == fused.KEPT_FIT).sum()),
            "off": np.array(times["A"]), "kept_fits": np.array(times["B"])}


def main(argv=None):
    p = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=_cli.positive_int, default=8, help="ABBA rounds (default 8)")
    p.add_argument("--block", type=_cli.positive_int, default=60, help="steps a block (default 60)")
    args = p.parse_args(argv)
    r = measure(args.rounds, args.block)
    A, B = r["off"], r["kept_fits"]
    print(f"{r['particles']} particles, {r['pinned']} pinned, {r['far']} far, {r['kept']} fits kept")
    print(f"ms a step (thread CPU): off median {1e3 * np.median(A):.3f} best {1e3 * A.min():.3f}; "
          f"kept median {1e3 * np.median(B):.3f} best {1e3 * B.min():.3f}; off / kept median "
          f"{np.median(A) / np.median(B):.3f}, best {A.min() / B.min():.3f}")
    return 0


if __name__ == "__main__":
    _cli.run(main, PROG)
