"""The adaptive (CFL) time step of ``simulate(dt="auto")`` (docs/method.md §8)."""

import math

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.sim.colliders import INSTANT_CONTACT_RAMP
from warp_esph.sim.fields import CompressionField
from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT
from warp_esph.simulate import adaptive_timestep, divergence_advice, resolve_timestep, simulate

FPS = 30.0
DX = 0.02
#: Speed at which the toothpaste box has blown up (a fall from its height reaches 1.1 m/s).
BOX_BLOWN_UP = 5.0


def _dropped_ball():
    # Soft (p-wave speed 6.4 m/s) so that the 2.4 m/s of the fall is a large part of the
    # signal speed; viscosity lets it settle after the bounce within the 1.33 s run below
    # (largest speed 0.006 m/s at 1.33 s, 0.014 at 1.5 s, 0.002 at 2 s). The default solver runs this elastic
    # ball on the conservative rest model, which keeps the energy of the bounce: at viscosity
    # 2 Pa s it still moved at 0.41 m/s at 2 s (the incremental composition, which lost much
    # of its bounce at impact: 0.07 m/s), at 30 Pa s 0.002 m/s.
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_sphere((0.0, 0.3 + 4 * DX, 0.0), 4 * DX, we.Material.from_young(2.0e4, 0.3, density=1000.0, viscosity=30.0))
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

    # 1.33 s: lands at 0.25 s (frame 7.4), bounces, settles: largest speed 0.006-0.077 m/s over
    # frames 36-40 (every one of them at 35 steps; 0.007-0.036 over 41-45, 0.002-0.004 m/s over
    # 56-60), measured.
    frames = 40
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
    # (measured 35 steps against 33: 5.5 % for gravity).
    assert n_rest <= max(rest) <= math.ceil(1.1 * n_rest), (rest, n_rest)

    # The same motion at fixed steps (float32): half the smallest adaptive one through the
    # flight (frames 0-6), then the stable step (the default's) to the end.
    def keep(frame, state):
        if frame == 6:
            flying["fixed"] = state.x.numpy().copy()

    landing = simulate(model, 7, fps=FPS, substeps=2 * max(n for _, n, _, _ in seen), progress=False, callback=keep)
    fixed = simulate(model, frames - 7, fps=FPS, substeps=n_rest, progress=False, state=landing, start_frame=7)
    # In flight: symplectic Euler's first-order error g t (dt_auto - dt_fixed) / 2, about
    # 0.03 spacings at 0.2 s (measured 0.025).
    assert np.abs(flying["auto"] - flying["fixed"]).max() < 0.05 * DX
    # After the bounce: an elastic body's resting shape is a minimum of its energy, which the
    # default's rest model keeps whatever the step, so the adaptive and the fixed run rest in
    # the same shape: measured at 40 frames, centroids and extents 2.3e-4 and 3.5e-4 spacings
    # apart (at most 3.3e-3 and 4.3e-3 at any frame from 34 on, 4.8e-4 and 6.1e-4 at 45); the
    # incremental composition's at 30 Pa s (``auto_runs_rest`` forced False), 6.7e-3 and 1.2e-2
    # (4.1e-3 and 8.4e-3 at the least from frame 34 on, 7.0e-3 and 1.3e-2 at 45). At 45
    # frames, against a fixed run at half the smallest adaptive step throughout (4320 steps
    # against the adaptive 1926) they read 1.1e-3 and 1.3e-3, and 3.0e-3 and 8.2e-3 with the
    # incremental composition, whose resting shape depended on the path (at 2 Pa s:
    # 0.71 spacings apart in the extents, 0.55 between two fixed steps).
    xa, xf = auto.x.numpy(), fixed.x.numpy()
    assert np.abs(xa.mean(axis=0) - xf.mean(axis=0)).max() < 0.005 * DX, (xa.mean(axis=0) - xf.mean(axis=0)) / DX
    assert np.abs(np.ptp(xa, axis=0) - np.ptp(xf, axis=0)).max() < 0.005 * DX, (np.ptp(xa, axis=0) - np.ptp(xf, axis=0)) / DX


