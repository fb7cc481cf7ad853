"""Float64 central differences for the step's inputs that the other gradient tests take on
other paths only: the initial positions, deformation gradients and plastic strains
(``Rollout``'s ``x0``, ``F0``, ``alpha0``) and the plasticity parameters of a block that
flows on the default (incremental, fused, variational) step while it rests on a floor or is
thrown into it; a flowing block under moving tools (the tools' checks in ``test_tools.py``
run elastic blocks, which the default solver puts on the rest model); two bodies of
different stress or deformation models pressed together; and the velocities of a plane and
of a sphere tool, which no other test moves at a velocity.

Each check takes a large relative step (1e-2 of a parameter: a jump of the loss inside it
would show) and a small one, at a tolerance the loss's curvature and round-off leave (the
numbers measured are in each test's docstring)."""

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from taped_loss import assert_central_differences_converge, random_weights, taped_rollout_loss, untaped_rollout_loss
from warp_esph import tools

DX = 0.02
DT = 1.0e-3
STEPS = 8
#: A pre-worked start, so that the loss reaches the hardening modulus and alpha0.
ALPHA0 = 0.02
BLOCK = 36
PLASTIC = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "hardening": 200.0,
           "pressure_stiffness": 1.0, "viscosity": 2.0}


def _block(scene, floor, params=None):
    """A 4 x 3 x 3 block (``BLOCK`` particles, the model's first, jittered by 1e-3 dx) whose
    bottom layer lies on the floor at y = 0.01: the rough ground, a plane tool whose static
    friction is twice its kinetic one, a no-slip ghost floor (52 ghosts after the block's
    particles) or the ground with floor images; ``rest``: from rest (F = I, v = 0) under
    gravity, its own weight (590 Pa at the bottom) past the yield stress; ``thrown``:
    stretched and squeezed, sliding along x and pushed into the floor."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (4 * DX, 3 * DX, 3 * DX), we.Material(density=1000.0, **{**PLASTIC, **(params or {})}),
              name="block")
    if floor == "tool":
        b.add_tool("plane", position=(0.0, 0.01, 0.0), friction=0.3, static_friction=0.6, name="floor")
    elif floor == "ghost":
        b.add_particle_floor("block", margin=DX, ghost=True)
    else:
        b.add_ground(0.01, friction=0.5, images=floor == "images")
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    if scene == "thrown":
        x0 = model.particle_x0[:BLOCK]
        v = np.zeros_like(model.particle_x0)
        v[:BLOCK] = (10.0 * (x0 - x0.mean(axis=0)) * np.array([1.0, -0.5, 0.0]) + np.array([0.2, -0.3, 0.0])
                     + np.random.default_rng(11).normal(scale=0.02, size=x0.shape))
        model.particle_v0 = v
    return model


def _loss(model, w, edit=None, taped=False):
    """The weighted sum of the final positions after ``STEPS`` steps from ``alpha = ALPHA0``;
    ``edit(model, state)`` changes the model or the first state before the run. ``taped``:
    also the solver and the states, after the backward pass."""
    solver = we.Solver(model)
    states = [model.state() for _ in range(STEPS + 1)] if taped else [model.state(requires_grad=False)]
    states[0].alpha.fill_(ALPHA0)
    if edit is not None:
        edit(model, states[0])
    if not taped:  # a central difference's run: no tape
        return untaped_rollout_loss(solver, states[0], DT, STEPS, w)
    loss, tape = taped_rollout_loss(solver, states, DT, w)
    tape.backward(loss)
    return solver, states


def _nudge(owner, array, index, delta):
    def edit(model, state):
        a = getattr({"model": model, "state": state, "tools": model.tools}[owner], array)
        v = a.numpy()
        v[index] += delta
        a.assign(v)
    return edit


def _offset_loss(make, w, owner, array, index):
    """``loss_at(offset)``: the loss with the entry ``index`` of ``array`` moved by ``offset``.
    One model for every run (a run from a model left by another is that of a new one, to the
    bit), the tools' nudged array put back after each."""
    model = make()
    tools_array = getattr(model.tools, array) if owner == "tools" else None
    original = tools_array.numpy().copy() if owner == "tools" else None

    def loss_at(offset):
        value = _loss(model, w, _nudge(owner, array, index, offset))
        if tools_array is not None:
            tools_array.assign(original)
        return value
    return loss_at


