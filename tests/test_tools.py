"""Tools and boundary conditions (``warp_esph/tools.py``): pinned sets, moving colliders,
reaction forces, and their gradients against float64 central differences."""

import dataclasses
import functools
import math
import pathlib
import re

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from taped_loss import random_weights, set_first_material, taped_rollout_loss
from warp_esph import tools
from warp_esph.builder import finalize_worlds
from warp_esph.model import AUTO_HOURGLASS, CONTACTS

from benchmarks.validation import come_to_rest, kinetic_damping

G = 9.81


def _elastic(E, nu=0.3, rho=1000.0, **kw):
    # Variational force, no SPH pressure: the elastic response alone (docs/tools.md).
    return we.Material.from_young(E, nu, density=rho, pressure_stiffness=0.0, elastic_force="variational", **kw)


def test_come_to_rest_stops_the_free_particles_and_keeps_a_moving_pins_velocity():
    """``come_to_rest`` on a block whose bottom layer is pinned and carried at 0.1 m/s: the
    pinned particles keep the pin's velocity (it wrote 0 there, ``(V - V) / 2``), while the
    free ones, carried along by then, are stopped."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(1e5), name="block")
    b.pin(region=((-1, -1, -1), (1, 0.015, 1)), motion=tools.Velocity((0.1, 0.0, 0.0)), name="carrier")
    m = b.finalize()
    s = we.Solver(m)
    dt = m.stable_dt()
    st = _run(s, m, 20, dt)
    held = m.tools.pins[0].indices
    free = np.setdiff1d(np.arange(m.particle_count), held)
    carried = np.abs(st.v.numpy()[free, 0]).max()
    come_to_rest(s, st, m.state(), dt)
    v = st.v.numpy()
    np.testing.assert_allclose(v[held], np.tile([0.1, 0.0, 0.0], (len(held), 1)), atol=1e-6)
    print(f"free particles' largest speed along the pin {carried:.3g} m/s, after the stop {np.abs(v[free]).max():.3g}")
    assert np.abs(v[free]).max() < 0.1 * carried


def _run(solver, model, steps, dt, relax_after=None, every=10, state=None):
    """Steps with two swapped states (from ``state``, else the rest state); after time
    ``relax_after`` kinetic damping (``benchmarks.validation.kinetic_damping``: every particle
    stopped where it is whenever the kinetic energy has dropped since the last check, the
    dynamic-relaxation way to the static solution)."""
    a, b = (state, model.state()) if state is not None else (model.state(), model.state())
    probe = model.state() if relax_after is not None else None
    mass = model.particle_mass.numpy().astype(np.float64)[:, None]
    ke_prev = 0.0
    for k in range(steps):
        solver.step(a, b, dt)
        a, b = b, a
        if relax_after is not None and a.time > relax_after and k % every == 0:
            ke_prev = kinetic_damping(solver, a, probe, dt, mass, ke_prev)
    return a


# ------------------------------------------------------------------------- pinned sets
def test_reaction_readings_refuse_a_state_that_is_not_the_models():
    """``reaction_forces(None)`` and ``collider_reactions(None)`` raised an AttributeError from
    deep inside; a state of a model without tools did too, and one of a model with another
    static collider was read as this model's rows without a word."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), _elastic(2e4), name="d")
    b.add_ground()
    b.add_tool("sphere", radius=0.05, position=(0.0, 0.6, 0.0), name="ball")
    s = we.Solver(b.finalize())
    other = we.SceneBuilder(spacing=0.05)
    other.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), _elastic(2e4), name="d")
    other.add_ground()
    other.add_box_collider((2.0, 0.0, 0.0), (0.1, 0.1, 0.1))
    foreign = other.finalize().state()
    for read in (s.reaction_forces, s.collider_reactions):
        with pytest.raises(ValueError, match=r"^state = None is not allowed: must be a warp_esph.State"):
            read(None)
        with pytest.raises(ValueError, match=r"^state(\.tool_pose_p = None)? .*not allowed|^state does not belong to this model"):
            read(foreign)
    assert set(s.reaction_forces(s.model.state())) == {"ball"}


@pytest.mark.parametrize("motion,moved", [
    (tools.Keyframes([0.0, 1.0], [(0.0, 0.0, 0.0), (0.0, 0.01, 0.0)]), "0.135"),
    (tools.Velocity((0.0, 0.1, 0.0), position=(0.0, 0.0, 0.0)), "0.135"),
    (tools.Scripted(lambda t: ((-0.09, 0.1 + 0.1 * t, 0.0), (0.0, 0.0, math.sin(0.1), math.cos(0.1)))), "0.00399"),
])
def test_a_pinned_set_whose_motion_starts_away_from_its_rest_pose_is_refused(motion, moved, tmp_path):
    """A pinned particle is placed at ``p(t) + R(t) (X - centroid)``: a clamp keyed from the
    origin (or given a Velocity position there) jumped 0.135 m in the first step, off its beam,
    which then fell free, and the run reported nothing. The message gives the centroid to start
    from; a motion that starts there is taken."""
    def build(m):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.1, 0.0), (0.2, 0.06, 0.06), _elastic(2e4), name="beam")
        b.pin(body="beam", region=((-1, -1, -1), (-0.08, 1, 1)), name="clamp", motion=m)
        return b.finalize()

    with pytest.raises(ValueError, match=rf"^pinned set 'clamp' is not allowed to start away from its rest pose: its "
                                         rf"{type(motion).__name__} motion .* up to {moved} m .* its centroid "
                                         r"\[-0\.09\d*, 0\.\d+, 0\.0\]"):
        build(motion)
    if isinstance(motion, tools.Keyframes):
        # From a scene file, the refusal names the file, the set's table and the key the set
        # starts at, as the file's other refusals do (it named neither, then the Python API's
        # words: 'its Keyframes motion puts its frame at ...').
        from warp_esph.scenes import load_scene_file  # noqa: PLC0415

        path = tmp_path / "clamp.toml"
        head = ('[[bodies]]\nshape = "box"\nname = "beam"\nmaterial = "dough"\ncenter = [0.0, 0.1, 0.0]\n'
                'size = [0.2, 0.06, 0.06]\n[scene]\nspacing = 0.02\n'
                '[[pins]]\nbody = "beam"\nname = "clamp"\nregion = [[-1, -1, -1], [-0.08, 1, 1]]\n')
        path.write_text(head + 'keyframe_times = [0.0, 1.0]\nkeyframe_positions = [[0, 0, 0], [0, 0.01, 0]]\n')
        with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: \[\[pins\]\] #1: keyframe_positions\[0\] = \[0\.0, 0\.0, "
                                             rf"0\.0\] is not allowed: pinned set 'clamp' starts there \(keyframe_times\[0\] = 0, "
                                             rf"its pose at t = 0\), which moves its particles up to {moved} m .*: give "
                                             r"keyframe_positions\[0\] = \[-0\.09, 0\.1, 0\.0\]$"):
            load_scene_file(path).builder.finalize()
        # Turned at its centroid: the orientation is named, not the position.
        path.write_text(head + 'keyframe_times = [0.0, 1.0]\nkeyframe_positions = [[-0.09, 0.1, 0], [-0.09, 0.1, 0]]\n'
                               'keyframe_orientations = [[0, 0, 0.0998334, 0.9950042], [0, 0, 0, 1]]\n')
        with pytest.raises(ValueError, match=r"#1: keyframe_orientations\[0\] = \[0\.0, 0\.0, 0\.0998\d*, 0\.995\d*\] is not "
                                             r"allowed: .*: give keyframe_orientations\[0\] = \[0, 0, 0, 1\]$"):
            load_scene_file(path).builder.finalize()
    m = build(tools.Keyframes([0.0, 1.0], [(-0.09, 0.1, 0.0), (-0.09, 0.11, 0.0)]))
    s, a, c = we.Solver(m), m.state(), m.state()
    s.step(a, c, 1e-4)
    held = m.tools.pins[0].indices
    np.testing.assert_allclose(c.x.numpy()[held], m.particle_x0[held] + [0.0, 1e-6, 0.0], atol=1e-6)


@pytest.mark.parametrize("cx", [26.2805, 1000.0123])
def test_a_held_pinned_set_far_out_in_float32_is_at_its_rest_pose(cx):
    """The rest-pose check compares the set's pose at t = 0 with its float64 centroid: a held
    set (no motion) 26 m out was refused for 2.3e-5 m (a float32 sum of the centroid) and 1 km
    out for 2.7e-4 m, within what float32 can say there; the set stays where it was built."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((cx, 0.1, 0.0), (0.2, 0.1, 0.2), _elastic(2e3), name="slab")
    b.pin(region=((cx - 1, 0, -1), (cx + 1, 0.07, 1)))
    m = b.finalize()
    s, a, c = we.Solver(m), m.state(), m.state()
    s.step(a, c, 1e-4)
    held = m.tools.pins[0].indices
    np.testing.assert_array_equal(c.x.numpy()[held], m.particle_x0[held].astype(np.float32))


def test_pinned_set_stays_exactly_where_held_and_a_moving_pin_follows_its_motion():
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), _elastic(2e4, viscosity=2.0), name="held")
    b.add_box((0.3, 0.1, 0.0), (0.1, 0.1, 0.1), _elastic(2e4, viscosity=2.0), name="carried")
    b.pin(body="held", region=((-1, -1, -1), (1, 0.07, 1)), name="base")
    v, w = np.array([0.0, 0.2, 0.1]), np.array([0.0, 1.0, 0.0])
    b.pin(body="carried", motion=tools.Velocity(v, w), name="grip")
    b.add_box((0.6, 0.1, 0.0), (0.1, 0.1, 0.1), _elastic(2e4, viscosity=2.0), name="scripted")
    c_s = np.concatenate(b._points)[250:].mean(axis=0)
    half = 0.5 * np.linalg.norm(w)
    b.pin(body="scripted", name="script", motion=tools.Scripted(
        lambda t: (c_s + v * t, (0.0, np.sin(half * t), 0.0, np.cos(half * t)))))
    m = b.finalize()
    held = m.tools.pins[0].indices
    carried = m.tools.pins[1].indices
    assert len(held) == 25 and len(carried) == 125
    s = we.Solver(m)
    dt = 1e-3
    st = _run(s, m, 60, dt)
    x = st.x.numpy()
    x0 = m.particle_x0
    # Held: bit for bit at the rest position (x = X + (p - c) + (R - I)(X - c), all zero).
    np.testing.assert_array_equal(x[held], x0[held])
    # The rest of the held body sagged under gravity.
    free = np.setdiff1d(np.arange(50, 125), held)
    assert (x[free, 1] - x0[free, 1]).mean() < -1e-6
    # Carried rigidly: x = c + v t + R(w t) (X - c).
    t = st.time
    c = x0[carried].mean(axis=0)
    ang = np.linalg.norm(w) * t
    R = np.array([[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]])
    expect = c + v * t + (x0[carried] - c) @ R.T
    np.testing.assert_allclose(x[carried], expect, atol=2e-6)
    # A Python callable giving the same motion moves its set the same way.
    scripted = m.tools.pins[2].indices
    np.testing.assert_allclose(x[scripted] - c_s, x[carried] - c, atol=2e-6)


def _clamped_beam(dx, L=0.2, t=0.05, nc=3, E=1.0e6, nu=0.3, rho=1000.0, **builder):
    """A square beam ``t`` thick and ``L`` long beyond ``nc`` clamped columns (pinned at
    x < 0); returns the model and its tip particles. ``builder``: more ``SceneBuilder``
    arguments (``fit_weight``)."""
    b = we.SceneBuilder(spacing=dx, **builder)
    b.add_box((L / 2 - nc * dx / 2, t / 2, 0.0), (L + nc * dx, t, t), _elastic(E, nu, rho), name="beam")
    b.pin(region=((-1, -1, -1), (-1e-9, 1, 1)), name="clamp")
    m = b.finalize()
    x0 = m.particle_x0
    return m, np.nonzero(x0[:, 0] > x0[:, 0].max() - 0.5 * dx)[0]


def _cantilever_theory(m, tip, L, t, E, nu, rho):
    """The tip deflection of Euler-Bernoulli + Timoshenko shear (kappa = 0.85) under the own
    weight, with the clamp line at the centre of the outermost held column (the tip test's
    docstring says why)."""
    x0 = m.particle_x0
    clamp_line = x0[m.tools.pins[0].indices, 0].max()
    Lc, xt = L - clamp_line, x0[tip, 0].mean() - clamp_line
    A, I, G_ = t * t, t**4 / 12, E / (2 * (1 + nu))
    q = rho * G * A
    return q * xt**2 * (6 * Lc * Lc - 4 * Lc * xt + xt * xt) / (24 * E * I) + q * (Lc * xt - xt * xt / 2) / (0.85 * G_ * A)


def _clamp_carries_the_weight(s, m, st):
    """The clamp's reaction is the beam's weight (static), and its moment the weight's moment
    about the clamp's reference point (its pose position, the clamp centroid)."""
    force, torque = s.reaction_forces(st)["clamp"]
    mass = m.particle_mass.numpy()
    weight = mass.sum() * G
    print(f"clamp force {force} N vs weight {weight:.4f} N")
    np.testing.assert_allclose(force, [0.0, weight, 0.0], atol=1e-2 * weight)
    xc = m.particle_x0[m.tools.pins[0].indices].mean(axis=0)
    arm = (mass * (st.x.numpy()[:, 0] - xc[0])).sum() / mass.sum()
    assert torque[2] == pytest.approx(weight * arm, rel=0.02)


@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
def test_clamped_cantilever_bends_like_a_beam_and_the_clamp_carries_its_weight(fit):
    """Clamped at x < 0 (3 particle columns held: deeper than the support radius, so the
    held particles' own fits are interior ones), 5 x 5 cm section (5 particles across), own
    weight. Static tip deflection vs Euler-Bernoulli + Timoshenko shear (kappa = 0.85). The
    theory's clamp line is the centre of the outermost held column (x = -dx/2), as the
    beam's supports are particle centres: a held particle fixes its position only, and the
    fits of the particles on both sides of x = 0 span the half spacing in between, so that
    strip deforms (the free length is L + dx/2 = 20.5 cm; measured with the clamp line at
    x = 0 instead: 1.39). With either fit it then agrees with the simply supported beam of
    the same thickness (docs/validation.md, "Clamped cantilever"). The corrected fit runs with
    the hourglass control the default runs for this scene (``Solver(m)``: this fit at
    ``AUTO_HOURGLASS``): without it the biweight's beam takes an interior checkerboard near the
    clamp and sags 1.127 x (the test below)."""
    E, nu, rho, dx, L, t = 1.0e6, 0.3, 1000.0, 0.01, 0.2, 0.05
    m, tip = _clamped_beam(dx, L, t, E=E, nu=nu, rho=rho)
    x0 = m.particle_x0
    s = we.Solver(m, fit=fit, hourglass=0.0 if fit == "linear" else AUTO_HOURGLASS)
    # The corrected fit settles later (docs/physics.md, "After the change"): with the control,
    # measured 1.087 / 1.057 at 900 steps, 1.060 / 1.057 at 1400 (poly6 / biweight fit
    # weight), the clamp's force off the weight by 1.4e-2 / 8.1e-3 of it at 900 steps and by
    # 3e-4 / 2.0e-3 at 1400 (the linear fit at 900: 1.262 / 1.345, 7.0e-3 / 3.6e-3). Those
    # steps were the full wave limit's; this fit's stable step is half of it (docs/method.md
    # §8), so it runs 2800 for the same time: 1.055 (biweight; 1.057 at the full limit). It is
    # read at 2000 (the suite's cost; measured: 1.0563, the clamp carrying 1.0010 of the weight
    # and 1.0018 of its moment, against 1.0549, 1.0004 and 1.0007 at 2800; at 1600 the force
    # read 0.9977, at 1400 0.9646; poly6 at 2000: 1.0580, 0.9994, 0.9988).
    st = _run(s, m, 900 if fit == "linear" else 2000, s.stable_dt(), relax_after=0.0)
    sag = st.x.numpy()[tip, 1].mean() - x0[tip, 1].mean()
    assert x0[m.tools.pins[0].indices, 0].max() == pytest.approx(-dx / 2)  # the clamp line
    ratio = -sag / _cantilever_theory(m, tip, L, t, E, nu, rho)
    print(f"cantilever tip deflection / (Euler-Bernoulli + shear) = {ratio:.3f}")
    assert sag < 0.0
    # The fit's bending deficit at 5 across, as the simply supported beam's at the same
    # thickness (static solutions, docs/validation.md: cantilever 1.253 / 1.066, beam 5 thick
    # 1.217 / 1.040, linear / corrected fit); measured here: 1.262 (900 steps) / 1.060 (1400,
    # with the control; 1.066 without).
    if fit == "linear":
        assert 1.15 < ratio < 1.35
    else:
        assert ratio == pytest.approx(1.0, abs=0.10)  # the beam tests' 10 %
    _clamp_carries_the_weight(s, m, st)


@pytest.mark.parametrize("fit_weight", ["poly6", "biweight"])
def test_cantilever_on_the_corrected_fit_without_the_control_by_fit_weight(fit_weight):
    """The cantilever above on the curvature-corrected fit without the hourglass control.
    With poly6 it settles at 1.066 x the theory (the static solution of its discretisation,
    ``benchmarks/static_stiffness.py``, 1.066). With the biweight the static solution is 1.061,
    but the dynamic beam settles later and deeper: 1.093, 1.122, 1.127, 1.127 at 1400, 2000,
    3000, 4000 steps, the clamp carrying 0.979, 0.994, 0.9998, 1.0000 of the weight: what it
    misses is the momentum rate of the still sinking beam (-2.1 % of the weight at 1400 steps),
    as the internal forces sum to within 3e-7 of it. The excess is the interior checkerboard
    ``(-1)^(i+j+k)`` (zero energy for the linear part of every interior fit) in the 3 x 3 core
    near the clamp, its particles up to 0.23 dx off the static solution; the amplitude read
    below 0.081 dx (poly6: 0.0038 dx, the smooth bend's second difference). The control
    removes it (the test above). Read at rest: 2000 / 3000 steps (poly6 at 1400: 1.0725, the
    clamp 0.9 % over the weight, still settling since ``come_to_rest`` (benchmarks/validation.py)
    stops the beam where zeroing the velocities left it the step's ``dt a / 2``; 1.0656 and
    4e-4 at 2000). Those are steps of the full wave limit, twice this fit's stable step
    (docs/method.md §8): run at the stable step for the same times, 4000 / 6000 steps, it reads
    1.0647 / 1.1246, checkerboard 3.85e-3 / 8.05e-2 dx (1.0656 / 1.1266 at the full limit).

    The test reads them at 2400 / 4000 steps (the suite's cost): measured, poly6 1.0703,
    checkerboard 3.83e-3 dx, the clamp carrying 1.0030 of the weight and 1.0045 of its moment
    (1.0730, 1.0041, 1.0066 at 2000); the biweight 1.1206, 8.03e-2 dx, 0.9970 and 0.9952 (at
    3200 still 1.1177 but the clamp 0.9810 of the weight: sinking). The checkerboard that
    tells the two apart is there from the start: the biweight's 6.7e-2 dx at 1600 steps
    already, where poly6's reads 4.0e-3."""
    E, nu, rho, dx, L, t = 1.0e6, 0.3, 1000.0, 0.01, 0.2, 0.05
    m, tip = _clamped_beam(dx, L, t, E=E, nu=nu, rho=rho, fit_weight=fit_weight)
    x0 = m.particle_x0
    s = we.Solver(m, fit="curvature_corrected", hourglass=0.0)
    st = _run(s, m, 2400 if fit_weight == "poly6" else 4000, s.stable_dt(), relax_after=0.0)
    u = st.x.numpy() - x0
    ratio = -u[tip, 1].mean() / _cantilever_theory(m, tip, L, t, E, nu, rho)
    # The checkerboard's amplitude: each core particle's offset from the mean of its six face
    # neighbours (a smooth field's is of order its second difference), signed by its parity,
    # averaged over the 3 x 3 core of the first 6 free columns (x = 0.5 .. 5.5 dx).
    k = np.rint((x0 - x0.min(axis=0)) / dx).astype(int)
    grid = np.zeros(k.max(axis=0) + 1, dtype=int)
    grid[k[:, 0], k[:, 1], k[:, 2]] = np.arange(len(k))
    U = u[grid]
    c = U[3:9, 1:4, 1:4]
    faces = (U[2:8, 1:4, 1:4] + U[4:10, 1:4, 1:4] + U[3:9, 0:3, 1:4] + U[3:9, 2:5, 1:4] + U[3:9, 1:4, 0:3]
             + U[3:9, 1:4, 2:5]) / 6.0
    parity = np.where(np.indices(c.shape[:3]).sum(axis=0) % 2 == 0, 1.0, -1.0)[..., None]
    checkerboard = np.abs((parity * (c - faces)).mean(axis=(0, 1, 2))).max() / 2.0 / dx
    print(f"{fit_weight}: tip / theory {ratio:.4f}, checkerboard {checkerboard:.2e} dx")
    _clamp_carries_the_weight(s, m, st)
    if fit_weight == "poly6":
        assert ratio == pytest.approx(1.0, abs=0.10) and checkerboard < 0.01
    else:
        assert 1.10 < ratio < 1.16 and checkerboard > 0.04