def test_the_adaptive_step_follows_a_hourglass_strength_set_during_the_run():
    """``simulate(dt="auto", solver=...)`` read the solver's hourglass strength once, at the
    start: a callback that raised it from 0.05 to 1000 (whose control needs a step 4.8 x
    shorter) left the frames at the old step, which warned and blew up after 61 steps. Each
    frame's step now bounds the control the frame's steps run."""
    import warnings

    b = we.SceneBuilder(spacing=DX)
    b.add_box((0.0, 0.1, 0.0), (0.06, 0.06, 0.06), we.Material(mu=2e4, lam=3e4, density=1000.0), velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    model = b.finalize()
    solver = we.Solver(model, fit="curvature_corrected", hourglass=0.05)
    assert model.stable_dt(hourglass=1000.0) < 0.25 * model.stable_dt(hourglass=0.05)

    def raise_control(frame, state):
        solver.hourglass = 1000.0

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a step past the stable limit warns
        final = simulate(model, 1, fps=FPS, dt="auto", solver=solver, callback=raise_control, progress=False)
    assert np.isfinite(final.v.numpy()).all() and np.abs(final.v.numpy()).max() < 2.0


def test_a_step_fitted_to_the_frame_is_not_warned_as_above_the_stable_limit():
    """The default and the adaptive step fit a whole number of steps to a frame, to rounding
    (1e-12): asked for ``fps = 1 / (n stable_dt)``, a natural way to run n stable steps a
    frame, 81 of n = 1..999 gave this clay box a step one rounding above ``stable_dt()``, and
    the solver warned of its own choice that the run may blow up. A step beyond rounding
    still warns."""
    import warnings

    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.05, 0.0), (0.06, 0.06, 0.06), we.Material.preset("clay"))
    model = b.finalize()
    stable = model.stable_dt()
    n = next(n for n in range(1, 100) if resolve_timestep(model, 1.0 / (n * stable))[1] > stable)
    fps = 1.0 / (n * stable)
    assert adaptive_timestep(model, model.state(), fps)[1] > stable  # the premise: both choose it
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        simulate(model, 1, fps=fps, progress=False)
        simulate(model, 1, fps=fps, dt="auto", progress=False)
    a, c = model.state(), model.state()
    with pytest.warns(RuntimeWarning, match="above the explicit stability limit"):
        we.Solver(model).step(a, c, stable * (1.0 + 1e-6))


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


def _toothpaste_box(pressure_force, fit_weight=DEFAULT_FIT_WEIGHT, **overrides):
    """The toothpaste preset without its viscosity (the smallest margin under ``stable_dt``
    of the presets), a 6^3 box at rest on the ground, its fits of ``fit_weight``."""
    mat = we.Material.preset("toothpaste", viscosity=0.0, pressure_force=pressure_force, **overrides)
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, 3 * DX, 0.0), (6 * DX,) * 3, mat)
    b.add_ground(0.0, friction=0.5)
    return b.finalize()


@pytest.mark.parametrize("pressure_force", ["spiky", "energy"])
def test_stable_dt_holds_for_the_tightest_preset(pressure_force):
    """``Model.stable_dt()`` is a bound that holds (docs/method.md §8). The toothpaste preset
    without its viscosity has the smallest measured margin: it must rest at 1.0 x for 400
    steps (0.65 / 0.69 s with the spiky / energy force's default stiffness), with either.
    Its fast plastic flow spreads the box into a thin layer whose fits can become
    ill-conditioned; the fit guard (``Solver``'s ``max_condition``, default 20) keeps them
    from setting a shorter step (docs/physics.md, "The step bound of undamped fast plastic
    flow"); ``test_stable_dt_bounds_either_pressure_force`` is the elastic case."""
    model = _toothpaste_box(pressure_force)
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
    # Measured peak 0.68 / 0.81 m/s (spiky / energy) at 1.0 x (the box settling from its
    # lattice); with the old guard (cond(A) > 1e3) the energy force blew up at 0.24 s.
    assert peak < 1.0, peak


def _jittered_peak(model, dt, seconds, seed, max_condition=None):
    """Largest speed over ``seconds`` at step ``dt`` (``_peak_speed``, blown up above
    ``BOX_BLOWN_UP``) from the model's start moved by up to 1e-5 m per coordinate
    (``seed``): the blow-ups of undamped plastic flow depend on the start at that level."""
    state = model.state()
    x = state.x.numpy()
    state.x.assign(x + np.random.default_rng(seed).uniform(-1e-5, 1e-5, size=x.shape).astype(x.dtype))
    return _peak_speed(model, dt, int(round(seconds / dt)), BOX_BLOWN_UP, state=state, max_condition=max_condition)