def _central(make, w, owner, array, index, h):
    loss_at = _offset_loss(make, w, owner, array, index)
    return (loss_at(h) - loss_at(-h)) / (2 * h)


#: (scene, floor) pairs; not at rest on the floor images, whose mirrored neighbourhoods keep
#: the block's weight below the yield stress (nothing flows: every plasticity gradient 0).
FLOORS = [("rest", "ground"), ("thrown", "ground"), ("rest", "tool"), ("thrown", "tool"), ("rest", "ghost"),
          ("thrown", "ghost"), ("thrown", "images")]


#: The most a ring's mean slope may stray from the tape, relative (``assert_central_differences_converge``),
#: by input: a kink of the gradient within a ring reads up to half its change there. Measured
#: (the largest of poly6's and the biweight's, over every floor): yield stress 2.3e-3,
#: flow rate 8.6e-6, hardening 8.2e-2, position 3.6e-3, F 1.3e-2, plastic strain 0.25, each
#: the biweight's on the imaged floor but the flow rate's and the position's. The flow rate,
#: whose rings meet no kink (the biweight's 8.6e-6 at rest on the tool), keeps the old
#: largest step's bound, 1e-4 (1e-3, a jump 100 x the rings' could pass); 5e-6 fails it.
SPREAD = {"yield_stress": 1e-2, "flow_rate": 1e-4, "hardening": 0.2, "x": 1e-2, "F": 5e-2, "alpha": 0.5}

#: Poly6's bound at each step of the ladder, relative: the old two steps' bounds (the largest
#: and the smallest step), the step between them held to the looser. Its trajectories meet
#: no kink within these steps, so it keeps the checks' strictness from before the ladder.
POLY6_BOUNDS = {"yield_stress": (1e-4, 2e-4, 2e-4), "flow_rate": (1e-4, 2e-4, 2e-4), "hardening": (1e-4, 2e-4, 2e-4),
                "x": (1e-2, 1e-2, 1e-4), "F": (1e-4, 1e-4, 1e-4), "alpha": (1e-4, 1e-4, 1e-4)}


def _tolerances(model, name):
    """``(bound, spread)`` of ``assert_central_differences_converge`` for ``name`` with
    ``model``'s fit weight: poly6 every step within its old bound (``POLY6_BOUNDS``), the
    biweight, whose bottom layer meets the flow rule's kink within the largest steps, the
    smallest step within its old bound and the rings within ``SPREAD``."""
    if model.fit_weight == "poly6":
        return POLY6_BOUNDS[name], None
    return POLY6_BOUNDS[name][-1], SPREAD[name]


