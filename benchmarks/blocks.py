"""The benchmarks' dough block: about ``particles`` particles (2 cm spacing) just above the
ground, falling at 1 m/s (``fit_bench``, ``gradient_bench``, ``worlds_bench``)."""

import numpy as np
import warp_esph as we

DX = 0.02


def block_builder(particles: int) -> we.SceneBuilder:
    """The block (``Material.preset("dough")``) and the ground (friction 0.5)."""
    side = max(2, round(particles ** (1.0 / 3.0)))
    size = side * DX
    b = we.SceneBuilder(spacing=DX)
    b.add_box((0.0, 0.5 * size + 0.01, 0.0), (size, size, size), we.Material.preset("dough"), velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    return b


def block_model(particles: int, dtype) -> we.Model:
    """``block_builder``'s scene with gradients, the lattice jittered by 1e-3 of the spacing
    (seed 0) and the rest density computed from the jittered positions."""
    model = block_builder(particles).finalize(dtype=dtype, requires_grad=True)
    model.particle_x0 += np.random.default_rng(0).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model