@pytest.mark.parametrize(("pressure_force", "blew_up"), [("spiky", 3), ("energy", 4)])
def test_undamped_fast_plastic_flow_rests_at_half_the_stable_step(pressure_force, blew_up):
    """Issue 12's target "no preset blows up at half ``stable_dt``, with or without
    viscosity" for its tightest case: the toothpaste preset without viscosity (flow rate
    200/s), three starts jittered by 1e-5 m, 1 s at 0.5 ``stable_dt``, with either pressure
    force (each start's peak over 2 s is its peak over the first 1 s: measured 0.823 / 0.812
    m/s). A fall from the box's height reaches 1.1 m/s; blown up is above 5 m/s. With the
    old fit guard (``cond(A) > 1e3``) the start ``blew_up`` blew up (spiky: the first at
    0.57 s; energy: the second at 0.68 s, start 4 since ``isotropic.svd``): a particle at the spreading layer's edge whose
    neighbours leave one direction unsampled (``cond(A)`` 200-500) oscillated step by step
    along it (docs/physics.md, "The step bound of undamped fast plastic flow"). Measured
    with the guard at 20 (a switch): peak 0.83 / 0.82 m/s for every start; with the fade
    from 20 to 40 (``guards.py``): 0.81 / 0.80; with the continuous contact law, the default
    since: 0.82 / 0.81. With ``max_condition = 1e3`` (the fade from
    1e3 to 2e3) starts 0-3 reach 3.6, 5.0, 2.3 m/s and blow up (spiky), 1.1, blow up, blow
    up, 0.80 m/s (energy; since ``isotropic.svd`` 3.9, 0.89, 2.3, 0.80, the comment below): the
    start ``blew_up`` is one that blows up. Within the 1 s of the
    three starts, measured with ``max_condition = 1e3``: spiky (the default contact) starts
    0-2 blow up at 0.62, 0.85 and 0.80 s; energy (the instant law) they reach 0.80, 4.6 and
    1.4 m/s: either fails the bound 1.1. All of it measured with the poly6 fit weight, named
    (with the biweight the spiky start 3 stays bounded under the old guard: peak 0.80 m/s)."""
    model = _toothpaste_box(pressure_force, fit_weight="poly6")
    dt = 0.5 * model.stable_dt()
    peaks = [_jittered_peak(model, dt, 1.0, seed) for seed in range(3)]
    assert max(peaks) < 1.1, peaks
    # The guard is what holds it: with the old threshold that start blows up. These starts
    # were found under the instant contact law; under the continuous one (the default) every
    # start of the spiky force blows up with the old guard and none of starts 0-5 of the
    # energy force does (peaks 0.81-1.00 m/s), so its start is run under the instant law.
    # Since a body at rest has no stress in float32 (isotropic.svd) its start 1 stays bounded
    # there (0.89 m/s); starts 0-7 reach 3.9, 0.89, 2.3, 0.80, blow up, 0.80, 3.7, 4.2 m/s.
    model.contact_ramp = INSTANT_CONTACT_RAMP
    assert _jittered_peak(model, dt, 2.0, blew_up, max_condition=1.0e3) == math.inf


@pytest.mark.parametrize("pressure_force", ["spiky", "energy", "energy_spiky", "isotropic"])
def test_stable_dt_bounds_either_pressure_force(pressure_force):
    """The wave limit of ``Model.stable_dt()`` bounds each SPH pressure force: the
    toothpaste box without viscosity, elastic (no plastic flow), rests at 1.0 x for 0.5 s and
    blows up at 3.5 x. (Measured today: peak 0.864 / 0.811 / 0.840 / 0.820 m/s over 0.5 s at
    1.0 x, spiky / energy / energy_spiky / isotropic, as over 1 s to 0.002; at 3.5 x blown
    up at 0.34 / 0.12 / 0.23 / 0.23 s, so a stable step 3.5 x too long, the mutation, fails
    the 0.5 s run. Measured before, 1 s: peak 0.78 / 0.85 m/s at 1.0 x and 0.72 / 0.78 at 2.5 x
    with the energy / spiky force; at 3.5 x blown up at 0.24 / 0.57 s. ``energy_spiky``, its
    spiky core included: 0.83 at 1.0 x, 0.75 at 2.5 x, blown up at 3.5 x; ``isotropic``, its
    pressure as a stress through the moments: 0.83 at 1.0 x, 0.83 at 2.5 x, blown up at 3.5 x
    at 0.23 s, where ``energy_spiky`` measured 0.85, 0.81 and 0.23 s in the same run.) The energy force's
    poly6 core sets no shorter step than its wave speed (docs/physics.md, the SPH pressure,
    item 4). Measured with the poly6 fit weight, named (with the biweight the spiky force
    stays bounded at 3.5 x: peak 1.10 m/s)."""
    model = _toothpaste_box(pressure_force, fit_weight="poly6", yield_stress=math.inf)
    dt = model.stable_dt()
    assert _peak_speed(model, dt, int(0.5 / dt), BOX_BLOWN_UP) < 1.0
    assert _peak_speed(model, 3.5 * dt, int(1.0 / (3.5 * dt)), BOX_BLOWN_UP) == math.inf