def test_kinetic_damping_stops_the_held_cantilever_without_pumping_its_edge_mode():
    """The held cantilever (the default solver: for this elastic beam the corrected fit on the
    rest model, the control at 0.05; float32; its stable step, ``Solver.stable_dt()``, the full
    wave limit) without gravity, so that its rest state is an equilibrium, started with the
    mode that grew in it: its two opposite long edges moving along (0, -1, 1), 1 cm/s, signs at
    random along the beam. Kinetic damping must take the energy out. Zeroing the velocities
    (before ``come_to_rest``) pumped that mode (at this step omega dt = 0.46 with the biweight,
    measured on the incremental composition: the zeroings fell every 20 steps in step with it,
    each adding up to the 1 / (1 - (omega dt / 2)^2) = 1.056 of ``come_to_rest``'s docstring):
    0.139 / 0.348 x the seed's energy after 500 / 1000 steps. Stopped at ``v = -dt a / 2``: 0.040 / 0.027. Undamped the same start keeps 0.64 /
    0.63 x of it after 1000 / 2000 steps: not the step. The biweight is named: the scene where
    it was found. That scene ran the corrected fit on the incremental composition
    (``Solver(fit="curvature_corrected")``) at this step, 2 x that path's stable step now
    (``CORRECTED_INCREMENTAL_STEP``); at its own step, omega dt 0.23 (bound 1.013), zeroing
    does not pump the mode (0.058 / 0.025 after 1000 / 2000 steps, the stop 0.028 / 0.014), so
    the guard runs the default solver, at whose step (the full wave limit) zeroing pumps it."""
    dx, L, t, nc = 0.01, 0.2, 0.05, 3
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), fit_weight="biweight")
    b.add_box((L / 2 - nc * dx / 2, t / 2, 0.0), (L + nc * dx, t, t), _elastic(1.0e6), name="beam")
    b.pin(region=((-1, -1, -1), (-1e-9, 1, 1)), name="clamp")
    m = b.finalize()
    s = we.Solver(m)
    assert s.fit == "curvature_corrected" and s.rest_model and s.hourglass == AUTO_HOURGLASS
    dt = s.stable_dt()
    x0 = m.particle_x0
    k = np.rint((x0 - x0.min(axis=0)) / dx).astype(int)
    edge = ((k[:, 1] == 4) & (k[:, 2] == 0)) | ((k[:, 1] == 0) & (k[:, 2] == 4))
    edge &= k[:, 0] >= nc
    sign = np.random.default_rng(0).choice([-1.0, 1.0], size=k[:, 0].max() + 1)
    v = np.zeros_like(x0)
    v[edge] = 1e-2 * sign[k[edge, 0], None] * np.array([0.0, -1.0, 1.0])
    st = m.state()
    st.v.assign(v.astype(np.float32))
    mass = m.particle_mass.numpy().astype(np.float64)[:, None]
    seed = 0.5 * float((mass * v * v).sum())

    def energy(st):
        # The largest kinetic energy over a period of the mode (13.6 steps), undamped: its energy.
        top = 0.0
        for _ in range(14):
            st = _run(s, m, 1, dt, state=st)
            top = max(top, 0.5 * float((mass * st.v.numpy().astype(np.float64) ** 2).sum()))
        return st, top

    st = _run(s, m, 500, dt, relax_after=0.0, state=st)
    st, e1 = energy(st)
    st = _run(s, m, 500, dt, relax_after=0.0, state=st)
    st, e2 = energy(st)
    print(f"kinetic energy after 500 / 1000 damped steps: {e1 / seed:.3f} / {e2 / seed:.3f} x the seed's")
    assert e2 < e1 < seed


def test_cantilever_8_across_settles_with_the_hourglass_control():
    """The 8-across cantilever (same beam, dx = 6.25 mm, 2240 particles) kept sagging under
    kinetic damping without the control: 1.18, 1.38, 1.43, 1.43 x the theory (clamp line at
    the held centres) at 900, 1800, 3600, 5400 steps, past the static solution's 1.099. With
    ``Solver(fit="linear", hourglass=0.1)`` it settled: 1.101, 1.105, 1.095, 1.096
    (docs/physics.md, "Still open: the cantilever at 8 across does not settle"), as the beam of
    that thickness (8 thick: 1.084 static). Those are poly6's, the fit weight then; with the
    biweight, the default since, 1.17, 1.25, 1.37, 1.40 without the control and 1.124, 1.127,
    1.117, 1.117 with it, at its static solution's 1.125 (its linear fit is softer in bending).
    So the test runs the linear fit: the default fit, for this elastic beam the
    curvature-corrected one, settles without the control as well (measured 1.029, 1.031,
    1.0325 at 900, 1000, 1200 steps with ``hourglass=0``, 1.026, 1.028, 1.029 with 0.1; poly6
    1.030, 1.032, 1.033 and 1.027, 1.029, 1.030), and could not tell the control's absence.
    CI size: read at 900 and 1000 steps of the linear fit's stable step (the full wave limit),
    the kinetic damping stopping at ``v = -dt a / 2`` (``come_to_rest``): measured with the
    control 1.124, 1.128, 1.129 at 900, 1000, 1200 steps; without it 1.172, 1.237, 1.248: off
    the theory by more than the 0.15 asked at 900 steps, and 5.5 % deeper 100 steps later
    against the 2 % asked of a settled beam. Recorded here before: 1.099, 1.103, 1.104 and
    1.178, 1.369, 1.383, poly6's: this test run with ``fit_weight="poly6"`` reads them today to
    the last digit (1.0989, 1.1030, 1.1038 and 1.1784, 1.3688, 1.3833), so the switch of weight
    moved them, not the damping's stop, the clamp line or the step."""
    E, nu, rho, L, t, n = 1.0e6, 0.3, 1000.0, 0.2, 0.05, 8
    dx = t / n
    m, tip = _clamped_beam(dx, L, t, E=E, nu=nu, rho=rho)
    x0 = m.particle_x0
    ref = _cantilever_theory(m, tip, L, t, E, nu, rho)
    s = we.Solver(m, fit="linear", hourglass=0.1)
    dt = s.stable_dt()  # the linear fit's: the full wave limit
    st = _run(s, m, 900, dt, relax_after=0.0)
    r1 = -(st.x.numpy()[tip, 1].mean() - x0[tip, 1].mean()) / ref
    st2 = _run(s, m, 100, dt, relax_after=0.0, state=st)
    r2 = -(st2.x.numpy()[tip, 1].mean() - x0[tip, 1].mean()) / ref
    print(f"8 across, linear fit, hourglass 0.1: {r1:.4f} at 900 steps, {r2:.4f} at 1000")
    assert r1 == pytest.approx(1.0, abs=0.15) and r2 == pytest.approx(1.0, abs=0.15)
    assert r2 == pytest.approx(r1, rel=0.02)  # settled (without the control +5.5 % from 900 to 1000 steps, poly6 +16 %)


def test_particle_floor_is_pinned_and_holds_a_resting_block_its_pin_reaction_is_the_weight():
    """``add_particle_floor``: two pinned layers of the block's own particles under its
    footprint plus 2 dx. After dynamic relaxation and 100 free steps the floor particles are
    bit for bit where they started, the block's free particles do not move on average, and
    the floor's reaction row carries the weight of the whole body (block and floor: a pinned
    set's reaction is the force its support adds, docs/tools.md). Measured: 2e-4 of the
    weight (ringing), mean velocity 1e-5 m/s against g t = 0.36 m/s."""
    dx = 0.02
    b = we.SceneBuilder(spacing=dx)
    blk = b.add_box((0.0, 0.05, 0.0), (0.1, 0.1, 0.1), _elastic(2e5, viscosity=1.0), name="block")
    n_block = b.particle_count
    name = b.add_particle_floor(blk, margin=2 * dx)
    m = b.finalize()
    x0 = m.particle_x0
    pin = m.tools.pins[0].indices
    assert name == "block_floor" and m.bodies[0].count == m.particle_count  # the floor is the body's
    np.testing.assert_array_equal(pin, np.arange(n_block, m.particle_count))
    # Two layers, dx apart, the top one dx below the block; under every column within 2 dx
    # of the block's 5 x 5: 5 x 5, 2 rows of 5 on each side, and at each corner only the
    # column at offset (1, 1) dx ((1, 2) is sqrt(5) dx away).
    block, floor = x0[:n_block], x0[pin]
    np.testing.assert_allclose(np.unique(floor[:, 1]), block[:, 1].min() - dx * np.array([2.0, 1.0]), atol=1e-7)
    assert len(pin) == 2 * (25 + 4 * 2 * 5 + 4 * 1)
    s = we.Solver(m)
    dt = m.stable_dt()
    st = _run(s, m, 400, dt, relax_after=0.0)
    st = _run(s, m, 100, dt, state=st)
    x, v = st.x.numpy(), st.v.numpy()
    np.testing.assert_array_equal(x[pin], x0[pin])
    free_v = v[:n_block].astype(np.float64).mean(axis=0)
    assert np.abs(free_v).max() < 1e-3 * G * 100 * dt, free_v
    assert abs((x[:n_block, 1] - x0[:n_block, 1]).mean()) < 0.05 * dx  # supported: it did not sink
    force, _ = s.reaction_forces(st)[name]
    weight = float(m.particle_mass.numpy().astype(np.float64).sum()) * G
    print(f"floor reaction {force} N vs weight {weight:.5f} N")
    np.testing.assert_allclose(force, [0.0, weight, 0.0], atol=1e-3 * weight)


@pytest.mark.parametrize("call,match", [
    (lambda b: b.add_particle_floor("nope", margin=0.0), r"body = 'nope' is not allowed: must be one of \['d', 'e'\]"),
    (lambda b: b.add_particle_floor(5, margin=0.0), r"body = 5 is not allowed: must be a body name or index \(0\.\.1\)"),
    (lambda b: b.add_particle_floor(True, margin=0.0), r"body = True is not allowed"),
    (lambda b: b.add_particle_floor("d", margin=0.0), r"body = 'd' is not allowed: .*must be the body added last \('e'\)"),
    (lambda b: b.add_particle_floor("e", margin=-0.1), r"margin = -0\.1 is not allowed: must be >= 0"),
    (lambda b: b.add_particle_floor("e", margin=float("nan")), r"margin = nan is not allowed"),
    (lambda b: b.add_particle_floor("e", margin=0.0, layers=0), r"layers = 0 is not allowed: must be an integer >= 1"),
    (lambda b: b.add_particle_floor("e", margin=0.0, layers=9), r"layers = 9 is not allowed: must be an integer in \[1, 8\]"),
    (lambda b: b.add_particle_floor("e", margin=0.0, layers=2.0), r"layers = 2\.0 is not allowed"),
    (lambda b: b.add_particle_floor("e", margin=1e6), r"margin = 1000000\.0 is not allowed: .*more than"),
    (lambda b: b.add_particle_floor("e", margin=1e300), r"margin = 1e\+300 is not allowed: .*inf particles"),
    # margin / spacing past the float range (1e308 / 0.02) is inf spacings: an OverflowError from math.floor.
    (lambda b: b.add_particle_floor("e", margin=1e308), r"margin = 1e\+308 is not allowed: .*inf particles"),
    (lambda b: b.add_particle_floor("e", margin=30.0), r"margin = 30\.0 is not allowed: .*1500 spacings .*column operations"),
    (lambda b: b.add_particle_floor("e", margin=0.0, where="disc"), r"where = 'disc' is not allowed: must be callable"),
    (lambda b: b.add_particle_floor("e", margin=0.0, where=lambda p: p[:, 0] > 1e3), r"keeps none of the floor's positions"),
    (lambda b: b.add_particle_floor("e", margin=0.0, where=lambda p: True), r"where is not allowed: it returned shape \(\)"),
    (lambda b: b.add_particle_floor("e", margin=0.0, where=lambda p: p.foo),
     r"where is not allowed: where\(floor_positions\) raised AttributeError"),
    # A float result was cast to bool: every position off x = 0 kept.
    (lambda b: b.add_particle_floor("e", margin=0.0, where=lambda p: p[:, 0]),
     r"where is not allowed: it returned float64 values; it must return a bool array"),
    (lambda b: b.pin(where=lambda p: 1 / 0), r"where is not allowed: where\(rest_positions\) raised ZeroDivisionError"),
    (lambda b: b.pin(where=lambda p: np.full(len(p), np.nan)), r"it returned float64 values"),
    (lambda b: b.pin(indices=[]), r"pin 'pin0' is not allowed: indices = \[\] select no particle"),
    (lambda b: b.pin(region=((-np.inf,) * 3, (np.inf,) * 3)), r"two 3-vectors of finite numbers"),
    (lambda b: b.add_particle_floor("e", margin=0.0, name=""), r"name = '' is not allowed"),
    (lambda b: (b.pin(indices=[0]), b.add_particle_floor("e", margin=0.0, name="pin0")), r"name = 'pin0' is not allowed"),
    (lambda b: (b.add_particle_floor("e", margin=0.0), b.add_particle_floor("e", margin=0.0, name="f2")),
     r"body = 'e' is not allowed: it has a particle floor already"),
    (lambda b: b.add_particle_floor("e", margin=0.0, elastic=1), r"elastic = 1 is not allowed: must be True or False"),
])
def test_bad_particle_floor_input_is_refused_by_name_and_leaves_the_builder_unchanged(call, match):
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0, 0, 0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    b.add_box((1, 0, 0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="e")
    with pytest.raises(ValueError, match=match):
        call(b)
    floors = len([p for p in b.pins if p.name.endswith("floor")])
    assert b.particle_count == 250 + 2 * 25 * floors and sum(x.count for x in b._bodies) == b.particle_count
    assert len(b._materials) == 2


def test_elastic_particle_floor_is_the_bodys_material_without_yield_and_leaves_the_bodys_own():
    """``add_particle_floor(elastic=True)``: the floor particles get the body's material with
    ``yield_stress = inf`` and every other field the same, as a material of their own after
    the body's; the body keeps its material; an elastic body's floor shares its material; the
    default floor is of the body's own material."""
    dough = we.Material.preset("dough")
    for elastic, mat, n_materials in ((True, dough, 2), (False, dough, 1), (True, _elastic(2e5), 1)):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.05, 0.0), (0.1, 0.1, 0.1), mat, name="d")
        n_body = b.particle_count
        b.add_particle_floor("d", margin=0.0, elastic=elastic)
        m = b.finalize()
        ids = m.particle_material_np
        assert len(m.materials) == n_materials
        assert (ids[:n_body] == 0).all() and (ids[n_body:] == n_materials - 1).all()
        assert m.materials[0] == mat
        assert m.materials[-1] == (dataclasses.replace(mat, yield_stress=math.inf) if elastic else mat)
        assert m.yield_stress.numpy()[-1] == (np.inf if elastic else mat.yield_stress)
        assert m.bodies[0].floor_material == (1 if n_materials == 2 else -1)


def test_fits_leave_an_elastic_particle_floors_material_as_built():
    """The elastic floor's material is a wall's: a fit of every material or of the body's
    (by name) leaves it out, an explicit index still selects it, and ``split_materials``
    gives the body's particles a material each but keeps the floor's one, still marked."""
    from warp_esph.fit import _material_indices  # noqa: PLC0415
    from warp_esph.rollout import split_materials  # noqa: PLC0415

    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.05, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    n_body = b.particle_count
    b.add_particle_floor("d", margin=0.0, elastic=True)
    m = b.finalize()
    assert _material_indices(m, None) == [0] and _material_indices(m, "d") == [0] and _material_indices(m, 1) == [1]
    sm = split_materials(m)
    wall = sm.bodies[0].floor_material
    assert len(sm.materials) == n_body + 1 and sm.materials[wall].yield_stress == math.inf
    assert (sm.particle_material_np[n_body:] == wall).all()
    assert len(set(sm.particle_material_np[:n_body].tolist())) == n_body
    assert sorted(_material_indices(sm, "d")) == sorted(set(range(n_body + 1)) - {wall})


# ------------------------------------------------------------------ plates and meshes
@pytest.mark.parametrize("shape", ["mesh", "box"])
def test_fast_blade_does_not_tunnel_and_momentum_balances_the_impulse(shape):
    """A 2 mm blade (a closed box mesh, or a box) sweeps at 20 m/s through a block: it moves
    about 4 mm a step, twice its thickness, so an end-of-step inside test alone would let
    particles through. Every particle in the blade's path must end in front of it."""
    dx = 0.02
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), _elastic(2e4), name="block")
    half = (0.001, 0.2, 0.2)
    speed = 20.0
    geometry = {"mesh": tools.box_mesh(half)} if shape == "mesh" else {"half_extents": half}
    b.add_tool(shape, **geometry, motion=tools.Velocity((speed, 0, 0), position=(-0.08, 0, 0)), name="blade")
    m = b.finalize(dtype=wp.float64)
    s = we.Solver(m)
    dt = 2e-4
    assert speed * dt > 2 * half[0] * 1.9
    steps = 20  # blade from x = -0.08 to 0.0
    a, c = m.state(), m.state()
    mass = m.particle_mass.numpy()[:, None]
    p0 = (mass * a.v.numpy()).sum(axis=0)
    impulse = np.zeros(3)
    for _ in range(steps):
        s.step(a, c, dt)
        a, c = c, a
        impulse += s.reaction_forces(a)["blade"][0] * dt
    x = a.x.numpy()
    front = -0.08 + speed * steps * dt + half[0]
    assert (x[:, 0] >= front - 1e-9).all(), x[:, 0].min() - front
    assert impulse[0] > 0.0
    # Internal forces cancel in pairs and there is no gravity: the material's momentum
    # changed by exactly the blade's impulse on it (minus the impulse on the blade).
    p1 = (mass * a.v.numpy()).sum(axis=0)
    np.testing.assert_allclose(p1 - p0, impulse, rtol=1e-9, atol=1e-12 * np.abs(impulse).max())


# The rods drag the particles of their row out of the block, whose rest neighbourhoods (the
# elastic default runs the rest model, tools included) then stretch past the rows' reach of 2:
# the step says so, as it must; this test is about tunnelling and momentum, not smoothness.
@pytest.mark.filterwarnings("ignore:a neighbour row was cut:RuntimeWarning")
@pytest.mark.parametrize("shape", ["sphere", "capsule", "cylinder", "box", "mesh", "plane"])
def test_fast_primitive_does_not_tunnel_at_the_stable_step_and_momentum_balances_the_impulse(shape):
    """A 2 mm thick sphere, or a rod across the block (capsule, cylinder, square box or box
    mesh, long axis along z) moves 2.5 times its thickness per step, at the material's
    stable step, through a row of particles: tested on its end-of-step position alone, it
    would step over them. Every particle in its path must end in front of it, none inside
    it; a fast plane (a half-space, which cannot be stepped over) checks the same
    bookkeeping."""
    r, hh = 0.001, 0.2
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), _elastic(2e4), name="block")
    m0 = b.finalize(dtype=wp.float64)
    dt = m0.stable_dt()
    speed = 2.5 * 2 * r / dt
    y_to_z = (np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4))  # the tool's y axis along world z
    geometry = {
        "sphere": {"radius": r}, "capsule": {"radius": r, "half_height": hh, "orientation": y_to_z},
        "cylinder": {"radius": r, "half_height": hh, "orientation": y_to_z}, "plane": {"normal": (1.0, 0.0, 0.0)},
        "box": {"half_extents": (r, r, hh)}, "mesh": {"mesh": tools.box_mesh((r, r, hh))},
    }[shape]
    start = -0.06
    b.add_tool(shape, **geometry, motion=tools.Velocity((speed, 0, 0), position=(start, 0, 0)), name="t")
    m = b.finalize(dtype=wp.float64)
    s = we.Solver(m)
    a, c = m.state(), m.state()
    mass = m.particle_mass.numpy()[:, None]
    p0 = (mass * a.v.numpy()).sum(axis=0)
    impulse = np.zeros(3)
    steps = 16  # the tool from x = -0.06 to 0.02, through three particles of its row
    for _ in range(steps):
        s.step(a, c, dt)
        a, c = c, a
        impulse += s.reaction_forces(a)["t"][0] * dt
    x = a.x.numpy()
    rel = x - np.array([start + speed * steps * dt, 0.0, 0.0])
    if shape == "sphere":
        lateral = np.hypot(rel[:, 1], rel[:, 2]) < r
        inside = np.linalg.norm(rel, axis=1) < r - 1e-9
    elif shape == "plane":
        lateral = np.ones(len(x), dtype=bool)
        inside = rel[:, 0] < -1e-9
    else:
        lateral = (np.abs(rel[:, 1]) < r) & (np.abs(rel[:, 2]) < hh)
        inside = lateral & (np.abs(rel[:, 0]) < r - 1e-9)
    in_path = (np.abs(m.particle_x0[:, 1]) < r) & (np.abs(m.particle_x0[:, 2]) < (r if shape == "sphere" else 1.0))
    in_path &= m.particle_x0[:, 0] < rel[:, 0].max()
    assert in_path.sum() >= 3  # the check is not vacuous
    behind = lateral & (rel[:, 0] < -1e-9)
    assert not inside.any() and not behind.any(), (inside.sum(), behind.sum())
    assert (rel[in_path, 0] >= -1e-9).all()
    assert impulse[0] > 0.0
    # No gravity, internal forces cancel in pairs: the material's momentum changed by the
    # impulse the tool gave it (minus the impulse on the tool).
    p1 = (mass * a.v.numpy()).sum(axis=0)
    np.testing.assert_allclose(p1 - p0, impulse, rtol=1e-9, atol=1e-12 * np.abs(impulse).max())