@pytest.mark.parametrize("scene, floor", FLOORS)
def test_gradients_in_the_initial_fields_and_the_plasticity_parameters_of_a_flowing_block_on_a_floor(scene, floor):
    """The tape's gradient in ``yield_stress``, ``flow_rate``, ``hardening`` (relative steps
    1e-2, 1e-3 and 1e-4), in the initial position of a bottom and a top particle (1e-5 m, half
    a thousandth of a spacing, to 1e-7 m), the initial F of each (an off-diagonal and a
    diagonal entry at F = I, where every singular value is repeated: 1e-4 to 1e-6), the
    initial plastic strain of the bottom one (1e-3 to 1e-5) against float64 central
    differences that close on it over the ladder of steps (``assert_central_differences_converge``:
    poly6 within its old bounds at every step, ``POLY6_BOUNDS``; the biweight within 2e-4 and
    1e-4 at the smallest, each ring between two steps within ``SPREAD`` of the tape, so no
    jump), and on the tool its kinetic friction (thrown: it slides; 3e-3, 3e-5).
    Measured with poly6 (within 1.7e-6 at the largest steps but the positions', up to 3.2e-3
    on the ghost floor, the loss's curvature) and the biweight alike, within 3.9e-5 / 3.6e-5
    at the smallest steps. On the imaged floor the biweight's bottom layer starts to flow in
    step 2 within the yield stress's largest steps (the flow rule's kink:
    ``plasticity.flow_fraction`` grows from 0; docs/physics.md, "The contact and tools
    gradients, traced"), which read the gradient's mean across it: 8.3e-4 and 2.1e-3 off at
    1e-2 and 1e-3 (2.6e-7 at 1e-4). Its largest steps are off for the hardening too, whose
    gradient is a third of poly6's (7.4e-2 / 1.5e-4 / 1.8e-5), the plastic strain (0.23 at
    1e-3, 8.5e-7 at 1e-4) and F's off-diagonal (1.2e-2 at 1e-4, 2.3e-6 at 1e-5)."""
    def make():
        return _block(scene, floor)

    model = make()
    w = random_weights(model.particle_count, 2)
    _solver, states = _loss(model, w, taped=True)
    alpha = states[-1].alpha.numpy()
    assert alpha.max() > ALPHA0 + 2e-4, "the block flows"
    if floor == "tool":
        assert np.abs(states[-1].reaction_force.numpy()).max() > 0.0, "the tool holds the block"
    elif floor == "ghost":
        assert np.abs(states[-1].ghost_force.numpy()).max() > 0.0, "the ghosts hold the block"
    else:
        assert np.abs(states[-1].collider_force.numpy()).max() > 0.0, "the ground holds the block"
    # One model for the parameters' runs (a run from a model another run left, its materials
    # set, is a new one's to the bit): the parameter set in each material made with it.
    m = make()
    materials = list(m.materials)
    for name in ("yield_stress", "flow_rate", "hardening"):
        g = getattr(model, name).grad.numpy()[0]
        base = PLASTIC[name]

        def loss_at(offset):
            value = base + offset
            m.set_materials([mt.replace(**{name: value}) if getattr(mt, name) == base else mt for mt in materials])
            return _loss(m, w)

        assert_central_differences_converge(g, loss_at, 1e-2 * base, (1, 10, 100), *_tolerances(model, name), what=name)
        assert abs(g) > 1e-11, f"the loss does not reach {name}"
    x0 = model.particle_x0[:BLOCK]
    bottom, top = int(np.argmin(x0[:, 1])), int(np.argmax(x0[:, 1]))
    checks = [("x", (bottom, 0), 1e-5), ("x", (top, 1), 1e-5), ("F", (bottom, 0, 1), 1e-4), ("F", (top, 1, 1), 1e-4),
              ("alpha", (bottom,), 1e-3)]
    for array, index, step in checks:
        g = getattr(states[0], array).grad.numpy()[index]
        assert_central_differences_converge(g, _offset_loss(make, w, "state", array, index), step, (1, 10, 100),
                                            *_tolerances(model, array), what=(array, index))
        assert abs(g) > 1e-8, (array, index)
    if floor == "tool":
        g = model.tools.friction.grad.numpy()[0]
        if scene == "rest":  # it sticks: no tangential speed for friction to take
            assert g == 0.0
        for h in (3e-3, 3e-5):
            fd = _central(make, w, "tools", "friction", 0, h)
            assert g == pytest.approx(fd, rel=1e-4, abs=1e-12), h
        if scene == "thrown":
            assert abs(g) > 1e-5


