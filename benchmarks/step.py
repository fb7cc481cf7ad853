"""Benchmark of the full elastoplastic step, side by side with SPlisHSPlasH and the paper.

    python -m benchmarks.step                                  # CPU (and CUDA if present), 10k/50k/200k
    python -m benchmarks.step --sizes 500 --steps 2 --warmup 1 --no-splishsplash --json out.json
    python -m benchmarks.step --variants --baseline-commit 566e8ac   # each optimisation's effect

Scene: a cube of ``Material.preset("dough")`` (E = 20 kPa, nu = 0.3, yield 150 Pa, SPH
pressure on, viscosity 10 Pa s) on a 1 cm lattice, its bottom layer 0.75 cm above the
ground and falling at 1 m/s (dropped from about 5 cm), float32, dt = 0.5 ms (the explicit
limit of docs/method.md §8 is 0.54 ms). ``--warmup`` steps run first (compilation, the impact
starts), then ``--steps`` are timed: the impact and the start of plastic flow.

For each device and size it reports

* forward particle-steps per second (wall clock; also the process's CPU time, which is
  steadier on a shared machine), the best of ``--blocks`` blocks and their mean;
* the time per phase (``Solver.profile_phases``: synchronise around each phase), for the
  default fused step and for the differentiable kernels the step runs under a tape;
* forward + backward: a taped window of ``--taped-steps`` steps with one ``State`` per
  step, a loss on the last positions, ``tape.backward``;
* memory per particle: the array bytes of the Model, two States and the Solver (plus the
  hash grid's estimate), and of one taped State (with its gradients);

then SPlisHSPlasH (``pip install pysplishsplash``) on the same particle counts and dt: an
elastic cube (Becker et al. 2009 elasticity, DFSPH pressure) dropped on a floor, run by
``benchmarks/splishsplash.py`` in a subprocess with one thread; and the paper's Table 1
rate. Ratios compare best blocks (on a shared machine the fastest block is the least disturbed estimate of each code's cost; the
means are in the JSON too). Everything also goes to ``--json`` (see docs/performance.md).
"""

import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks import _cli
from benchmarks.splishsplash import bench_splishsplash

PROG = "python -m benchmarks.step"

#: Paper (Gerszewski et al. 2009, Table 1; one core of a 2008 Xeon), assuming 30 frames/s.
PAPER = {
    "fig1": {"particles": 52316, "dt": 5.0e-4, "seconds_per_frame": 96.5},
    "fig5": {"particles": 665, "dt": 1.0e-4, "seconds_per_frame": 4.8},
    "fps": 30.0,
}
for _fig in ("fig1", "fig5"):
    _p = PAPER[_fig]
    _p["particle_steps_per_second"] = _p["particles"] * (1.0 / PAPER["fps"] / _p["dt"]) / _p["seconds_per_frame"]
PAPER_RATES = (PAPER["fig1"]["particle_steps_per_second"], PAPER["fig5"]["particle_steps_per_second"])

DX = 0.01
DT = 5.0e-4


