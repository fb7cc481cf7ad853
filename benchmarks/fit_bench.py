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
    ap.add_argument("--checkpoint", default="sqrt", type=_cli.Check(_checkpoint),
                    help="segment length for the checkpointed runs: an integer or 'sqrt'")
    ap.add_argument("--repeats", type=_cli.positive_int, default=1, help="timed repeats per configuration (the fastest is kept)")
    ap.add_argument("--quick", action="store_true", help="a tiny run: 125 particles, 20 steps (not with --particles, --steps)")
    ap.add_argument("--json", default="fit_bench.json", type=_cli.output_file, help="output JSON path")
    a = ap.parse_args(argv)
    if a.quick:
        for option, value in (("--particles", a.particles), ("--steps", a.steps)):
            if value is not None:
                ap.error(f"{option} is not allowed with --quick (it runs 125 particles, 20 steps)")
    from warp_esph.startup import init_warp  # noqa: PLC0415 (log_level, no native CUDA note)

    init_warp()
    sizes = [125] if a.quick else (a.particles or [250, 1000, 4000])
    step_counts = [20] if a.quick else (a.steps or [50, 200])

    rows = []
    for n in sizes:
        model = block_model(n, wp.float64)
        for steps in step_counts:
            seg = math.ceil(math.sqrt(steps)) if a.checkpoint == "sqrt" else a.checkpoint
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
    report = {
        "command": " ".join([os.path.basename(sys.argv[0])] + (argv if argv is not None else sys.argv[1:])),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "python": platform.python_version(),
                    "warp": wp.config.version, "device": "cpu", "dtype": "float64"},
        "rows": rows,
    }
    with open(a.json, "w") as f:
        json.dump(report, f, indent=2)
    print("wrote", a.json)
    return 0


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