@pytest.mark.parametrize("shape,kw", [
    ("sphere", {"radius": 0.05}), ("capsule", {"radius": 0.04, "half_height": 0.05}),
    ("cylinder", {"radius": 0.04, "half_height": 0.05}), ("box", {"half_extents": (0.04, 0.04, 0.04)}),
])
def test_rotating_primitive_keeps_particles_out(shape, kw):
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.2, 0.0), (0.12, 0.06, 0.12), _elastic(5e4, viscosity=2.0), name="slab")
    q = (np.sin(0.3), 0.0, 0.0, np.cos(0.3))
    b.add_tool(shape, motion=tools.Velocity((0, 0.3, 0), (0, 0, 4.0), position=(0, 0.08, 0), orientation=q), name="t", **kw)
    m = b.finalize()
    s = we.Solver(m)
    st, spare = m.state(), m.state()
    impulse = np.zeros(3)
    for _ in range(300):
        s.step(st, spare, 5e-4)
        st, spare = spare, st
        impulse += s.reaction_forces(st)["t"][0] * 5e-4
    p, qq = m.tools.pose(st)["t"]
    xl = (st.x.numpy() - p) @ tools.quat_to_matrix(qq)  # rows: R^T (x - p)
    if shape == "sphere":
        inside = np.linalg.norm(xl, axis=1) < kw["radius"] - 1e-5
    elif shape == "capsule":
        y = np.clip(xl[:, 1], -kw["half_height"], kw["half_height"])
        inside = np.linalg.norm(xl - np.stack([0 * y, y, 0 * y], 1), axis=1) < kw["radius"] - 1e-5
    elif shape == "cylinder":
        inside = (np.hypot(xl[:, 0], xl[:, 2]) < kw["radius"] - 1e-5) & (np.abs(xl[:, 1]) < kw["half_height"] - 1e-5)
    else:
        inside = np.all(np.abs(xl) < np.array(kw["half_extents"]) - 1e-5, axis=1)
    assert not inside.any()
    assert impulse[1] > 0.0  # the tool met the slab and pushed it up


# -------------------------------------------------------------------------- gradients
STEPS, DT = 8, 1e-3


def _grad_model(friction=0.3, press_v=-0.5, key_y=0.0, E=5e3):
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(E, viscosity=1.0), name="block", velocity=(0.4, 0.0, 0.1))
    # The floor on the base layer's centres and the pusher touching the block: a start inside
    # a tool is placed on its surface at finalize, a block thinned where it met it.
    b.add_tool("plane", position=(0, 0.01, 0), friction=friction, name="floor")
    b.add_tool("box", half_extents=(0.1, 0.01, 0.1), friction=0.2,
               motion=tools.Velocity((0, press_v, 0), position=(0, 0.0602, 0)), name="press")
    b.add_tool("sphere", radius=0.03, friction=0.1,
               motion=tools.Keyframes([0.0, 0.01], [(-0.05, 0.03, 0.0), (-0.035 + key_y, 0.03, 0.0)]), name="pusher")
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    m.particle_x0 += np.random.default_rng(3).normal(scale=2e-5, size=m.particle_x0.shape)
    return m


@wp.kernel(module="unique")
def _loss_kernel(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), rf: wp.array(dtype=wp.vec3d), k: int,
                 c: wp.float64, loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], w[i]))
    if i == 0:
        wp.atomic_add(loss, 0, c * rf[k][1])


def _loss(model, grad=False):
    s = we.Solver(model)
    # The elastic block runs the default's rest model, tools and all: the tape through the
    # tools' contact is checked on it.
    assert s.rest_model
    states = [model.state() for _ in range(STEPS + 1)]
    n = model.particle_count
    w = wp.array(np.random.default_rng(7).normal(size=(n, 3)), dtype=wp.vec3d, requires_grad=False)
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    press = model.tools.index("press")
    tape = wp.Tape()
    with tape:
        for k in range(STEPS):
            s.step(states[k], states[k + 1], DT)
            # A loss on every step's press reaction: a force-displacement curve.
            wp.launch(_loss_kernel, n, [states[k + 1].x, w, states[k + 1].reaction_force, press, 1e-3], [loss])
    value = loss.numpy()[0]
    if not grad:
        return value
    tape.backward(loss)
    t = model.tools
    out = {
        "friction": t.friction.grad.numpy()[t.index("floor")],
        "press_v": t.velocity.grad.numpy()[t.index("press")][1],
        "key_y": t.keyframe_positions.grad.numpy()[t.keyframe_start[t.index("pusher")] + 1][0],
        "mu": model.mu.grad.numpy()[0],
    }
    # Contacts happen: the check is not vacuous.
    rf = np.array([st.reaction_force.numpy() for st in states[1:]])
    assert np.abs(rf[:, t.index("floor")]).max() > 0 and np.abs(rf[:, press]).max() > 0 and np.abs(rf[:, t.index("pusher")]).max() > 0
    return value, out


def test_gradients_of_friction_tool_velocity_keyframe_and_a_reaction_force_loss_match_central_differences():
    _, g = _loss(_grad_model(), grad=True)
    h = {"friction": 1e-5, "press_v": 1e-5, "key_y": 1e-6, "mu": 1e-2}
    base = {"friction": 0.3, "press_v": -0.5, "key_y": 0.0}
    for name in ("friction", "press_v", "key_y"):
        lp = _loss(_grad_model(**{**{name: base[name] + h[name]}}))
        lm = _loss(_grad_model(**{**{name: base[name] - h[name]}}))
        fd = (lp - lm) / (2 * h[name])
        print(name, g[name], fd)
        assert g[name] == pytest.approx(fd, rel=1e-4, abs=1e-9), name
    mu0 = _grad_model().materials[0].mu
    dmu = 1e-4 * mu0

    def with_mu(mu):
        m = _grad_model()
        m.mu.assign(np.array([mu]))
        return _loss(m)

    fd = (with_mu(mu0 + dmu) - with_mu(mu0 - dmu)) / (2 * dmu)
    print("mu", g["mu"], fd)
    assert g["mu"] == pytest.approx(fd, rel=1e-4)


def _floor_grad_model(mu=None, yield_stress=None):
    """A yield-stress block sliding over an elastic particle floor that holds its base."""
    mat = we.Material.from_young(5e3, 0.3, density=1000.0, yield_stress=60.0, flow_rate=50.0, viscosity=1.0,
                                 elastic_force="variational")
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), mat, name="block", velocity=(0.4, 0.0, 0.1))
    b.add_particle_floor("block", margin=0.02, elastic=True)
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    m.particle_x0 += np.random.default_rng(3).normal(scale=2e-5, size=m.particle_x0.shape)
    set_first_material(m, mu=mu, yield_stress=yield_stress)
    return m


def _floor_loss(model, grad=False):
    s = we.Solver(model)
    states = [model.state() for _ in range(STEPS + 1)]
    loss, tape = taped_rollout_loss(s, states, DT, random_weights(model.particle_count, 7))
    if not grad:
        return loss.numpy()[0]
    tape.backward(loss)
    return model.mu.grad.numpy()[0], model.yield_stress.grad.numpy()[0], states[-1].alpha.numpy()


def test_gradients_of_a_block_flowing_over_an_elastic_particle_floor_match_central_differences():
    """The body's mu and yield stress through 8 steps of a dough-like block sliding at
    0.4 m/s over an elastic floor that holds its base (9 of its 27 particles flow): the
    float64 tape against central differences at a relative step of 1e-4. Measured: relative
    differences 7e-9 (mu) and 5e-8 (yield stress)."""
    g_mu, g_y, alpha = _floor_loss(_floor_grad_model(), grad=True)
    assert (alpha[:27] > 0).sum() >= 5  # the block flows: the check is not vacuous
    mu0 = _floor_grad_model().materials[0].mu
    for value, key, p0 in ((g_mu, "mu", mu0), (g_y, "yield_stress", 60.0)):
        h = 1e-4 * p0
        fd = (_floor_loss(_floor_grad_model(**{key: p0 + h})) - _floor_loss(_floor_grad_model(**{key: p0 - h}))) / (2 * h)
        print(key, value, fd)
        assert value == pytest.approx(fd, rel=1e-5, abs=0.0), key


def _mesh_keyframe_model(crossing=False):
    """A frictional mesh press sliding over a block while pressing it, and a box pusher
    keyframed in position and orientation (it turns 0.2 rad about y as it advances).
    ``crossing``: the pusher passes a keyframe mid-step (at 4.5 ms, steps of 1 ms), where it
    turns back, speeds up and rises, and touches the block in that step: keyframe 1 is that
    one."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(5e3, viscosity=1.0), name="block", velocity=(0.4, 0.0, 0.1))
    b.add_tool("plane", position=(0, 0.01, 0), friction=0.3, name="floor")
    b.add_tool("mesh", mesh=tools.box_mesh((0.1, 0.01, 0.1)), friction=0.2,
               motion=tools.Velocity((0.2, -0.5, 0.0), position=(0, 0.0602, 0)), name="press")
    turn = (0.0, np.sin(0.1), 0.0, np.cos(0.1))
    motion = tools.Keyframes([0.0, 0.01], [(-0.045, 0.03, 0.0), (-0.03, 0.03, 0.0)], [tools.IDENTITY, turn])
    if crossing:
        back = (0.0, -np.sin(0.05), 0.0, np.cos(0.05))
        motion = tools.Keyframes([0.0, 0.0045, 0.01], [(-0.045, 0.03, 0.0), (-0.036, 0.03, 0.0), (-0.024, 0.032, 0.0)],
                                 [tools.IDENTITY, turn, back])
    b.add_tool("box", half_extents=(0.02, 0.03, 0.03), friction=0.1, name="pusher", motion=motion)
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    m.particle_x0 += np.random.default_rng(3).normal(scale=2e-5, size=m.particle_x0.shape)
    return m


#: (array of model.tools, tool, row offset (keyframe index), component, step h)
_TOOL_PARAMS = {
    "mesh velocity x": ("velocity", "press", 0, 0, 1e-5),
    "mesh velocity y": ("velocity", "press", 0, 1, 1e-5),
    "mesh friction": ("friction", "press", 0, None, 1e-5),
    "keyframe time": ("keyframe_times", "pusher", 1, None, 1e-7),
    "keyframe position": ("keyframe_positions", "pusher", 1, 0, 1e-6),
    "keyframe orientation": ("keyframe_orientations", "pusher", 1, 1, 1e-6),
}


def _row(t, array, tool, offset):
    k = t.index(tool)
    return (t.keyframe_start[k] + offset) if array.startswith("keyframe") else k


def _perturbed(loss, model, array, row, comp, delta):
    """``loss(model)`` with ``model.tools``' ``array`` moved by ``delta`` at ``row`` (in
    component ``comp``; ``None``: a scalar row), then put back bit for bit: the central
    differences reuse one model (a build per loss was a third of the mesh test's time), and
    its losses are those of fresh models, to the last bit (checked on the mesh, keyframe and
    capsule parameters)."""
    a = getattr(model.tools, array)
    original = a.numpy().copy()
    v = original.copy()
    if comp is None:
        v[row] += delta
    else:
        v[row][comp] += delta
    a.assign(v)
    try:
        return loss(model)
    finally:
        a.assign(original)


@pytest.mark.parametrize("crossing", [False, True])
def test_gradients_of_a_mesh_tool_and_of_keyframe_times_and_orientations_match_central_differences(crossing):
    """Mesh contact (float64 geometry on the face Warp's float32 query picks), its velocity
    and friction; a keyframe's time, position and orientation (raw quaternion component):
    the tape against float64 central differences of the same loss as above. ``crossing``:
    that keyframe falls inside a step, whose velocity and rotation are the pieces of the two
    segments either side of it."""
    model = _mesh_keyframe_model(crossing)
    _loss(model, grad=True)  # (it also checks that every tool touched the block)
    fd_model = _mesh_keyframe_model(crossing)
    t = model.tools
    grads = {name: getattr(t, arr).grad.numpy()[_row(t, arr, tool, off)] for name, (arr, tool, off, _c, _h) in _TOOL_PARAMS.items()}
    for name, (arr, tool, off, comp, h) in _TOOL_PARAMS.items():
        if arr.startswith("keyframe"):
            # A contact starts within 1e-6 m of the crossed keyframe's position (one-sided
            # differences there: -4.59 and +2.85, the tape's -4.5887), which central
            # differences reach to 1e-7 from 1e-7 m down. Without the crossing one starts
            # within 1e-6 m below keyframe 1's x (one-sided at 1e-6: -1.877 and -14.12; at
            # 1e-7 and 1e-8 both within 6e-4 and 6e-5 of the tape's -1.8717).
            h = 1e-8
        g = grads[name] if comp is None else grads[name][comp]
        vals = [_perturbed(_loss, fd_model, arr, _row(t, arr, tool, off), comp, sign * h) for sign in (1, -1)]
        fd = (vals[0] - vals[1]) / (2 * h)
        print(name, g, fd)
        assert g == pytest.approx(fd, rel=1e-4, abs=1e-9), name
        assert abs(fd) > 1e-6, name  # the parameter acts on the loss


@wp.kernel(module="unique")
def _row_loss_kernel(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), rf: wp.array(dtype=wp.vec3d),
                     tq: wp.array(dtype=wp.vec3d), k: int, wf: wp.vec3d, wt: wp.vec3d, loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], w[i]))
    if i == 0:
        wp.atomic_add(loss, 0, wp.dot(rf[k], wf) + wp.dot(tq[k], wt))


def _row_loss(model, row, params=(), steps=STEPS):
    """The positions' weighted sum after ``steps`` plus tool ``row``'s reaction force and
    torque, weighed, at every step; with ``params`` (``(array of model.tools, component)``
    pairs), also the tape's gradient in each, at ``row``. The elastic block runs the
    default's rest model."""
    s = we.Solver(model)
    assert s.rest_model
    states = [model.state() for _ in range(steps + 1)]
    n = model.particle_count
    w = wp.array(np.random.default_rng(7).normal(size=(n, 3)), dtype=wp.vec3d)
    k = model.tools.index(row)
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        for i in range(steps):
            s.step(states[i], states[i + 1], DT)
            wp.launch(_row_loss_kernel, n, [states[i + 1].x, w, states[i + 1].reaction_force, states[i + 1].reaction_torque,
                                            k, wp.vec3d(0.3, 1.0, -0.2), wp.vec3d(20.0, -10.0, 30.0)], [loss])
    touched = max(np.abs(st.reaction_force.numpy()[k]).max() for st in states[1:])
    if not params:
        return loss.numpy()[0], touched
    tape.backward(loss)
    return loss.numpy()[0], touched, [getattr(model.tools, a).grad.numpy()[k][c] for a, c in params]


def _swept_model(shape):
    """A block on a rough plane tool, pressed by a capsule or cylinder tool (standing on its
    axis) that descends onto its top layer while it turns about z."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(5e3, viscosity=1.0), name="block", velocity=(0.1, 0.0, 0.05))
    b.add_tool("plane", position=(0, 0.01, 0), friction=0.3, name="floor")
    # The tool's lowest point starts 1 mm above the top layer's centres.
    low = 0.051 + 0.03 + 0.05 if shape == "capsule" else 0.051 + 0.05
    b.add_tool(shape, radius=0.03, half_height=0.05, friction=0.3, name="roller",
               motion=tools.Velocity((0.0, -0.6, 0.0), (0.0, 0.0, 3.0), position=(0.012, low, 0.004)))
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    m.particle_x0 += np.random.default_rng(3).normal(scale=2e-5, size=m.particle_x0.shape)
    return m


def _pinned_model():
    """A block whose column of particles at one end is pinned and moved: it slides along x
    and turns about z (its neighbours follow through the fit and the pressure only)."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.045, 0.0), (0.1, 0.08, 0.08), _elastic(5e3, viscosity=1.0), name="block")
    b.pin(body="block", region=((-1.0, -1.0, -1.0), (-0.03, 1.0, 1.0)), name="grip",
          motion=tools.Velocity((0.2, 0.0, 0.0), (0.0, 0.0, 1.0)))
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    m.particle_x0 += np.random.default_rng(3).normal(scale=2e-5, size=m.particle_x0.shape)
    return m


_MOTION_PARAMS = (("velocity", 0), ("velocity", 1), ("angular_velocity", 2))


@pytest.mark.parametrize("case", ["capsule", "cylinder", "pin"])
def test_gradients_of_swept_tools_and_moving_pins_and_their_reaction_torque_match_central_differences(case):
    """A capsule and a cylinder tool turning as they press a block, and a pinned set moved
    rigidly (translating and turning): the tape's gradient in their linear and angular
    velocity against float64 central differences, of a loss that weighs the block's final
    positions and the tool's (the pin's) reaction force and torque at every step."""
    make = _pinned_model if case == "pin" else functools.partial(_swept_model, case)
    row = "grip" if case == "pin" else "roller"
    _, touched, grads = _row_loss(make(), row, _MOTION_PARAMS)
    assert touched > 0.0  # the tool touched the block (the pin carried its set)
    fd_model = make()
    h = 1e-6
    for (array, comp), g in zip(_MOTION_PARAMS, grads):
        vals = [_perturbed(lambda m: _row_loss(m, row)[0], fd_model, array, fd_model.tools.index(row), comp, sign * h)
                for sign in (1, -1)]
        fd = (vals[0] - vals[1]) / (2 * h)
        print(case, array, comp, g, fd, abs(g / fd - 1))
        assert abs(fd) > 1e-6, (array, comp)  # the parameter acts on the loss
        assert g == pytest.approx(fd, rel=1e-5), (array, comp)


# ------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("call,match", [
    (lambda b: b.add_tool("cone"), "shape = 'cone' is not allowed: must be one of 'plane', 'box'"),
    (lambda b: b.add_tool("sphere"), "radius = None is not allowed: must be a number"),
    (lambda b: b.add_tool("box", half_extents=(1, -1, 1)), r"half_extents = \(1, -1, 1\) is not allowed: every component must be > 0"),
    (lambda b: b.add_tool("plane", friction=0.5, static_friction=0.2), r"static_friction = 0\.2 is not allowed: must be >= friction = 0\.5"),
    (lambda b: b.add_tool("plane", motion="up"), r"motion = 'up' is not allowed: must be tools\.Keyframes"),
    (lambda b: b.add_tool("mesh"), "mesh = None is not allowed: a mesh tool needs a mesh file"),
    # Warp's mesh queries are float32 in either precision: a mesh at scale 1e39 (or 1e300) was a
    # tool of inf points, with a numpy warning only, and the run went on without it.
    *((lambda b, s=s: b.add_tool("mesh", mesh=tools.box_mesh((1.0, 1.0, 1.0)), scale=s),
       rf"^scale = {re.escape(f'{s:g}')} is not allowed for mesh \(points, triangles\): it puts the mesh's points up to "
       rf"{re.escape(f'{s:.3g}')} m from the "
       r"tool's origin; a mesh tool's points must be within 1\.84e\+19 m of it \(Warp's mesh queries are float32\); give a "
       r"smaller scale$") for s in (1e39, 1e300)),
    (lambda b: b.add_tool("mesh", mesh=tools.box_mesh((1e20, 1e20, 1e20))),
     r"^mesh \(points, triangles\) is not allowed: its points \(scale 1\) lie up to 1e\+20 m from the tool's origin"),
    # The motion's start pose overrode the one beside it without a word.
    (lambda b: b.add_tool("sphere", radius=0.01, position=(0.5, 0.5, 0.5), motion=tools.Velocity((0, -1, 0), position=(0.3, 0.3, 0.3))),
     r"^position = \(0\.5, 0\.5, 0\.5\) is not allowed beside a Velocity motion with position = \(0\.3, 0\.3, 0\.3\): give "
     r"the start pose once \(in the motion, or as add_tool's position with the motion's left None\)$"),
    (lambda b: b.add_tool("plane", orientation=(0, 1, 0, 1), motion=tools.Velocity(orientation=(1, 0, 0, 1))),
     r"^orientation = \(0\.0, 0\.7071.*\) is not allowed beside a Velocity motion with orientation = \(0\.7071"),
    (lambda b: b.pin(), "pin 'pin0': no selection is not allowed: give indices, body, region"),
    (lambda b: b.pin(region=((1, 1, 1), (2, 2, 2))), "pin 'pin0' is not allowed: the selection holds no particle"),
    (lambda b: b.pin(body="nope"), r"body = 'nope' is not allowed: must be one of \['d'\]"),
    (lambda b: b.pin(body=1), r"body = 1 is not allowed: must be a body name or index \(0\.\.0\)"),
    (lambda b: b.pin(body=True), r"body = True is not allowed: must be a body name or index \(0\.\.0\)"),
    (lambda b: b.pin(indices=[0, 10_000]), r"indices = \[0, 10000\] is not allowed: must be integers in \[0, 124\]"),
    (lambda b: (b.pin(indices=[0, 1]), b.pin(indices=[1, 2])), "pin 'pin1' is not allowed: it shares particles with pin 'pin0'"),
    (lambda b: tools.Keyframes([0.0, 0.0], [(0, 0, 0), (1, 0, 0)]), r"times = \[0\.0, 0\.0\] is not allowed: must be one or more finite, increasing"),
    (lambda b: tools.Keyframes([0.0, 1.0], [(0, 0, 0)]),
     r"positions = \[\(0, 0, 0\)\] is not allowed: must be \(2, 3\) finite numbers, one row per time \(it has 1 row\)"),
])
def test_bad_tool_input_is_a_value_error_naming_it(call, match):
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0, 0, 0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    with pytest.raises(ValueError, match=match):
        call(b)