def _shaken_block(n=8):
    """An elastic block of n^3 particles without gravity, every velocity component random
    (1 mm/s): all modes, the hourglass ones too, start with some energy."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (n * DX,) * 3, we.Material.from_young(1.0e5, 0.3, density=1000.0, pressure_stiffness=0.0))
    model = b.finalize()
    state = model.state()
    state.v.assign(np.random.default_rng(1).normal(scale=1e-3, size=(model.particle_count, 3)))
    return model, state


def _peak_speed(model, dt, steps, limit, hourglass=0.0, state=None, max_condition=None):
    """Largest speed over ``steps`` steps (checked every 20) of a solver with ``hourglass``
    (and the fit guard ``max_condition``, None: the default) from ``state`` (default the
    model's start), inf once it is non-finite or above ``limit`` (blown up)."""
    solver = we.Solver(model, hourglass=hourglass, **({} if max_condition is None else {"max_condition": max_condition}))
    a, c = model.state(), model.state()
    if state is not None:
        a.assign(state)
    peak = 0.0
    with pytest.warns(RuntimeWarning) if dt > model.stable_dt(hourglass=hourglass) else _nothing():
        for k in range(steps):
            solver.step(a, c, dt)
            a, c = c, a
            if k % 20 == 19:
                v = float(np.abs(a.v.numpy()).max())
                if not v < limit:
                    return math.inf
                peak = max(peak, v)
    return peak


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_stable_dt_includes_the_hourglass_control_and_holds():
    """``Model.stable_dt(hourglass=c)`` adds the limit of the hourglass control's springs
    (``sim/hourglass.py``) to the wave limit, and it holds. At ``c = 3`` the step is 4.0 %
    shorter and a run at it stays bounded. At ``c = 1000`` (a stiffness test, not a setting)
    the control rules: a run at the returned step stays bounded, one at 3 x it blows up,
    while the same 3 x step without the control is stable (it is below the wave limit).
    ``Model.hourglass`` is the default, the solver's warning and ``simulate``'s steps (fixed
    and adaptive) follow the solver's ``c``."""
    from warp_esph.model import AUTO_HOURGLASS

    model, state = _shaken_block()
    plain = model.stable_dt(hourglass=0.0)
    # A strength near the float floor is the plain step (its limit's square passed the float
    # range: OverflowError from the CLI and the API).
    assert model.stable_dt(hourglass=1e-320) == plain
    # The default for this elastic block (fit "auto") runs the control at AUTO_HOURGLASS.
    assert model.stable_dt() == model.stable_dt(hourglass=AUTO_HOURGLASS) < plain
    mild, stiff = model.stable_dt(hourglass=3.0), model.stable_dt(hourglass=1000.0)
    print(f"stable_dt: c = 0 {plain:.4e}, c = 3 {mild:.4e} ({mild / plain:.4f} x), c = 1000 {stiff:.4e} ({stiff / plain:.4f} x)")
    assert 0.95 * plain < mild < plain and stiff < plain / 3.0
    start = float(np.abs(state.v.numpy()).max())
    peaks = [_peak_speed(model, dt, 200, 1.0, c, state) for c, dt in ((3.0, mild), (1000.0, stiff), (1000.0, 3.0 * stiff), (0.0, 3.0 * stiff))]
    print(f"peak speed / start ({start:.2e} m/s): c = 3 at its step {peaks[0] / start:.2f}, c = 1000 at its step "
          f"{peaks[1] / start:.2f}, at 3 x {peaks[2] / start:.3g}, c = 0 at that step {peaks[3] / start:.2f}")
    # Bounded: an undamped elastic block keeps its energy (the peak speed wanders within a
    # few times the start as the modes beat); blown up: past 1 m/s within 200 steps. Measured:
    # peaks 0.88 / 1.10 / 0.83 x the start, each the same over 400 steps; 3 x blown up by step
    # 20, as a step 1.6 x the control's limit is (1.4 x stays bounded: 1.45 x over 400).
    assert peaks[0] < 3.0 * start and peaks[1] < 3.0 * start and peaks[3] < 3.0 * start
    assert peaks[2] == math.inf
    with pytest.warns(RuntimeWarning, match="hourglass control at c = 1000"):
        we.Solver(model, hourglass=1000.0).check_dt(1.01 * stiff)
    model.hourglass = 1000.0
    assert model.stable_dt() == stiff and model.stable_dt(hourglass=0.0) == plain
    assert resolve_timestep(model, 100.0)[1] <= stiff
    # simulate's steps follow the solver it is given (the model's control is 1000 here).
    fixed = simulate(model, 1, fps=100.0, solver=we.Solver(model, hourglass=0.0), progress=False)
    adaptive = simulate(model, 1, fps=100.0, dt="auto", progress=False, state=state)
    assert np.isfinite(fixed.x.numpy()).all() and np.abs(adaptive.v.numpy()).max() < 3.0 * start
    model.hourglass = 0.0
    with pytest.raises(ValueError, match="hourglass = -1 is not allowed"):
        model.stable_dt(hourglass=-1)


def test_stable_dt_halves_the_wave_limit_where_the_step_runs_the_corrected_incremental_fit():
    """Where the step runs the curvature-corrected fit with the incremental composition
    (``Model.corrected_incremental``), ``Model.stable_dt(fit=)`` keeps half the wave limit
    (``CORRECTED_INCREMENTAL_STEP``: the breathing cube and the box on the imaged ground that
    ran away / gained at the full one, tests/test_validation_suite.py and
    tests/test_static_colliders.py). The rest model (``fit="auto"`` on this elastic block), the
    linear fit and a comparison model keep the full limit; the answer kept between calls
    follows ``fit``; a solver's check, ``Solver.stable_dt``, ``resolve_timestep`` and
    ``simulate`` with a given solver follow the fit it was asked for."""
    import warnings

    from warp_esph.model import CORRECTED_INCREMENTAL_STEP

    model, state = _shaken_block(4)
    plain = model.stable_dt(hourglass=0.0, fit="linear")
    assert CORRECTED_INCREMENTAL_STEP == 0.5
    assert not model.corrected_incremental() and model.corrected_incremental("curvature_corrected")
    assert model.stable_dt(hourglass=0.0) == plain  # the rest model
    corrected = model.stable_dt(hourglass=0.0, fit="curvature_corrected")
    assert corrected == 0.5 * plain and model.stable_dt(hourglass=0.0) == plain
    assert model.stable_dt(fit="curvature_corrected") < corrected  # the control's springs add
    assert model.world_stable_dts(hourglass=0.0, fit="curvature_corrected") == [corrected]
    assert resolve_timestep(model, 1.0 / (10 * plain), fit="curvature_corrected")[1] <= corrected
    solver = we.Solver(model, fit="curvature_corrected", hourglass=0.0)
    assert solver.asked_fit == "curvature_corrected" and solver.stable_dt() == corrected
    with pytest.warns(RuntimeWarning, match="the wave limit x 0.5 for the curvature-corrected fit"):
        solver.check_dt(0.6 * plain)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        we.Solver(model, hourglass=0.0).check_dt(0.6 * plain)  # the rest model: within its limit
        out = simulate(model, 1, fps=1.0 / (10 * plain), solver=solver, progress=False, state=state)
    assert np.isfinite(out.x.numpy()).all()
    # Floor images keep an elastic body on the incremental composition: the default halves.
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 2 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(1.0e5, 0.3, density=1000.0, pressure_stiffness=0.0))
    b.add_ground(0.0, images=True)
    imaged = b.finalize()
    assert imaged.corrected_incremental() and imaged.stable_dt(hourglass=0.0) == 0.5 * plain
    # A comparison model runs its total fit against the rest neighbourhood, not F <- dF F.
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * DX,) * 3, we.Material.from_young(1.0e5, 0.3, density=1000.0, pressure_stiffness=0.0,
                                                                   deformation="rest"))
    rest = b.finalize()
    assert not rest.corrected_incremental("curvature_corrected")
    assert rest.stable_dt(hourglass=0.0, fit="curvature_corrected") == plain