def test_the_ladder_of_central_differences_passes_a_kink_and_fails_a_jump():
    """``assert_central_differences_converge`` on a cubic loss of slope 2 at 0 (steps 1e-2,
    1e-3, 1e-4; bound 1e-4, rings within 1e-2): a kink of the slope by 1 % at 3e-3, which
    one step of 1e-2 reads 3.2e-3 off, passes; a jump of 5e-2 x the slope x the largest step
    at 3e-3 fails in its ring, one of 1e-5 x it at 5e-5 at the smallest step; with a bound
    per step (3e-3, 1e-4, 1e-4) and no spread the kink fails."""
    def cubic(x):
        return 2.0 * x + 50.0 * x ** 2 + 30.0 * x ** 3

    def run(extra):
        return assert_central_differences_converge(2.0, lambda x: cubic(x) + extra(x), 1e-2, (1, 10, 100), 1e-4, 1e-2)

    errors, _rings = run(lambda x: 0.0)
    assert errors[-1] < 1e-6
    errors, _rings = run(lambda x: 0.01 * 2.0 * max(x - 3e-3, 0.0))
    assert errors[0] > 3e-3  # what one step of 1e-2 reads
    with pytest.raises(AssertionError, match="a jump"):
        run(lambda x: 5e-2 * 2.0 * 1e-2 * (x > 3e-3))
    with pytest.raises(AssertionError, match="do not close"):
        run(lambda x: 1e-5 * 2.0 * 1e-2 * (x > 5e-5))
    # A bound per step and no spread (poly6's checks, the old steps' bounds): the kink, whose
    # ring the spread of 1e-2 took (5.6e-3), fails at the largest step (5.0e-3 off), where the
    # smooth cubic reads 1.5e-3.
    def kinked(x):
        return cubic(x) + 0.01 * 2.0 * max(x - 3e-3, 0.0)

    errors, _rings = assert_central_differences_converge(2.0, cubic, 1e-2, (1, 10, 100), (3e-3, 1e-4, 1e-4), None)
    assert errors[0] > 1e-3
    with pytest.raises(AssertionError, match="a step's difference strays"):
        assert_central_differences_converge(2.0, kinked, 1e-2, (1, 10, 100), (3e-3, 1e-4, 1e-4), None)


