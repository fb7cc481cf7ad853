"""SPlisHSPlasH (Bender et al.; ``pip install pysplishsplash``) as a baseline for
``benchmarks.step``: the same drop of an elastic cube on a floor, timed per step.

SPlisHSPlasH's Python module runs one scene per process, so each size runs in its own
subprocess (``python -m benchmarks.splishsplash --side S --dx DX --dt DT --out FILE``) with
``OMP_NUM_THREADS=1``, the single core the paper and the CPU runs of warp_esph use, and
``LD_PRELOAD`` of libGLdispatch, which its import needs on Debian.
"""

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks import _cli

PROG = "python -m benchmarks.splishsplash"
GLDISPATCH = "/lib/x86_64-linux-gnu/libGLdispatch.so.0"

_UNIT_BOX_OBJ = """v -0.5 -0.5 -0.5
v 0.5 -0.5 -0.5
v 0.5 0.5 -0.5
v -0.5 0.5 -0.5
v -0.5 -0.5 0.5
v 0.5 -0.5 0.5
v 0.5 0.5 0.5
v -0.5 0.5 0.5
f 1 3 2
f 1 4 3
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 4 8 7
f 4 7 3
f 1 5 8
f 1 8 4
f 2 3 7
f 2 7 6
"""


def splishsplash_scene(side: int, dx: float, dt: float, workdir: str) -> str:
    """The drop for SPlisHSPlasH: a block of side^3 particles of radius dx/2 (its
    block sampling puts one particle per 2r cell strictly inside the box), E, nu and
    density of the dough, Becker et al. 2009 elasticity, DFSPH pressure, a static floor
    box (volume map). Solver settings as in SPlisHSPlasH's own deformable example
    (data/Scenes/DeformableModel.json): DFSPH max. density error 0.01 %, zero-energy
    mode control alpha = 0.1, standard viscosity 0.01."""
    L = (side + 1) * dx
    bottom = 0.25 * dx
    with open(os.path.join(workdir, "UnitBox.obj"), "w") as fh:
        fh.write(_UNIT_BOX_OBJ)
    floor = max(1.0, 3 * L)
    scene = {
        "Configuration": {
            "timeStepSize": dt, "particleRadius": dx / 2, "numberOfStepsPerRenderUpdate": 1,
            "simulationMethod": 4, "gravitation": [0, -9.81, 0], "cflMethod": 0, "cflFactor": 1,
            "cflMaxTimeStepSize": dt, "boundaryHandlingMethod": 2,
            "enablePartioExport": False, "enableVTKExport": False, "enableRigidBodyExport": False,
            "DFSPH": {"minIterations": 2, "maxIterations": 100, "maxError": 0.01, "maxIterationsV": 100,
                      "maxErrorV": 0.1, "enableDivergenceSolver": True},
        },
        "Materials": [{
            "id": "Fluid", "density0": 1150, "elasticityMethod": 1, "viscosityMethod": 1,
            "Standard viscosity": {"viscosity": 0.01},
            "Becker et al. 2009": {"youngsModulus": 2.0e4, "poissonsRatio": 0.3, "alpha": 0.1},
        }],
        "RigidBodies": [{
            "geometryFile": "UnitBox.obj", "translation": [0, -0.25, 0], "scale": [floor, 0.5, floor],
            "isDynamic": False, "isWall": False, "mapInvert": False, "mapThickness": 0.0, "mapResolution": [20, 10, 20],
        }],
        "FluidBlocks": [{
            "denseMode": 0, "start": [-L / 2, bottom, -L / 2], "end": [L / 2, bottom + L, L / 2],
            "initialVelocity": [0, -1.0, 0],
        }],
    }
    path = os.path.join(workdir, "scene.json")
    with open(path, "w") as fh:
        json.dump(scene, fh, indent=1)
    return path


