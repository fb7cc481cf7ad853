"""The adaptive (CFL) time step of ``simulate(dt="auto")`` (docs/method.md §8)."""

import math

import numpy as np
import pytest

import warp_esph as we
from warp_esph.simulate import adaptive_timestep, resolve_timestep, simulate

FPS = 30.0
DX = 0.02


def _dropped_ball():
    # Soft (p-wave speed 6.4 m/s) so that the 2.4 m/s of the fall is a large part of the
    # signal speed; a little viscosity lets it settle after the bounce.
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_sphere((0.0, 0.3 + 4 * DX, 0.0), 4 * DX, we.Material.from_young(2.0e4, 0.3, density=1000.0, viscosity=2.0))
    b.add_ground(0.0, friction=0.5)
    return b.finalize()


def test_adaptive_step_is_smaller_in_flight_than_at_rest_and_matches_a_small_fixed_step():
    model = _dropped_ball()
    seen = []  # (frame, substeps chosen for the next frame, max speed, centroid height)

    def record(frame, state):
        n, dt = adaptive_timestep(model, state, FPS)
        assert math.isclose(n * dt, 1.0 / FPS, rel_tol=1e-12)
        v = state.v.numpy()
        seen.append((frame, n, float(np.linalg.norm(v, axis=1).max()), float(state.x.numpy()[:, 1].mean())))

    frames = 45  # 1.5 s: lands at 0.25 s (frame 7.4), bounces, settles
    flying = {}

    def record_and_keep(frame, state):
        record(frame, state)
        if frame == 6:
            flying["auto"] = state.x.numpy().copy()

    auto = simulate(model, frames, fps=FPS, dt="auto", progress=False, callback=record_and_keep)
    n_rest = resolve_timestep(model, FPS)[0]  # the stable step: what a body at rest gets
    flight = [n for f, n, speed, _ in seen if speed > 1.5]
    rest = [n for f, n, speed, _ in seen[-5:]]
    assert flight, seen
    assert seen[-1][2] < 0.1, seen[-1]  # at rest at the end
    # In flight the speed (> 1.5 m/s) adds to the 5.9 m/s wave speed: more, shorter steps.
    assert min(flight) > max(rest), (flight, rest)
    assert max(flight) >= 1.3 * max(rest), (flight, rest)
    # At rest: the stable step up to the gravity margin (|g| / fps = 0.33 m/s of 5.9)
    # (measured 36 steps against 33: 5.5 % for gravity, the rest for a 0.05 m/s jitter).
    assert n_rest <= max(rest) <= math.ceil(1.1 * n_rest), (rest, n_rest)

    # The same motion as a fixed step half the smallest adaptive one (float32).
    def keep(frame, state):
        if frame == 6:
            flying["fixed"] = state.x.numpy().copy()

    fixed = simulate(model, frames, fps=FPS, substeps=2 * max(n for _, n, _, _ in seen), progress=False, callback=keep)
    # In flight: symplectic Euler's first-order error g t (dt_auto - dt_fixed) / 2, about
    # 0.03 spacings at 0.2 s.
    assert np.abs(flying["auto"] - flying["fixed"]).max() < 0.05 * DX
    # After the bounce the particles' arrangement depends on the step (two fixed steps,
    # 100 and 200 per frame, end up to 2.7 spacings apart particle by particle and 0.17
    # spacings apart in the centroid), so the resting ball is compared by its centroid.
    xa, xf = auto.x.numpy(), fixed.x.numpy()
    assert np.abs(xa.mean(axis=0) - xf.mean(axis=0)).max() < 0.5 * DX, (xa.mean(axis=0) - xf.mean(axis=0)) / DX
    assert np.abs(np.ptp(xa, axis=0) - np.ptp(xf, axis=0)).max() < 0.5 * DX


def test_adaptive_step_rejects_bad_input():
    model = _dropped_ball()
    with pytest.raises(ValueError, match=r"dt = 'fast' is not allowed: must be a number of seconds or 'auto'"):
        simulate(model, 1, dt="fast", progress=False)
    with pytest.raises(ValueError, match=r"substeps = 4 and dt = 'auto' are not allowed together"):
        simulate(model, 1, dt="auto", substeps=4, progress=False)


def test_cli_adaptive_dt(tmp_path, capsys):
    from warp_esph.cli import main

    out = tmp_path / "ball.usdc"
    tiny = ["--scale", "0.4", "--frames", "2", "--no-progress"]
    assert main(["run", "rubber_bounce", "-o", str(out), "--dt", "auto", *tiny]) == 0
    assert "adaptive dt (CFL)" in capsys.readouterr().out
    assert main(["run", "rubber_bounce", "-o", str(out), "--adaptive-dt", *tiny]) == 0
    assert main(["run", "rubber_bounce", "-o", str(out), "--adaptive-dt", "--dt", "0.001", *tiny]) == 2
    assert "--dt = 0.001 and --adaptive-dt are not allowed together" in capsys.readouterr().err


def test_stable_dt_holds_for_the_tightest_preset():
    """``Model.stable_dt()`` is a bound that holds (docs/method.md §8). The toothpaste preset
    without its viscosity has the smallest measured margin (a 6^3 box at rest on the ground
    blew up at 1.5 x stable_dt within 400 steps, not at 1.0 x); it must rest at 1.0 x."""
    mat = we.Material.preset("toothpaste", viscosity=0.0)
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 3 * DX, 0.0), (6 * DX,) * 3, mat)
    b.add_ground(0.0, friction=0.5)
    model = b.finalize()
    solver = we.Solver(model)
    dt = model.stable_dt()
    a, c = model.state(), model.state()
    peak = 0.0
    for k in range(400):
        solver.step(a, c, dt)
        a, c = c, a
        if k % 20 == 19:
            v = a.v.numpy()
            assert np.isfinite(v).all(), k
            peak = max(peak, float(np.abs(v).max()))
    # Measured peak 0.68 m/s at 1.0 x (the box settling from its lattice), 69 m/s at 1.5 x.
    assert peak < 1.0, peak
