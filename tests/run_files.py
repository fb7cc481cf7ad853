"""What the command-line, reliability, tool and USD tests share: the small box-on-the-ground
scene file, a run the CLI refuses, reading a run's USD file back from disk, and running a
script in a process of its own."""

import os
import subprocess
import sys

from pxr import Sdf, Usd

from warp_esph.cli import main

_BOX_ON_GROUND = """
[scene]
name = "{name}"
spacing = 0.05
frames = {frames}

[materials.{material}]
preset = "{preset}"
E = {E}
nu = 0.3

[[bodies]]
shape = "box"
material = "{material}"
center = [0.0, 0.15, 0.0]
size = [0.2, 0.15, 0.2]

[[colliders]]
type = "ground"
"""


def box_on_ground(name: str, frames: int, material: str, preset: str, E) -> str:
    """A 0.2 x 0.15 x 0.2 m box of ``preset`` at Young's modulus ``E`` (as written, so a
    test may give '1e400') standing on the ground, at spacing 0.05."""
    return _BOX_ON_GROUND.format(name=name, frames=frames, material=material, preset=preset, E=E)


def refused_run(capsys, scene, out, *extra) -> str:
    """``warp-esph run SCENE -o OUT --no-progress EXTRA`` in this process, which must exit 2;
    its stderr."""
    assert main(["run", str(scene), "-o", str(out), "--no-progress", *extra]) == 2
    return capsys.readouterr().err


def open_fresh(path) -> Usd.Stage:
    """Open ``path`` from disk, bypassing any layer of that name cached in this process."""
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    assert layer is not None, f"pxr cannot open {path}"
    return Usd.Stage.Open(layer)


def frames_in(path, prim="/World/dough") -> list[float]:
    """The time samples of ``prim``'s points in the USD file at ``path``."""
    stage = open_fresh(path)  # kept alive while its prims are used
    return stage.GetPrimAtPath(prim).GetAttribute("points").GetTimeSamples()


def run_script(script, cwd, timeout: float) -> subprocess.CompletedProcess:
    """Run the Python file ``script`` in a process of its own from ``cwd``, with this checkout
    first on its path: what only a process's own end shows (a second signal ending it, workers
    importing their parent's script)."""
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=repo + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, str(script)], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)