def test_the_adaptive_step_of_the_corrected_incremental_fit_is_set_by_its_speed_term_and_holds():
    """On the corrected fit with the incremental composition (the imaged ground keeps an
    elastic body on it) ``stable_dt`` is half the wave limit; the adaptive step's speed term
    ``C dx / (c_P + v_max + |g| / fps)`` is not halved, and is below that half only where
    ``v_max + |g| / fps > c_P``. A soft 4^3 box (E 20 kPa, c_P 5.9 m/s, float64) dropped from 2
    spacings onto ``add_ground(images=True)`` at 1 fps (|g| / fps = 9.8 m/s) takes the speed
    term's step every frame, 0.70-0.75 x the stable step, and rings after the impact with no
    more kinetic energy than the fall gave it (measured 0.174 / 0.090 / 0.086 J, the largest in
    the 1st / 2nd / 3rd second; with the speed term halved 0.177 / 0.128 / 0.099 J; at 2 x the
    stable step, the full wave limit, 0.168 / 0.135 / 0.284 J: it gains). Docs/physics.md,
    "The biweight's incremental composition (measured)", has the faster scenes."""
    fps = 1.0
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 4 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(2.0e4, 0.3, density=1000.0))
    b.add_ground(0.0, images=True)
    model = b.finalize(dtype=wp.float64)
    solver = we.Solver(model)
    assert model.corrected_incremental() and solver.fit == "curvature_corrected"
    stable = solver.stable_dt()
    c = float(np.max(model.wave_speeds()))
    mass = model.particle_mass.numpy()[:, None]
    a, spare = model.state(), model.state()
    peaks = []
    for _ in range(3):
        n, dt = adaptive_timestep(model, a, fps, hourglass=solver.next_hourglass(), fit=solver.asked_fit)
        v = a.v.numpy()
        speed_term = 0.3 * DX / (c + float(np.sqrt((v * v).sum(axis=1)).max()) + 9.81 / fps)
        # The speed term sets it, unhalved: rounded down to whole steps a frame, no further
        # (dt <= speed_term alone passed with the term halved).
        assert speed_term * n / (n + 1) < dt <= speed_term < 0.8 * stable, (dt, speed_term, stable)
        top = 0.0
        for k in range(n):
            solver.step(a, spare, dt)
            a, spare = spare, a
            if k % 20 == 0:
                v = a.v.numpy()
                top = max(top, 0.5 * float((mass * v * v).sum()))
        peaks.append(top)
    assert max(peaks[1:]) <= peaks[0], peaks