def test_a_pin_takes_a_body_by_its_index_as_the_other_builder_calls_do():
    """``pin(body=k)`` takes the index an ``add_*`` returned, as ``add_particle_floor`` and
    ``add_compression_field`` do (it was refused, 'must be one of ['a', '0']'); a body named
    "0" is still taken by its name."""
    b = we.SceneBuilder(spacing=0.02)
    first = b.add_box((0, 0, 0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="a")
    second = b.add_box((0.5, 0, 0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="0")
    start, count = b._bodies[second].start, b._bodies[second].count
    b.pin(body=np.int64(second), name="by_index")
    assert (first, second) == (0, 1) and b.pins[0].indices.tolist() == list(range(start, start + count))
    assert tools.select_particles(b, body="0", name="by_name").tolist() == list(range(start, start + count))


def test_a_body_starting_inside_a_mesh_tool_is_refused_as_inside_the_other_shapes():
    """A box mesh tool in the middle of a block was not measured at all (only the primitive
    shapes were): the first steps pushed the particles inside out onto its faces and read
    69 N on it. Refused as the box tool of the same size is; the same mesh resting on the
    block's top is taken, turned or not."""
    def builder():
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.05, 0.0), (0.04, 0.04, 0.04), we.Material.preset("clay"), name="blk")
        return b

    for shape, geometry in (("mesh", {"mesh": tools.box_mesh((0.03,) * 3)}), ("box", {"half_extents": (0.03,) * 3})):
        b = builder()
        b.add_tool(shape, position=(0.0, 0.05, 0.0), name="m", **geometry)
        with pytest.raises(ValueError, match=r"^body 'blk' is not allowed where it is: 8 of its particles start inside "
                                             r"tool 'm' at its first pose, up to 0\.02 m deep"):
            b.finalize()
    b = builder()
    b.add_tool("mesh", mesh=tools.box_mesh((0.05, 0.01, 0.05)), position=(0.0, 0.09, 0.0), name="m")
    b.add_tool("mesh", mesh=tools.box_mesh((0.05, 0.01, 0.05)), name="turned",
               motion=tools.Velocity(position=(0.0, 0.01, 0.12), orientation=(0.7071068, 0.0, 0.0, 0.7071068)))
    b.finalize()
    b = builder()  # turned a quarter about x, the slab stands in the block, 0.03 m thick each side of z = 0
    b.add_tool("mesh", mesh=tools.box_mesh((0.05, 0.03, 0.05)), name="turned",
               motion=tools.Velocity(position=(0.0, 0.05, 0.0), orientation=(0.7071068, 0.0, 0.0, 0.7071068)))
    with pytest.raises(ValueError, match="start inside tool 'turned'"):
        b.finalize()


def _block_under_a_hammer(**tool):
    """A clay block on the ground under a box tool 'hammer' (given its motion), or held by a
    pinned set 'clamp' (``pin=motion``)."""
    b = we.SceneBuilder(spacing=0.01)
    b.add_box((0.0, 0.03, 0.0), (0.04, 0.04, 0.04), we.Material.preset("clay"), name="blk")
    b.add_ground()
    if "pin" in tool:
        b.pin(body="blk", region=((-1, -1, -1), (1, 0.02, 1)), name="clamp", motion=tool["pin"])
    else:
        b.add_tool("box", half_extents=(0.01, 0.05, 0.05), name="hammer", **tool)
    return b.finalize()


# Its bodies are coarse on purpose (a tiny scene, or one torn apart): the run's under-resolution warning is expected.
@pytest.mark.filterwarnings("ignore:the deformation fit was skipped:RuntimeWarning")
def test_a_scripted_motion_moving_more_than_a_spacing_a_step_stops_the_run_at_that_step():
    """A ``Scripted`` motion is known only as the steps evaluate it: a step that moves it more
    than a spacing stops the run there (``SimulationError``, the pre-run refusal's message),
    the frames before it kept, with a fixed dt and with the adaptive step. It is not called
    ahead of the run: a function reading what the run's callback sets (a controller) was
    refused before the first step with the KeyError of a frame not yet run."""
    dt, fps = 1e-4, 1000.0  # 10 steps a frame, at most 0.01 / 1e-4 = 100 m/s

    model = _block_under_a_hammer

    class Frames:
        def __init__(self):
            self.written = []

        def write_frame(self, frame, state):
            self.written.append(frame)

    # 0.1 m in the step from t = 2 ms (step 21, in frame 3), 1000 m/s.
    jumped = tools.Scripted(lambda t: ((0.1 if t <= 0.002 + 1e-9 else 0.2, 0.03, 0.0), tools.IDENTITY))
    for run_dt in (dt, "auto"):
        m, out = model(motion=jumped), Frames()
        with pytest.raises(we.SimulationError, match=r"^the simulation stopped in step (\d+), in frame 3: tool 'hammer': its "
                                                     r"Scripted motion moves its points at up to [\d.e+]+ m/s \(\|v\| \+ \|omega\| "
                                                     r"r, r = 0\.0714 m; from t = 0\.002 s\), which is not allowed at dt = "
                                                     r".* so at most [\d.e+]+ m/s; give a slower motion or a smaller dt=$") as e:
            we.simulate(m, 5, fps=fps, dt=run_dt, progress=False, writer=out)
        assert out.written == [0, 1, 2] and e.value.frame == 3 and e.value.particle is None
        # The advice apart, as a divergence's (a sweep's row leaves it out; run names --dt).
        assert e.value.advice == tools.TOO_FAST_ADVICE and str(e.value) == e.value.reason + e.value.advice
        if run_dt == dt:
            assert e.value.step == 21 and "up to 1e+03 m/s" in str(e.value) and "at most 100 m/s" in str(e.value)
    # A pinned set turning about its centroid at 1e4 rad/s: 1 rad a step, its farthest
    # particles (0.0212 m out) at 212 m/s, from the first step.
    c = (0.0, 0.015, 0.0)
    turning = tools.Scripted(lambda t: (c, (0.0, math.sin(5000.0 * t), 0.0, math.cos(5000.0 * t))))
    with pytest.raises(we.SimulationError, match=r"^the simulation stopped in step 1, in frame 1: pinned set 'clamp': its "
                                                 r"Scripted motion moves its points at up to 212 m/s \(\|v\| \+ \|omega\| r, "
                                                 r"r = 0\.0212 m; from t = 0 s\)"):
        we.simulate(model(pin=turning), 5, fps=fps, dt=dt, progress=False)
    we.simulate(model(motion=tools.Scripted(lambda t: ((0.1 - 90.0 * t, 0.03, 0.0), tools.IDENTITY))), 2, fps=fps, dt=dt,
                progress=False)
    # A controller: each frame's pose set by the callback after the frame before; it runs,
    # and the tool ends where the plan put it.
    plan, calls, fps = {0: 0.15}, [], 100.0

    def fn(t):
        calls.append(t)
        return (0.0, plan[max(0, math.ceil(t * fps - 1e-6) - 1)], 0.0), tools.IDENTITY

    def callback(frame, state):
        plan[frame + 1] = plan[frame] - 0.001

    b = we.SceneBuilder(spacing=0.01)
    b.add_box((0.0, 0.03, 0.0), (0.04, 0.04, 0.04), we.Material.preset("clay"), name="blk")
    b.add_tool("sphere", radius=0.03, name="ind", motion=tools.Scripted(fn))
    m = b.finalize()
    end = we.simulate(m, 3, fps=fps, dt=dt, progress=False, callback=callback)
    assert min(calls) == 0.0 and max(calls) == pytest.approx(0.03)
    assert m.tools.pose(end)["ind"][0][1] == pytest.approx(0.148)


def test_a_tool_or_pin_moving_more_than_a_spacing_a_step_is_refused_before_the_run(tmp_path, capsys):
    """The swept contact lets no particle through a fast tool, but gives every particle it
    meets the tool's speed: a box at 3 spacings a step flattened a resting block into a sheet
    half a millimetre thick and the run exited 0. Refused before the first step as a start
    faster than a spacing a step is (the speed of the fastest point, |v| + |omega| r, while
    the run lasts); the adaptive step follows the tool instead."""
    from warp_esph.cli import main  # noqa: PLC0415
    from warp_esph.simulate import adaptive_timestep  # noqa: PLC0415

    dt, fps = 1e-4, 1000.0  # at most 0.01 / 1e-4 = 100 m/s

    model = _block_under_a_hammer

    fast = [
        (dict(motion=tools.Velocity((-300.0, 0.0, 0.0), position=(0.1, 0.03, 0.0))),
         r"^tool 'hammer': its Velocity motion moves its points at up to 300 m/s \(\|v\| \+ \|omega\| r, r = 0\.0714 m; "
         r"from t = 0 s\), which is not allowed at dt = 0\.0001 s: a step may carry a tool at most one spacing "
         r"\(0\.01 m\), so at most 100 m/s; give a slower motion or a smaller dt=$"),
        # 2000 rad/s about its centre: its corners (0.0714 m out) at 143 m/s.
        (dict(motion=tools.Velocity(angular_velocity=(0.0, 2000.0, 0.0), position=(0.1, 0.03, 0.0))), "up to 143 m/s"),
        # Keyed to jump 0.1 m in 0.5 ms at t = 2 ms.
        (dict(motion=tools.Keyframes([0.0, 0.002, 0.0025], [(0.1, 0.03, 0.0), (0.1, 0.03, 0.0), (0.2, 0.03, 0.0)])),
         r"its Keyframes motion moves its points at up to 200 m/s .*from t = 0\.002 s"),
        (dict(pin=tools.Velocity((0.0, 0.0, 150.0))), r"^pinned set 'clamp': its Velocity motion .* up to 150 m/s"),
    ]
    for tool, match in fast:
        m = model(**tool)
        with pytest.raises(ValueError, match=match):
            we.simulate(m, 5, fps=fps, dt=dt, progress=False)
        n, step = adaptive_timestep(m, m.state(), fps)
        assert max(speed for _, speed, _ in m.tools.fastest(0.0, 1.0 / fps)) * step < 0.3 * m.spacing
    # Slow enough, or fast only after the run: runs.
    we.simulate(model(motion=tools.Velocity((-90.0, 0.0, 0.0), position=(0.1, 0.03, 0.0))), 1, fps=fps, dt=dt, progress=False)
    we.simulate(model(**fast[2][0]), 1, fps=fps, dt=dt, progress=False)
    # A jump the adaptive step cannot follow (0.1 m in 1 ns, 1e8 m/s), in the run's tenth frame:
    # refused before the first, naming the tool (it was read as the body's initial velocity).
    jump = model(motion=tools.Keyframes([0.0, 0.0095, 0.0095 + 1e-9], [(0.1, 0.03, 0.0), (0.1, 0.03, 0.0), (0.2, 0.03, 0.0)]))
    with pytest.raises(ValueError, match=r"^tool 'hammer': its Keyframes motion's speed \(from t = 0\.0095 s\) of 1\.\d+e\+08 m/s "
                                         r"is not allowed with the adaptive step: it would take .* steps a frame, more than 1e\+06"):
        we.simulate(jump, 10, fps=fps, dt="auto", progress=False)
    we.simulate(jump, 9, fps=fps, dt="auto", progress=False)
    # The command line: one line, exit 2, nothing written.
    path = tmp_path / "fast.toml"
    path.write_text(SCENE_TOML.replace("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.0, 0.0001]"))
    out = tmp_path / "fast.usdc"
    capsys.readouterr()
    assert main(["run", str(path), "-o", str(out), "--no-progress", "--dt", "0.001"]) == 2
    # The command's options, not a Python caller's dt=.
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {path}: tool 'plate': its Keyframes motion moves its points"), err
    assert err[0].endswith("at dt = 0.001 s: a step may carry a tool at most one spacing (0.02 m), so at most 20 m/s; "
                           "give a slower motion or a smaller --dt"), err
    path.write_text(SCENE_TOML.replace("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.0, 1e-12]"))
    capsys.readouterr()
    assert main(["run", str(path), "-o", str(out), "--no-progress", "--dt", "auto"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {path}: tool 'plate': its Keyframes motion's speed"), err
    assert not out.exists() and not (tmp_path / "fast.usdc_tools.csv").exists()


def test_a_run_with_tools_checks_their_speeds_and_keyframe_times_once_before_its_first_step(monkeypatch):
    """Redundant work, not wrong results: finalize checked keyframe times against the
    precision twice (the builder, then the tool set), and an adaptive run with tools called
    ``adaptive_timestep`` twice before its first step (the start's speed over the first
    frame, then the tools' over the run), then once per frame. Now once each: the start's
    check takes the tools' speeds to the run's end."""
    import importlib  # noqa: PLC0415

    sim = importlib.import_module("warp_esph.simulate")  # the module, not warp_esph.simulate the function
    times = []
    monkeypatch.setattr(tools, "keyframe_times_problem", lambda t, npf, f=tools.keyframe_times_problem: times.append(t) or f(t, npf))
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.05, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name="blk")
    b.add_ground()
    b.add_tool("sphere", radius=0.03, name="ind", motion=tools.Keyframes([0.0, 1.0], [(0.0, 0.15, 0.0), (0.0, 0.1, 0.0)]))
    m = b.finalize()
    assert times == [(0.0, 1.0)]
    calls = []
    monkeypatch.setattr(sim, "adaptive_timestep", lambda *a, f=sim.adaptive_timestep, **k: calls.append(k.get("until")) or f(*a, **k))
    we.simulate(m, 2, fps=100.0, dt="auto", progress=False)
    assert calls == [pytest.approx(0.02), None, None]  # the whole run's check, then one per frame


def test_warp_esph_run_checks_the_start_and_the_tools_once_before_it_opens_its_output(tmp_path, monkeypatch):
    """``warp-esph run`` checks the start's speed and the tools' speeds before it opens its
    output (a refused run writes nothing), then ``simulate`` checked both again before the
    first step: every tool motion sampled at every step time twice. Now once each, in a new
    run (fixed and adaptive step) and in a resumed one (whose start is not checked again)."""
    import importlib  # noqa: PLC0415

    from warp_esph.cli import main  # noqa: PLC0415

    sim = importlib.import_module("warp_esph.simulate")  # the module, not warp_esph.simulate the function
    calls = []
    monkeypatch.setattr(sim, "check_start_speed", lambda *a, f=sim.check_start_speed, **k: calls.append("start") or f(*a, **k))
    monkeypatch.setattr(tools.ToolSet, "check_speed", lambda self, *a, f=tools.ToolSet.check_speed: calls.append("tools") or f(self, *a))
    monkeypatch.setattr(sim, "adaptive_timestep", lambda *a, f=sim.adaptive_timestep, **k: calls.append(
        "tools to the end" if k.get("until") is not None else "frame") or f(*a, **k))
    path = tmp_path / "press.toml"
    path.write_text(SCENE_TOML)
    out = str(tmp_path / "press.usda")
    assert main(["run", str(path), "-o", out, "--no-progress", "--frames", "2", "--dt", "0.001", "--checkpoint-every", "1"]) == 0
    assert calls == ["start", "tools"]
    calls.clear()
    assert main(["run", "--resume", out + ".checkpoint.npz", "--no-progress", "--frames", "3"]) == 0
    assert calls == ["tools"]
    calls.clear()
    assert main(["run", str(path), "-o", out, "--no-progress", "--frames", "1", "--dt", "auto"]) == 0
    assert calls == ["start", "tools to the end", "frame"]


_TIMES = r"must be one or more finite, increasing numbers"
_ROWS = r"must be \(2, 3\) finite numbers, one row per time"
_QUATS = r"must be \(2, 4\) quaternions \(x, y, z, w\), none zero, one row per time"


@pytest.mark.parametrize("args,match", [
    (([0, 1], {"a": 1}), rf"^positions = \{{'a': 1\}} is not allowed: {_ROWS} \(it is of type dict, not a list, tuple or array\)$"),
    (([0, 1j], [[0, 0, 0]] * 2), rf"^times = \[0, 1j\] is not allowed: {_TIMES} \(times\[1\] = 1j: must be a number\)$"),
    (((x for x in [0, 1]), [[0, 0, 0]] * 2), rf"^times = <generator .*> is not allowed: {_TIMES} \(it is of type generator, not a list"),
    (([0, 10**400], [[0, 0, 0]] * 2),
     rf"^times = \[0, 1000.*\.\.\. is not allowed: {_TIMES} \(times\[1\] = 1\.000e\+400: must be a finite number \(it overflows a float\)\)$"),
    (([0, 1], [[0, 0, 0], [0, 0]]), rf"^positions = \[\[0, 0, 0\], \[0, 0\]\] is not allowed: {_ROWS} \(positions\[1\] = \[0, 0\]: must be a sequence of 3"),
    (([0, 1], [[0, 0, 0]] * 2, [[0, 0, 0, 1], [0, 0, 1]]), rf"^orientations = .* is not allowed: {_QUATS} \(orientations\[1\] = \[0, 0, 1\]: must be a sequence of 4"),
    (([0, 1], [[0, 0, 0]] * 2, [[0, 0, 0, 1], [0, 0, 0, 0]]), rf"^orientations = .* is not allowed: {_QUATS} \(orientations\[1\] = \[0, 0, 0, 0\]: must be a non-zero quaternion"),
    (([0, 1], [[0, 0, 0]] * 2, [[0, 0, 0, 1]]), rf"^orientations = \[\[0, 0, 0, 1\]\] is not allowed: {_QUATS} \(it has 1 row\)$"),
    (("abc", [[0, 0, 0]]), rf"^times = 'abc' is not allowed: {_TIMES} \(it is of type str, not a list, tuple or array\)$"),
    (([[0, 1]], [[0, 0, 0]] * 2), rf"^times = \[\[0, 1\]\] is not allowed: {_TIMES} \(times\[0\] = \[0, 1\]: must be a number\)$"),
    ((np.array([[0.0, 1.0]]), [[0, 0, 0]] * 2), rf"^times = array\(\[\[0\., 1\.\]\]\) is not allowed: {_TIMES} \(its shape is \(1, 2\)\)$"),
    ((3, [[0, 0, 0]]), rf"^times = 3 is not allowed: {_TIMES} \(it is of type int, not a list, tuple or array\)$"),
    (({0, 1}, [[0, 0, 0]] * 2), rf"^times = \{{0, 1\}} is not allowed: {_TIMES} \(it is of type set"),
    (([True, 2], [[0, 0, 0]] * 2), rf"^times = \[True, 2\] is not allowed: {_TIMES} \(times\[0\] = True: must be a number\)$"),
    ((["0", "1"], [[0, 0, 0]] * 2), rf"^times = \['0', '1'\] is not allowed: {_TIMES} \(times\[0\] = '0': must be a number\)$"),
    (([1, 0], [[0, 0, 0]] * 2), rf"^times = \[1, 0\] is not allowed: {_TIMES} \(times\[1\] = 0 is not after times\[0\] = 1\)$"),
    (([0, 1], [[0, 0, 10**400]] * 2), rf"^positions = .* is not allowed: {_ROWS} \(positions\[0\]\[2\] = 1\.000e\+400: must be a finite number"),
])
def test_bad_keyframes_are_a_value_error_naming_the_argument_and_what_is_allowed(args, match):
    """Each was a TypeError, an OverflowError or numpy's own message ('inhomogeneous shape'),
    or was taken ([[0, 1]] read as [0, 1], '0' as 0, True as 1)."""
    with pytest.raises(ValueError, match=match):
        tools.Keyframes(*args)


def test_keyframes_take_sequences_and_arrays_and_keep_plain_floats():
    k = tools.Keyframes(np.array([0, 1]), np.zeros((2, 3)), [tools.IDENTITY, (0, 0, 0, -2)])
    assert k.times == (0.0, 1.0) and all(type(v) is float for v in k.times + k.positions[0] + k.orientations[1])
    assert k.orientations[1] == (0.0, 0.0, 0.0, 1.0)  # the shortest arc from the first
    assert tools.Keyframes(k.times, k.positions, k.orientations) == k


def _raise(e):
    raise e


_AT_REST = ((0.0, 0.5, 0.0), tools.IDENTITY)  # clear of the block


@pytest.mark.parametrize("fn,match,cause", [
    (lambda t: 1 / 0, r"^tool 'ball': its scripted motion at t = 0 is not allowed: it raised ZeroDivisionError: division by zero$",
     ZeroDivisionError),
    (lambda t: {}["a"], r"^tool 'ball': its scripted motion at t = 0 is not allowed: it raised KeyError: 'a'$", KeyError),
    (lambda t: _raise(ValueError("no pose yet")) if t > 0 else _AT_REST,
     r"^tool 'ball': its scripted motion at t = 0\.0001 is not allowed: it raised ValueError: no pose yet$", ValueError),
    (lambda t: ((float("nan"), 0, 0), (0, 0, 0, 1)),
     r"^tool 'ball': its scripted motion at t = 0 is not allowed: it returned position\[0\] = nan, which must be a finite number$", None),
    (lambda t: ((0, 0, 0), (0, 0, 0, 0)) if t > 0 else _AT_REST,
     r"^tool 'ball': its scripted motion at t = 0\.0001 is not allowed: it returned quaternion = \(0, 0, 0, 0\), which must be a non-zero",
     None),
    (lambda t: 5, r"^tool 'ball': its scripted motion at t = 0 is not allowed: it returned 5; must return \(position, quaternion", None),
    (lambda t: ((0, 1e39, 0), tools.IDENTITY) if t > 0 else _AT_REST,
     r"^tool 'ball': its scripted motion at t = 0\.0001 is not allowed in float32: it returned position = \(0\.0, 1e\+39, 0\.0\), "
     r"beyond 1\.84e\+19 m; use dtype=float64", None),
])
def test_a_scripted_motion_that_raises_or_returns_a_bad_pose_is_a_value_error_naming_the_tool_and_time(fn, match, cause):
    """The callable runs on the host in ``finalize`` (the tool's first pose) and deep in
    ``Solver.step``: its ZeroDivisionError or KeyError came out as it was, and a bad pose said
    'position[0] = nan' without the tool or the time (a float32 pose at 1e39 m wrote NaN and
    the run went on)."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    b.add_tool("sphere", radius=0.05, name="ball", motion=tools.Scripted(fn))
    with pytest.raises(ValueError, match=match) as info:
        m = b.finalize()
        we.Solver(m).step(m.state(), m.state(), 1e-4)
    if cause is not None:
        assert isinstance(info.value.__cause__, cause)
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    # A pinned set starts at its rest pose (the block's centroid), not where the tool does.
    pin_rest = ((0.0, 0.1, 0.0), tools.IDENTITY)
    b.pin(body="d", name="grip", motion=tools.Scripted(lambda t: pin_rest if (r := fn(t)) is _AT_REST else r))
    with pytest.raises(ValueError, match=match.replace("^tool 'ball'", "^pinned set 'grip'")):
        m = b.finalize()
        we.Solver(m).step(m.state(), m.state(), 1e-4)


@pytest.mark.parametrize("times,shown", [([1.0, 1.0 + 1e-9], "1.0 and 1.000000001"), ([0.0, 1e-46], "0.0 and 1e-46")])
def test_keyframe_times_equal_in_float32_are_refused_at_finalize_and_float64_takes_them(times, shown):
    """Increasing in float64 but equal once packed in float32: the first step refused them as
    'keyframe_times of tool 'ball' = [1.0, 1.0] ... must be finite and increasing', times the
    user never gave."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    b.add_tool("sphere", radius=0.05, name="ball", motion=tools.Keyframes(times, [(0, 0.5, 0)] * 2))
    with pytest.raises(ValueError, match=rf"^tool 'ball': Keyframes times = .* is not allowed in float32: {re.escape(shown)} are "
                                         r"equal in float32; use dtype=float64 or times further apart$"):
        b.finalize()
    assert b.finalize(dtype=wp.float64).tools.keyframe_times.numpy().tolist() == times


def test_keyframe_times_written_in_place_between_steps_are_checked_again():
    """Each step reads the keyframe times as they are now (a fit writes the array in place)
    and refuses times that are not increasing, also after steps that found the earlier
    times valid (the step keeps which values it checked last)."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    b.add_tool("sphere", radius=0.05, name="ball", motion=tools.Keyframes([0.0, 1.0], [(0, 0.5, 0)] * 2))
    m = b.finalize()
    s, x, y = we.Solver(m), m.state(), m.state()
    s.step(x, y, 1e-4)
    s.step(y, x, 1e-4)
    m.tools.keyframe_times.assign(np.array([1.0, 0.5], dtype=np.float32))
    with pytest.raises(ValueError, match=r"^keyframe_times of tool 'ball' = \[1\.0, 0\.5\] is not allowed: must be finite "
                                         r"and increasing$"):
        s.step(x, y, 1e-4)
    m.tools.keyframe_times.assign(np.array([0.0, 2.0], dtype=np.float32))
    s.step(x, y, 1e-4)


@pytest.mark.parametrize("name, bad, message", [
    ("friction", [float("nan")], r"friction of tool 'ball' = nan is not allowed: must be a finite number >= 0"),
    ("friction", [-5.0], r"friction of tool 'ball' = -5\.0 is not allowed: must be a finite number >= 0"),
    ("static_friction", [-1.0], r"static_friction of tool 'ball' = -1\.0 is not allowed: must be a finite number >= 0"),
    ("keyframe_positions", [[0, 0.5, 0], [0, np.nan, 0], [0, 0, 0]],
     r"keyframe_positions of tool 'ball' = \[\[0\.0, 0\.5, 0\.0\], \[0\.0, nan, 0\.0\]\] is not allowed: must be finite"),
    ("keyframe_orientations", [[0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 1]],
     r"keyframe_orientations of tool 'ball' = \[\[0\.0, 0\.0, 0\.0, 1\.0\], \[0\.0, 0\.0, 0\.0, 0\.0\]\] is not allowed: must "
     r"be finite quaternions \(x, y, z, w\), none zero"),
    ("velocity", [[0, 0, 0], [0, np.inf, 0]], r"velocity of pinned set 'base' = \[0\.0, inf, 0\.0\] is not allowed: must be finite"),
])
def test_tool_arrays_written_in_place_are_checked_before_the_step(name, bad, message):
    """The tools' other differentiable arrays are refused as the keyframe times are, when they
    hold what no tool could, before the step launches anything: a NaN keyframe position took
    the tool out of the contact and a negative friction drove the material along it, and the
    steps went on without a word (a NaN friction ran to NaN positions)."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    b.add_tool("sphere", radius=0.05, name="ball", friction=0.2, motion=tools.Keyframes([0.0, 1.0], [(0, 0.5, 0)] * 2))
    b.pin(region=((-0.1, 0.0, -0.1), (0.1, 0.08, 0.1)), motion=tools.Velocity(), name="base")
    m = b.finalize()
    s, x, y = we.Solver(m), m.state(), m.state()
    s.step(x, y, 1e-4)
    good = getattr(m.tools, name).numpy().copy()
    getattr(m.tools, name).assign(np.array(bad, dtype=np.float32))
    before = x.x.numpy().copy()
    with pytest.raises(ValueError, match=f"^{message}$"):
        s.step(y, x, 1e-4)
    np.testing.assert_array_equal(x.x.numpy(), before)  # refused before any kernel wrote state_out
    getattr(m.tools, name).assign(good)
    s.step(y, x, 1e-4)


_coulomb64 = we.sim.colliders.funcs(wp.float64).coulomb_response


@wp.kernel(module="unique")
def _tangential_after_contact(vt: wp.array(dtype=wp.float64), mu_s: wp.float64, mu_k: wp.float64, ramp: wp.float64,
                              out: wp.array(dtype=wp.float64)):
    # A particle resting on a plane (normal +y) whose step added 1 m/s inward: all of it is removed.
    i = wp.tid()
    dt = wp.float64(1.0e-3)
    v = _coulomb64(wp.vec3d(vt[i], wp.float64(-1.0), wp.float64(0.0)), wp.vec3d(), wp.vec3d(0.0, 1.0, 0.0), dt, dt, ramp,
                   mu_s, mu_k, wp.float64(0.0))
    out[i] = v[0]


@pytest.mark.parametrize("contact", ["continuous", "instant"])
def test_a_kinetic_friction_written_above_the_static_one_acts_as_both(contact):
    """``friction`` and ``static_friction`` are separate arrays: a descent on the kinetic
    coefficient alone leaves the static one below it, which the builder refuses. The contact
    law then ran its slip branch on a negative excess, where friction raised a particle's
    tangential speed (0.01 to 1.43 m/s at static 0, kinetic 0.5, 1 m/s of normal speed
    removed) or reversed it (to -0.49 m/s, the instant law). The static coefficient is now
    taken as at least the kinetic one: the law leaves what Coulomb friction at the kinetic
    coefficient leaves, and a block sliding to rest on a plane tool whose friction was written
    from 0.1 to 0.6 runs as one built with 0.6 (before: 1e-5 m apart at 80 ms)."""
    ramp = CONTACTS[contact]
    vt = np.array([0.01, 0.1, 0.3, 0.45, 0.5, 0.55, 0.6, 1.0])
    out = wp.zeros(len(vt), dtype=wp.float64)
    wp.launch(_tangential_after_contact, len(vt), [wp.array(vt, dtype=wp.float64), 0.0, 0.5, ramp], [out])
    left = out.numpy()
    assert (left >= 0.0).all() and (left <= np.maximum(vt - 0.5, 0.0) + 1e-12).all(), left  # Coulomb's, or less in the rounding
    assert left[-1] == pytest.approx(0.5)  # sliding past the band: exactly Coulomb

    def run(built, written=None):
        b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0), contact=contact)
        b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(1e5, viscosity=1.0), name="block", velocity=(0.3, 0.0, 0.1))
        b.add_tool("plane", position=(0.0, 0.01, 0.0), friction=built, name="floor")
        m = b.finalize(dtype=wp.float64)
        if written is not None:
            m.tools.friction.assign(np.array([written]))
        s, x, y = we.Solver(m), m.state(), m.state()
        for _ in range(400):
            s.step(x, y, 2e-4)
            x, y = y, x
        return x.x.numpy(), x.v.numpy()

    x_built, v_built = run(0.6)
    x_written, v_written = run(0.1, 0.6)
    np.testing.assert_array_equal(x_written, x_built)
    np.testing.assert_array_equal(v_written, v_built)


