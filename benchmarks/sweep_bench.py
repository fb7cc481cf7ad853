"""Sweep benchmark: the same ``warp-esph sweep`` on N worker processes against one process.

Each configuration runs as a fresh ``python -m warp_esph sweep ...`` command, timed from
start to exit, so both include what a user waits for: interpreter and Warp start-up,
kernel loading (from the kernel cache), and for N > 1 the spawn of N worker processes.
The two commands alternate (``--repeats`` rounds) and the fastest time of each is kept,
which damps the noise of a shared machine; the load average before and after is
recorded, and so are the CPU seconds of each command with its workers: on a shared
machine the wall-clock ratio depends on the other jobs, while ``workers x CPU(1) /
CPU(N)`` is the speedup the same sweep gets on N free cores. It also checks that both wrote the same table (every column but ``wall_s``).

    python -m benchmarks.sweep_bench                      # 8 samples of dough_drop at scale 0.5 (343 particles), 2 vs 1 workers
    python -m benchmarks.sweep_bench --samples 4 --frames 10 --repeats 1 --json out.json

Prints the ratio (target on 2 cores: >= 1.8) and writes JSON (``--json``, default
``sweep_bench.json``). Not a test.
"""

import csv
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

from benchmarks import _cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PROG = "python -m benchmarks.sweep_bench"


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_sweep(args, workers: int, folder: str) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the command and its worker processes)."""
    cmd = [sys.executable, "-m", "warp_esph", "sweep", args.scene, "--scale", str(args.scale),
           "--param", f"yield_stress=50:5000:log:{args.samples}", "--frames", str(args.frames),
           "--workers", str(workers), "-o", folder, "--no-progress"]
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cpu0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    seconds, cpu = time.perf_counter() - t0, _children_cpu() - cpu0
    if proc.returncode not in (0, 3):
        lines = (proc.stderr or proc.stdout).strip().splitlines()
        _cli.fail(PROG, f"sweep with {workers} workers failed ({proc.returncode}): {lines[-1] if lines else 'no output'}")
    return seconds, cpu


def read_table(folder: str) -> list[dict]:
    with open(os.path.join(folder, "sweep.csv"), newline="") as f:
        return [{k: v for k, v in row.items() if k != "wall_s"} for row in csv.DictReader(f)]


def _scene(text, name):
    """A built-in scene's name or the path of a .toml scene file that exists."""
    from warp_esph.scenes import SCENES  # noqa: PLC0415

    if text in SCENES or (str(text).lower().endswith(".toml") and os.path.isfile(text)):
        return text
    raise _cli.refuse(name, text, f"must be a built-in scene ({', '.join(SCENES)}) or the path of a .toml scene file")


def main(argv=None) -> int:
    p = _cli.Parser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="dough_drop", type=_cli.Check(_scene))
    p.add_argument("--scale", type=_cli.positive_float, default=0.5, help="scene resolution scale (default 0.5: 343 particles of dough_drop)")
    p.add_argument("--samples", type=_cli.positive_int, default=8, help="grid levels of yield_stress (default 8)")
    p.add_argument("--frames", type=_cli.positive_int, default=60, help="frames per sample (default 60)")
    p.add_argument("--workers", type=_cli.positive_int, default=2, help="workers of the parallel run (default 2)")
    p.add_argument("--repeats", type=_cli.positive_int, default=2,
                   help="alternating rounds; the fastest of each is kept (default 2)")
    p.add_argument("--json", default="sweep_bench.json", type=_cli.output_file)
    args = p.parse_args(argv)

    load_before = os.getloadavg()
    times = {1: [], args.workers: []}
    cpus = {1: [], args.workers: []}
    with tempfile.TemporaryDirectory() as tmp:
        folders = {n: os.path.join(tmp, f"w{n}") for n in times}
        for _ in range(args.repeats):
            for n in (args.workers, 1):
                wall, cpu = run_sweep(args, n, folders[n])
                times[n].append(wall)
                cpus[n].append(cpu)
                print(f"{n} worker(s): {wall:.2f} s wall, {cpu:.2f} s CPU", flush=True)
        same = read_table(folders[1]) == read_table(folders[args.workers])
        rows = read_table(folders[1])
    serial, parallel = min(times[1]), min(times[args.workers])
    ratio = serial / parallel
    # On a machine shared with other jobs the wall-clock ratio depends on their load; the
    # CPU seconds do not: N x (CPU of 1 worker / CPU of N) is the speedup N free cores give.
    cpu_ratio = args.workers * min(cpus[1]) / min(cpus[args.workers])
    report = {
        "command": " ".join([os.path.basename(sys.executable), "-m", "benchmarks.sweep_bench", *(argv or sys.argv[1:])]),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_average_before": load_before, "load_average_after": os.getloadavg()},
        "config": {k: v for k, v in vars(args).items() if k != "json"},
        "particles": int(rows[0]["particles"]) if rows else None,
        "steps_per_sample": int(rows[0]["steps"]) if rows else None,
        "seconds": {str(k): v for k, v in times.items()},
        "cpu_seconds": {str(k): v for k, v in cpus.items()},
        "speedup": ratio,
        "speedup_on_free_cores": cpu_ratio,
        "same_table": same,
    }
    with open(args.json, "w") as f:
        json.dump(report, f, indent=2)
    print(f"{args.samples} samples x {report['steps_per_sample']} steps x {report['particles']} particles: "
          f"1 worker {serial:.2f} s, {args.workers} workers {parallel:.2f} s -> {ratio:.2f}x wall "
          f"({cpu_ratio:.2f}x from CPU seconds, i.e. on {args.workers} free cores); same table: {same}; "
          f"load average {load_before[0]:.1f} -> {report['machine']['load_average_after'][0]:.1f} on {os.cpu_count()} cores")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
