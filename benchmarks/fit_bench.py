"""Differentiable rollout benchmark: time per step and memory, full tape vs checkpointing.

For a block of dough falling onto the ground (float64, one material, SPH on), for each
particle count and step count, with the whole run on one tape and with segment
checkpointing (``checkpoint_every = ceil(sqrt(steps))`` by default), it measures

- forward seconds per step (taped, or untaped with checkpoints),
- backward seconds per step (the checkpointed backward re-runs each segment on a tape),
- memory: bytes held by the rollout's Warp arrays (taped states with gradients,
  checkpoints, frame buffers: exact), the peak of Python allocations (``tracemalloc``)
  and the process's peak resident set size so far,
- and checks the two modes give the same gradient.

    python -m benchmarks.fit_bench                          # 250, 1000, 4000 particles x 50, 200 steps
    python -m benchmarks.fit_bench --particles 500 --steps 20 --json out.json
    python -m benchmarks.fit_bench --quick

``--loss-only`` times instead a small fit of the block's yield stress and flow rate (from 2x
off, a global stage of 3 samples, the diagnostics) whose loss-only runs (the global stage,
Gauss-Newton's residual runs, the diagnostics' forward differences) record no tape, against
the same fit with every run taped, as all were before (``fit._Run.tape_values``): the two
alternate in one process, best of ``--repeats`` each, wall-clock and CPU time, for
Gauss-Newton (forward runs only) and L-BFGS (taped gradients; its diagnostics forward only),
and the two histories must be equal (losses, parameters, gradients)::

    python -m benchmarks.fit_bench --loss-only                          # 125, 1000 particles x 40 steps
    python -m benchmarks.fit_bench --loss-only --particles 125 --steps 40 --repeats 5

``--rejected`` times L-BFGS fits of the block (from 2, 0.5, 1.01 and 1.0001 times the
yield stress and flow rate, the diagnostics on) whose rejected line-search trials run their
backward only where the minimum-within test may read it (``fit.LBFGS_TRIAL_BACKWARDS``),
against the same fits with every trial's backward run, as before: alternating, best of
``--repeats``; the fits must be the same to the bit (points, losses, gradients both read,
verdicts, fitted values, Fisher matrix)::

    python -m benchmarks.fit_bench --rejected --repeats 3

With ``--starts K`` (K > 1) each of those fits is a worlds fit of K starts (``worlds=True``,
the starts drawn within ``--sample-range`` of the guess, default 4), whose rounds run no
backward where no start of the round reads its gradient::

    python -m benchmarks.fit_bench --rejected --starts 2 --sample-range 1.0000001 --repeats 3

It prints a table and writes JSON (``--json``, default ``fit_bench.json``). Not a test.
"""

import gc
import json
import math
import os
import platform
import resource
import sys
import time
import tracemalloc

import numpy as np
import warp as wp

try:
    import warp_esph as we
except ImportError:  # run from a checkout without installing the package
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import warp_esph as we

from benchmarks import _cli
from benchmarks.blocks import block_model
from warp_esph import fit as fit_module
from warp_esph.losses import PositionLoss
from warp_esph.rollout import PARAMETERS, Rollout


def _rss_mb() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / 2**20