# ------------------------------------------------------------- scene files, CLI, USD
SCENE_TOML = """
[scene]
spacing = 0.02
frames = 2
fps = 50

[[bodies]]
shape = "box"
name = "block"
material = "dough"
center = [0.0, 0.05, 0.0]
size = [0.1, 0.1, 0.1]

[[tools]]
shape = "plane"
name = "base"

[[tools]]
shape = "box"
name = "plate"
half_extents = [0.1, 0.01, 0.1]
friction = 0.2
keyframe_times = [0.0, 0.04]
keyframe_positions = [[0.0, 0.1, 0.0], [0.0, 0.09, 0.0]]

[[pins]]
name = "left"
body = "block"
region = [[-1, -1, -1], [-0.035, 1, 1]]
"""


def test_scene_file_tools_and_pins_run_through_the_cli_to_usd_csv_and_json(tmp_path):
    import csv  # noqa: PLC0415
    import json  # noqa: PLC0415

    from pxr import Usd, UsdGeom  # noqa: PLC0415

    from warp_esph.cli import main  # noqa: PLC0415
    from warp_esph.scenes import load_scene_file  # noqa: PLC0415

    path = tmp_path / "press.toml"
    path.write_text(SCENE_TOML)
    out = tmp_path / "press.usdc"
    assert main(["run", str(path), "-o", str(out), "--no-progress"]) == 0
    with open(tmp_path / "press.usdc_tools.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["tool"] for r in rows] == ["base", "plate", "left"] * 3
    plate = [r for r in rows if r["tool"] == "plate"]
    assert [float(r["py"]) for r in plate] == pytest.approx([0.1, 0.095, 0.09], abs=1e-6)  # keyframes at t = 0, 0.02, 0.04
    assert float(plate[-1]["fy"]) < 0.0  # the plate presses down on the block
    with open(tmp_path / "press.usdc_tools.json") as fh:
        data = json.load(fh)
    assert len(data["rows"]) == 9 and data["units"]["force"] == "N"
    stage = Usd.Stage.Open(str(out))
    prim = stage.GetPrimAtPath("/World/Tools/plate")
    assert prim.GetAttribute("xformOp:translate").Get(2)[1] == pytest.approx(0.09, abs=1e-6)
    assert prim.GetAttribute("warp_esph:reaction_force").Get(2)[1] < 0.0
    assert UsdGeom.Cube(stage.GetPrimAtPath("/World/Tools/plate/geom"))
    # The pinned particles are in the USD frame exactly where they started.
    model = load_scene_file(path).builder.finalize()
    held = model.tools.pins[0].indices
    x2 = np.array(UsdGeom.Points(stage.GetPrimAtPath("/World/block")).GetPointsAttr().Get(2))
    np.testing.assert_array_equal(x2[held], model.particle_x0[held].astype(np.float32))
    # A second output with the same stem in the same folder keeps its own force log.
    before = (tmp_path / "press.usdc_tools.csv").read_bytes()
    assert main(["run", str(path), "-o", str(tmp_path / "press.usda"), "--no-progress", "--frames", "1"]) == 0
    with open(tmp_path / "press.usda_tools.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 6  # frames 0 and 1
    assert (tmp_path / "press.usdc_tools.csv").read_bytes() == before


_PLATE = r"\[\[tools\]\] #2 \(shape 'box'\)"


@pytest.mark.parametrize("old,new,pattern", [
    ('name = "plate"', 'name = "plate"\nhalf_extent = 1.0', rf"unknown key 'half_extent' in {_PLATE}; did you mean 'half_extents'"),
    ('shape = "box"\nname = "plate"', 'shape = "cone"\nname = "plate"', r"shape = 'cone' in \[\[tools\]\] #2 is not allowed"),
    ("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.0, 0.04]\nvelocity = [0, 1, 0]", rf"{_PLATE}: .*not allowed together"),
    ('body = "block"', 'body = "blok"', r"\[\[pins\]\] #1: body = 'blok' is not allowed"),
    # The file's keys, not tools.Keyframes' arguments (it said 'times = []', 'positions with shape').
    ("keyframe_times = [0.0, 0.04]", "keyframe_times = []",
     rf"{_PLATE}: keyframe_times = \[\] is not allowed: must be one or more finite, increasing numbers$"),
    ("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.0, 0.04, 0.08]",
     rf"{_PLATE}: keyframe_positions = .* is not allowed: must be \(3, 3\) finite numbers, one row per time \(it has 2 rows\)$"),
    ("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.0, 0.04]\nkeyframe_orientations = [[0, 0, 0, 1]]",
     rf"{_PLATE}: keyframe_orientations = \[\[0, 0, 0, 1\]\] is not allowed: must be \(2, 4\) quaternions .*\(it has 1 row\)$"),
    ("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.04, 0.0]",
     rf"{_PLATE}: keyframe_times = .* \(keyframe_times\[1\] = 0\.0 is not after keyframe_times\[0\] = 0\.04\)$"),
    ('body = "block"', 'body = "block"\nkeyframe_times = [0.0, 1.0]\nkeyframe_positions = [[0, 0, 0]]',
     r"\[\[pins\]\] #1: keyframe_positions = \[\[0, 0, 0\]\] is not allowed: must be \(2, 3\)"),
    # Keys that do not belong to the shape or the motion were ignored.
    ('shape = "plane"\nname = "base"', 'shape = "mesh"\nname = "base"', r"missing key 'file' in \[\[tools\]\] #1 \(shape 'mesh'\)$"),
    ('half_extents = [0.1, 0.01, 0.1]', 'half_extents = [0.1, 0.01, 0.1]\nradius = 0.3',
     rf"key 'radius' in {_PLATE} is not allowed: a box tool takes half_extents \(radius is a key of sphere, capsule and "
     r"cylinder tools\)$"),
    ('shape = "plane"\nname = "base"', 'shape = "sphere"\nname = "base"\nradius = 0.1\nfile = "x.obj"',
     r"key 'file' in \[\[tools\]\] #1 \(shape 'sphere'\) is not allowed: a sphere tool takes radius \(file is a key of a mesh tool\)$"),
    ('shape = "plane"\nname = "base"', 'shape = "sphere"\nname = "base"\nradius = 0.1\nscale = 2.0',
     r"key 'scale' in \[\[tools\]\] #1 \(shape 'sphere'\) is not allowed: a sphere tool takes radius"),
    ('shape = "plane"\nname = "base"', 'shape = "sphere"\nname = "base"', r"missing key 'radius' in \[\[tools\]\] #1 \(shape 'sphere'\)$"),
    ("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.0, 0.04]\nposition = [0, 1, 0]",
     rf"key 'position' in {_PLATE} is not allowed with keyframe_\*: the keyframes give the tool's pose at every time"),
    ("keyframe_times = [0.0, 0.04]", "keyframe_times = [0.0, 0.04]\norientation = [0, 0, 0, 1]",
     rf"key 'orientation' in {_PLATE} is not allowed with keyframe_\*"),
])
def test_scene_file_tool_errors_name_the_table_and_key(tmp_path, old, new, pattern):
    from warp_esph.scenes import load_scene_file  # noqa: PLC0415

    path = tmp_path / "bad.toml"
    assert old in SCENE_TOML
    path.write_text(SCENE_TOML.replace(old, new))
    with pytest.raises(ValueError, match=pattern):
        load_scene_file(path)


def test_scene_file_tool_shapes_are_the_tool_kinds_and_a_velocity_tool_keeps_its_position(tmp_path):
    from warp_esph.scene_file import TOOL_SHAPES  # noqa: PLC0415
    from warp_esph.scenes import load_scene_file  # noqa: PLC0415

    assert tuple(TOOL_SHAPES) == tools.KINDS
    path = tmp_path / "v.toml"
    path.write_text(SCENE_TOML.replace('name = "base"', 'name = "base"\nposition = [0, 0.01, 0]\nvelocity = [0, 1, 0]'))
    base = load_scene_file(path).builder.tools[0]
    assert base.motion == tools.Velocity((0, 1, 0), (0, 0, 0), (0, 0.01, 0), tools.IDENTITY)


def test_tool_names_that_clean_to_the_same_usd_prim_get_prims_of_their_own(tmp_path):
    """'x y' (index 0) and 'tool_0_x_y' both became /World/Tools/tool_0_x_y: the second
    authored its xformOps again and the run failed reading its own output ('The xformOp
    ... already exists (a damaged or foreign file?)')."""
    from warp_esph.cli import main  # noqa: PLC0415
    from warp_esph.usd import UsdFrames  # noqa: PLC0415

    path = tmp_path / "n2.toml"
    path.write_text(SCENE_TOML.replace('name = "base"', 'name = "x y"').replace('name = "plate"', 'name = "tool_0_x_y"')
                    .replace("frames = 2", "frames = 1"))
    out = tmp_path / "n2.usdc"
    assert main(["run", str(path), "-o", str(out), "--no-progress"]) == 0
    data = UsdFrames(out)  # (its stage must outlive the tools' prims)
    read = {t.name: t for t in data.tools}
    assert sorted(read) == ["tool_0_x_y", "x y"]
    assert read["x y"].kind == "plane" and read["tool_0_x_y"].kind == "box"
    assert read["tool_0_x_y"].pose(1)[0][1] == pytest.approx(0.095, abs=1e-6)  # its own keyframes, at t = 0.02
    # Valid names keep their prims; a cleaned one takes a suffix where it meets another.
    assert tools.usd_names(["x y", "tool_0_x_y", "a+", "a-", "tool_0_x_y_1", "ok"]) == [
        "tool_0_x_y_2", "tool_0_x_y", "tool_2_a_", "tool_3_a_", "tool_0_x_y_1", "ok"]


def test_each_tool_geometry_in_usd_authors_the_extent_of_its_own_size(tmp_path):
    """A sphere, capsule or cylinder tool authored its radius and height but no extent, so USD
    answered with the schema's fallback extent, that of radius 1 (a capsule's 0.5, height 1):
    a tool sphere of radius 0.03 read as 2 m across, one of radius 2 m as only 2 m across,
    though USD asks an extent of whoever authors a radius, height or size. Each tool's
    authored extent is the one its geometry computes, at every kind and size."""
    from pxr import Sdf, Usd, UsdGeom  # noqa: PLC0415

    b = we.SceneBuilder(spacing=0.04)
    b.add_box((0.0, 0.06, 0.0), (0.08, 0.08, 0.08), we.Material.preset("dough"))
    b.add_tool("sphere", radius=0.03, position=(0.5, 0.5, 0.0), name="ball")
    b.add_tool("sphere", radius=2.0, position=(0.0, 5.0, 0.0), name="big")
    b.add_tool("capsule", radius=0.02, half_height=0.1, position=(-0.5, 0.5, 0.0), name="pin")
    b.add_tool("cylinder", radius=0.05, half_height=0.01, position=(0.0, 0.5, 0.5), name="disc")
    b.add_tool("box", half_extents=(0.1, 0.02, 0.05), position=(0.0, 0.5, -0.5), name="plate")
    m = b.finalize()
    out = tmp_path / "tools.usda"
    with we.UsdWriter(out, m, 30.0) as w:
        w.write_frame(0, m.state())
    stage = Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(out)))
    sizes = {"ball": 0.03, "big": 2.0, "pin": 0.12, "disc": 0.05, "plate": 1.0}  # the largest half extent in its frame
    for name, half in sizes.items():
        geom = UsdGeom.Boundable(stage.GetPrimAtPath(f"/World/Tools/{name}/geom"))
        assert geom.GetExtentAttr().HasAuthoredValue(), name
        authored = np.array(geom.GetExtentAttr().Get(0.0), dtype=np.float64)
        computed = np.array(UsdGeom.Boundable.ComputeExtentFromPlugins(geom, Usd.TimeCode(0.0)), dtype=np.float64)
        np.testing.assert_allclose(authored, computed, rtol=1e-6, err_msg=name)
        assert np.abs(authored).max() == pytest.approx(half, rel=1e-6), name


def test_fig8_with_plates_elastic_cube_recovers_and_plastic_cube_keeps_the_squeeze():
    from warp_esph.scenes import get_scene  # noqa: PLC0415

    # Scale 0.5 (5 particles across): at 0.35 (3.5 across) the variational force rests the
    # released elastic cube 5.4 % tall, at 0.5 within 1.4 %, a resolution effect.
    scene = get_scene("lab_fig8_plates", 0.5)
    model = scene.builder.finalize()
    state = we.simulate(model, scene.frames, fps=scene.fps, dt=scene.dt, progress=False)
    x, x0 = state.x.numpy(), model.particle_x0
    width = {}
    for b in model.bodies:
        s = slice(b.start, b.start + b.count)
        width[b.name] = (x[s].max(axis=0) - x[s].min(axis=0)) / (x0[s].max(axis=0) - x0[s].min(axis=0))
    print({k: np.round(v, 3).tolist() for k, v in width.items()})  # measured: elastic 1.004, 1.016; plastic 0.877, 1.432
    # Squeezed 15 % in x and z for 0.3 s, then released.
    assert np.all(np.abs(width["elastic"] - 1.0) < 0.05)
    assert width["plastic"][0] < 0.92 and width["plastic"][2] < 0.92 and width["plastic"][1] > 1.1