def _dots(strength, **field):
    """Three particles far apart (0.2 m: no neighbours, so no material force) under a
    compression field of ``strength`` (1/s^2), without gravity: each particle is the field's
    harmonic oscillator alone, of angular frequency ``sqrt(strength)``."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_particles(np.array([[0.1, 0.2 * i, 0.05] for i in range(3)]),
                    we.Material.from_young(1.0e5, 0.3, density=1000.0), name="dots")
    if strength is not None:
        b.add_compression_field((0.0, 0.0, 0.0), strength, **field)
    return b.finalize()


# Its bodies are coarse on purpose (a tiny scene, or one torn apart): the run's under-resolution warning is expected.
@pytest.mark.filterwarnings("ignore:the deformation fit was skipped:RuntimeWarning")
def test_stable_dt_includes_the_force_fields_and_holds():
    """A compression field of strength ``k`` is a spring of angular frequency ``sqrt(k)``,
    which symplectic Euler follows only while ``dt < 2 / sqrt(k)``: ``Model.stable_dt()``
    adds its limit ``2 / (1.5 sqrt(k))`` to the wave and hourglass limits as they add
    (``1 / dt^2`` summed). At ``k = 1e9`` (``2 / sqrt(k) = 6.3e-5 s``, a seventh of the wave
    limit) it ignored the field: a run at half its step multiplied the particles' distance
    from the axis about 50-fold a step, and ``simulate`` at its default step raised a
    divergence advising a smaller dt than the stable limit it was already under. A field
    switched on later bounds the step from the start; a repelling one (``k < 0``) sets none
    of its own and lessens the net strength of those it overlaps."""
    k = 1.0e9
    plain = _dots(None).stable_dt()
    model = _dots(k)
    stable = model.stable_dt()
    assert stable < 2.0 / math.sqrt(k)
    assert math.isclose(stable ** -2, plain ** -2 + (1.5 * math.sqrt(k) / 2.0) ** 2, rel_tol=1e-9)
    assert _dots(k, t_on=0.5, t_off=0.6).stable_dt() == stable
    assert _dots(-k).stable_dt() == plain
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    for i, name in enumerate(("a", "b")):
        b.add_particles(np.array([[0.1, 0.2 * i, 0.05]]), we.Material.from_young(1.0e5, 0.3, density=1000.0), name=name)
    b.add_compression_field((0.0, 0.0, 0.0), 2.0 * k, body="a")
    b.add_compression_field((0.0, 0.0, 0.0), -k)  # on both: a net k on "a", -k on "b"
    assert b.finalize().stable_dt() == stable

    solver = we.Solver(model)
    a, c = model.state(), model.state()
    r0 = np.hypot(a.x.numpy()[:, 0], a.x.numpy()[:, 2]).max()
    peak = 0.0
    for _ in range(200):  # 21 periods
        solver.step(a, c, 0.5 * stable)
        a, c = c, a
        peak = max(peak, float(np.hypot(a.x.numpy()[:, 0], a.x.numpy()[:, 2]).max()))
    # Symplectic Euler keeps the amplitude within 1 / sqrt(1 - (omega dt / 2)^2) = 1.06 x.
    assert peak < 1.1 * r0, peak / r0
    end = simulate(model, 2, fps=300.0, progress=False)
    assert np.hypot(end.x.numpy()[:, 0], end.x.numpy()[:, 2]).max() < 1.1 * r0


def test_a_field_that_sets_the_step_is_named():
    """Where a field's limit is the shortest, the refusals name it and advise a weaker field,
    not a softer material or a larger spacing (which leave its limit as it is), and the
    solver's warning lists it. ``k = 1e17`` switched on at 0.5 s: a step of 4.2e-9 s, 7.9e6
    steps a frame."""
    model = _dots(1.0e17, t_on=0.5)
    named = r"the limit of compression field 0 \(on every body\) at net strength k = 1e\+17 1/s\^2, .* = 4.22e-09 s, with the wave limit"
    with pytest.raises(ValueError, match=rf"the stable step 4.22e-09 s is not allowed: .* a compression field sets it \({named}"
                                         r".*\): use a weaker compression field"):
        resolve_timestep(model, FPS)
    with pytest.raises(ValueError, match=rf"the adaptive step is not allowed .* its stable step, 4.22e-09 s \({named}"
                                         r".*\), would take 7.91e\+06 steps a frame, .*; use a weaker compression field"):
        adaptive_timestep(model, model.state(), FPS)
    with pytest.warns(RuntimeWarning, match=r"and that of compression field 0 \(on every body\) at net strength k = 1e\+17 1/s\^2"):
        we.Solver(model).check_dt(1e-3)
    # A field that sets the step crushes a body of more than a particle across, which is then
    # stiffer than the limit allows for (docs/method.md §8): the divergence's advice says so,
    # where it advised softer material settings and a smaller dt than the run was already under.
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.5, 0.0), (0.2, 0.2, 0.2), we.Material.preset("dough"))
    b.add_compression_field((0.0, 0.0, 0.0), 1.0e7)
    box = b.finalize()
    with pytest.raises(we.SimulationError, match=r"try a smaller dt= \(stable limit 0.000417 s, set by compression field 0 "
                                                 r"\(on every body\) at net strength k = 1e\+07 1/s\^2; a body it crushes is stiffer"):
        simulate(box, 2, progress=False)


def test_the_field_limit_is_the_largest_net_strength_a_particle_feels():
    """``k`` is the largest net strength a particle of some body feels at some time. Taken only
    at the times a field switches on, a repelling field switched off under an attracting one
    (net 0, then ``k``) set no limit: the run past ``t_off`` had the unbounded step. Taken also
    for fields on every body alone, it counted a net no particle feels where each body's own
    field cancels them. A field added to the model after ``finalize`` counts at once."""
    k = 1.0e9
    plain, alone = _dots(None).stable_dt(), _dots(k).stable_dt()
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_particles(np.array([[0.1, 0.0, 0.05]]), we.Material.from_young(1.0e5, 0.3, density=1000.0), name="a")
    b.add_compression_field((0.0, 0.0, 0.0), k)
    b.add_compression_field((0.0, 0.0, 0.0), -k, 0.0, 0.5)
    assert b.finalize().stable_dt() == alone
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    for i, name in enumerate(("a", "b")):
        b.add_particles(np.array([[0.1, 0.2 * i, 0.05]]), we.Material.from_young(1.0e5, 0.3, density=1000.0), name=name)
        b.add_compression_field((0.0, 0.0, 0.0), -k, body=name)
    b.add_compression_field((0.0, 0.0, 0.0), k)
    model = b.finalize()
    assert model.stable_dt() == plain
    # Each world's bodies feel their own fields: a field on one world's body only sets it.
    worlds = we.finalize_worlds([b, b])
    assert worlds.stable_dt() == plain
    worlds.force_fields.append(CompressionField((0.0, 0.0, 0.0), k, body=3))  # w1/b: net k
    assert worlds.stable_dt() == alone


def test_a_field_added_after_finalize_is_checked_as_finalize_checks_it():
    """``finalize`` refuses a field the model's float type cannot run (1e39 in float32 wrote
    NaN positions in the first step); one appended to ``model.force_fields`` afterwards had no
    check, nor had its body index (past the bodies, it acted on nothing without a word). Now
    ``stable_dt``, which the step asks before its first launch, refuses it by name, and the
    state is left as it was."""
    model = _dots(None)
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    x0 = a.x.numpy().copy()
    # The field's own refusal, which says 'is not allowed' itself, follows the entry unwrapped:
    # '... = CompressionField(...) is not allowed: CompressionField.strength = 1e+39 is not
    # allowed in float32: ...' said it twice.
    cases = [(CompressionField((0.0, 0.0, 0.0), 1.0e39), r": CompressionField.strength = 1e\+39 is not allowed in "
              r"float32: must be at most 1.84e\+19 in size; use dtype=float64 or a smaller value$"),
             (CompressionField((0.0, 0.0, 0.0), 1.0e3, body=1), r" is not allowed: CompressionField.body = 1 is not a "
              r"body of the model: must be a body index in 0..0 or -1 \(every particle\)$"),
             ((0.0, 1.0e3), r" is not allowed: must be a warp_esph.sim.fields.CompressionField$")]
    for field, why in cases:
        model.force_fields.append(field)
        with pytest.raises(ValueError, match=r"^model.force_fields\[0\] = (?:(?!is not allowed)[^:])*" + why):
            model.stable_dt()
        with pytest.raises(ValueError, match=why):
            solver.step(a, b, 1.0e-4)
        assert (a.x.numpy() == x0).all() and a.time == 0.0
        model.force_fields.clear()
    model.force_fields = None
    with pytest.raises(ValueError, match=r"model.force_fields = None is not allowed: must be a list of CompressionField"):
        model.stable_dt()
    model.force_fields = (CompressionField((0.0, 0.0, 0.0), 1.0e3, body=0),)
    assert model.stable_dt() < _dots(None).stable_dt()


def test_a_field_is_named_only_where_it_sets_the_step():
    """Where the viscous limit is shorter than the field's, the viscous limit sets the step,
    and a divergence names no field (it said the field set the limit, and advised a weaker
    one, where only a less viscous material lengthens the step); where the field sets it, each
    message names it alike: its index, its body and the net strength."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_particles(np.array([[0.1, 0.2 * i, 0.05] for i in range(2)]),
                    we.Material.from_young(1.0e5, 0.3, density=1000.0, viscosity=1.0e4), name="dots")
    b.add_compression_field((0.0, 0.0, 0.0), 1.0e9, body="dots")
    model = b.finalize()
    assert model.stable_dt() == pytest.approx(0.025 * 1000.0 * model.support_radius**2 / 1.0e4, rel=1e-12, abs=0.0)
    assert divergence_advice(model, 0.0) == f"try a smaller dt= (stable limit {model.stable_dt():.3g} s) or stiffer-to-softer material settings"
    model.set_material(0, we.Material.from_young(1.0e5, 0.3, density=1000.0))
    assert divergence_advice(model, 0.0, "--dt").startswith(
        "try a smaller --dt (stable limit 4.2e-05 s, set by compression field 0 (on body 'dots') at net strength k = 1e+09 1/s^2;")
