"""Cost of one gradient against one forward run, side by side in one process.

For a dough block (about 10k particles by default) and the star of
``examples/fit_dough_star.py`` (its default scale 0.5, 142 particles), in float32 and
float64, it times, interleaved, over the same ``--steps`` steps from the same state:

- ``fused``: the production forward (``Solver`` with its fused fast path, no tape),
- ``taped``: ``Rollout.forward`` (the differentiable kernels recorded on a ``wp.Tape``),
- ``backward``: ``Rollout.backward`` of a position loss on the last frame,

and reports the ratios ``gradient / fused = (taped + backward) / fused`` and
``backward / fused`` (best of ``--repeats``), the memory of one taped step (a ``State``
with its gradients, bytes per particle), and, with ``--profile``, the time of each
kernel's adjoint launch in the backward pass. With both precisions it prints the float32
gradient's error against float64's (``float32_relative_error`` in ``--json``): ``v0``'s
``|g32 - g64| / |g64|`` (L2 over the particles), each material parameter ``p``'s
``max |p (g32 - g64)| / max(max |p g64|, 1e-6 L64)`` over the materials (``L64`` the float64
loss; an infinite ``p``, an elastic yield stress, counts as 1), i.e. of its sensitivity
``p dL/dp``, floored at 1e-6 of the loss (``material_gradient_errors``: a parameter that
hardly moves the loss, ``mu`` after a couple of steps from rest, has a round-off gradient,
and dividing by it gave 2.8e+21).

    python -m benchmarks.gradient_bench                      # 10k block and fit star, f32 + f64
    python -m benchmarks.gradient_bench --generated --profile   # also the old path; per-kernel times
    python -m benchmarks.gradient_bench --sizes 1000 --repeats 2 --profile
    python -m benchmarks.gradient_bench --step-memos 20   # the star with the step's two memos off / on
    python -m benchmarks.gradient_bench --kept-records 20   # the star with a taped step's kept launch records off / on

``--generated`` also runs the rollout with ``Solver.hand_adjoints = False`` (the
differentiable kernels on the tape with Warp's generated adjoints: the code before the
hand-written adjoints), for a before/after in one run. Ratios are printed in wall and CPU time.

Not a test.
"""

import collections
import contextlib
import json
import os
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
from benchmarks.blocks import block_model
from warp_esph.losses import PositionLoss
from warp_esph.rollout import Rollout, state_nbytes
from warp_esph.sim.replay import Launches
from warp_esph.sim.solver import Solver


#: The material parameters whose float32 gradient is compared with float64's.
MATERIAL_GRADS = ("mu", "yield_stress", "flow_rate")
#: A parameter ``p`` whose float64 sensitivity ``|p dL/dp|`` is below this fraction of the
#: float64 loss ``L`` hardly moves the loss (its gradient is round-off: ``mu`` after 2 steps
#: from rest, 3e-45 against float32's -1e-23); its error is measured against that floor.
SENSITIVITY_FLOOR = 1e-6


def material_gradient_errors(g32: dict, g64: dict, values: dict) -> dict:
    """The float32 material gradients' error against float64's, per parameter: ``max |p
    (g32 - g64)| / max(max |p g64|, SENSITIVITY_FLOOR * L64)`` (``p`` the material values,
    ``L64`` the float64 loss): relative to the gradient's own scale, a sensitivity too small
    to move the loss measured against the floor instead (divided by the gradient alone, ``mu``'s
    error after 2 steps from rest was 2.8e+21). An infinite value (``yield_stress`` of an
    elastic material) has no sensitivity: its gradient is compared as it is, against the floor."""
    floor = SENSITIVITY_FLOOR * abs(g64["loss"])
    err = {}
    for k in MATERIAL_GRADS:
        p = np.asarray(values[k], dtype=np.float64)
        scale = np.where(np.isfinite(p), np.abs(p), 1.0)
        ref = scale * np.asarray(g64["grads"][k], dtype=np.float64)
        diff = scale * (np.asarray(g32["grads"][k], dtype=np.float64) - np.asarray(g64["grads"][k], dtype=np.float64))
        err[k] = float(np.abs(diff).max() / max(np.abs(ref).max(), floor, 1e-300))
    return err