@pytest.mark.parametrize("mu_k,mu_s", [(0.0, 0.0), (0.2, 0.2), (0.2, 1.0)])
def test_block_on_a_slope_slides_with_coulomb_acceleration_or_sticks(mu_k, mu_s):
    """A block settled on a plane tool, then gravity tilted by 20 degrees (the plane tilted
    under it): the centroid accelerates at g (sin th - mu_k cos th) while sliding (tan 20 deg
    = 0.364); with mu_s = 1 (above twice tan th, so the sway after the sudden tilt cannot
    start a slip) it stays put. It settles 0.15 s first, by kinetic damping, to rest: the
    block set down unloaded bounces on the plane (0.01 m/s), its base's normal load swinging
    about the weight, and its viscosity (1 Pa s) damps that slowly. Settled by the dynamics
    alone, the bounce left at the tilt (kinetic energy per mass 2.7e-5 m^2/s^2 with poly6,
    4.7e-5 with the biweight, whose bounce decays slower) unloaded the base enough for the
    biweight's block with mu_s = 1 to slip (8.2 mm in 0.2 s; after 0.3 s, 3.5e-6 left, it
    stuck); at rest (5e-9) it moves 2.9e-5 / 3.3e-5 m (poly6 / biweight), the elastic sway."""
    th, g, dt, steps = np.radians(20.0), 9.81, 2e-4, 1000
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -g, 0.0))
    b.add_box((0, 0.03, 0), (0.06, 0.06, 0.06), _elastic(1e5, viscosity=1.0), name="block")
    b.add_tool("plane", position=(0, 0.01, 0), friction=mu_k, static_friction=mu_s, name="slope")
    m = b.finalize()
    s = we.Solver(m)
    a, c = _run(s, m, 750, dt, relax_after=0.0), m.state()  # settle on the level plane
    m.gravity = (g * np.sin(th), -g * np.cos(th), 0.0)  # read by every step
    xs, forces = [], []
    for _ in range(steps):
        s.step(a, c, dt)
        a, c = c, a
        xs.append(a.x.numpy()[:, 0].mean())
        forces.append(s.reaction_forces(a)["slope"][0])
    t = dt * np.arange(1, steps + 1)
    late = slice(steps // 2, steps)
    acc = 2.0 * np.polyfit(t[late], np.array(xs)[late], 2)[0]
    f = np.mean(forces[steps // 2:], axis=0)
    weight = m.particle_mass.numpy().sum() * g
    print(f"mu_k={mu_k} mu_s={mu_s}: acceleration {acc:.4f} m/s^2, friction/normal {-f[0] / f[1]:.4f}")
    assert f[1] == pytest.approx(weight * np.cos(th), rel=0.02)  # the normal reaction carries the weight
    if mu_s < np.tan(th):
        assert acc == pytest.approx(g * (np.sin(th) - mu_k * np.cos(th)), rel=0.01)
        assert -f[0] / f[1] == pytest.approx(mu_k, abs=1e-3)
    else:
        assert abs(xs[-1] - xs[0]) < 3e-4 and abs(acc) < 0.05  # stuck: only the elastic sway


# ------------------------------------------------------------------------------ worlds
#: The press's height at which it touches the bar's top layer (the centres at x = 0.02 and
#: 0.04, y = 0.055, 1.5e-5 m off its surface): pressing from the first step of a short taped
#: run, as a start inside it would, which finalize places on its surface.
PRESSING = 0.0833


def _world_builder(material, press_y=0.085):
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.035, 0.0), (0.1, 0.06, 0.06), material, name="bar", velocity=(0.0, -0.3, 0.0))
    b.pin(region=((-0.06, -1, -1), (-0.03, 1, 1)), name="clamp")
    b.add_tool("sphere", radius=0.03, friction=0.3, motion=tools.Velocity((0.0, -0.6, 0.0), position=(0.03, press_y, 0.0)), name="press")
    b.add_tool("plane", position=(0.0, 0.012, 0.0), friction=0.5, name="floor")
    return b


def test_tools_in_worlds_act_per_world_and_report_each_world_its_own_reaction():
    """Two worlds of different stiffness meet the same press, floor and clamp: each world's
    positions and reaction rows ("w<w>/<name>") are those of its scene run alone, and the
    worlds' reactions differ (the comparison cannot pass by accident)."""
    soft, stiff = _elastic(4e3, viscosity=1.0), _elastic(2e4, viscosity=1.0)
    model = _world_builder(soft).finalize(dtype=wp.float64, worlds=2)
    model.set_material(0, stiff, world=1)
    names = model.tools.names
    assert model.tools.row_names == [f"w{w}/{n}" for w in range(2) for n in names]
    steps, dt = 40, 5e-4

    def run(m):
        s = we.Solver(m)
        a, c = m.state(), m.state()
        total = {}
        for _ in range(steps):
            s.step(a, c, dt)
            a, c = c, a
            for key, (f, _t) in s.reaction_forces(a).items():
                total[key] = total.get(key, 0.0) + f * dt
        return a.x.numpy(), a.v.numpy(), total

    x, v, imp = run(model)
    for w, mat in enumerate((soft, stiff)):
        xs, vs, imp_s = run(_world_builder(mat).finalize(dtype=wp.float64))
        sl = model.world_particles(w)
        np.testing.assert_allclose(x[sl], xs, rtol=0, atol=1e-12)
        np.testing.assert_allclose(v[sl], vs, rtol=0, atol=1e-9)
        for n in names:
            np.testing.assert_allclose(imp[f"w{w}/{n}"], imp_s[n], rtol=1e-10, atol=1e-14)
            assert np.abs(imp_s[n]).max() > 0.0, n  # every tool acted
    assert np.abs(imp["w0/press"] - imp["w1/press"]).max() > 1e-3 * np.abs(imp["w1/press"]).max()
    # Worlds share their tools: a world whose tools differ is refused before anything runs.
    other = _world_builder(soft)
    other.tools[0] = dataclasses.replace(other.tools[0], friction=0.4)
    with pytest.raises(ValueError, match=r"builders\[1\] tools and pinned sets"):
        finalize_worlds([_world_builder(soft), other])


def test_gradient_of_a_shared_tool_parameter_in_worlds_is_the_sum_over_the_worlds():
    """A loss on both worlds' press reactions: the tape's gradient with respect to the shared
    press velocity and friction is the sum of the single-world gradients."""
    soft, stiff = _elastic(4e3, viscosity=1.0), _elastic(2e4, viscosity=1.0)

    def grads(model, rows):
        s = we.Solver(model)
        states = [model.state() for _ in range(9)]
        loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        zero = wp.zeros(model.particle_count, dtype=wp.vec3d)
        tape = wp.Tape()
        with tape:
            for k in range(8):
                s.step(states[k], states[k + 1], 5e-4)
                for r in rows:
                    wp.launch(_loss_kernel, model.particle_count, [states[k + 1].x, zero, states[k + 1].reaction_force, r, 1e-3], [loss])
        tape.backward(loss)
        t = model.tools
        k = t.index("press")
        return np.array([t.velocity.grad.numpy()[k][1], t.friction.grad.numpy()[k]])

    model = _world_builder(soft, PRESSING).finalize(dtype=wp.float64, requires_grad=True, worlds=2)
    model.set_material(0, stiff, world=1)
    rows = [model.tools.row_names.index(f"w{w}/press") for w in range(2)]
    g = grads(model, rows)
    alone = []
    for mat in (soft, stiff):
        m = _world_builder(mat, PRESSING).finalize(dtype=wp.float64, requires_grad=True)
        alone.append(grads(m, [m.tools.index("press")]))
    print(g, alone)
    assert np.abs(alone[0] - alone[1]).max() > 1e-3 * np.abs(alone[1]).max()  # the worlds differ
    np.testing.assert_allclose(g, alone[0] + alone[1], rtol=1e-9)


def test_reaction_force_loss_on_one_world_of_a_rollout():
    """``ReactionForceLoss(tool="w1/press")`` through a checkpointed ``Rollout`` of two
    worlds: the loss and the gradient of world 1's shear modulus are those of world 1's
    scene alone; world 0's material gets none."""
    from warp_esph.losses import ReactionForceLoss
    from warp_esph.rollout import Rollout

    soft, stiff = _elastic(4e3, viscosity=1.0), _elastic(2e4, viscosity=1.0)
    model = _world_builder(soft, PRESSING).finalize(dtype=wp.float64, requires_grad=True, worlds=2)
    model.set_material(0, stiff, world=1)
    r = Rollout(model, 8, 5e-4, frames=[8], checkpoint_every=4)
    r.forward()
    assert r.step_forces().shape == (8, 6, 3)
    value, g = r.backward(ReactionForceLoss(np.zeros((1, 1)), "w1/press", [8], window=4, components="y"))
    alone = _world_builder(stiff, PRESSING).finalize(dtype=wp.float64, requires_grad=True)
    r1 = Rollout(alone, 8, 5e-4, frames=[8], checkpoint_every=4)
    r1.forward()
    value1, g1 = r1.backward(ReactionForceLoss(np.zeros((1, 1)), "press", [8], window=4, components="y"))
    assert value1 > 0.0 and abs(g1["mu"][0]) > 0.0
    assert value == pytest.approx(value1, rel=1e-12)
    assert g["mu"][0] == 0.0
    assert g["mu"][1] == pytest.approx(g1["mu"][0], rel=1e-9, abs=0.0)


# ------------------------------------------------------------ non-differentiable motions
def test_a_scripted_motion_has_no_gradient_and_says_so_while_keyframes_and_velocity_do():
    """``tools.Scripted`` is a host callable: a taped step warns that its motion gets no
    gradient, and asking for that gradient is a ValueError, not silent zeros. The same press
    given as ``tools.Velocity`` gets a non-zero gradient in the same taped run."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0))
    b.add_box((-0.05, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(1e4), name="left")
    b.add_box((0.05, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(1e4), name="right")
    b.add_tool("plane", position=(0, 0.01, 0), name="floor")
    b.add_tool("sphere", radius=0.02, name="scripted",
               motion=tools.Scripted(lambda t: ((-0.05, 0.07 - 0.5 * t, 0.0), tools.IDENTITY)))
    b.add_tool("sphere", radius=0.02, name="pressed", motion=tools.Velocity((0.0, -0.5, 0.0), position=(0.05, 0.07, 0.0)))
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    s = we.Solver(m)
    states = [m.state() for _ in range(6)]
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    w = wp.array(np.ones((m.particle_count, 3)), dtype=wp.vec3d)
    tape = wp.Tape()
    with pytest.warns(UserWarning, match=r"\['scripted'\].*Scripted.*no gradient flows to their motion"):
        with tape:
            for k in range(5):
                s.step(states[k], states[k + 1], 1e-3)
            wp.launch(_loss_kernel, m.particle_count, [states[-1].x, w, states[-1].reaction_force, 0, 0.0], [loss])
    tape.backward(loss)
    # Both presses touched their blocks.
    rf = states[-1].reaction_force.numpy()
    assert abs(rf[m.tools.index("scripted")][1]) > 0 and abs(rf[m.tools.index("pressed")][1]) > 0
    g = m.tools.motion_gradient("pressed")
    assert abs(g["velocity"][1]) > 0
    with pytest.raises(ValueError, match=r"'scripted' follows a tools.Scripted motion.*Keyframes or tools.Velocity"):
        m.tools.motion_gradient("scripted")
    # One warning per tool set, not one per step.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with wp.Tape():
            s.step(states[0], states[1], 1e-3)


# ------------------------------------------------------- resting and sliding on a tool
def _block_on_tool(shape, friction, velocity=(0.0, 0.0, 0.0)):
    """A 3 x 3 x 3 elastic block whose bottom layer starts on a held tool: the top of a box
    (or of a mesh of that box), or the apex of a sphere (R = 0.5 m)."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), _elastic(1e5, viscosity=1.0), name="block", velocity=velocity)
    if shape == "box":
        b.add_tool("box", half_extents=(0.5, 0.05, 0.5), position=(0.0, 0.01 - 0.05, 0.0), friction=friction, name="support")
    elif shape in ("mesh", "wide mesh"):
        # "wide mesh": a floor 20000 spacings wide about its origin, the block near that origin,
        # float64 (its far corners 200 m out, where float32 resolves 2.4e-5 m: it was refused,
        # though Warp's float32 queries meet the particles where float32 resolves 1e-8 m).
        half = 0.5 if shape == "mesh" else 1e4 * 0.02
        b.add_tool("mesh", mesh=tools.box_mesh((half, 0.05, half)), position=(0.0, 0.01 - 0.05, 0.0), friction=friction,
                   name="support")
    else:
        b.add_tool("sphere", radius=0.5, position=(0.0, 0.01 - 0.5, 0.0), friction=friction, name="support")
    m = b.finalize(dtype=wp.float64 if shape == "wide mesh" else wp.float32)
    return m, we.Solver(m)


@pytest.mark.parametrize("kind, top, dt", [("sphere tool", 0.01, 1e-4), ("sphere tool", 0.3, 2e-4),
                                           ("static sphere", 0.3, 1e-4), ("box tool", 0.3, 2e-4)])
def test_particles_resting_on_a_sphere_in_float32_carry_their_whole_weight_each_step(kind, top, dt):
    """Five lone particles (no neighbours: gravity and the contact alone) resting on the top
    of a sphere of radius 0.5 m, held as a tool or a static collider, its top ``top`` m up (or
    on a held box tool's top face), float32, friction 0.5: from the 100th step on every step's
    reaction is their weight to 1e-5 (measured 4e-9). A resting particle starts each step a
    few units in the last place on either side of where the contact finds the surface; read
    as landing when outside, the touchdown share kept part of its inward speed: up to 9 %, 4.1 %
    and 20 % less than the weight, in 133, 33 and 200 of the 200 steps, in the first three
    cases (docs/physics.md, "The touchdown share's round-off"). The box's face puts the
    particles back exactly (it passed before)."""
    dx, radius = 0.02, 0.5
    gap = tools.CONTACT_MARGIN * dx
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -G, 0.0))
    spots = np.array([[x, 0.0, 0.013 * x] for x in (-0.1, -0.05, 0.0, 0.05, 0.1)])
    for p in spots:
        b.add_box((p[0], top + 0.5 * dx, p[2]), (dx, dx, dx), we.Material(density=1000.0, mu=1e3, lam=1e3))
    centre = np.array([0.0, top - radius, 0.0])
    if kind == "sphere tool":
        b.add_tool("sphere", radius=radius, position=tuple(centre), friction=0.5, name="t")
    elif kind == "static sphere":
        b.add_sphere_collider(tuple(centre), radius, friction=0.5)
    else:
        b.add_tool("box", half_extents=(0.5, 0.05, 0.5), position=(0.0, top - 0.05, 0.0), friction=0.5, name="t")
    m = b.finalize(device="cpu", dtype=wp.float32)
    assert m.particle_count == len(spots)
    if kind == "box tool":
        spots[:, 1] = top + gap
    else:  # on the sphere, the contact's margin out (the static one puts them on it)
        d = spots - centre
        d[:, 1] = np.sqrt(radius ** 2 - d[:, 0] ** 2 - d[:, 2] ** 2)
        spots = centre + d * (radius + gap) / radius
    m.particle_x0 = spots
    s = we.Solver(m)
    a, c = m.state(), m.state()
    weight = float(m.particle_mass.numpy().astype(np.float64).sum()) * G
    forces = []
    for k in range(300):
        s.step(a, c, dt)
        a, c = c, a
        if k >= 100:
            r = s.collider_reactions(a)["sphere0"] if kind == "static sphere" else s.reaction_forces(a)["t"]
            forces.append(np.asarray(r[0], dtype=np.float64))
    forces = np.array(forces) / weight
    worst = np.abs(forces[:, 1] - 1.0).max()
    assert worst < 1e-5, (worst, int((np.abs(forces[:, 1] - 1.0) > 1e-5).sum()))


def test_a_block_sticking_on_a_held_sphere_tool_does_not_creep():
    """Friction 0.5 on the apex of a held sphere tool: relaxed, then 0.4 s left alone, no
    particle moves sideways by more than 2 um, and the tool carries the weight. A particle
    resting on a tool is stopped where its path enters it (the swept test); before the
    tangential displacement was taken from the start of the path (``tangential_follow``),
    each step moved a sticking particle back by the drift after that entry point, against
    the tangential force (measured: 25 um sideways in 0.4 s, and growing; 4 um when first measured, 0.7 um before the
    inside test had the contact's margin, 0.6 um before it counted a particle within the margin as touching, 0.85 um
    now)."""
    m, s = _block_on_tool("sphere", 0.5)
    a = _run(s, m, 2000, 2e-4, relax_after=0.0)
    x1 = a.x.numpy().copy()
    c = m.state()
    forces = []
    for _ in range(2000):
        s.step(a, c, 2e-4)
        a, c = c, a
        forces.append(s.reaction_forces(a)["support"][0])
    d = a.x.numpy() - x1
    sideways = np.hypot(d[:, 0], d[:, 2]).max()
    force = np.mean(forces, axis=0)
    weight = m.particle_mass.numpy().sum() * G
    print(f"largest sideways displacement over 0.4 s: {sideways:.2e} m; support force {force} N, weight {weight:.4f} N")
    assert sideways < 2e-6, sideways  # measured 0.85 um: a return to the first 4 um fails
    np.testing.assert_allclose(force, [0.0, weight, 0.0], atol=1e-2 * weight)


def _floor_with_fin(thickness, fin_height=0.03, half_z=0.05):
    """A closed mesh: a floor slab 0.3 m long, 2 cm thick, its top at y = 0, with a fin
    ``thickness`` wide over x in [0, thickness] standing on it (a profile in x-y extruded along
    z), outward wound."""
    T, H = thickness, fin_height
    prof = np.array([(-0.15, -0.02), (0.15, -0.02), (0.15, 0.0), (T, 0.0), (T, H), (0.0, H), (0.0, 0.0), (-0.15, 0.0)])
    n = len(prof)
    pts = np.concatenate([np.c_[prof, np.full(n, -half_z)], np.c_[prof, np.full(n, half_z)]])
    sides = [t for i in range(n) for t in ((i, (i + 1) % n, n + (i + 1) % n), (i, n + (i + 1) % n, n + i))]
    cap = [(0, 1, 2), (0, 2, 3), (0, 3, 6), (0, 6, 7), (6, 3, 4), (6, 4, 5)]
    tris = np.array(sides + [(a, c, b) for a, b, c in cap] + [(n + a, n + b, n + c) for a, b, c in cap], dtype=np.int32)
    return pts, tris


def test_a_particle_sliding_on_a_mesh_tool_into_a_thin_fin_of_it_does_not_pass_through():
    """A block sliding at 8 m/s (4 mm a step) on a mesh floor into a 2 mm fin of the same
    mesh: no particle gets into or past the fin below its top. The contact's tangential move
    along the floor, from where the path met it, went through the fin: the bottom row, whose
    path dipped below the floor before it reached the fin, ended 0.04 mm past its back face
    at 8 m/s, and 16 particles were past it 6 ms in, up to 3 cm (a convex shape has no other
    face such a move could meet; a mesh can)."""
    pts, tris = _floor_with_fin(0.002)
    a, b_, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    assert np.einsum("ij,ij->i", a, np.cross(b_, c)).sum() / 6 == pytest.approx(0.3 * 0.02 * 0.1 + 0.002 * 0.03 * 0.1)  # closed, outward
    b = we.SceneBuilder(spacing=0.01, gravity=(0.0, -G, 0.0))
    b.add_box((-0.025, 0.0101, 0.0), (0.04, 0.03, 0.04), we.Material.preset("dough"), name="block", velocity=(8.0, -0.5, 0.0))
    b.add_tool("mesh", mesh=(pts, tris), name="floor_fin")
    m = b.finalize(dtype=wp.float64)
    s, x, y = we.Solver(m), m.state(), m.state()
    past = []
    for _ in range(12):
        s.step(x, y, 5e-4)
        x, y = y, x
        p = x.x.numpy()
        past.append(int(((p[:, 0] > 0.0) & (p[:, 1] < 0.03 - m.tools.margin)).sum()))
    assert np.abs(x.x.numpy()[:, 0]).max() < 0.2 and max(past) == 0, past
    assert p[:, 0].max() > -0.002  # the block reached the fin