def _pressed(params=None):
    """The flowing block of ``_block`` sliding on a plane tool, pressed by a box tool that
    descends at 0.5 m/s onto its top layer and pushed by a keyframed sphere."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (4 * DX, 3 * DX, 3 * DX), we.Material(density=1000.0, **{**PLASTIC, **(params or {})}),
              name="block", velocity=(0.2, 0.0, 0.05))
    b.add_tool("plane", position=(0.0, 0.01, 0.0), friction=0.3, name="floor")
    b.add_tool("box", half_extents=(0.1, 0.01, 0.1), friction=0.2,
               motion=tools.Velocity((0.0, -0.5, 0.0), position=(0.0, 0.0602, 0.0)), name="press")
    b.add_tool("sphere", radius=0.03, friction=0.1,
               motion=tools.Keyframes([0.0, 0.01], [(-0.065, 0.03, 0.0), (-0.04, 0.03, 0.0)]), name="pusher")
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    return model


def test_gradients_of_a_flowing_block_under_moving_tools_match_central_differences():
    """A block that flows (the incremental step, not the rest model the tools' other checks
    run) pressed by a descending box, pushed by a keyframed sphere, on a rough plane tool:
    the tape's gradient in the press's velocity (x, y), the pusher's last keyframe position
    (x), the floor's and the press's friction (steps 1e-4, 1e-5 and 1e-6: the central
    differences close on the tape over the ladder, ``assert_central_differences_converge``,
    poly6 within the old bounds at every step, 1e-4 but the keyframe's 2e-2 above 1e-6 m; the
    biweight within 1e-4 at 1e-6, each ring's slope within 1e-4, the keyframe's 6e-2), the yield stress
    and the flow rate (relative 1e-2 and 1e-5) and an initial velocity against float64
    central differences. Measured with poly6 and the biweight: within 9.1e-8 / 3.3e-8 at 1e-6;
    the keyframe 1.2e-2 / 2.6e-2 off at 1e-4 m and 2.4e-6 / 2.2e-6 at 1e-5 m, its top ring
    1.3e-2 / 2.9e-2 (the others' rings within 2.1e-7): particle 6's drift in the last step
    reaches the pusher 8.7e-5 / 7.0e-5 m from the keyframe, where the tools' whole-depth
    contact steps the gradient by 17 % (docs/physics.md, "The contact and tools gradients,
    traced"); the yield stress 7.2e-4 (poly6, the loss's curvature; 9e-7 at 1e-5)."""
    model = _pressed()
    w = random_weights(model.particle_count, 2)
    solver, states = _loss(model, w, taped=True)
    assert not solver.rest_model and states[-1].alpha.numpy().max() > ALPHA0 + 1e-3, "the block flows"
    rows = np.array([np.abs(st.reaction_force.numpy()).max(axis=1) for st in states[1:]])
    assert (rows.max(axis=0) > 0.0).all(), "every tool touches the block"
    t = model.tools
    pusher_key = t.keyframe_start[t.index("pusher")] + 1
    # (array, index, poly6's old bound at 1e-4 (1e-4 at 1e-6), the biweight's rings' spread): the
    # old bounds hold poly6 at every step; the biweight's keyframe crosses the whole-depth
    # contact within 1e-4 m, read by the rings.
    checks = [("velocity", (t.index("press"), 1), 1e-4, 1e-4), ("velocity", (t.index("press"), 0), 1e-4, 1e-4),
              ("keyframe_positions", (pusher_key, 0), 2e-2, 6e-2), ("friction", t.index("floor"), 1e-4, 1e-4),
              ("friction", t.index("press"), 1e-4, 1e-4)]
    for array, index, old, spread in checks:
        g = getattr(t, array).grad.numpy()[index]
        bound, spread = ((old, old, 1e-4), None) if model.fit_weight == "poly6" else (1e-4, spread)
        assert_central_differences_converge(g, _offset_loss(_pressed, w, "tools", array, index), 1e-4, (1, 10, 100),
                                            bound, spread, what=(array, index))
        assert abs(g) > 1e-5, (array, index)
    for name in ("yield_stress", "flow_rate"):
        g = getattr(model, name).grad.numpy()[0]
        for rel in (1e-2, 1e-5):
            e = rel * PLASTIC[name]
            fd = (_loss(_pressed({name: PLASTIC[name] + e}), w) - _loss(_pressed({name: PLASTIC[name] - e}), w)) / (2 * e)
            assert abs(fd) > 1e-11, name
            assert g == pytest.approx(fd, rel=2e-3 if rel > 1e-3 else 1e-4), (name, rel)
    g = states[0].v.grad.numpy()[0, 1]
    for h in (1e-4, 1e-6):
        fd = _central(_pressed, w, "state", "v", (0, 1), h)
        assert g == pytest.approx(fd, rel=1e-4), h


#: Two bodies of different models pressed together on the ground: (first body's material
#: options, second's). ``rest``: a flowing incremental block beside one on the rest model;
#: ``hyperelastic_stvk``: the hyperelastic and the St. Venant-Kirchhoff stresses.
PAIRS = {
    "rest": ({}, {"deformation": "rest"}),
    "hyperelastic_stvk": ({"model": "hyperelastic"}, {"model": "stvk"}),
}


def _pair(case, body=None, name=None, value=None):
    first, second = ({**PLASTIC, **o} for o in PAIRS[case])
    second["mu"] = 2.0e3
    if body is not None:
        (first, second)[body][name] = value
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((-0.031, 0.03, 0.0), (3 * DX, 3 * DX, 3 * DX), we.Material(density=1000.0, **first), name="a",
              velocity=(1.0, -0.2, 0.1))
    b.add_box((0.031, 0.03, 0.003), (3 * DX, 3 * DX, 3 * DX), we.Material(density=1000.0, **second), name="b")
    b.add_ground(0.01, friction=0.5)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    return model


@pytest.mark.parametrize("case", sorted(PAIRS))
def test_gradients_of_two_bodies_of_different_models_pressed_together_match_central_differences(case):
    """A block thrown at 1 m/s into another of another stress or deformation model, both
    flowing on the ground: the tape's gradient in each body's shear modulus and yield
    stress against float64 central differences at relative steps of 1e-5 (within 1e-4;
    measured 6.5e-6 at most) and 1e-2 (within 5 %: the St. Venant-Kirchhoff body's yield
    stress has a kink of the loss within that step, where a particle starts to yield in
    some step: 4.0 % off there, the others within 3e-3; a jump would grow as the step
    shrinks, where this falls to the small step's 5e-6)."""
    model = _pair(case)
    w = random_weights(model.particle_count, 2)
    _solver, states = _loss(model, w, taped=True)
    second = model.particle_body.numpy() == 1
    assert states[-1].v.numpy()[second, 0].mean() > 0.02, "the bodies met"
    assert states[-1].alpha.numpy()[second].max() > ALPHA0, "the second body flows"
    for name in ("mu", "yield_stress"):
        g = getattr(model, name).grad.numpy()
        for k in (0, 1):
            base = getattr(model.materials[k], name)
            for rel, tol in ((1e-5, 1e-4), (1e-2, 5e-2)):
                e = rel * base
                fd = (_loss(_pair(case, k, name, base + e), w) - _loss(_pair(case, k, name, base - e), w)) / (2 * e)
                assert abs(fd) > 1e-11, (name, k)
                assert g[k] == pytest.approx(fd, rel=tol, abs=0.0), (name, k, rel)


def _moving_floor():
    """The flowing block of ``_block`` on a plane tool tilted by 10 degrees that rises,
    slides and turns under it, pressed by a spinning sphere tool that descends onto its top
    layer (its surface speed, spin times radius, reaches the block through friction)."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (4 * DX, 3 * DX, 3 * DX), we.Material(density=1000.0, **PLASTIC), name="block")
    tilt = np.radians(10.0)
    b.add_tool("plane", normal=(-np.sin(tilt), np.cos(tilt), 0.0), friction=0.4,
               motion=tools.Velocity((0.05, 0.3, 0.02), (0.0, 0.0, 0.5), position=(0.0, 0.0095, 0.0)), name="floor")
    b.add_tool("sphere", radius=0.05, friction=0.5,
               motion=tools.Velocity((0.0, -0.3, 0.0), (3.0, 0.0, 5.0), position=(0.01, 0.1002, 0.005)), name="ball")
    # The flat base meets the tilted plane where the plane is above it (x > 0, up to 0.24
    # spacings deep): finalize places those particles on it, so the base lies on the plane.
    with pytest.warns(UserWarning, match="body 'block': 6 of its particles start inside tool 'floor'.*placed on its surface"):
        model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    return model


def test_gradients_of_a_moving_plane_tool_and_a_spinning_sphere_tool_match_central_differences():
    """The linear and angular velocity of a plane tool and of a sphere tool (the other
    tests move boxes, meshes, capsules, cylinders and pins at a velocity, spheres by
    keyframes), under a flowing block: the tape against float64 central differences at
    steps of 1e-4 and 1e-6. Measured (the base placed on the plane): within 1.0e-6 and
    7.9e-6 (the sphere's spin about y, which reaches the loss by 8.5e-6 per rad/s)."""
    model = _moving_floor()
    w = random_weights(model.particle_count, 2)
    solver, states = _loss(model, w, taped=True)
    assert not solver.rest_model
    assert (np.abs(states[-1].reaction_force.numpy()).max(axis=1) > 0.0).all(), "both tools touch the block"
    t = model.tools
    for array, tool, c in (("velocity", "floor", 1), ("velocity", "floor", 0), ("angular_velocity", "floor", 2),
                           ("velocity", "ball", 0), ("angular_velocity", "ball", 0), ("angular_velocity", "ball", 1)):
        index = (t.index(tool), c)
        g = getattr(t, array).grad.numpy()[index]
        for h in (1e-4, 1e-6):
            fd = _central(_moving_floor, w, "tools", array, index, h)
            assert abs(fd) > 1e-6, (array, tool, c)
            assert g == pytest.approx(fd, rel=1e-4), (array, tool, c, h)