def star_model(dtype, scale: float = 0.5) -> we.Model:
    """The fit example's star (``examples/fit_dough_star.py``), at ``dtype``."""
    dx = 0.01 / scale
    b = we.SceneBuilder(spacing=dx, support_radius=2.5 * dx)
    b.add_star((0.0, 0.07, 0.0), outer_radius=0.15, inner_radius=0.065, thickness=0.04,
               material=we.Material.preset("dough").replace(mu=2.0 * we.Material.preset("dough").mu), name="star")
    b.add_ground(friction=0.6)
    model = b.finalize(dtype=dtype, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * dx, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model


class AdjointProfile:
    """Times each launch while active by kernel name, in CPU time of the calling thread (CPU
    launches are synchronous and run on it): in a backward pass, the generated adjoints and
    the hand-written adjoint kernels. Both ways a launch is made are timed: ``wp.launch`` and
    the model's replayed launches (``sim/replay.py``'s ``Launches``, which call the kernel
    without ``wp.launch``: every launch of the step, and the hand-written adjoints; timing
    ``wp.launch`` alone missed them); a launch made inside another timed one counts once, in
    the outer. ``seconds["(outside launches)"]``: the rest of the block's CPU time (Python,
    the tape's zeroing and copies)."""

    OUTSIDE = "(outside launches)"

    def __init__(self):
        self.seconds = collections.defaultdict(float)
        self.calls = collections.Counter()

    def _timed(self, launch, kernel_at):
        depth = self._depth

        def timed(*args, **kwargs):
            if depth[0]:
                return launch(*args, **kwargs)
            depth[0] += 1
            t0 = time.thread_time()
            try:
                return launch(*args, **kwargs)
            finally:
                depth[0] -= 1
                kernel = args[kernel_at] if len(args) > kernel_at else kwargs["kernel"]
                # The kernel's own name: its key also names the function that made it.
                name = kernel.key.rsplit("__locals__", 1)[-1]
                if kwargs.get("adjoint"):
                    name += " (generated adjoint)"
                self.seconds[name] += time.thread_time() - t0
                self.calls[name] += 1

        return timed

    def __enter__(self):
        self._depth = [0]
        self._launch = wp.launch
        self._replayed = Launches.__call__
        wp.launch = self._timed(self._launch, 0)
        Launches.__call__ = self._timed(self._replayed, 1)
        self._t0 = time.thread_time()
        return self

    def __exit__(self, *exc):
        total = time.thread_time() - self._t0
        wp.launch = self._launch
        Launches.__call__ = self._replayed
        self.seconds[self.OUTSIDE] = max(total - sum(self.seconds.values()), 0.0)


def measure(model: we.Model, steps: int, repeats: int, profile: bool, hand: bool = True, fused_tape: bool = True) -> dict:
    dt = model.stable_dt()
    n = model.particle_count
    fused = Solver(model)
    pair = [model.state(requires_grad=False) for _ in range(2)]
    initial = model.state(requires_grad=False)
    rollout = Rollout(model, steps, dt)
    rollout.solver.hand_adjoints = hand
    if not fused_tape:
        # The taped forward on the differentiable kernels (hand-written adjoints where they
        # exist for them): how a variational-force model ran before its adjoint was written.
        rollout.solver.fused = False

    def run_fused():
        pair[0].assign(initial)
        a, b = pair
        for _ in range(steps):
            fused.step(a, b, dt)
            a, b = b, a
        return a

    # Warm-up (kernel compilation, first allocations), and the loss.
    run_fused()
    positions = rollout.forward()
    loss = PositionLoss(positions + 1e-3, frames=[steps])
    rollout.backward(loss)

    # Wall time (best of the repeats) and CPU time (best, the process's: Warp's CPU
    # launches run on the calling thread, so it is the cost without other load's waits).
    t_fused, t_taped, t_back = [], [], []
    c_fused, c_taped, c_back = [], [], []
    clocks = (time.perf_counter, time.process_time)
    for _ in range(repeats):
        t0, c0 = (c() for c in clocks)
        run_fused()
        t1, c1 = (c() for c in clocks)
        rollout.forward()
        t2, c2 = (c() for c in clocks)
        value, grads = rollout.backward(loss)
        t3, c3 = (c() for c in clocks)
        t_fused.append(t1 - t0)
        t_taped.append(t2 - t1)
        t_back.append(t3 - t2)
        c_fused.append(c1 - c0)
        c_taped.append(c2 - c1)
        c_back.append(c3 - c2)
    f, tf, bw = min(t_fused), min(t_taped), min(t_back)
    cf, ctf, cbw = min(c_fused), min(c_taped), min(c_back)
    out = {
        "particles": n,
        "adjoints": ("hand-written" if fused_tape else "hand-written, differentiable taped forward") if hand else "generated",
        "dtype": model.types.np_dtype.__name__,
        "steps": steps,
        "fused_ms_per_step": 1e3 * f / steps,
        "taped_ms_per_step": 1e3 * tf / steps,
        "backward_ms_per_step": 1e3 * bw / steps,
        "taped_over_fused": tf / f,
        "backward_over_fused": bw / f,
        "gradient_over_fused": (tf + bw) / f,
        "cpu_taped_over_fused": ctf / cf,
        "cpu_backward_over_fused": cbw / cf,
        "cpu_gradient_over_fused": (ctf + cbw) / cf,
        "taped_bytes_per_particle_step": state_nbytes(rollout._states[1]) / n,
        "loss": float(value),
        "grads": {k: np.asarray(grads[k]).tolist() for k in MATERIAL_GRADS},
        "grad_v0": grads["v0"],
    }
    if profile:
        with AdjointProfile() as fused_prof:
            run_fused()
        with AdjointProfile() as taped_prof:
            rollout.forward()
        with AdjointProfile() as prof:
            rollout.backward(loss)
        for key, p in (("fused_launch_ms_per_step", fused_prof), ("taped_launch_ms_per_step", taped_prof),
                       ("adjoint_ms_per_step", prof)):
            out[key] = {k: 1e3 * s / steps for k, s in sorted(p.seconds.items(), key=lambda kv: -kv[1])}
    return out


@contextlib.contextmanager
def _without_step_memos(off: bool):
    """Inside (where ``off``), the step as before its two memos (docs/performance.md, "The
    step's Python at the fit example's size"): the step's bookkeeping clears the state's check
    (``State.BOOKKEEPING``), and the parameter rows' answers are computed at every question
    (``Model._answer``)."""
    from warp_esph.model import Model, State  # noqa: PLC0415

    kept = State.BOOKKEEPING, Model._answer
    if off:
        State.BOOKKEEPING = frozenset(("time",))
        Model._answer = lambda self, question, answer: answer(self._read_parameters())
    try:
        yield
    finally:
        State.BOOKKEEPING, Model._answer = kept


@contextlib.contextmanager
def _without_kept_records(off: bool):
    """Inside (where ``off``), a taped step keeps no records of its launches with its
    ``state_out`` (docs/performance.md, "Kept records of a taped step's launches"): its
    launches share the replay's few slots per kernel, as before."""
    kept = Solver.step
    if off:
        Solver.step = Solver._step
    try:
        yield
    finally:
        Solver.step = kept


def step_memos(model, steps: int, blocks: int) -> dict:
    """The fused forward, taped forward and backward of ``model`` with the step's memos off and
    on (``_without_step_memos``) in ``blocks`` alternating blocks each: CPU ms a step, best
    block, the ratio of the best blocks and the median of the paired blocks' ratios, and
    whether both gave the same bits."""
    return paired(model, steps, blocks, _without_step_memos)


def kept_records(model, steps: int, blocks: int) -> dict:
    """As ``step_memos``, with a taped step's kept launch records off and on
    (``_without_kept_records``)."""
    return paired(model, steps, blocks, _without_kept_records)


def paired(model, steps: int, blocks: int, without) -> dict:
    """The fused forward, taped forward and backward of ``model`` with what ``without(True)``
    turns off off and on, in ``blocks`` alternating blocks each (see ``step_memos``)."""
    dt = 1.0 / 30.0 / 40.0
    frames = sorted({max(1, steps // 3), steps})
    rollout = Rollout(model, steps, dt, frames=frames)
    loss = PositionLoss(rollout.forward() + 0.001, frames=frames)
    solver = Solver(model)
    pair = [model.state(), model.state()]
    times = {k: {False: [], True: []} for k in ("fused", "taped", "backward")}
    got = {}
    for b in range(blocks + 1):  # the first, untimed: the launches' first recordings
        for on in ((False, True) if b % 2 == 0 else (True, False)):
            with without(not on):
                t0 = time.thread_time()
                for k in range(steps):
                    solver.step(pair[k % 2], pair[(k + 1) % 2], dt)
                t1 = time.thread_time()
                positions = rollout.forward()
                t2 = time.thread_time()
                value, grads = rollout.backward(loss)
                t3 = time.thread_time()
            for k, t in (("fused", t1 - t0), ("taped", t2 - t1), ("backward", t3 - t2)):
                if b > 0:
                    times[k][on].append(t)
            got[on] = (positions, value, grads)
    times["gradient"] = {on: [a + b for a, b in zip(times["taped"][on], times["backward"][on])] for on in (False, True)}
    out = {}
    for k, t in times.items():
        off, on = np.array(t[False]), np.array(t[True])
        out[k] = {"off_ms": 1e3 * off.min() / steps, "on_ms": 1e3 * on.min() / steps, "best_ratio": on.min() / off.min(),
                  "median_ratio": float(np.median(on / off))}
    (p0, v0, g0), (p1, v1, g1) = got[False], got[True]
    out["same_bits"] = bool(np.array_equal(p0, p1) and v0 == v1 and all(np.array_equal(g0[k], g1[k]) for k in g0))
    return out


def report(r: dict, profile: bool):
    print(f"{r['scene']:>6} {r['dtype']} ({r['adjoints']} adjoints): {r['particles']} particles, {r['steps']} steps, "
          f"fused {r['fused_ms_per_step']:.2f} ms/step; taped {r['taped_over_fused']:.2f}x, "
          f"backward {r['backward_over_fused']:.2f}x, gradient {r['gradient_over_fused']:.2f}x the fused forward "
          f"(CPU time: {r['cpu_taped_over_fused']:.2f}x, {r['cpu_backward_over_fused']:.2f}x, "
          f"{r['cpu_gradient_over_fused']:.2f}x); {r['taped_bytes_per_particle_step']:.0f} B per particle per taped step",
          flush=True)
    if profile:
        for key, label in (("fused_launch_ms_per_step", "fused"), ("taped_launch_ms_per_step", "taped"),
                           ("adjoint_ms_per_step", "backward")):
            print(f"    {label} launches, ms/step: " + ", ".join(f"{k} {v:.2f}" for k, v in r[key].items() if v > 0.005))


def _sizes(text, name):
    """A comma-separated list of block particle counts (integers >= 1) and 'star': the entries as text."""
    parts = [p.strip() for p in str(text).split(",")]
    for part in parts:
        if part == "star":
            continue
        try:
            ok = int(part) >= 1
        except ValueError:
            ok = False
        if not ok:
            raise _cli.refuse(name, text, "must be a comma-separated list of particle counts (integers >= 1) or "
                                          f"'star' ({part!r} is not one)")
    return parts


PROG = "python -m benchmarks.gradient_bench"


def main(argv=None) -> int:
    ap = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="10000,star", type=_cli.Check(_sizes),
                    help="comma-separated: particle counts of a block, or 'star'")
    ap.add_argument("--dtypes", default="float32,float64", type=_cli.choice_list(("float32", "float64")))
    ap.add_argument("--steps", type=_cli.positive_int, default=20)
    ap.add_argument("--star-steps", type=_cli.positive_int, default=150,
                    help="steps of the star (it must reach the ground for the material to matter)")
    ap.add_argument("--repeats", type=_cli.positive_int, default=3)
    ap.add_argument("--profile", action="store_true", help="time each kernel's adjoint launch")
    ap.add_argument("--generated", action="store_true",
                    help="also time the rollout with Warp's generated adjoints only (Solver.hand_adjoints = False)")
    ap.add_argument("--differentiable", action="store_true",
                    help="also time the rollout with the taped forward on the differentiable kernels (Solver.fused = "
                         "False; hand-written adjoints where they exist for them)")
    ap.add_argument("--step-memos", type=_cli.positive_int, default=None, metavar="BLOCKS",
                    help="only time the star (--star-steps) with the step's two memos off and on in BLOCKS alternating "
                         "blocks each (docs/performance.md)")
    ap.add_argument("--kept-records", type=_cli.positive_int, default=None, metavar="BLOCKS",
                    help="only time the star (--star-steps) with a taped step's kept launch records off and on in "
                         "BLOCKS alternating blocks each (docs/performance.md)")
    ap.add_argument("--json", default=None, type=_cli.output_file, help="write the results here")
    a = ap.parse_args(argv)
    from warp_esph.startup import init_warp  # noqa: PLC0415 (log_level, no native CUDA note)

    init_warp()
    rows = []
    for what, blocks, run in (("memos", a.step_memos, step_memos), ("kept records", a.kept_records, kept_records)):
        if blocks is None:
            continue
        for name in a.dtypes:
            r = run(star_model(getattr(wp, name)), a.star_steps, blocks)
            print(f"  star {name}, {a.star_steps} steps, {what} off -> on, CPU ms a step (best of {blocks} blocks; "
                  f"ratio of the best, median of the paired ratios): " + "; ".join(
                      f"{k} {v['off_ms']:.3f} -> {v['on_ms']:.3f} ({v['best_ratio']:.3f}, {v['median_ratio']:.3f})"
                      for k, v in r.items() if k != "same_bits") + f"; same bits: {r['same_bits']}", flush=True)
            rows.append({"scene": "star", "dtype": name, "steps": a.star_steps, run.__name__: r})
    if a.step_memos is not None or a.kept_records is not None:
        if a.json:
            with open(a.json, "w") as f:
                json.dump(rows, f, indent=2)
        return 0
    for size in a.sizes:
        by_dtype = {}
        for name in a.dtypes:
            dtype = getattr(wp, name)
            model = star_model(dtype) if size == "star" else block_model(int(size), dtype)
            steps = a.star_steps if size == "star" else a.steps
            runs = [measure(model, steps, a.repeats, a.profile, hand=True)]
            if a.differentiable:
                runs.append(measure(model, steps, a.repeats, a.profile, hand=True, fused_tape=False))
            if a.generated:
                runs.append(measure(model, steps, a.repeats, a.profile, hand=False))
            for r in runs[1:]:
                r["scene"] = size
                report(r, a.profile)
                r.pop("grad_v0")
                rows.append(r)
            r = runs[0]
            r["scene"] = size
            by_dtype[name] = r
            report(r, a.profile)
        if "float32" in by_dtype and "float64" in by_dtype:
            g32, g64 = by_dtype["float32"], by_dtype["float64"]
            err = material_gradient_errors(g32, g64, {k: [getattr(m, k) for m in model.materials] for k in MATERIAL_GRADS})
            ref = g64["grad_v0"]
            err["v0"] = float(np.linalg.norm(g32["grad_v0"] - ref) / max(np.linalg.norm(ref), 1e-300))
            g32["float32_relative_error"] = err
            print("    float32 gradient vs float64 (material p: max|p (g32 - g64)| / max(max|p g64|, 1e-6 L64); v0: L2 "
                  "relative): " + ", ".join(f"{k} {v:.1e}" for k, v in err.items()))
        for r in by_dtype.values():
            r.pop("grad_v0")
            rows.append(r)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(_cli.run(main, PROG))