@pytest.mark.parametrize("face", [0.0217, 0.10432, 0.3, 1.0])
def test_particles_on_a_mesh_tools_face_within_float32s_resolution_are_put_the_margin_outside(face):
    """A sheet of particles at rest on a box mesh's top face, modelled ``face`` m up, 0 to 2e-8
    m above it (within float32's resolution there), no gravity: one step puts every one the
    contact's margin above the face, straight up. Warp's float32 sign read most of them
    inside: 99 of 100 were put the margin inside the face at 0.3 and 1.0 m (4 and 6 at 0.104
    and 0.022), their inward speed kept, and the one on the diagonal between the top's two
    triangles went the margin sideways; within the margin the face's plane now decides."""
    b = we.SceneBuilder(spacing=0.01, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, face + 0.005, 0.0), (0.1, 0.01, 0.1), _elastic(1e5), name="sheet")
    pts, tris = tools.box_mesh((0.2, 0.05, 0.2))
    b.add_tool("mesh", mesh=(pts + np.array([0.0, face - 0.05, 0.0]), tris), name="table")
    m = b.finalize(dtype=wp.float64)
    x0 = m.particle_x0.copy()
    x0[:, 1] = face + np.linspace(0.0, 2e-8, len(x0))
    m.particle_x0 = x0
    s, a, c = we.Solver(m), m.state(), m.state()
    s.step(a, c, 1e-4)
    x = c.x.numpy()
    np.testing.assert_allclose(x[:, 1] - face, m.tools.margin, rtol=1e-9)
    np.testing.assert_allclose(x[:, [0, 2]], x0[:, [0, 2]], rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape", ["box", "mesh", "wide mesh"])
def test_a_block_on_a_held_box_tool_comes_to_rest_at_the_contacts_margin(shape):
    """A block resting on a held box tool (or a mesh of it, also one 20000 spacings wide): over 0.2-0.4 s its bottom layer stays where the
    contact put it, the margin (a thousandth of a spacing) above the top face, to 1e-7 m
    (measured: not at all), its kinetic energy dies out (0.3-0.4 s: 0.35 of 0.2-0.3 s) and
    the tool carries the weight (0.9996). When the inside test put a particle found inside
    the margin outside but did not count one within the margin as touching, a resting
    particle fell back through the margin every few steps and was lifted again: the bottom
    layer bounced over the whole margin (2e-5 m) for ever, the kinetic energy stayed at 1.2e-5
    J (57 times that at rest), and a slowly lifted block carried 12 % more than its
    0.5 M v^2 (docs/tools.md). The mesh's inside test had the margin from the first and
    bounced so too (measured: 1.2e-5 J, the heights over 2e-5 m, the same as the box's)."""
    m, s = _block_on_tool(shape, 0.5)
    a, c = m.state(), m.state()
    mass = m.particle_mass.numpy()
    bottom = m.particle_x0[:, 1] < 0.02
    heights, kinetic, forces = [], [], []
    for k in range(2000):
        s.step(a, c, 2e-4)
        a, c = c, a
        if k >= 1000:
            heights.append(a.x.numpy()[bottom, 1])
            v = a.v.numpy()
            kinetic.append(0.5 * float((mass[:, None] * v * v).sum()))
            forces.append(s.reaction_forces(a)["support"][0][1])
    heights = np.array(heights)
    margin = tools.CONTACT_MARGIN * m.spacing
    assert bottom.sum() == 9
    assert np.ptp(heights, axis=0).max() < 1e-7, np.ptp(heights, axis=0).max()
    np.testing.assert_allclose(heights.mean(), 0.01 + margin, atol=0.01 * margin)
    assert np.mean(kinetic[500:]) < 0.5 * np.mean(kinetic[:500]), (np.mean(kinetic[:500]), np.mean(kinetic[500:]))
    assert np.mean(forces) == pytest.approx(mass.sum() * G, rel=2e-3)


@pytest.mark.parametrize("shape", ["box", "sphere"])
def test_where_a_path_ends_just_inside_or_outside_a_tool_or_its_margin_moves_the_particle_alike(shape):
    """A particle falling 1 mm in a step onto a held tool, float64: its path ending 1e-9 m
    inside the surface or 1e-9 m outside, or as far inside or outside the margin, it ends the
    step within 1e-8 m of the same height, the margin (a thousandth of a spacing) above the
    surface. When a particle within the margin did not count as touching, the entry test put
    one whose path ended just inside the margin outside and left one that ended just outside
    where it was: the two ended the margin (2e-5 m) apart (docs/method.md §1)."""
    dx = 0.02
    margin = tools.CONTACT_MARGIN * dx

    def height(end):
        b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0))
        b.add_box((0.0, 0.5, 0.0), (dx, dx, dx), we.Material(density=1000.0, mu=1e3, lam=1e3), velocity=(0.0, -1.0, 0.0))
        if shape == "box":
            b.add_tool("box", half_extents=(0.5, 0.05, 0.5), position=(0.0, -0.05, 0.0), name="t")
        else:
            b.add_tool("sphere", radius=0.5, position=(0.0, -0.5, 0.0), name="t")
        m = b.finalize(dtype=wp.float64)
        assert m.particle_count == 1
        m.particle_x0 = np.array([[0.0, 1e-3 + end, 0.0]])
        a, c = m.state(), m.state()
        we.Solver(m).step(a, c, 1e-3)
        return c.x.numpy()[0, 1]

    for surface in (0.0, margin):
        below, above = height(surface - 1e-9), height(surface + 1e-9)
        assert below == pytest.approx(margin, abs=1e-8) and above == pytest.approx(margin, abs=1e-8), (surface, below, above)


@pytest.mark.parametrize("kind", ["sphere", "cylinder"])
def test_a_block_pressed_into_a_curved_held_tool_has_a_loss_without_round_off_jumps(kind):
    """A float64 block started 0.2 mm inside a held sphere (or a cylinder's side) of radius
    10 m: over relative changes of lam of 1e-7 to 1e-6 each increment of the loss is the
    tape's gradient times the change (measured within 1.2e-3 of it). The inside tests put a
    particle exactly on the surface and the entry tests a thousandth of a spacing outside;
    one left on the surface was classified by round-off the next step, and the loss jumped
    by 1e-5 to 4e-5 where the gradient predicts 3e-11 (a particle's position by the whole
    margin, 2e-5 m). Now both put it the margin outside (docs/method.md §1)."""
    dx, top, radius = 0.02, 0.0102, 10.0
    w = random_weights(36, 2)

    def loss(lam, grad=False):
        b = we.SceneBuilder(spacing=dx, gravity=(0.0, -G, 0.0))
        b.add_box((0.0, 0.03, 0.0), (4 * dx, 3 * dx, 3 * dx),
                  we.Material(density=1000.0, mu=1e3, lam=lam, yield_stress=10.0, flow_rate=50.0, hardening=200.0,
                              pressure_stiffness=1.0, viscosity=2.0), name="block")
        if kind == "sphere":
            b.add_tool("sphere", radius=radius, position=(0.0, top - radius, 0.0), friction=0.5, name="t")
        else:  # its axis along z: the block lies across its side
            b.add_tool("cylinder", radius=radius, half_height=0.2, position=(0.0, top - radius, 0.0),
                       orientation=(math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4)), friction=0.5, name="t")
        # The premise is the start inside, which finalize places on the surface: put it back.
        with pytest.warns(UserWarning, match="start inside tool 't'.*placed on its surface"):
            m = b.finalize(dtype=wp.float64, requires_grad=True)
        m.particle_x0[:] = np.concatenate(b._points)
        m.compute_rest_density()
        m.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * dx, size=m.particle_x0.shape)
        states = [m.state() for _ in range(9)]
        value, tape = taped_rollout_loss(we.Solver(m), states, 1e-3, w)
        if not grad:
            return value.numpy()[0]
        tape.backward(value)
        return value.numpy()[0], m.lam.grad.numpy()[0]

    lam = 1.5e3
    l0, g = loss(lam, grad=True)
    changes = lam * np.array([-1e-6, -3e-7, -1e-7, 1e-7, 3e-7, 1e-6])
    increments = np.array([loss(lam + d) for d in changes]) - l0
    predicted = g * changes
    assert np.abs(predicted).min() > 1e-12, "the loss reaches lam"
    np.testing.assert_allclose(increments, predicted, rtol=1e-2)


def test_a_rollouts_backward_leaves_the_tools_gradients_a_plain_tape_gives():
    """``Rollout.backward`` sums the tools' gradients over its passes and leaves them on
    ``model.tools`` (``motion_gradient``, ``friction.grad``): the tape's zeroing after each
    pass had left them 0, with the full tape and with checkpointing, which read as "no
    sensitivity" (measured since: equal to a plain tape's, and to central differences to 1e-8)."""
    from warp_esph.rollout import Rollout

    steps, dt = 12, 5e-4
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name="block")
    b.add_ground()
    b.add_tool("box", half_extents=(0.05, 0.01, 0.05), position=(0.0, 0.062, 0.0), friction=0.4, name="press",
               motion=tools.Velocity((0.3, -0.6, 0.0), (0.0, 0.0, 0.0)))
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    weights = np.random.default_rng(0).normal(size=(m.particle_count, 3))
    # The plain tape's gradient.
    states = [m.state() for _ in range(steps + 1)]
    solver = we.Solver(m)
    tape = wp.Tape()
    with tape:
        for a, c in zip(states[:-1], states[1:]):
            solver.step(a, c, dt)
    states[-1].x.grad.assign(weights)
    tape.backward()
    ref_v, ref_f = m.tools.motion_gradient("press")["velocity"], m.tools.friction.grad.numpy()[0]
    tape.zero()
    assert np.abs(ref_v).max() > 0.0 and ref_f != 0.0
    for every in (None, 4):
        r = Rollout(m, steps=steps, dt=dt, checkpoint_every=every)
        r.forward()
        r.backward({steps: weights})
        np.testing.assert_allclose(m.tools.motion_gradient("press")["velocity"], ref_v, rtol=1e-10, err_msg=str(every))
        assert m.tools.friction.grad.numpy()[0] == pytest.approx(ref_f, rel=1e-10, abs=0.0)


def _refused_box_mesh_tool_run(tmp_path, capsys, name, half_extents, spacing, center, size, tool_keys=""):
    """``(scene, stderr)`` of the refused run of NAME.toml: a dough box of ``size`` at
    ``center`` (TOML arrays) at ``spacing``, and a mesh tool of NAME.obj, a box mesh of
    ``half_extents``, with the further keys ``tool_keys`` (TOML lines)."""
    from run_files import refused_run
    from warp_esph import meshes

    meshes.write_mesh(tmp_path / f"{name}.obj", *tools.box_mesh(half_extents))
    scene = tmp_path / f"{name}.toml"
    scene.write_text(f'[scene]\nspacing = {spacing}\nframes = 1\n[[bodies]]\nshape = "box"\nmaterial = "dough"\n'
                     f'center = {center}\nsize = {size}\n'
                     f'[[tools]]\nshape = "mesh"\nfile = "{name}.obj"\n{tool_keys}')
    return scene, refused_run(capsys, scene, tmp_path / "t.usdc")


def test_a_tool_smaller_than_the_contacts_margin_is_refused_naming_its_size_and_the_spacing(tmp_path, capsys):
    """A mesh tool at scale 1e-9 (a 2e-10 m box at spacing 0.05) was taken, and the run went
    on as if it were not there. A tool smaller in every direction than the contact's margin
    (a thousandth of a spacing) is refused, naming the key that sized it; a tenth of a
    spacing is still taken (it stops the particles in its path, the test above)."""
    scene, err = _refused_box_mesh_tool_run(tmp_path, capsys, "cube", (0.1, 0.1, 0.1), 0.05, "[0, 0.15, 0]",
                                            "[0.2, 0.15, 0.2]", "scale = 1e-9\nposition = [0, 0.5, 0]\n")
    assert err == (f"warp-esph: error: {scene}: [[tools]] #1 (shape 'mesh'): scale = 1e-09 is not allowed for mesh tool "
                   f"'mesh_tool0' of '{tmp_path / 'cube.obj'}': the tool is 2e-10 m across at most, less than 5e-05 m, a "
                   "thousandth of the spacing 0.05 (the contact's margin): the particles pass it by; give a larger scale or "
                   "a smaller spacing\n"), err
    b = we.SceneBuilder(spacing=0.02)
    with pytest.raises(ValueError, match=r"^radius = 1e-06 is not allowed for sphere tool 'pin': the tool is 2e-06 m across "
                                         r"at most, less than 2e-05 m"):
        b.add_tool("sphere", radius=1e-6, name="pin")
    with pytest.raises(ValueError, match=r"^half_extents = \(1e-06, 1e-06, 1e-06\) is not allowed for box tool"):
        b.add_tool("box", half_extents=(1e-6, 1e-6, 1e-6))
    assert b.add_tool("sphere", radius=1e-3) == "sphere_tool0"  # a tenth of a spacing across
    assert b.add_tool("box", half_extents=(0.1, 1e-6, 0.1)) == "box_tool1"  # a thin plate


def test_a_scene_file_s_mesh_tool_the_particles_meet_beyond_float32_is_refused_by_its_table(tmp_path, capsys):
    """The refusal made at finalize, where the particles are known, names the file's tool
    table and the command's option, as add_tool's refusals do."""
    scene, err = _refused_box_mesh_tool_run(tmp_path, capsys, "slab", (100.0, 50.0, 100.0), 0.02, "[0, 50.03, 0]",
                                            "[0.06, 0.06, 0.06]")
    assert err.startswith(f"warp-esph: error: {scene}: [[tools]] #1 (shape 'mesh'): mesh tool 'mesh_tool0' is not allowed "
                          "in float32: the faces the particles can touch reach 100 m from its origin"), err
    assert err.endswith("split its faces there into smaller ones, use dtype=float64 (--dtype float64), or a larger spacing\n"), err
    from warp_esph.cli import main

    assert main(["run", str(scene), "-o", str(tmp_path / "t.usdc"), "--no-progress", "--dtype", "float64"]) == 0