def measure(model: we.Model, steps: int, checkpoint_every: int | None, repeats: int = 1) -> dict:
    """Times (without tracemalloc, which slows Python down) then memory (with it)."""
    dt = model.stable_dt()
    frames = sorted({steps // 2, steps})
    gc.collect()
    rollout = Rollout(model, steps, dt, frames=frames, checkpoint_every=checkpoint_every)
    positions = rollout.forward()  # warm-up (compiles kernels on the first call)
    loss = PositionLoss(positions + 1e-3, frames=frames)
    rollout.backward(loss)
    fwd, bwd = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        rollout.forward()
        t1 = time.perf_counter()
        _, grads = rollout.backward(loss)
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        bwd.append(t2 - t1)
    mem = rollout.memory_bytes()
    rollout.release()
    del rollout
    gc.collect()

    # Python-side peak of a fresh rollout's forward and backward.
    tracemalloc.start()
    rollout = Rollout(model, steps, dt, frames=frames, checkpoint_every=checkpoint_every)
    rollout.forward()
    rollout.backward(loss)
    _, py_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rollout.release()
    del rollout
    gc.collect()
    return {
        "particles": model.particle_count,
        "steps": steps,
        "checkpoint_every": checkpoint_every,
        "segments": math.ceil(steps / checkpoint_every) if checkpoint_every else 1,
        "forward_ms_per_step": 1e3 * min(fwd) / steps,
        "backward_ms_per_step": 1e3 * min(bwd) / steps,
        "array_bytes": mem,
        "array_bytes_per_particle_step": mem["total"] / (model.particle_count * steps),
        "python_peak_bytes": py_peak,
        "process_peak_rss_mb": _rss_mb(),
        "grad_norms": {k: float(np.linalg.norm(grads[k])) for k in ("mu", "yield_stress", "flow_rate", "v0")},
        "_grads": {k: grads[k] for k in list(PARAMETERS) + ["v0"]},
    }


#: The loss-only benchmark's fit: the fitted values, optimisers, evaluations and global stage.
LOSS_ONLY_PARAMS = ("yield_stress", "flow_rate")
LOSS_ONLY_OPTIMIZERS = ("gauss-newton", "lbfgs")
LOSS_ONLY_ITERATIONS = 12
LOSS_ONLY_SAMPLES = 3


def _guess_model(particles: int, factor: float) -> we.Model:
    """The benchmark block (float64) with its yield stress and flow rate times ``factor``."""
    model = block_model(particles, wp.float64)
    m = model.materials[0]
    model.set_material(0, m.replace(yield_stress=factor * m.yield_stress, flow_rate=factor * m.flow_rate))
    return model


def _timeless(history) -> list[dict]:
    return [{k: v for k, v in h.items() if k != "seconds"} for h in history]


def measure_loss_only(particles: int, steps: int, repeats: int = 3) -> list[dict]:
    """The fit (module doc) with its loss-only runs untaped and, alternating, taped: one row
    per optimiser."""
    truth = _guess_model(particles, 1.0)
    dt = truth.stable_dt()
    frames = sorted({steps // 2, steps})
    loss = PositionLoss(Rollout(truth, steps, dt, frames=frames).forward(), frames=frames)

    def run(tape_values, optimizer):
        model = _guess_model(particles, 2.0)  # fit leaves the model holding its result
        fit_module._Run.tape_values = tape_values
        try:
            gc.collect()
            w0, c0 = time.perf_counter(), time.process_time()
            result = fit_module.fit(model, loss, list(LOSS_ONLY_PARAMS), steps=steps, dt=dt, optimizer=optimizer,
                                    iterations=LOSS_ONLY_ITERATIONS, samples=LOSS_ONLY_SAMPLES, noise=1e-4,
                                    progress=False)
            return result, time.perf_counter() - w0, time.process_time() - c0
        finally:
            fit_module._Run.tape_values = False

    rows = []
    for optimizer in LOSS_ONLY_OPTIMIZERS:
        for tape_values in (True, False):  # warm-up: each path's kernels compiled or loaded
            run(tape_values, optimizer)
        best = {True: (math.inf, math.inf), False: (math.inf, math.inf)}
        results = {}
        for k in range(repeats):
            # Alternating, the order swapped every repeat: the shared machine's load hits both alike.
            for tape_values in ((True, False) if k % 2 == 0 else (False, True)):
                result, wall, cpu = run(tape_values, optimizer)
                results[tape_values] = result
                best[tape_values] = (min(best[tape_values][0], wall), min(best[tape_values][1], cpu))
        old, new = results[True], results[False]
        same = (_timeless(old.history) == _timeless(new.history)
                and all(np.array_equal(old.params[n], new.params[n]) for n in old.params)
                and np.array_equal(old.diagnostics.fisher, new.diagnostics.fisher))
        gradient_runs = sum(1 for h in new.history if h["grad"] is not None)
        # Diagnostics.evaluations counts every run the diagnostics make.
        runs = len(new.history) + new.diagnostics.evaluations
        rows.append({
            "particles": truth.particle_count,
            "steps": steps,
            "optimizer": optimizer,
            "forward_runs": runs,
            "gradient_runs": gradient_runs,
            "loss_only_runs": runs - gradient_runs,
            "taped_wall_s": best[True][0],
            "untaped_wall_s": best[False][0],
            "wall_ratio": best[False][0] / best[True][0],
            "taped_cpu_s": best[True][1],
            "untaped_cpu_s": best[False][1],
            "cpu_ratio": best[False][1] / best[True][1],
            "same_history": bool(same),
            "stopped": new.stopped,
        })
    return rows


def _loss_only_main(a, sizes, step_counts, argv) -> int:
    rows = []
    for n in sizes:
        for steps in step_counts:
            rows += measure_loss_only(n, steps, a.repeats)
    hdr = (f"{'particles':>9} {'steps':>6} {'optimizer':>12} {'runs':>5} {'loss-only':>9} {'taped s':>8} {'untaped s':>9} "
           f"{'wall ratio':>10} {'taped cpu':>9} {'untaped cpu':>11} {'cpu ratio':>9} {'same':>5}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(f"{r['particles']:>9} {r['steps']:>6} {r['optimizer']:>12} {r['forward_runs']:>5} {r['loss_only_runs']:>9} "
              f"{r['taped_wall_s']:>8.3f} {r['untaped_wall_s']:>9.3f} {r['wall_ratio']:>10.3f} {r['taped_cpu_s']:>9.3f} "
              f"{r['untaped_cpu_s']:>11.3f} {r['cpu_ratio']:>9.3f} {str(r['same_history']):>5}")
    _write(a, argv, rows)
    return 0 if all(r["same_history"] for r in rows) else 1


#: The rejected-trials benchmark's starts (factors on the block's yield stress and flow rate)
#: and evaluation cap: starts whose line searches reject trials near and far from the minimum.
REJECTED_FACTORS = (2.0, 0.5, 1.01, 1.0001)
REJECTED_ITERATIONS = 40


def _backward_count(history) -> int:
    return sum(1 for h in history if h.get("grad") is not None)


def _same_fit(old, new) -> bool:
    """The same fit to the bit: each evaluation's point and loss, the gradients both read, the
    fitted values, the verdict and the diagnostics' Fisher matrix."""
    if len(old.history) != len(new.history) or old.stopped != new.stopped:
        return False
    for a, b in zip(old.history, new.history):
        if a["params"] != b["params"] or a["loss"] != b["loss"]:
            return False
        if b["grad"] is not None and a["grad"] != b["grad"]:
            return False
    return (all(np.array_equal(old.params[n], new.params[n]) for n in old.params)
            and np.array_equal(old.diagnostics.fisher, new.diagnostics.fisher))


def measure_rejected(particles: int, steps: int, repeats: int = 3, starts: int = 1, sample_range: float = 4.0) -> list[dict]:
    """L-BFGS fits of the block (``REJECTED_FACTORS`` off, diagnostics on) with every
    line-search trial's backward run (``fit.LBFGS_TRIAL_BACKWARDS = "always"``, as before)
    and, alternating, with a rejected trial's run only where its slope may decide the
    minimum-within test (``"read"``): one row per start, best of ``repeats`` each. ``starts``
    > 1: worlds fits of that many starts within ``sample_range`` of the guess (seed 0), a
    round's backward skipped only where no start of the round reads its gradient."""
    truth = _guess_model(particles, 1.0)
    dt = truth.stable_dt()
    frames = sorted({steps // 2, steps})
    loss = PositionLoss(Rollout(truth, steps, dt, frames=frames).forward(), frames=frames)

    def run(mode, factor):
        model = _guess_model(particles, factor)
        fit_module.LBFGS_TRIAL_BACKWARDS = mode
        try:
            gc.collect()
            w0, c0 = time.perf_counter(), time.process_time()
            many = {"starts": starts, "worlds": True, "sample_range": sample_range} if starts > 1 else {}
            result = fit_module.fit(model, loss, list(LOSS_ONLY_PARAMS), steps=steps, dt=dt, optimizer="lbfgs",
                                    iterations=REJECTED_ITERATIONS, noise=1e-4, progress=False, **many)
            return result, time.perf_counter() - w0, time.process_time() - c0
        finally:
            fit_module.LBFGS_TRIAL_BACKWARDS = "read"

    rows = []
    for factor in REJECTED_FACTORS:
        for mode in ("always", "read"):  # warm-up
            run(mode, factor)
        best = {m: (math.inf, math.inf) for m in ("always", "read")}
        results = {}
        for k in range(repeats):
            for mode in (("always", "read") if k % 2 == 0 else ("read", "always")):
                result, wall, cpu = run(mode, factor)
                results[mode] = result
                best[mode] = (min(best[mode][0], wall), min(best[mode][1], cpu))
        old, new = results["always"], results["read"]
        evaluations = len(new.history)
        rows.append({
            "particles": truth.particle_count, "steps": steps, "factor": factor, "starts": starts,
            "sample_range": sample_range if starts > 1 else None,
            "evaluations": evaluations, "stopped": new.stopped,
            "backwards_before": _backward_count(old.history), "backwards_now": _backward_count(new.history),
            "wall_before_s": best["always"][0], "wall_now_s": best["read"][0],
            "wall_ratio": best["read"][0] / best["always"][0],
            "cpu_before_s": best["always"][1], "cpu_now_s": best["read"][1],
            "cpu_ratio": best["read"][1] / best["always"][1],
            "same_fit": bool(_same_fit(old, new)),
        })
    return rows


def _rejected_main(a, sizes, step_counts, argv) -> int:
    rows = []
    for n in sizes:
        for steps in step_counts:
            rows += measure_rejected(n, steps, a.repeats, a.starts, a.sample_range)
    hdr = (f"{'particles':>9} {'steps':>6} {'start':>7} {'evals':>5} {'bwd before':>10} {'bwd now':>7} {'wall before':>11} "
           f"{'wall now':>8} {'ratio':>6} {'cpu ratio':>9} {'stopped':>10} {'same':>5}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(f"{r['particles']:>9} {r['steps']:>6} {r['factor']:>7g} {r['evaluations']:>5} {r['backwards_before']:>10} "
              f"{r['backwards_now']:>7} {r['wall_before_s']:>11.3f} {r['wall_now_s']:>8.3f} {r['wall_ratio']:>6.3f} "
              f"{r['cpu_ratio']:>9.3f} {r['stopped']:>10} {str(r['same_fit']):>5}")
    _write(a, argv, rows)
    return 0 if all(r["same_fit"] for r in rows) else 1


def _write(a, argv, rows) -> None:
    report = {
        "command": " ".join([os.path.basename(sys.argv[0])] + (argv if argv is not None else sys.argv[1:])),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "python": platform.python_version(),
                    "warp": wp.config.version, "device": "cpu", "dtype": "float64",
                    "load_average": list(os.getloadavg())},
        "rows": rows,
    }
    with open(a.json, "w") as f:
        json.dump(report, f, indent=2)
    print("wrote", a.json)


def _checkpoint(text, name):
    """'sqrt' or a segment length >= 1."""
    if str(text).strip() == "sqrt":
        return "sqrt"
    return _cli.as_int(text, name, 1, "must be 'sqrt' or an integer >= 1")


PROG = "python -m benchmarks.fit_bench"


def main(argv=None) -> int:
    ap = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", default=None, type=_cli.positive_int_list,
                    help="comma-separated particle counts (approximate; default 250,1000,4000)")
    ap.add_argument("--steps", default=None, type=_cli.positive_int_list, help="comma-separated step counts (default 50,200)")
    ap.add_argument("--checkpoint", default=None, type=_cli.Check(_checkpoint),
                    help="segment length for the checkpointed runs: an integer or 'sqrt' (default)")
    ap.add_argument("--loss-only", action="store_true",
                    help="time a small fit's loss-only runs untaped against taped (default 125, 1000 particles x 40 steps)")
    ap.add_argument("--rejected", action="store_true",
                    help="time L-BFGS fits whose rejected line-search trials run their backward only where read, "
                         "against every trial's (default 125 particles x 40 steps)")
    ap.add_argument("--starts", type=_cli.positive_int, default=1,
                    help="with --rejected: worlds fits of this many starts (default 1: single fits)")
    ap.add_argument("--sample-range", type=_cli.number(1.0, lo_open=True), default=None,
                    help="with --starts: the starts' range about the guess (factor; default 4)")
    ap.add_argument("--repeats", type=_cli.positive_int, default=1, help="timed repeats per configuration (the fastest is kept)")
    ap.add_argument("--quick", action="store_true", help="a tiny run: 125 particles, 20 steps (not with --particles, --steps)")
    ap.add_argument("--json", default="fit_bench.json", type=_cli.output_file, help="output JSON path")
    a = ap.parse_args(argv)
    if a.quick:
        for option, value in (("--particles", a.particles), ("--steps", a.steps)):
            if value is not None:
                ap.error(f"{option} is not allowed with --quick (it runs 125 particles, 20 steps)")
    if a.loss_only and a.checkpoint is not None:
        # Its fits run a full tape: a checkpointed rollout's forward is untaped either way.
        ap.error(f"--checkpoint = {a.checkpoint!r} is not allowed with --loss-only (its fits run one full tape each)")
    from warp_esph.startup import init_warp  # noqa: PLC0415 (log_level, no native CUDA note)

    init_warp()
    if a.loss_only and a.rejected:
        ap.error("--loss-only is not allowed with --rejected: each is a benchmark of its own")
    if a.rejected and a.checkpoint is not None:
        ap.error(f"--checkpoint = {a.checkpoint!r} is not allowed with --rejected (its fits run one full tape each)")
    if a.starts > 1 and not a.rejected:
        ap.error(f"--starts = {a.starts} is not allowed without --rejected (the other benchmarks fit one start)")
    if a.sample_range is not None and a.starts == 1:
        ap.error(f"--sample-range = {a.sample_range:g} is not allowed without --starts > 1 (it places the other starts)")
    a.sample_range = 4.0 if a.sample_range is None else a.sample_range
    if a.rejected:
        return _rejected_main(a, [125] if a.quick else (a.particles or [125]), [20] if a.quick else (a.steps or [40]),
                              argv)
    if a.loss_only:
        sizes = [125] if a.quick else (a.particles or [125, 1000])
        step_counts = [20] if a.quick else (a.steps or [40])
        return _loss_only_main(a, sizes, step_counts, argv)
    sizes = [125] if a.quick else (a.particles or [250, 1000, 4000])
    step_counts = [20] if a.quick else (a.steps or [50, 200])
    checkpoint = a.checkpoint or "sqrt"

    rows = []
    for n in sizes:
        model = block_model(n, wp.float64)
        for steps in step_counts:
            seg = math.ceil(math.sqrt(steps)) if checkpoint == "sqrt" else checkpoint
            full = measure(model, steps, None, a.repeats)
            ck = measure(model, steps, seg, a.repeats)
            worst = 0.0
            for k, g in full.pop("_grads").items():
                scale = float(np.abs(g).max())
                if scale > 0:
                    worst = max(worst, float(np.abs(g - ck["_grads"][k]).max()) / scale)
            ck.pop("_grads")
            ck["max_relative_gradient_difference_vs_full_tape"] = worst
            rows += [full, ck]

    hdr = f"{'particles':>9} {'steps':>6} {'mode':>10} {'fwd ms/step':>12} {'bwd ms/step':>12} {'arrays MB':>10} {'B/(p*step)':>11} {'py peak MB':>11}"
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        mode = "full tape" if r["checkpoint_every"] is None else f"ckpt {r['checkpoint_every']}"
        print(f"{r['particles']:>9} {r['steps']:>6} {mode:>10} {r['forward_ms_per_step']:>12.3f} {r['backward_ms_per_step']:>12.3f} "
              f"{r['array_bytes']['total'] / 2**20:>10.1f} {r['array_bytes_per_particle_step']:>11.0f} {r['python_peak_bytes'] / 2**20:>11.2f}")
    diffs = [r["max_relative_gradient_difference_vs_full_tape"] for r in rows if "max_relative_gradient_difference_vs_full_tape" in r]
    print(f"checkpointed vs full-tape gradients: max relative difference {max(diffs):.2e}")
    _write(a, argv, rows)
    return 0


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
