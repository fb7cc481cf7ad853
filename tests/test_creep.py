"""A slumped yield-stress cylinder must come to rest (issue 12; evidence in docs/physics.md, "The slump creep").

Cylinder H0 = 2 R0 = 8 dx of a Bingham-like material (shear yield stress 0.1 rho g H0,
mu = 10 rho g H0, flow rate 200/s, variational force) on a floor with friction 1,
dt = 0.9 Model.stable_dt(). The 1-D static analysis gives h/H0 = S (1 - ln S) = 0.477
(S = sqrt(3/2) Y / (rho g H0)); a pile at rest has a top that no longer sinks.
Before the fix of static friction in ``colliders.respond`` (docs/physics.md, "The slump creep") the top still sank
1.3 % H0/s at 3 s (h/H0 0.417, then 0.409 at 4 s), at a rate proportional to dt; now it stops
(0.046 % H0/s from 2.5 to 3 s, h/H0 0.535, measured at a24ecff; 0.02 % and
0.539 on an older tree: at 8 dx the pile slumps less than the 1-D theory).

Why 2 s, with the biweight fit weight named (measured at ab956e2f): the biweight's pile is
at rest by then, 0.0025 % H0/s from 1.5 to 2 s (h/H0 0.5252; 0.00058 % from 2.5 to 3 s),
40 x under the bound; with the static friction's position correction in ``colliders.respond``
dropped (the fix's mutation) its top sinks 3.3 % H0/s from 1.5 to 2 s (h/H0 0.428), 33 x
over it. poly6's pile settles more slowly (0.29 % H0/s from 1.5 to 2 s, 0.12 % from 2 to
2.5 s, 0.054 % from 2.5 to 3 s, h/H0 0.537): this test ran it 3 s, for either weight as the
default, until the weight was named here to cut a third of the suite's cost of it. Read
again at 7cee5e65: 0.0025 % H0/s at h/H0 0.5252, the mutation 3.34 % H0/s at 0.427.
"""

import math

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.sim.solver import Solver


def _slump(n=8, dx=0.01, t_end=2.0, window=0.5, fit_weight="biweight"):
    H0 = n * dx
    rho, g = 1000.0, 9.81
    scale = rho * g * H0
    mu = 10.0 * scale
    Y = math.sqrt(2.0) * 0.1 * scale  # shear yield stress Y / sqrt(2) = 0.1 rho g H0
    mat = we.Material.from_young(2.0 * mu * 1.3, 0.3, yield_stress=Y, flow_rate=200.0, density=rho, elastic_force="variational")
    b = we.SceneBuilder(spacing=dx, fit_weight=fit_weight)
    b.add_cylinder((0.0, H0 / 2, 0.0), H0 / 2, H0, mat)
    b.add_ground(0.0, friction=1.0)
    model = b.finalize(dtype=wp.float32)
    dt = 0.9 * model.stable_dt()
    solver = Solver(model)
    s0, s1 = model.state(), model.state()
    x0 = s0.x.numpy()
    core = np.hypot(x0[:, 0], x0[:, 2]) < 1.5 * dx
    steps = int(round(t_end / dt))
    mark = steps - int(round(window / dt))
    heights = {}
    for k in range(1, steps + 1):
        solver.step(s0, s1, dt)
        s0, s1 = s1, s0
        if k in (mark, steps):
            heights[k] = float(s0.x.numpy()[core, 1].max()) + 0.5 * dx
    sink = (heights[mark] - heights[steps]) / H0 / ((steps - mark) * dt)
    return heights[steps] / H0, sink


def test_slumped_cylinder_comes_to_rest():
    h, sink = _slump()
    S = math.sqrt(1.5) * math.sqrt(2.0) * 0.1
    theory = S * (1.0 - math.log(S))
    # At rest: the top sinks below 0.1 % H0/s (issue 12's target).
    assert sink < 1.0e-3, f"top still sinks {100 * sink:.2f} % H0/s at 2 s (h/H0 = {h:.3f})"
    # 8 particles tall is coarse: within 15 % of the 1-D theory here (10 % is the target at
    # the finer resolutions of the validation suite).
    assert abs(h - theory) < 0.15 * theory, f"h/H0 = {h:.3f}, 1-D theory {theory:.3f}"


@pytest.mark.slow
def test_energy_pressure_force_lets_the_16_across_slump_come_to_rest():
    """``benchmarks.validation.slump(0.5, resolution=16)`` (3328 particles, 4 s: minutes on
    one core) with ``Material(pressure_force="energy")`` (the default). With the spiky pressure
    force the top still sinks a flat 2.0-2.5 % H0/s from 1 to 3 s (h/H0 0.787 at 3 s); with
    the energy force (its default ``k_p = K / (4 rho0)``) the flow decays: measured 0.42 % H0/s
    at 3 s, 0.23 at 4 s, 0.14 at 4.75 s (per 0.25 s), h/H0 0.811 at 4 s against the 1-D 0.847
    (at ``K / (2 rho0)``: 0.55, 0.23, 0.10 at 5 s; docs/physics.md, the SPH pressure)."""
    import pathlib
    import sys

    root = str(pathlib.Path(__file__).resolve().parent.parent)
    if root not in sys.path:
        sys.path.insert(0, root)
    from benchmarks import validation  # noqa: PLC0415

    # Measured on the ground collider, the suite's floor before the particle floor became
    # its default: kept on it so that the numbers above stand.
    r = validation.slump(0.5, resolution=16, duration=4.0, pressure_force="energy", floor="ground")
    assert r["finite"]
    # The suite's rate: a line through the last quarter of the run (3-4 s).
    assert r["top_rate_pct_H0_per_s"] < 0.5, r["top_rate_pct_H0_per_s"]
    assert r["h_over_H0"] == pytest.approx(r["theory_h_over_H0"], rel=0.10), r["h_over_H0"]