def test_a_mesh_tool_whose_points_float32_cannot_resolve_the_contacts_margin_is_refused():
    """Warp's mesh queries are float32: a box mesh modelled 1000 m from its origin (put back
    by its position) at spacing 0.02 resolves 1.2e-4 m there, six times the contact's margin,
    and a block landing on it was put the margin inside it in 41 of 400 steps (130 m out:
    still wrong; 10 km out it ended inside). It is refused, naming the reach, what float32
    resolves there and the margin; the same mesh about its origin, placed 1000 m out by its
    position, and one 40 m out are taken. What counts is where the particles can touch it:
    a mesh 200 m across about its origin is refused once a block sits near its corner, 90 m
    out, and taken with the block on the middle of its top, 50 m up (a wide floor under a
    block near its origin: the test above); a Scripted tool's poses are not known before the
    run, so there its farthest point counts."""
    pts, tri = tools.box_mesh((0.1, 0.05, 0.1))
    b = we.SceneBuilder(spacing=0.02)
    with pytest.raises(ValueError, match=r"^mesh \(points, triangles\) is not allowed: its points \(scale 1\) lie 1e\+03 m "
                                         r"and more from the tool's origin, where float32 \(Warp's mesh queries\) resolves "
                                         r"0\.00012 m, more than half the contact's margin 2e-05 m \(a thousandth of the "
                                         r"spacing 0\.02\): particles that touch it would be put inside it; model the mesh "
                                         r"about its origin"):
        b.add_tool("mesh", mesh=(pts + 1000.0, tri), position=(-1000.0, -1000.0, -1000.0))
    assert b.add_tool("mesh", mesh=(pts, tri), position=(1000.0, 0.0, 0.0)) == "mesh_tool0"
    assert b.add_tool("mesh", mesh=(pts + 40.0, tri), position=(-40.0, -40.0, -40.0)) == "mesh_tool1"
    scripted = tools.Scripted(lambda t: ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    queries = (r"^mesh tool 'slab' is not allowed: the particles can touch it up to 100 m from its origin, where float32 "
               r"\(Warp's mesh queries\) resolves 1\.2e-05 m, more than half the contact's margin 2e-05 m")
    # A float32 model computes the contact on the face from its vertices: the top's two
    # triangles reach its corners, 100 m out.
    faces = (r"^mesh tool 'slab' is not allowed in float32: the faces the particles can touch reach 100 m from its origin, "
             r"where float32 \(the model's contact and Warp's mesh queries\) resolves 1\.2e-05 m, more than half")
    for place, motion, dtype, refused in (((90.0, 50.03, 90.0), None, wp.float64, queries),
                                          ((0.0, 50.03, 0.0), None, wp.float64, None),
                                          ((0.0, 50.03, 0.0), None, wp.float32, faces),
                                          ((0.0, 50.03, 0.0), scripted, wp.float64, queries)):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box(place, (0.06, 0.06, 0.06), we.Material.preset("dough"), name="block")
        b.add_tool("mesh", mesh=(pts, tri), scale=1000.0, name="slab", motion=motion)  # 200 x 100 x 200 m
        if refused is None:
            assert b.finalize(dtype=dtype).particle_count == 27
            continue
        with pytest.raises(ValueError, match=refused):
            b.finalize(dtype=dtype)


def test_a_run_stops_where_the_particles_meet_a_mesh_tool_beyond_float32s_resolution():
    """finalize bounds where the particles can meet a mesh tool by their start (their box grown
    by its diagonal, from the tool's start place): a plate 200 m wide about its origin moving
    at 15 m/s under a block resting 80 m out was taken (float64), and the run went on with the
    block on it 84 m and more out, where float32 (Warp's mesh queries) no longer resolves half
    the contact's margin (a small mesh met 100 m out put particles inside it). The run stops
    at the frame where they meet it there (frame 8: 80 + 15 t passes 83.9 m at t = 0.26 s)."""
    from warp_esph.simulate import SimulationError

    b = we.SceneBuilder(spacing=0.02)
    b.add_box((80.0, 0.03, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name="block")
    b.add_tool("mesh", mesh=tools.box_mesh((100.0, 0.05, 100.0)), name="belt", friction=0.0,
               motion=tools.Velocity((-15.0, 0.0, 0.0), position=(0.0, 0.01 - 0.05, 0.0)))
    m = b.finalize(dtype=wp.float64)
    with pytest.raises(SimulationError, match=r"^the simulation stopped after step \d+ \(frame 8, t = 0\.2667 s\): the "
                                              r"particles met mesh tool 'belt' far from its origin \(they are at it 84 m "
                                              r"from it\), where float32 \(Warp's mesh queries\) resolves 1e-05 m, more "
                                              r"than half the contact's margin 2e-05 m") as info:
        we.simulate(m, 12, fps=30.0, progress=False)
    assert info.value.frame == 8 and info.value.body == "block"


def test_a_run_stopped_at_a_far_mesh_tool_names_the_callers_precision_option(tmp_path, monkeypatch, capsys):
    """That stop told 'warp-esph run' to 'use dtype=float64', a Python caller's parameter: the
    command's option is --dtype float64. The scene above in float32, finalize's bound left out
    (in float32 it refuses this scene already; a scene file reaches the stop with a mesh file)."""
    from warp_esph import scenes  # noqa: PLC0415
    from warp_esph.cli import main  # noqa: PLC0415

    def belt():
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((80.0, 0.03, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name="block")
        b.add_tool("mesh", mesh=tools.box_mesh((100.0, 0.05, 100.0)), name="belt", friction=0.0,
                   motion=tools.Velocity((-15.0, 0.0, 0.0), position=(0.0, 0.01 - 0.05, 0.0)))
        return b

    monkeypatch.setattr(we.SceneBuilder, "_check_mesh_tool_reach", lambda self, scalar: None)
    monkeypatch.setattr(scenes, "load_scaled_scene", lambda *a, **k: scenes.Scene("belt", "", belt(), frames=2))
    cure = (r"; model the mesh about where they meet it \(its points less that place, the place added to position\), split "
            r"its faces there into smaller ones, use {}, or use a larger spacing")
    out = tmp_path / "f.usdc"
    assert main(["run", "-o", str(out), "--no-progress"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert re.fullmatch(r"warp-esph: error: the simulation stopped after step \d+ \(frame 1, t = 0\.03333 s\): the particles "
                        r"met mesh tool 'belt' far from its origin \(the faces they are at reach 100 m from it\), where float32 "
                        r"\(the model's contact and Warp's mesh queries\) .*" + cure.format("--dtype float64")
                        + rf" \({re.escape(str(out))} keeps the 1 frame finished\)", err[0]), err
    with pytest.raises(we.SimulationError, match=cure.format("dtype=float64") + "$"):
        we.simulate(belt().finalize(), 2, fps=30.0, progress=False)


def test_the_far_mesh_check_of_a_frame_does_not_rebuild_the_meshs_faces(monkeypatch):
    """In float32 the frame's check of a far mesh tool built the (faces, 3, 3) array of the
    whole mesh's vertices (float64) at every frame; the faces' bounds and reach are now built
    once a run (``_far_mesh_tools``), and a frame's check allocates per face only a few
    booleans. A floor of 20172 faces 200 m wide, a block on it 90 m out: the check finds the
    faces the block is at reaching 92.4 m (as the vertices gave it) and allocates less than a
    third of the one array it built (1.45 MB)."""
    import tracemalloc  # noqa: PLC0415

    from warp_esph.simulate import _far_mesh_contact, _far_mesh_tools  # noqa: PLC0415

    # 41 x 41 tiles 5 m apart (closed boxes, 12 faces each), their tops at y = 0.
    box_pts, box_tri = tools.box_mesh((2.4, 0.05, 2.4))
    centres = [(x, -0.05, z) for x in np.linspace(-100.0, 100.0, 41) for z in np.linspace(-100.0, 100.0, 41)]
    pts = np.concatenate([box_pts + c for c in centres])
    tri = np.concatenate([box_tri + 8 * k for k in range(len(centres))])
    assert len(tri) == 20172
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((90.0, 0.04, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name="block")
    b.add_tool("mesh", mesh=(pts, tri), name="floor", friction=0.0, motion=tools.Velocity((0.0, 0.0, 0.0)))
    # finalize refuses this plate in float32 already; the frame's check is what is looked at here.
    monkeypatch.setattr(we.SceneBuilder, "_check_mesh_tool_reach", lambda self, scalar: None)
    model = b.finalize(dtype=wp.float32)
    far = _far_mesh_tools(model)
    state = model.state()
    _far_mesh_contact(model, state, far)  # warm: imports, first calls
    tracemalloc.start()
    try:
        met = _far_mesh_contact(model, state, far)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert met is not None and "(the faces they are at reach 92.4 m from it)" in met[0], met
    assert peak < len(tri) * 9 * 8 / 3, peak


@wp.kernel(module="unique")
def _pinned_x_plus_y(x: wp.array(dtype=wp.vec3d), i: int, weight: wp.float64, loss: wp.array(dtype=wp.float64)):
    wp.atomic_add(loss, 0, weight * (x[i][0] + x[i][1]))


def test_keyframes_on_step_boundaries_give_the_keyframe_pose_the_crossed_segments_velocity_and_a_one_sided_time_gradient():
    """A keyframed motion is a kink at each keyframe time; where one falls exactly on a step
    boundary (dt = 2^-10 s, keyframes at 0, 2 dt, 4 dt: +x, then +y), both steps that meet
    there take the pose at it from the same side. The pinned particles sit at the keyframe pose
    there, and their velocity is the segment the step just crossed (symplectic Euler's
    backward difference, x_n - x_{n-1} = dt v_n). The loss reads the pose at the keyframe
    through the step ending there (x_2) and the step starting there (v_3 = (x_3 - x_2) / dt):
    L = f(x_2) + 2 dt f(v_3). The tape's derivative in the keyframe's time is one of its two
    one-sided derivatives (measured: 0 from the tape; the left difference 0, the right -1.024:
    the segment that starts there, as for the keyframe moved earlier); the step ending there
    taking its end pose from the segment before and the next its start from the one after would
    give +1.024, neither (measured with the samples so split)."""
    dt = 2.0 ** -10
    c = np.array([-0.02, 0.1, 0.0])  # the pinned column's rest centroid

    def model(t1=2 * dt):
        b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
        b.add_box((0.0, 0.1, 0.0), (0.06, 0.06, 0.06), _elastic(2e3), name="block")
        b.pin(body="block", region=((-1.0, -1.0, -1.0), (-0.01, 1.0, 1.0)), name="grip",
              motion=tools.Keyframes((0.0, t1, 4 * dt), (c, c + (0.002, 0.0, 0.0), c + (0.002, 0.004, 0.0))))
        return b.finalize(dtype=wp.float64, requires_grad=True)

    m = model()
    i = int(m.tools.pins[0].indices[0])
    x0 = m.particle_x0[i]
    solver = we.Solver(m)
    states = [m.state() for _ in range(5)]
    for n in range(4):
        solver.step(states[n], states[n + 1], dt)
    x = np.array([s.x.numpy()[i] for s in states])
    v = np.array([s.v.numpy()[i] for s in states])
    np.testing.assert_allclose(x[2] - x0, (0.002, 0.0, 0.0), atol=1e-15)  # the keyframe's pose
    np.testing.assert_allclose(x[4] - x0, (0.002, 0.004, 0.0), atol=1e-15)
    np.testing.assert_allclose(v[1:], np.diff(x, axis=0) / dt, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(v[2], (0.002 / (2 * dt), 0.0, 0.0), rtol=1e-12)  # the segment crossed, +x
    np.testing.assert_allclose(v[3], (0.0, 0.004 / (2 * dt), 0.0), rtol=1e-12)  # the next one, +y

    def loss(mm, grad=False):
        s = we.Solver(mm)
        sts = [mm.state() for _ in range(4)]
        out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        tape = wp.Tape()
        with tape:
            for n in range(3):  # across the keyframe's time
                s.step(sts[n], sts[n + 1], dt)
            wp.launch(_pinned_x_plus_y, 1, [sts[2].x, i, 1.0], [out])
            wp.launch(_pinned_x_plus_y, 1, [sts[3].v, i, 2.0 * dt], [out])
        if grad:
            tape.backward(out)
            return mm.tools.keyframe_times.grad.numpy()[1]
        return out.numpy()[0]

    tape = loss(model(), grad=True)
    h = 1e-8
    here = loss(model())
    left, right = (here - loss(model(2 * dt - h))) / h, (loss(model(2 * dt + h)) - here) / h
    assert abs(left - right) > 0.5  # a kink: 0 and -1.024
    assert min(abs(tape - left), abs(tape - right)) < 1e-4, (tape, left, right)


def test_a_motion_keyed_from_t_0_reads_its_first_segment_there_and_its_gradients_match_central_differences():
    """The first keyframe at t = 0, a step boundary (dt = 2^-10 s, keyframes at 0, 2 dt,
    4 dt: +x, then +y): the step starting there is inside the first segment, as a step
    starting at any other keyframe is inside the segment starting there, so the pinned
    particles move at that segment's velocity from the first step, and the tape's derivative
    in the first keyframe's time is the one for the keyframe moved earlier, the side every
    other keyframe on a step boundary gives (measured: tape 0.512, left difference 0.512,
    right -1.536; the sample at t = 0 took the hold before the first keyframe, and the tape
    read -1.536, the other side). The derivatives in the keyframe positions, smooth across
    t = 0, match float64 central differences."""
    dt = 2.0 ** -10
    c = np.array([-0.02, 0.1, 0.0])

    def model(t0=0.0, dp=None):
        p = np.array([c, c + (0.002, 0.0, 0.0), c + (0.002, 0.004, 0.0)])
        if dp is not None:
            p = p + dp
        b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
        b.add_box((0.0, 0.1, 0.0), (0.06, 0.06, 0.06), _elastic(2e3), name="block")
        b.pin(body="block", region=((-1.0, -1.0, -1.0), (-0.01, 1.0, 1.0)), name="grip",
              motion=tools.Keyframes((t0, 2 * dt, 4 * dt), [tuple(r) for r in p]))
        return b.finalize(dtype=wp.float64, requires_grad=True)

    m = model()
    i = int(m.tools.pins[0].indices[0])
    x0 = m.particle_x0[i]

    def loss(mm, grad=False):
        s = we.Solver(mm)
        sts = [mm.state() for _ in range(3)]
        out = wp.zeros(1, dtype=wp.float64, requires_grad=True)
        tape = wp.Tape()
        with tape:
            for n in range(2):
                s.step(sts[n], sts[n + 1], dt)
            # The pose and velocity the first step, which starts at the keyframe, gives.
            wp.launch(_pinned_x_plus_y, 1, [sts[1].x, i, 1.0], [out])
            wp.launch(_pinned_x_plus_y, 1, [sts[1].v, i, 2.0 * dt], [out])
        if grad:
            tape.backward(out)
            return (mm.tools.keyframe_times.grad.numpy()[0], mm.tools.keyframe_positions.grad.numpy().copy(),
                    sts[1].x.numpy()[i] - x0, sts[1].v.numpy()[i])
        return out.numpy()[0]

    g_t, g_p, x1, v1 = loss(m, grad=True)
    np.testing.assert_allclose(x1, (0.001, 0.0, 0.0), atol=1e-15)
    np.testing.assert_allclose(v1, (0.002 / (2 * dt), 0.0, 0.0), rtol=1e-12)  # the first segment's, +x
    h = 1e-8
    here = loss(model())
    left, right = (here - loss(model(-h))) / h, (loss(model(h)) - here) / h
    assert abs(left - right) > 1.0  # a kink: 0.512 and -1.536
    assert abs(g_t - left) < 1e-4 * abs(left), (g_t, left, right)
    h = 1e-7
    for k in range(3):
        for a in range(2):
            e = np.zeros((3, 3))
            e[k, a] = h
            fd = (loss(model(dp=e)) - loss(model(dp=-e))) / (2 * h)
            assert abs(g_p[k, a] - fd) < 1e-6 * max(1.0, abs(fd)), (k, a, g_p[k, a], fd)


@pytest.mark.parametrize("motion", ["velocity", "keyframes", "turning", "turning_keyframes"])
def test_a_pinned_set_moving_steadily_reports_no_force_each_step_in_float32(motion):
    """A weightless body pinned whole and moved at a constant 5 cm/s, 0.3 m from the origin,
    needs no force: every step's reaction must be 0. Its velocity was the difference of the
    set's two places over dt, which carried float32's resolution of them, eps |x| / dt
    (1e-4 m/s here), and the reaction read that change over dt again: measured 0.2 N per step
    (std) on a 0.24 kg set, 8 % of its weight, in float32 (0 in float64); now 3e-11 N. (Here,
    8 particles: 0.0071 N, 1.1 % of their weight.) Turning at 2 rad/s about its centroid, which
    stays at rest, its step rotation of the offsets carried their resolution the same way:
    0.015 N per step on the 0.24 kg set, now 2e-6 N."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    c0, V, w = np.array([0.3, 0.3, 0.0]), np.array([0.05, 0.0, 0.0]), 2.0
    turning = motion.startswith("turning")
    if turning:
        V = np.zeros(3)
    b.add_box(tuple(c0), (0.04, 0.04, 0.04), _elastic(1e5), velocity=tuple(V), angular_velocity=(0.0, 0.0, w if turning else 0.0),
              name="blk")
    half_turn = (0.0, 0.0, math.sin(w / 2), math.cos(w / 2))  # the turn of 1 s at w rad/s
    m = {"velocity": tools.Velocity(tuple(V)),
         "keyframes": tools.Keyframes([0.0, 1.0], [tuple(c0), tuple(c0 + V)]),
         "turning": tools.Velocity((0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, w)),
         "turning_keyframes": tools.Keyframes([0.0, 1.0], [tuple(c0)] * 2, [tools.IDENTITY, half_turn])}[motion]
    b.pin(body="blk", motion=m, name="carrier")
    model = b.finalize(device="cpu", dtype=wp.float32)
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    dt = model.stable_dt()
    weight = float(model.particle_mass.numpy().sum()) * G
    worst = 0.0
    for _ in range(100):
        solver.step(a, c, dt)
        a, c = c, a
        worst = max(worst, float(np.abs(solver.reaction_forces(a)["carrier"][0]).max()))
    assert worst < 1e-4 * weight, (worst, weight)
    if not turning:
        np.testing.assert_allclose(a.v.numpy(), np.tile(V, (model.particle_count, 1)), atol=1e-6)


def test_a_block_riding_a_moving_plane_tool_feels_no_tangential_force_each_step_in_float32():
    """A block of 8 particles sticking (mu = 1) on a plane tool that translates at 5 cm/s along
    itself rides it at that speed, and no tangential force acts on it once it does. The tool's
    surface velocity was the difference of its two world points over dt, with float32's
    resolution of the place (0.3 m out): measured 0.015 N per step (2 % of the block's weight)
    of tangential force that was round-off, and the block rode at 0.04997 m/s; now 3e-4 N and
    0.0500006 m/s."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.3, 0.02, 0.0), (0.04, 0.04, 0.04), we.Material.preset("rubber", viscosity=50.0), name="blk")
    b.add_tool("plane", friction=1.0, motion=tools.Velocity((0.05, 0.0, 0.0), position=(0, 0.01, 0)), name="belt")
    model = b.finalize(device="cpu", dtype=wp.float32)
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    dt = model.stable_dt()
    weight = float(model.particle_mass.numpy().sum()) * G
    fx = []
    for k in range(600):
        solver.step(a, c, dt)
        a, c = c, a
        if k >= 500:
            fx.append(float(solver.reaction_forces(a)["belt"][0][0]))
    assert max(abs(f) for f in fx) < 2e-3 * weight, (max(abs(f) for f in fx), weight)
    assert a.v.numpy()[:, 0].mean() == pytest.approx(0.05, abs=5e-6)


def test_a_pinned_set_carried_through_dense_keyframes_reports_no_force_each_step_in_float32():
    """A weightless body pinned whole and carried at a constant 1/16 m/s through 41 keyframes
    (every 2^-10 s, exact in float32, so the stored motion has one speed) needs no force. A
    step crossing a keyframe differenced the two float32 poses (the rates were used only
    within a segment): measured 0.0022 N per step (std; 0.014 N at worst, 2 % of the set's
    weight) at the stable step; now the pieces on either side of the keyframe, 6e-12 N."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    c0, V = np.array([0.3125, 0.3125, 0.0]), np.array([0.0625, 0.0, 0.0])
    b.add_box(tuple(c0), (0.04, 0.04, 0.04), _elastic(1e5), velocity=tuple(V), name="blk")
    ts = np.arange(41) * 2.0 ** -10
    b.pin(body="blk", motion=tools.Keyframes(tuple(ts), [tuple(c0 + V * t) for t in ts]), name="carrier")
    model = b.finalize(device="cpu", dtype=wp.float32)
    assert np.array_equal(model.tools.keyframe_positions.numpy().astype(np.float64), c0 + V * ts[:, None])
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    dt = model.stable_dt()
    weight = float(model.particle_mass.numpy().sum()) * G
    crossed, worst = 0, 0.0
    for _ in range(70):
        crossed += int(np.floor(a.time / 2.0 ** -10 + dt / 2.0 ** -10) > np.floor(a.time / 2.0 ** -10))
        solver.step(a, c, dt)
        a, c = c, a
        worst = max(worst, float(np.abs(solver.reaction_forces(a)["carrier"][0]).max()))
    assert crossed > 20  # most steps here cross a keyframe
    assert worst < 1e-5 * weight, (worst, weight)
    np.testing.assert_allclose(a.v.numpy(), np.tile(V, (model.particle_count, 1)), atol=1e-6)


@pytest.mark.parametrize("spot", ["back", "neck"])
def test_a_soft_block_comes_to_rest_on_a_curved_part_of_a_mesh_tool_with_its_weight_on_it(spot):
    """A 27-particle soft block (E = 30 kPa, viscosity 20) dropped 3 mm onto Warp's bunny
    (``bunny.usd`` at scale 0.1, 16 cm tall, faces about 3 mm across) held as a mesh tool: on
    its back, convex (radius about 8 cm: the block lands on one particle, tips onto others and
    rests, as on an analytic sphere of that radius), or on its neck, a saddle between back and
    head. With the faces' normals changing under it, the block comes to rest and the tool
    carries its weight. Measured over 0.6-0.7 s in float32: the summed reaction's mean M g to
    1.2e-5 (back) and 3e-6 (neck), sideways 3e-5 and 2e-5 of it, each step's to 2.7e-4 and
    1.7e-4 (float64 on the back 1.6e-4, a slow rocking), the centroid moving 1.1e-7 and 4e-8
    m. Each step's was 8e-4 on the back while the touchdown share read a resting particle a few
    units in the last place outside the surface as landing: it kept about 5 % of g dt in
    single steps (docs/physics.md, "The touchdown share's round-off"). Its bottom layer rests on the curved
    surface: one particle at the contact margin, others up to 0.6 mm (back) and 1.5 mm (neck)
    above it."""
    import warp.examples

    bunny = str(pathlib.Path(warp.examples.get_asset_directory()) / "bunny.usd")
    x0, z0, surface = {"back": (0.005, 0.02, 0.1048), "neck": (-0.025, 0.02, 0.0995)}[spot]
    dx = 0.005
    b = we.SceneBuilder(spacing=dx)
    b.add_box((x0, surface + 0.003 + dx, z0), (3 * dx, 3 * dx, 3 * dx),
              we.Material.from_young(3e4, 0.3, density=1000.0, viscosity=20.0), name="blk")
    b.add_tool("mesh", mesh=bunny, scale=0.1, friction=0.5, name="bunny")
    model = b.finalize(device="cpu", dtype=wp.float32)
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    dt = model.stable_dt()
    weight = float(model.particle_mass.numpy().sum()) * G
    steps, last = int(0.7 / dt), int(0.1 / dt)
    forces = []
    for k in range(steps):
        if k == steps - last:
            start = a.x.numpy().astype(np.float64).mean(axis=0)
        solver.step(a, c, dt)
        a, c = c, a
        if k >= steps - last:
            forces.append(solver.reaction_forces(a)["bunny"][0].astype(np.float64))
    forces = np.array(forces) / weight
    x = a.x.numpy().astype(np.float64)
    bottom = x[np.argsort(x[:, 1])[:9]]
    gap = -model.tools.mesh_depth(model.tools.index("bunny"), bottom)  # the tool is held at the origin
    print(spot, forces.mean(axis=0), np.abs(forces[:, 1] - 1.0).max(), np.abs(x.mean(axis=0) - start).max(), gap.min(), gap.max())
    assert np.abs(forces[:, 1] - 1.0).max() < 5e-4  # each step
    assert np.abs(forces.mean(axis=0) - (0.0, 1.0, 0.0)).max() < 1e-3
    assert np.abs(x.mean(axis=0) - start).max() < 1e-6  # at rest
    assert gap.min() < 2e-3 * dx and gap.max() > 1e-4, gap


def test_steps_across_one_or_two_keyframes_move_a_turning_pinned_set_by_its_velocity_times_dt():
    """A pinned set keyframed in position and orientation (turns about three axes), with
    keyframes inside steps of 1 ms: one at 2.5 ms, two inside the fifth step (4.2 and 4.7 ms)
    and the last at 7.5 ms, then a hold. A crossing step's velocity is the pieces of the
    segments on either side and the whole ones between (rotations composed in order), and
    symplectic Euler's positions must follow it: x_n - x_{n-1} = dt v_n at every step, to
    3e-14 m/s in float64 (measured; composing the rotations in the reverse order: 0.79 m/s in
    the step with two keyframes)."""
    dt = 1e-3
    c = np.array([-0.02, 0.1, 0.0])  # the pinned column's rest centroid

    def turn(axis, angle):
        a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        return tuple(a * math.sin(angle / 2)) + (math.cos(angle / 2),)

    def mul(a, b):
        ax, ay, az, aw = a
        bx, by, bz, bw = b
        return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)

    q1 = turn((0, 0, 1), 0.3)
    q2 = mul(q1, turn((1, 0.5, 0), 0.4))
    q3 = mul(q2, turn((0, 1, 0), -0.5))
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.1, 0.0), (0.06, 0.06, 0.06), _elastic(2e3), name="block")
    b.pin(body="block", region=((-1.0, -1.0, -1.0), (-0.01, 1.0, 1.0)), name="grip",
          motion=tools.Keyframes((0.0, 0.0025, 0.0042, 0.0047, 0.0075),
                                 (c, c + (0.002, 0, 0), c + (0.002, 0.003, 0), c + (0.0, 0.004, 0.001), c + (0.001, 0.001, 0.0)),
                                 [tools.IDENTITY, q1, q2, q3, q1]))
    model = b.finalize(dtype=wp.float64)
    pinned = model.tools.pins[0].indices
    solver = we.Solver(model)
    states = [model.state() for _ in range(10)]
    for n in range(9):
        solver.step(states[n], states[n + 1], dt)
    x = np.array([s.x.numpy()[pinned] for s in states])
    v = np.array([s.v.numpy()[pinned] for s in states])
    assert np.abs(v[1:8]).max() > 1.0  # it moves and turns
    np.testing.assert_allclose(v[1:], np.diff(x, axis=0) / dt, rtol=0, atol=1e-10)
    np.testing.assert_allclose(v[-1], 0.0, atol=1e-10)  # held after the last keyframe


@pytest.mark.parametrize("crossing", [False, True])
def test_a_keyframed_pinned_set_given_an_angular_velocity_too_moves_by_its_step_rotation(crossing):
    """A pinned set keyframed to turn about z (0.6 rad over its segment) whose angular velocity
    (about x, 40 rad/s) an optimiser wrote in place: its pose is ``E(w t) Q(t)``, so the step's
    rotation in the frame at its start is ``E(R(t0)^T w dt) E(r_seg dt / T)``, the two composed
    in the order the pose is built. The pinned particles' velocity (the step rotation applied
    to their offsets) must be their places' difference over dt, x_n - x_{n-1} = dt v_n, to
    round-off in float64 (the two rotation vectors added: 0.012 m/s off within the segment and
    0.054 m/s on the run across the keyframe, of up to 2.9 m/s, second order in dt;
    composed: round-off), within a segment and on steps across a keyframe."""
    dt = 1e-3
    c = np.array([-0.02, 0.1, 0.0])  # the pinned column's rest centroid
    turn = (0.0, 0.0, math.sin(0.3), math.cos(0.3))
    times = (0.0, 0.0045, 0.02) if crossing else (0.0, 0.02)
    positions = [c, c + (0.001, 0.0, 0.0), c + (0.002, 0.001, 0.0)][:len(times)]
    orientations = [tools.IDENTITY, turn, tools.IDENTITY][:len(times)]
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.1, 0.0), (0.06, 0.06, 0.06), _elastic(2e3), name="block")
    b.pin(body="block", region=((-1.0, -1.0, -1.0), (-0.01, 1.0, 1.0)), name="grip",
          motion=tools.Keyframes(times, [tuple(p) for p in positions], orientations))
    model = b.finalize(dtype=wp.float64)
    model.tools.angular_velocity.assign(np.array([[40.0, 0.0, 0.0]]))
    pinned = model.tools.pins[0].indices
    solver = we.Solver(model)
    states = [model.state() for _ in range(8)]
    for n in range(7):
        solver.step(states[n], states[n + 1], dt)
    x = np.array([s.x.numpy()[pinned] for s in states])
    v = np.array([s.v.numpy()[pinned] for s in states])
    assert np.abs(v[1:]).max() > 0.5  # it turns
    np.testing.assert_allclose(v[1:], np.diff(x, axis=0) / dt, rtol=0, atol=1e-10)