def worker(args):
    """Runs inside the subprocess: one size, writes its result to ``args.out``."""
    import pysplishsplash as sph  # noqa: PLC0415

    workdir = tempfile.mkdtemp(prefix="sph_bench_")
    scene = splishsplash_scene(args.side, args.dx, args.dt, workdir)
    total = args.warmup + args.steps
    stamps = []
    info = {}

    def on_step():
        stamps.append(time.perf_counter())
        if not info:
            fm = sph.Simulation.getCurrent().getFluidModel(0)
            eb = fm.getElasticityBase()
            info["particles"] = int(fm.numActiveParticles())
            info["elasticity"] = eb.getMethodName() if eb is not None else None

    base = sph.Exec.SimulatorBase()
    base.init(sceneFile=scene, useGui=False, useCache=False, outputDir=os.path.join(workdir, "out"),
              initialPause=False, stopAt=(total + 0.5) * args.dt)
    base.setTimeStepCB(on_step)
    t0 = time.perf_counter()
    base.run()
    wall = time.perf_counter() - t0
    steps = np.diff(np.array(stamps))[max(0, args.warmup - 1):]
    n = info.get("particles", 0)
    result = {
        "particles": n,
        "elasticity": info.get("elasticity"),
        "steps_timed": int(len(steps)),
        "ms_per_step": 1e3 * float(np.mean(steps)),
        "ms_per_step_best_block": 1e3 * float(min(np.mean(b) for b in np.array_split(steps, max(1, min(args.blocks, len(steps)))))),
        "particle_steps_per_second": n / float(np.mean(steps)),
        "run_seconds_including_setup": wall,
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
    }
    result["particle_steps_per_second_best_block"] = n / (result["ms_per_step_best_block"] * 1e-3)
    with open(args.out, "w") as fh:
        json.dump(result, fh)
    shutil.rmtree(workdir, ignore_errors=True)


def bench_splishsplash(sizes: list[int], *, side_of, dx: float, dt: float, warmup: int, steps: int, blocks: int) -> dict:
    """Time SPlisHSPlasH on a block of ``side_of(n)**3`` particles for each ``n`` in ``sizes``,
    one subprocess per size (``OMP_NUM_THREADS=1``); a missing ``pysplishsplash`` gives
    ``{"available": False, "message": ...}`` instead of an error."""
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    if os.path.exists(GLDISPATCH):
        env["LD_PRELOAD"] = (GLDISPATCH + " " + env.get("LD_PRELOAD", "")).strip()
    probe = subprocess.run([sys.executable, "-c", "import pysplishsplash"], env=env, capture_output=True, text=True)
    if probe.returncode != 0:
        msg = probe.stderr.strip().splitlines()[-1] if probe.stderr.strip() else f"exit code {probe.returncode}"
        return {"available": False, "message": f"SPlisHSPlasH skipped: pysplishsplash does not import ({msg}); "
                                               "install it with `pip install pysplishsplash`"}
    out = {"available": True, "threads": 1, "method": "DFSPH + Becker et al. 2009 elasticity", "results": {}}
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for n in sizes:
        with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as fh:
            result_path = fh.name
        cmd = [sys.executable, "-m", "benchmarks.splishsplash", "--side", str(side_of(n)), "--dx", repr(dx),
               "--dt", repr(dt), "--out", result_path, "--warmup", str(warmup), "--steps", str(steps),
               "--blocks", str(blocks)]
        proc = subprocess.run(cmd, env=env, cwd=root, capture_output=True, text=True)
        if proc.returncode != 0 or not os.path.getsize(result_path):
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            out["results"][str(n)] = {"error": f"exit code {proc.returncode}: {' | '.join(tail)}"}
        else:
            with open(result_path) as fh:
                out["results"][str(n)] = json.load(fh)
        os.unlink(result_path)
    return out


def main(argv=None) -> int:
    p = _cli.Parser(prog=PROG, description="One SPlisHSPlasH run (the worker that benchmarks.step starts).")
    p.add_argument("--side", type=_cli.positive_int, required=True, help="particles per edge of the cube")
    p.add_argument("--dx", type=_cli.positive_float, required=True, help="particle spacing (m)")
    p.add_argument("--dt", type=_cli.positive_float, required=True, help="time step (s)")
    p.add_argument("--out", type=_cli.output_file, required=True, help="JSON file for the result")
    p.add_argument("--warmup", type=_cli.nonnegative_int, default=40, help="untimed steps first")
    p.add_argument("--steps", type=_cli.positive_int, default=40, help="timed steps")
    p.add_argument("--blocks", type=_cli.positive_int, default=4, help="the timed steps are split into this many blocks")
    args = p.parse_args(argv)
    try:
        import pysplishsplash  # noqa: F401, PLC0415 (optional: only this worker needs it)
    except ImportError as e:
        p.error(f"the optional package pysplishsplash (SPlisHSPlasH) does not import ({e}); install it with "
                "`pip install pysplishsplash` (it is optional: benchmarks.step skips SPlisHSPlasH without it)")
    worker(args)
    return 0


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
