"""Render time of one frame against its particle count: ``python -m benchmarks.render_bench``.

Renders a dough block of about 50k particles and one of about 6k at 800 x 600 in the
same run and prints seconds per frame and their ratio (the z-buffer pass is linear in the
particle count; the collider ray cast is done once per renderer and excluded).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import warp_esph as we
from warp_esph.render import Renderer, RenderOptions
from warp_esph.usd import UsdFrames


def frame_seconds(side: float, workdir: Path, repeats: int = 3) -> tuple[int, float]:
    b = we.SceneBuilder(spacing=0.01)
    b.add_box((0.0, 0.2, 0.0), (side, side, side), we.Material.preset("dough"))
    b.add_ground()
    model = b.finalize()
    path = workdir / f"block_{model.particle_count}.usdc"
    with we.UsdWriter(path, model, 30.0) as writer:
        writer.write_frame(0, model.state())
    data = UsdFrames(path)
    r = Renderer(data, data.frames, RenderOptions(width=800, height=600, supersample=1))
    r.render(0)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        r.render(0)
        best = min(best, time.perf_counter() - t0)
    return model.particle_count, best


def main(argv=None):
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        n_small, t_small = frame_seconds(0.18, Path(tmp))
        n_big, t_big = frame_seconds(0.37, Path(tmp))
    print(f"{n_small} particles: {t_small:.3f} s/frame; {n_big} particles: {t_big:.3f} s/frame; "
          f"ratio {t_big / t_small:.2f} for {n_big / n_small:.2f}x the particles")


if __name__ == "__main__":
    main()
