"""Two runs with the same inputs on the CPU give identical output files."""

import hashlib

import warp_esph as we
from warp_esph.scenes import get_scene


def _run(path):
    scene = get_scene("three_cylinders", scale=0.35)
    model = scene.builder.finalize()
    with we.UsdWriter(path, model, scene.fps) as writer:
        we.simulate(model, 3, fps=scene.fps, writer=writer, progress=False)
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_two_runs_write_identical_files(tmp_path):
    assert _run(tmp_path / "a.usda") == _run(tmp_path / "b.usda")
    assert _run(tmp_path / "a.usdc") == _run(tmp_path / "b.usdc")