def _sizes(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        part = part.strip().lower()
        if not part:
            continue
        scale = 1
        if part.endswith("k"):
            part, scale = part[:-1], 1000
        elif part.endswith("m"):
            part, scale = part[:-1], 1_000_000
        out.append(int(float(part) * scale))
    return out


def _size_list(text, name):
    """``text`` if ``_sizes`` reads it as one or more particle counts >= 1."""
    what = "must be a comma-separated list of particle counts >= 1 (as 500, 10k, 1.5m)"
    try:
        sizes = _sizes(text)
    except (ValueError, OverflowError):
        raise _cli.refuse(name, text, what) from None
    if not sizes or min(sizes) < 1:
        raise _cli.refuse(name, text, what)
    return text


def _device_list(text, name):
    """``text`` if it is 'auto' or a comma list of Warp devices there are here."""
    if text == "auto":
        return text
    names = [d.strip() for d in str(text).split(",") if d.strip()]
    if not names:
        raise _cli.refuse(name, text, "must be 'auto' or a comma list of Warp devices (cpu, cuda:0, ...)")
    for d in names:
        problem = _cli.device_problem(d)
        if problem:
            raise _cli.refuse(name, text, f"{d!r} is not a device here: {problem}")
    return text


def _check_commit(commit: str, name: str) -> None:
    """``ValueError`` unless ``commit`` names a commit of this repository."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    ok = False
    if commit and not commit.startswith("-"):
        try:
            ok = subprocess.run(["git", "-C", root, "rev-parse", "--verify", "--quiet", f"{commit}^{{commit}}"],
                                capture_output=True, text=True).returncode == 0
        except OSError:
            pass
    if not ok:
        raise _cli.refuse(name, commit, f"not a commit of the repository at {root}")


def _fit_weight(text, name):
    """``text`` if it names a fit weight (``smoothing.FIT_WEIGHTS``)."""
    from warp_esph.sim.smoothing import FIT_WEIGHTS  # noqa: PLC0415 (Warp starts later, quietly)

    if text not in FIT_WEIGHTS:
        raise _cli.refuse(name, text, f"must be one of {', '.join(FIT_WEIGHTS)}")
    return text


def box_side(n: int) -> int:
    return max(2, round(n ** (1.0 / 3.0)))


# ------------------------------------------------------------------ warp_esph
def build_model(we, n: int, device, requires_grad: bool = False, elastic_force: str | None = None,
                pressure_force: str | None = None, max_neighbors: int | str | None = None, images: bool | str = False,
                fit_weight: str | None = None):
    """The dough cube dropped on the ground; ``images``: with floor images (friction 0.5, at
    rest over each step), or ``"frictionless"`` (friction 0, moving with their particles)."""
    import warp as wp

    side = box_side(n)
    L = side * DX
    # Options only where given: a baseline commit's builder may not have them.
    options = {k: v for k, v in (("max_neighbors", max_neighbors), ("fit_weight", fit_weight)) if v is not None}
    b = we.SceneBuilder(spacing=DX, **options)
    mat = we.Material.preset("dough")
    if elastic_force is not None:
        mat = mat.replace(elastic_force=elastic_force)
    if pressure_force is not None:
        mat = mat.replace(pressure_force=pressure_force)
    b.add_box((0.0, L / 2 + 0.25 * DX, 0.0), (L, L, L), mat, velocity=(0.0, -1.0, 0.0))
    if images == "frictionless":
        b.add_ground(0.0, friction=0.0, images=True)
    elif images:
        b.add_ground(0.0, friction=0.5, images=True)
    else:
        b.add_ground(0.0, friction=0.5)
    return b.finalize(device=device, dtype=wp.float32, requires_grad=requires_grad)


def _sync(device):
    import warp as wp

    wp.synchronize_device(device)


def _array_bytes(obj, seen: set) -> int:
    import warp as wp

    total = 0
    for value in vars(obj).values():
        if isinstance(value, wp.array) and id(value) not in seen:
            seen.add(id(value))
            total += value.capacity
            if value.grad is not None and id(value.grad) not in seen:
                seen.add(id(value.grad))
                total += value.grad.capacity
    return total


def memory_report(model, states, solver, taped_state) -> dict:
    n = model.particle_count
    seen: set = set()
    model_b = _array_bytes(model, seen)
    states_b = sum(_array_bytes(s, seen) for s in states)
    solver_b = _array_bytes(solver, seen)
    search = getattr(solver, "search", None)
    search_b = _array_bytes(search, seen) if search is not None else 0
    grid_b = 0
    dims = getattr(search, "_grid_dims", None)
    if dims:
        # HashGrid (native): cell starts and ends, and per point its id, cell and key.
        grid_b = 2 * 4 * dims[0] * dims[1] * dims[2] + 16 * n
    taped_b = _array_bytes(taped_state, set())
    forward_total = model_b + states_b + solver_b + search_b + grid_b
    return {
        "model_bytes": model_b,
        "two_states_bytes": states_b,
        "solver_bytes": solver_b + search_b,
        "hash_grid_bytes_estimate": grid_b,
        "forward_bytes_per_particle": forward_total / n,
        "model_and_two_states_bytes_per_particle": (model_b + states_b) / n,
        "taped_state_bytes_per_particle_per_step": taped_b / n,
        "neighbor_candidate_capacity": getattr(search, "capacity", None),
    }


def _loss_kernel():
    import warp as wp

    @wp.kernel(module="unique")
    def position_loss(x: wp.array(dtype=wp.vec3f), w: wp.array(dtype=wp.vec3f), loss: wp.array(dtype=wp.float32)):
        i = wp.tid()
        wp.atomic_add(loss, 0, wp.dot(x[i], w[i]))

    return position_loss


def warmed_states(model, solver, warmup: int) -> list:
    """Two states of ``model`` after ``warmup`` steps, the latest first."""
    states = [model.state(), model.state()]
    for _ in range(warmup):
        solver.step(states[0], states[1], DT)
        states.reverse()
    return states


def time_block(solver, states, k: int, device, dt: float = DT) -> tuple[float, float]:
    """Wall and CPU seconds per step over ``k`` steps of ``dt`` from ``states[0]`` (a list,
    left holding the latest state first)."""
    a, b = states
    _sync(device)
    t0, c0 = time.perf_counter(), time.thread_time()
    for _ in range(k):
        solver.step(a, b, dt)
        a, b = b, a
    _sync(device)
    states[0], states[1] = a, b
    return (time.perf_counter() - t0) / k, (time.thread_time() - c0) / k


def time_interleaved(prepared, device, args):
    """``args.steps`` steps of every ``(name, solver, states, times)`` in ``args.blocks``
    blocks, interleaved so a load change on a shared machine hits every variant; each
    block's ``time_block`` is appended to its ``times``."""
    per_block = max(1, args.steps // args.blocks)
    for _ in range(args.blocks):
        for _name, solver, states, times in prepared:
            times.append(time_block(solver, states, per_block, device))


def time_forward(solver, states, steps: int, blocks: int, device) -> dict:
    per_block = max(1, steps // blocks)
    walls, cpus = [], []
    done = 0
    while done < steps:
        k = min(per_block, steps - done)
        wall, cpu = time_block(solver, states, k, device)
        walls.append(wall)
        cpus.append(cpu)
        done += k
    n = solver.model.particle_count
    mean_wall = float(np.mean(walls))
    return {
        "steps": steps,
        "ms_per_step": 1e3 * mean_wall,
        "ms_per_step_best_block": 1e3 * min(walls),
        "particle_steps_per_second": n / mean_wall,
        "particle_steps_per_second_best_block": n / min(walls),
        "particle_steps_per_second_cpu_time": n / float(np.mean(cpus)) if device.is_cpu else None,
    }


def time_phases(solver, states, steps: int) -> dict:
    a, b = states
    solver.profile_phases(True)
    for _ in range(steps):
        solver.step(a, b, DT)
        a, b = b, a
    times = {k: 1e3 * v / steps for k, v in solver.phase_times.items()}
    solver.profile_phases(False)
    states[0], states[1] = a, b
    return {"ms_per_step": times, "total_ms_per_step": sum(times.values())}


def time_taped(we, n: int, device, source_state, taped_steps: int, repeats: int,
               fit_weight: str | None = None) -> tuple[dict, object]:
    import warp as wp

    model = build_model(we, n, device, requires_grad=True, fit_weight=fit_weight)
    solver = we.Solver(model)
    states = [model.state() for _ in range(taped_steps + 1)]
    for name in we.State.STATE_FIELDS:
        wp.copy(getattr(states[0], name), getattr(source_state, name))
    weights = wp.array(np.random.default_rng(0).normal(size=(model.particle_count, 3)), dtype=wp.vec3f, device=device)
    loss = wp.zeros(1, dtype=wp.float32, device=device, requires_grad=True)
    kernel = _loss_kernel()
    best = None
    for _ in range(repeats):
        loss.zero_()
        tape = wp.Tape()
        _sync(device)
        t0, c0 = time.perf_counter(), time.thread_time()
        with tape:
            for k in range(taped_steps):
                solver.step(states[k], states[k + 1], DT)
            wp.launch(kernel, model.particle_count, [states[-1].x, weights], [loss], device=device)
        _sync(device)
        t1, c1 = time.perf_counter(), time.thread_time()
        tape.backward(loss)
        _sync(device)
        t2, c2 = time.perf_counter(), time.thread_time()
        grad_ok = bool(np.isfinite(model.mu.grad.numpy()).all() and np.isfinite(states[0].v.grad.numpy()).all())
        tape.zero()
        if best is None or t2 - t0 < best[2] - best[0]:
            best = (t0, t1, t2, grad_ok, c0, c1, c2)
        del tape
    t0, t1, t2, grad_ok, c0, c1, c2 = best
    npart = model.particle_count
    return {
        "taped_steps": taped_steps,
        "fit_weight": model.fit_weight,
        "forward_ms_per_step": 1e3 * (t1 - t0) / taped_steps,
        "backward_ms_per_step": 1e3 * (t2 - t1) / taped_steps,
        # Thread CPU time (Warp's CPU kernels run on the calling thread): steadier than the
        # wall clock on a shared machine, as the forward blocks' CPU-time rates.
        "forward_cpu_ms_per_step": 1e3 * (c1 - c0) / taped_steps,
        "backward_cpu_ms_per_step": 1e3 * (c2 - c1) / taped_steps,
        "particle_steps_per_second": npart * taped_steps / (t2 - t0),
        "gradients_finite": grad_ok,
    }, states[1]


def compile_kernels(we, device, fit_weight: str | None = None) -> float:
    """Loads (or compiles) every module the benchmark runs, on a tiny model, untimed:
    the fused step, the differentiable step, and a taped step with its backward pass."""
    t0 = time.perf_counter()
    for fused in (True, False):
        model = build_model(we, 64, device, fit_weight=fit_weight)
        solver = we.Solver(model, fused=fused)
        a, b = model.state(), model.state()
        solver.step(a, b, DT)
    time_taped(we, 64, device, a, 1, 1, fit_weight=fit_weight)
    _sync(device)
    return time.perf_counter() - t0


def bench_warp_esph(we, n: int, device, args) -> dict:
    weight = getattr(args, "fit_weight", None)
    model = build_model(we, n, device, fit_weight=weight)
    solver = we.Solver(model)
    t0 = time.perf_counter()
    states = warmed_states(model, solver, args.warmup)
    _sync(device)
    warm_s = time.perf_counter() - t0
    solver.search.rebuilds = solver.search.updates = 0
    forward = time_forward(solver, states, args.steps, args.blocks, device)
    forward["neighbor_rebuilds"] = solver.search.rebuilds
    forward["neighbor_updates"] = solver.search.updates
    phases = time_phases(solver, states, args.phase_steps)
    unfused = we.Solver(model, fused=False)
    phases_diff = time_phases(unfused, states, args.phase_steps)
    taped, taped_state = time_taped(we, n, device, states[0], args.taped_steps, args.taped_repeats, fit_weight=weight)
    memory = memory_report(model, states, solver, taped_state)
    x = states[0].x.numpy()
    return {
        "particles": model.particle_count,
        "fit_weight": model.fit_weight,
        "box_side": box_side(n),
        "warmup_steps": args.warmup,
        "warmup_seconds": warm_s,
        "forward": forward,
        "phases_fused": phases,
        "phases_differentiable": phases_diff,
        "forward_backward": taped,
        "memory": memory,
        "guard_counts": solver.guard_counts(),
        "finite": bool(np.isfinite(x).all()),
        "lowest_particle_y": float(x[:, 1].min()),
    }


def variant_rates(n: int, device, args, baseline=None) -> dict:
    """Forward rate of each optimisation switched off and on, in one run."""
    import warp_esph as we

    configs = [
        ("differentiable kernels, fresh search", dict(fused=False, neighbor_skin=0.0)),
        ("differentiable kernels, skin", dict(fused=False)),
        ("fused, fresh search", dict(neighbor_skin=0.0)),
        ("fused, skin (default)", dict()),
    ]
    runs = []
    if baseline is not None:
        runs.append((f"baseline {args.baseline_commit}", baseline, {}))
    runs += [(name, we, kw) for name, kw in configs]
    prepared = []
    for name, mod, kw in runs:
        model = build_model(mod, n, device)
        solver = mod.Solver(model, **kw)
        prepared.append((name, solver, warmed_states(model, solver, args.warmup), []))
    time_interleaved(prepared, device, args)
    out = {}
    ref = None
    for name, solver, states, times in prepared:
        wall = min(t for t, _ in times)
        cpu = min(c for _, c in times)
        rate = solver.model.particle_count / wall
        rate_cpu = solver.model.particle_count / cpu
        ref = ref or (rate, rate_cpu)
        out[name] = {
            "particle_steps_per_second_best_block": rate,
            "particle_steps_per_second_cpu_time_best_block": rate_cpu,
            "speedup_vs_first": rate / ref[0],
            "speedup_vs_first_cpu_time": rate_cpu / ref[1],
        }
    return out


def elastic_force_rates(n: int, device, args) -> dict:
    """Forward rate of the dough with each elastic force (the default variational one and
    the paper's eqs. 10-13), blocks interleaved in one run; ratios against the paper's."""
    return _interleaved_rates(n, device, args, "elastic_force", ("paper", "variational"))


def pressure_force_rates(n: int, device, args) -> dict:
    """Forward rate of the dough with each SPH pressure force (the paper's spiky one and
    the energy force, the default, each at its default ``k_p``), blocks interleaved in one
    run; ratios against the spiky one."""
    return _interleaved_rates(n, device, args, "pressure_force", ("spiky", "energy"))


def ground_image_rates(n: int, device, args) -> dict:
    """Forward rate of the dough on the plain ground, on the ground with floor images
    (``add_ground(images=True)``: the bottom layers' fits, energy and densities take the
    images in, docs/physics.md) and on the frictionless imaged ground (friction 0: the images
    move with their particles), blocks interleaved in one run; the ratios against the plain."""
    return _interleaved_rates(n, device, args, "images",
                              (("plain", False), ("images", True), ("frictionless_images", "frictionless")))


def fit_weight_rates(n: int, device, args) -> dict:
    """Forward rate of the dough with the paper's poly6 fit weight
    (``SceneBuilder(fit_weight="poly6")``) and the biweight (the default), blocks interleaved in one run; the
    ratio biweight / poly6. Then the taped window (forward + backward, ``time_taped``) of
    each from its own warmed state, ``--taped-repeats`` windows alternating between the
    weights (the best of each), so that the cost of a switch to the other weight is
    measured for the gradients too: ``"taped"``, with the ratios ``biweight_over_poly6``."""
    import warp_esph as we

    weights = ("poly6", "biweight")
    out = _interleaved_rates(n, device, args, "fit_weight", weights)
    sources = {}
    for w in weights:
        model = build_model(we, n, device, fit_weight=w)
        sources[w] = warmed_states(model, we.Solver(model), args.warmup)[0]
    best = {}
    for _ in range(args.taped_repeats):
        for w in weights:
            r, _state = time_taped(we, n, device, sources[w], args.taped_steps, 1, fit_weight=w)
            total = r["forward_ms_per_step"] + r["backward_ms_per_step"]
            if w not in best or total < best[w]["forward_ms_per_step"] + best[w]["backward_ms_per_step"]:
                best[w] = r
    taped = dict(best)
    taped["biweight_over_poly6"] = {k: best["biweight"][k] / best["poly6"][k]
                                    for k in ("forward_ms_per_step", "backward_ms_per_step", "particle_steps_per_second",
                                              "forward_cpu_ms_per_step", "backward_cpu_ms_per_step")}
    out["taped"] = taped
    return out


def _interleaved_rates(n: int, device, args, field: str, choices) -> dict:
    """Forward rates of the dough with ``build_model(field=choice)`` (a Material field, the
    ground's ``images`` or the builder's ``fit_weight``) for each choice (a value, or a pair ``(label, value)``), the
    timed blocks interleaved so that a drifting machine load affects each alike; the ratios
    ``"<choice>_over_<first>"`` of every other choice."""
    import warp_esph as we

    prepared = []
    choices = [c if isinstance(c, tuple) else (c, c) for c in choices]
    for choice, value in choices:
        model = build_model(we, n, device, **{field: value})
        solver = we.Solver(model)
        prepared.append((choice, solver, warmed_states(model, solver, args.warmup), []))
    time_interleaved(prepared, device, args)
    out = {}
    for choice, solver, _states, times in prepared:
        n_p = solver.model.particle_count
        out[choice] = {
            "particle_steps_per_second_best_block": n_p / min(t for t, _ in times),
            "particle_steps_per_second_mean": n_p / float(np.mean([t for t, _ in times])),
            "particle_steps_per_second_cpu_time_best_block": n_p / min(c for _, c in times),
        }
    first = choices[0][0]
    for other, _value in choices[1:]:
        for key in ("particle_steps_per_second_best_block", "particle_steps_per_second_mean",
                    "particle_steps_per_second_cpu_time_best_block"):
            out.setdefault(f"{other}_over_{first}", {})[key] = out[other][key] / out[first][key]
    return out


#: The sides of ``baseline_rates``: label, which package (None: this one, else a baseline's
#: commit), and the ``build_model`` options. A side whose package lacks an option (the paper's
#: 30-wide rows or the pressure force at an old commit, which had only those) is left out.
BASELINE_SIDES = (
    ("{c} default", "baseline", {}),
    ("{c} variational", "baseline", {"elastic_force": "variational"}),
    ("this tree, default", None, {}),
    ("this tree, paper force, spiky pressure", None, {"elastic_force": "paper", "pressure_force": "spiky"}),
    ("this tree, paper force, spiky pressure, 30-wide rows", None,
     {"elastic_force": "paper", "pressure_force": "spiky", "max_neighbors": "paper"}),
    ("this tree, variational, spiky pressure, 30-wide rows", None,
     {"pressure_force": "spiky", "max_neighbors": "paper"}),
)


def _supports(mod, options: dict) -> bool:
    fields = getattr(mod.Material, "__dataclass_fields__", {})
    if "pressure_force" in options and "pressure_force" not in fields:
        return False
    if options.get("max_neighbors") is not None:
        import inspect

        return "max_neighbors" in inspect.signature(mod.SceneBuilder).parameters
    return True


def baseline_rates(n: int, device, args, commits) -> dict:
    """This tree's default step against each baseline commit's default (what a user sees),
    and like for like (the same elastic force, pressure force and row width where a side
    offers them): ``BASELINE_SIDES``, the timed blocks interleaved over all sides, so that a
    drifting machine load hits each alike. Per side: thread CPU time per step (Warp's CPU
    kernels run on the calling thread; on a shared machine wall clock mostly measures the
    other jobs), best block and median, and the rate ratios against the first commit's
    default."""
    import warp_esph as we

    mods = {c: load_baseline(c) for c in commits}
    sides = []
    for label, which, options in BASELINE_SIDES:
        for c in (commits if which == "baseline" else [None]):
            mod = we if c is None else mods[c]
            if options.get("elastic_force") == mod.Material.preset("dough").elastic_force and c is not None:
                continue  # the commit's default already
            if _supports(mod, options):
                sides.append((label.format(c=c), mod, options))
    prepared = []
    for name, mod, options in sides:
        model = build_model(mod, n, device, **options)
        solver = mod.Solver(model)
        prepared.append((name, solver, warmed_states(model, solver, args.warmup), []))
    time_interleaved(prepared, device, args)
    out = {}
    ref = None
    for name, solver, _states, times in prepared:
        cpu = [c for _, c in times]
        wall = [w for w, _ in times]
        r = {"particles": solver.model.particle_count,
             "cpu_ms_per_step_best_block": 1e3 * min(cpu), "cpu_ms_per_step_median": 1e3 * float(np.median(cpu)),
             "wall_ms_per_step_best_block": 1e3 * min(wall), "wall_ms_per_step_median": 1e3 * float(np.median(wall))}
        if hasattr(solver, "guard_counts"):
            r["neighbors_cut"] = solver.guard_counts().get("neighbors_cut")
        ref = ref or r
        for k in ("cpu_ms_per_step_best_block", "cpu_ms_per_step_median"):
            r["rate_ratio_" + k.replace("_ms_per_step", "")] = ref[k] / r[k]
        out[name] = r
    return out


def compare_with_cpu(we, device, n: int = 4000, steps: int = 20) -> dict:
    """The same run on ``device`` and on the CPU: neighbour rows and trajectories agree."""
    out = {}
    runs = {}
    for dev in ("cpu", device):
        model = build_model(we, n, dev)
        solver = we.Solver(model)
        a, b = model.state(), model.state()
        rows = []
        for _ in range(steps):
            solver.step(a, b, DT)
            rows.append((b.neighbors.numpy(), b.neighbor_count.numpy(), b.x.numpy()))
            a, b = b, a
        runs[str(dev)] = (model, a, rows)
    (m0, a0, r0), (_, a1, r1) = runs["cpu"], runs[str(device)]
    same_rows, same_sets, nearest_differing = [], [], math.inf
    h = float(m0.support_radius)
    for (n0, c0, x), (n1, c1, _) in zip(r0, r1):
        mask = np.arange(n0.shape[1])[None, :] < c0[:, None]
        same = (c0 == c1) & np.all(np.where(mask, n0 == n1, True), axis=1)
        same_rows.append(float(same.mean()))
        # Rows that differ: in order only, or in members? A member in one row and not the
        # other matters only if it carries weight, i.e. if it is well inside the support radius.
        sets = 0
        for i in np.flatnonzero(~same):
            a, b = set(n0[i, :c0[i]].tolist()), set(n1[i, :c1[i]].tolist())
            if a == b:
                sets += 1
                continue
            d = np.linalg.norm(x[list(a ^ b)] - x[i], axis=1).min() / h
            nearest_differing = min(nearest_differing, float(d))
        same_sets.append(float(same.mean()) + sets / len(same))
    x0, x1 = a0.x.numpy(), a1.x.numpy()
    disp = np.abs(x0 - m0.particle_x0).max()
    out = {
        "particles": m0.particle_count,
        "steps": steps,
        "fraction_identical_neighbor_rows_min_over_steps": min(same_rows),
        "fraction_same_neighbor_sets_min_over_steps": min(same_sets),
        # Of the neighbours in one device's row and not the other's, the nearest (CPU
        # positions), in support radii; inf where every row holds the same members.
        "nearest_differing_neighbor_over_h": nearest_differing,
        "max_position_difference": float(np.abs(x0 - x1).max()),
        "max_displacement": float(disp),
        "finite": bool(np.isfinite(x1).all()),
    }
    return out


def load_baseline(commit: str):
    """The warp_esph package of a git commit, importable as ``warp_esph_<commit>`` (one name
    per commit, so several baselines load beside this package and each other)."""
    import importlib

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sha = subprocess.run(["git", "-C", root, "rev-parse", "--short=7", commit], capture_output=True, check=True,
                         text=True).stdout.strip()
    name = f"warp_esph_{sha}"
    if name in sys.modules:
        return sys.modules[name]
    tmp = tempfile.mkdtemp(prefix="warp_esph_baseline_")
    archive = subprocess.run(["git", "-C", root, "archive", commit, "warp_esph"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
    os.rename(os.path.join(tmp, "warp_esph"), os.path.join(tmp, name))
    sys.path.insert(0, tmp)
    return importlib.import_module(name)


# ---------------------------------------------------------------------- main
def machine_info() -> dict:
    import warp as wp

    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    info = {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "warp": wp.config.version,
        "numpy": np.__version__,
        "load_average_at_start": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "cuda_devices": [str(wp.get_device(f"cuda:{k}").name) for k in range(wp.get_cuda_device_count())],
    }
    return info


def _fmt_rate(r):
    if r is None:
        return "-"
    return f"{r / 1e6:.2f} M" if r >= 1e6 else f"{r / 1e3:.0f} k"


def print_report(report: dict):
    print()
    print(f"machine: {report['machine']['cpu']} ({report['machine']['cpu_count']} cores), "
          f"warp {report['machine']['warp']}, python {report['machine']['python']}")
    sph = report.get("splishsplash", {})
    for dev, per_size in report["warp_esph"].items():
        if not per_size:
            continue
        print(f"\n== warp_esph on {dev}: particle-steps/s (dt {DT * 1e3:g} ms, float32, dough, pressure on)")
        print(f"{'particles':>10} {'best blk':>10} {'mean':>10} {'cpu-time':>10} {'fwd+bwd':>10} "
              f"{'B/particle':>11} {'B/p/taped':>10} {'rebuilds':>9}")
        for key, r in per_size.items():
            f, t, m = r["forward"], r["forward_backward"], r["memory"]
            print(f"{r['particles']:>10} {_fmt_rate(f['particle_steps_per_second_best_block']):>10} "
                  f"{_fmt_rate(f['particle_steps_per_second']):>10} "
                  f"{_fmt_rate(f['particle_steps_per_second_cpu_time']):>10} {_fmt_rate(t['particle_steps_per_second']):>10} "
                  f"{m['forward_bytes_per_particle']:>11.0f} {m['taped_state_bytes_per_particle_per_step']:>10.0f} "
                  f"{f['neighbor_rebuilds']:>4}/{f['neighbor_updates']:<4}")
        print("   phases, ms per step (fused step | differentiable kernels):")
        for key, r in per_size.items():
            pf = ", ".join(f"{k} {v:.2f}" for k, v in r["phases_fused"]["ms_per_step"].items())
            pd = ", ".join(f"{k} {v:.2f}" for k, v in r["phases_differentiable"]["ms_per_step"].items())
            print(f"   {r['particles']:>8}: {pf} | {pd}")
        sizes = list(per_size)
        if len(sizes) > 1:
            base_key = sizes[0]
            base = per_size[base_key]
            c0 = base["forward"]["ms_per_step_best_block"] / base["particles"]
            growth = ", ".join(
                f"{per_size[k]['particles']}: x{(per_size[k]['forward']['ms_per_step_best_block'] / per_size[k]['particles']) / c0:.2f}"
                for k in sizes[1:]
            )
            print(f"   cost per particle-step (best block) relative to {base['particles']}: {growth}")
    if report.get("ratios"):
        print("\n== ratios (forward, wall clock, best block of each)")
        for dev, rows in report["ratios"].items():
            for key, r in rows.items():
                vs_sph = f"x{r['vs_splishsplash']:.2f}" if r.get("vs_splishsplash") else "-"
                print(f"   {dev} {r['particles']:>8}: vs SPlisHSPlasH {vs_sph:>7} | vs paper "
                      f"x{r['vs_paper_fig1']:.1f} (Fig. 1 rate {PAPER_RATES[0] / 1e3:.1f} k/s), "
                      f"x{r['vs_paper_fig5']:.1f} (Fig. 5 rate {PAPER_RATES[1] / 1e3:.1f} k/s)")
    if sph:
        if not sph.get("available"):
            print("\n" + sph.get("message", "SPlisHSPlasH skipped"))
        else:
            print("\n== SPlisHSPlasH (DFSPH + Becker 2009 elasticity, 1 thread)")
            for key, r in sph["results"].items():
                if "error" in r:
                    print(f"   {key}: {r['error']}")
                else:
                    print(f"   {r['particles']:>8}: {_fmt_rate(r['particle_steps_per_second_best_block'])} particle-steps/s "
                          f"best block ({_fmt_rate(r['particle_steps_per_second'])} mean), {r['ms_per_step']:.1f} ms/step")
    if report.get("variants"):
        print("\n== each optimisation (forward, best block, interleaved; speed-up vs the first row, wall | cpu time)")
        for dev, per_size in report["variants"].items():
            for key, rows in per_size.items():
                print(f"   {dev} {key} particles:")
                for name, r in rows.items():
                    print(f"      {name:40s} {_fmt_rate(r['particle_steps_per_second_best_block']):>9} "
                          f"x{r['speedup_vs_first']:.2f} | x{r['speedup_vs_first_cpu_time']:.2f}")


def main(argv=None):
    p = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="10000,50000,200000", type=_cli.Check(_size_list), help="particle counts on the CPU (cubes of round(n^(1/3))^3)")
    p.add_argument("--cuda-sizes", default="10000,50000,200000,1000000", type=_cli.Check(_size_list), help="particle counts on CUDA devices")
    p.add_argument("--devices", default="auto", type=_cli.Check(_device_list), help="'auto' (cpu, and cuda:0 if present) or a comma list")
    p.add_argument("--steps", type=_cli.positive_int, default=40, help="timed forward steps")
    p.add_argument("--warmup", type=_cli.nonnegative_int, default=40, help="untimed steps first (compilation, impact)")
    p.add_argument("--blocks", type=_cli.positive_int, default=4, help="the timed steps are split into this many blocks")
    p.add_argument("--phase-steps", type=_cli.positive_int, default=5, help="instrumented steps for the phase split")
    p.add_argument("--taped-steps", type=_cli.positive_int, default=4, help="steps of the taped forward+backward window")
    p.add_argument("--taped-repeats", type=_cli.positive_int, default=2)
    p.add_argument("--no-splishsplash", action="store_true", help="skip SPlisHSPlasH")
    p.add_argument("--splishsplash-sizes", default=None, type=_cli.Check(_size_list), help="particle counts for SPlisHSPlasH (default: --sizes)")
    p.add_argument("--variants", action="store_true", help="also time each optimisation off/on (CPU sizes)")
    p.add_argument("--baseline-commit", default=None, help="with --variants: also time warp_esph at this git commit")
    p.add_argument("--baselines", default=None,
                   help="comma list of git commits: time this tree's default step against each commit's default and "
                        "like for like, blocks interleaved, thread CPU time (CPU sizes)")
    p.add_argument("--comparisons-only", action="store_true",
                   help="skip the full benchmark (phases, taped window, memory) and SPlisHSPlasH; run only the "
                        "comparisons asked for (--variants, --baselines, --elastic-forces, --pressure-forces, "
                        "--ground-images, --fit-weights)")
    p.add_argument("--compare-cpu", action="store_true", help="check a short run on each CUDA device against the CPU")
    p.add_argument("--elastic-forces", action="store_true",
                   help="also time the dough with the variational (default) and the paper's elastic force, interleaved")
    p.add_argument("--ground-images", action="store_true",
                   help="also time the dough on the ground with floor images against the plain ground (interleaved)")
    p.add_argument("--fit-weights", action="store_true",
                   help="also time the dough with the poly6 and the biweight (default) fit weight, interleaved, "
                        "forward and a taped forward + backward window")
    p.add_argument("--fit-weight", default=None, type=_cli.Check(_fit_weight),
                   help="the fit weight of the main benchmark's model (SceneBuilder(fit_weight=); default: the "
                        "builder's default)")
    p.add_argument("--pressure-forces", action="store_true",
                   help="also time the dough with the paper's spiky and the energy (default) SPH pressure force, interleaved")
    p.add_argument("--json", default="benchmark_step.json", type=_cli.output_file, help="where the results go")
    args = p.parse_args(argv)
    for option, commits in (("--baseline-commit", [args.baseline_commit] if args.baseline_commit else []),
                            ("--baselines", [c.strip() for c in (args.baselines or "").split(",") if c.strip()])):
        for commit in commits:
            _check_commit(commit, option)

    import warp as wp

    from warp_esph.startup import init_warp  # noqa: PLC0415 (log_level, no native CUDA note)

    init_warp()
    import warp_esph as we
    from warp_esph.sim.solver import DEFAULT_SKIN

    if args.devices == "auto":
        devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
    else:
        devices = [d.strip() for d in args.devices.split(",") if d.strip()]
    report = {
        "command": " ".join([os.path.basename(sys.executable), "-m", "benchmarks.step"] + (list(argv) if argv is not None else sys.argv[1:])),
        "machine": machine_info(),
        "config": {
            "scene": "dough cube (Material.preset('dough')) dropped on the ground at 1 m/s",
            "spacing": DX, "dt": DT, "dtype": "float32", "steps": args.steps, "warmup": args.warmup,
            "blocks": args.blocks, "taped_steps": args.taped_steps, "fit_weight": args.fit_weight,
            "neighbor_skin": DEFAULT_SKIN,
        },
        "paper": PAPER,
        "warp_esph": {},
    }
    for dev_name in devices:
        device = wp.get_device(dev_name)
        sizes = _sizes(args.sizes if device.is_cpu else args.cuda_sizes)
        report["warp_esph"][dev_name] = {}
        if args.comparisons_only:
            continue
        report.setdefault("compile_seconds", {})[dev_name] = compile_kernels(we, device, args.fit_weight)
        for n in sizes:
            print(f"warp_esph {dev_name} {n} ...", flush=True)
            report["warp_esph"][dev_name][str(n)] = bench_warp_esph(we, n, device, args)
    if args.compare_cpu:
        report["device_vs_cpu"] = {}
        for dev_name in devices:
            if not wp.get_device(dev_name).is_cpu:
                report["device_vs_cpu"][dev_name] = r = compare_with_cpu(we, wp.get_device(dev_name))
                print(f"{dev_name} vs cpu: {r}", flush=True)
    if args.variants:
        baseline = load_baseline(args.baseline_commit) if args.baseline_commit else None
        report["variants"] = {}
        for dev_name in devices:
            device = wp.get_device(dev_name)
            report["variants"][dev_name] = {}
            for n in _sizes(args.sizes if device.is_cpu else args.cuda_sizes):
                print(f"variants {dev_name} {n} ...", flush=True)
                report["variants"][dev_name][str(n)] = variant_rates(n, device, args, baseline)
    if args.baselines:
        commits = [c.strip() for c in args.baselines.split(",") if c.strip()]
        report["baselines"] = {}
        for dev_name in devices:
            device = wp.get_device(dev_name)
            report["baselines"][dev_name] = {}
            for n in _sizes(args.sizes if device.is_cpu else args.cuda_sizes):
                print(f"baselines {dev_name} {n} ...", flush=True)
                rows = report["baselines"][dev_name][str(n)] = baseline_rates(n, device, args, commits)
                for name, r in rows.items():
                    print(f"  {name:55s} CPU ms/step {r['cpu_ms_per_step_best_block']:7.1f} best, "
                          f"{r['cpu_ms_per_step_median']:7.1f} median; rate ratio {r['rate_ratio_cpu_best_block']:.3f} "
                          f"best, {r['rate_ratio_cpu_median']:.3f} median", flush=True)
    # Each choice of one Material field, blocks interleaved (the ratio against its first).
    for flag, key, label, rates, choices in (
            ("elastic_forces", "elastic_forces", "elastic forces", elastic_force_rates, ("paper", "variational")),
            ("pressure_forces", "pressure_forces", "pressure forces", pressure_force_rates, ("spiky", "energy")),
            ("ground_images", "ground_images", "ground images", ground_image_rates,
             ("plain", "images", "frictionless_images")),
            ("fit_weights", "fit_weights", "fit weights", fit_weight_rates, ("poly6", "biweight"))):
        if not getattr(args, flag):
            continue
        report[key] = {}
        ratio = f"{choices[-1]}_over_{choices[0]}"
        for dev_name in devices:
            device = wp.get_device(dev_name)
            report[key][dev_name] = {}
            for n in _sizes(args.sizes if device.is_cpu else args.cuda_sizes):
                print(f"{label} {dev_name} {n} ...", flush=True)
                r = report[key][dev_name][str(n)] = rates(n, device, args)
                print("  " + ", ".join(f"{f}: {r[f]['particle_steps_per_second_best_block'] / 1e3:.0f} k/s best block "
                                       f"({r[f]['particle_steps_per_second_cpu_time_best_block'] / 1e3:.0f} k/s CPU time)"
                                       for f in choices)
                      + "".join(f"; {c} / {choices[0]}: " + ", ".join(f"{v:.3f}" for v in r[f"{c}_over_{choices[0]}"].values())
                                for c in choices[1:]),
                      flush=True)
                if "taped" in r:
                    t = r["taped"]
                    print("  taped: " + ", ".join(f"{f}: {t[f]['forward_ms_per_step']:.1f} ms forward, "
                                                  f"{t[f]['backward_ms_per_step']:.1f} ms backward per step" for f in choices)
                          + f"; {ratio}: " + ", ".join(f"{k} {v:.3f}" for k, v in t[ratio].items()), flush=True)
    if args.no_splishsplash or args.comparisons_only:
        report["splishsplash"] = {"available": False, "message": "SPlisHSPlasH skipped (--no-splishsplash)"}
    else:
        sph_sizes = _sizes(args.splishsplash_sizes or args.sizes)
        print(f"SPlisHSPlasH {sph_sizes} ...", flush=True)
        report["splishsplash"] = bench_splishsplash(sph_sizes, side_of=box_side, dx=DX, dt=DT, warmup=args.warmup,
                                                    steps=args.steps, blocks=args.blocks)
    report["ratios"] = {}
    sph_by_n = {}
    if report["splishsplash"].get("available"):
        for key, r in report["splishsplash"]["results"].items():
            if "error" not in r:
                sph_by_n[int(key)] = r
    for dev_name, per_size in report["warp_esph"].items():
        report["ratios"][dev_name] = {}
        for key, r in per_size.items():
            # Best block against best block: on a shared machine the fastest block is the
            # least disturbed estimate of each code's own cost; the means are in the JSON.
            rate = r["forward"]["particle_steps_per_second_best_block"]
            s = sph_by_n.get(int(key))
            report["ratios"][dev_name][key] = {
                "particles": r["particles"],
                "particle_steps_per_second_best_block": rate,
                "particle_steps_per_second_mean": r["forward"]["particle_steps_per_second"],
                "vs_splishsplash": rate / s["particle_steps_per_second_best_block"] if s else None,
                "vs_splishsplash_means": r["forward"]["particle_steps_per_second"] / s["particle_steps_per_second"] if s else None,
                "splishsplash_particles": s["particles"] if s else None,
                "vs_paper_fig1": rate / PAPER_RATES[0],
                "vs_paper_fig5": rate / PAPER_RATES[1],
            }
    with open(args.json, "w") as fh:
        json.dump(report, fh, indent=1, default=float)
    print_report(report)
    print(f"\nresults: {os.path.abspath(args.json)}")
    return 0


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
