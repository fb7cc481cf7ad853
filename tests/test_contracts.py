"""The core API's contracts, over every option of a scene (README, "Precision"; ``sim/solver.py``):

- a float64 model computes in float64: every array the model, the solver, the states, a
  rollout and a checkpoint hold is float64 (Warp's float32-only hash grid and mesh queries
  aside), and a float64 step responds linearly to a change far below float32's resolution and
  is translation invariant to float64 round-off, where a float32 value anywhere on the way
  would show;
- ``Solver.step(state_in, state_out, dt)`` leaves every bit of ``state_in`` as it was (the
  round-off carries, the floor images' ``F``, ``alpha``, the gradients), taped or not, and so
  do the calls that only read a state;
- no state is shared between models: models of other precisions or fit weights stepped in
  turn in one process give the very states each gives alone.
"""

import contextlib
import copy
import pathlib
import types

import numpy as np
import pytest
import warp as wp
import warp.examples

import warp_esph as we
from warp_esph import checkpoint, tools
from warp_esph.rollout import Rollout
from warp_esph.sim.smoothing import FIT_WEIGHTS

BUNNY = pathlib.Path(warp.examples.get_asset_directory()) / "bunny.usd"
DX = 0.05
# x and z only: the ground stays at y = 0. Powers of two, so the float64 offset itself is exact.
OFFSET = (0.375, 0.0, -0.125)

#: Each option of the step: the material and solver settings a scene takes and what it adds.
OPTIONS = ("plain", "floor_images", "ghost_floor", "ghost_floor_slip", "particle_floor", "particle_floor_elastic",
           "mesh_tool", "keyframed_tools", "pins", "hourglass", "curvature_corrected", "rest_model_auto", "biweight",
           "pressure_energy", "pressure_spiky", "pressure_isotropic", "deformation_rest", "deformation_additive", "hyperelastic", "stvk",
           "non_newtonian", "viscosity", "colliders", "compression_field", "worlds", "yield_with_pressure")


def _scene(option, dtype, offset=(0.0, 0.0, 0.0), requires_grad=False):
    """A 125-particle block thrown onto the floor with ``option`` (in the air with the mesh tool
    or the pins); returns the model and the solver's keyword arguments. Everything is placed
    relative to ``offset``."""
    off = np.asarray(offset, dtype=np.float64)

    def at(*c):
        return tuple(np.asarray(c, dtype=np.float64) + off)

    plastic = dict(mu=2000.0, lam=3000.0, yield_stress=100.0, flow_rate=100.0)
    material, solver = we.Material(**plastic), {}
    elastic = we.Material(mu=2000.0, lam=3000.0)
    if option == "hourglass":
        material, solver = elastic, dict(fit="linear", hourglass=0.1)
    elif option == "curvature_corrected":
        material, solver = elastic, dict(fit="curvature_corrected")
    elif option == "rest_model_auto":
        material = elastic
    elif option.startswith("pressure_"):
        material = we.Material(**plastic, pressure_force=option[len("pressure_"):])
    elif option.startswith("deformation_"):
        material = we.Material(**plastic, deformation=option[len("deformation_"):], elastic_force="paper")
    elif option in ("hyperelastic", "stvk", "non_newtonian"):
        material = we.Material(**plastic, model=option)
    elif option == "viscosity":
        material = we.Material(**plastic, viscosity=1.0)
    elif option == "yield_with_pressure":
        solver = dict(yield_with_pressure=True)
    b = we.SceneBuilder(spacing=DX, **({"fit_weight": option} if option in FIT_WEIGHTS else {}))
    b.add_box(center=at(0, 0.13, 0), size=(0.25, 0.25, 0.25), material=material, name="block",
              velocity=(0.1, -0.3, 0.05), angular_velocity=(2.0, -3.0, 1.0))
    if option.startswith("ghost_floor"):
        b.add_particle_floor("block", margin=DX, ghost=True, slip=option.endswith("slip"))
    elif option.startswith("particle_floor"):
        b.add_particle_floor("block", margin=DX, elastic=option.endswith("elastic"))
    elif option not in ("mesh_tool", "pins"):
        # The mesh tool and the pins without the ground: their integrators' variants are then
        # those other tests compile; with the ground they were this file's alone (0.8-9.1 s of
        # compiling each, measured), and the ground is checked with every other option.
        b.add_ground(0.0, friction=0.5, images=option == "floor_images")
    if option == "mesh_tool":
        b.add_tool("mesh", mesh=str(BUNNY), scale=0.1, friction=0.3,
                   motion=tools.Velocity((0.0, -0.5, 0.0), position=at(0.02, 0.2, 0.01)))
    elif option == "keyframed_tools":
        b.add_tool("box", half_extents=(0.2, 0.02, 0.2), friction=0.2,
                   motion=tools.Keyframes([0.0, 1.0], [at(0, 0.27, 0), at(0, 0.17, 0)]))
        b.add_tool("sphere", radius=0.05, motion=tools.Keyframes(
            [0.0, 1.0], [at(0.12, 0.2, 0), at(0.05, 0.2, 0)], [(0, 0, 0, 1), (0, 0.3826834, 0, 0.9238795)]))
    elif option == "pins":
        b.pin(body="block", region=(at(-1, 0.2, -1), at(1, 1, 1)), motion=tools.Velocity((0.0, -0.2, 0.0)), name="grip")
    elif option == "colliders":
        b.add_sphere_collider(at(0.1, 0.27, 0), 0.06)
        b.add_box_collider(at(-0.1, 0.27, 0), (0.03, 0.05, 0.03))
    elif option == "compression_field":
        b.add_compression_field(at(0, 0.13, 0), 10.0)
    starts_inside = option in ("colliders", "mesh_tool", "keyframed_tools")
    placed = pytest.warns(UserWarning, match=r"body 'block': \d+ of its particles start inside .*placed on its surface")
    with placed if starts_inside else contextlib.nullcontext():
        model = b.finalize(device="cpu", dtype=dtype, requires_grad=requires_grad, worlds=2 if option == "worlds" else 1)
    if starts_inside:
        # Started inside them (the colliders 0.4 and 0.2 spacings, the bunny 0.24, the
        # keyframed sphere 0.43), so that the contact of a particle found inside runs from the
        # first step: finalize places such a start on the surfaces.
        model.particle_x0[:] = np.concatenate(b._points)
        model.compute_rest_density()
    return model, solver


def _stirred(model, state):
    """``state`` with a seeded random velocity on top: every particle's neighbourhood deforms
    from the first step (a rigidly thrown block leaves ``F`` at ``I``)."""
    rng = np.random.default_rng(1)
    state.v.assign(state.v.numpy() + 0.3 * rng.standard_normal((model.particle_count, 3)))
    return state


def _arrays(root, skip=()):
    """Every ``wp.array`` reachable from ``root`` through this package's objects, containers,
    namespaces and Warp structs, as ``{path: array}`` (each array once, under the first path
    found). Instances of ``skip`` are not entered."""
    found, seen = {}, set()

    def walk(obj, path, depth):
        if id(obj) in seen or depth > 8 or isinstance(obj, skip):
            return
        seen.add(id(obj))
        if isinstance(obj, wp.array):
            found[path] = obj
        elif isinstance(obj, (list, tuple)):
            for i, v in enumerate(obj):
                walk(v, f"{path}[{i}]", depth + 1)
        elif isinstance(obj, dict):
            for k, v in obj.items():
                walk(v, f"{path}[{k!r}]", depth + 1)
        elif isinstance(obj, types.SimpleNamespace) or type(obj).__module__.startswith("warp_esph"):
            for k, v in vars(obj).items():
                walk(v, f"{path}.{k}", depth + 1)
        elif hasattr(obj, "_cls") and hasattr(obj._cls, "vars"):  # a wp.struct instance
            for k in obj._cls.vars:
                walk(getattr(obj, k), f"{path}.{k}", depth + 1)

    walk(root, type(root).__name__, 0)
    return found


def _float32_arrays(roots, solvers=()):
    """The paths of the arrays of a float32 (or float16) scalar reachable from ``roots``, but
    for the points of each solver's hash grids: ``wp.HashGrid`` takes float32 points only,
    and the candidates it finds are kept or dropped by their distance in the model's
    precision (``sim/neighbors.py``, ``sim/ghost_floor.py``)."""
    grid_points = set()
    for s in solvers:
        grid_points.add(id(s.search._points))
        if s.ghost_search is not None:
            grid_points.add(id(s.ghost_search.points))
    bad = []
    for root in roots:
        for path, a in _arrays(root).items():
            scalar = getattr(a.dtype, "_wp_scalar_type_", a.dtype)
            if scalar in (wp.float32, wp.float16) and id(a) not in grid_points:
                bad.append(f"{path}: {a.dtype.__name__}")
    return bad


def _snapshot(state):
    """Every bit of ``state``: its arrays and their gradients, and its plain attributes."""
    arrays = _arrays(state, skip=(we.Model, we.Solver))
    bits = {p: a.numpy().tobytes() for p, a in arrays.items()}
    bits.update({p + ".grad": a.grad.numpy().tobytes() for p, a in arrays.items() if a.grad is not None})
    plain = {k: v for k, v in vars(state).items() if isinstance(v, (bool, int, float, str, type(None)))}
    return bits, plain


def _changed(before, after):
    return ([p for p in before[0] if after[0].get(p) != before[0][p]]
            + [f"{k}: {before[1][k]!r} -> {after[1].get(k)!r}" for k in before[1] if after[1].get(k) != before[1][k]])


@pytest.mark.parametrize("option", OPTIONS)
def test_a_float64_model_its_solver_and_states_hold_no_float32_array_also_after_a_taped_step(option):
    model, kw = _scene(option, wp.float64, requires_grad=True)
    solver = we.Solver(model, **kw)
    states = [model.state() for _ in range(3)]
    tape = wp.Tape()
    with tape:
        for a, b in zip(states, states[1:]):
            solver.step(a, b, 0.5 * model.stable_dt())
    states[-1].x.grad.fill_(1.0)
    tape.backward()
    assert _float32_arrays([model, solver, *states], [solver]) == []
    # The walk reaches the arrays it is meant to judge: the round-off carries, the
    # parameters, the step's scratch and the neighbour search's own.
    found = {id(a) for root in (model, solver, *states) for a in _arrays(root).values()}
    for array in (states[0].x_lo, states[0].F_lo, states[0].F_image, model.mu, solver.scratch.pressure,
                  solver.search._x_ref):
        assert id(array) in found
    assert model.mu.grad.dtype is wp.float64 and states[0].x.grad.dtype is wp.vec3d


@pytest.mark.parametrize("option", OPTIONS)
def test_a_float64_step_computes_in_float64_throughout(option):
    """A value rounded to float32 anywhere (an array, a cast in a kernel) shows in two ways.
    The step's response to a change of the initial velocities by 1e-8 m/s is no longer linear:
    float32's steps in the value are 1e4 times the change, so the response to twice the
    change is not twice the response (5e-2-1e-1 off with the fit's weight rounded to float32,
    measured; 5e-8-2e-7 in float64, measured). Where the rounded value is a position, the
    step is no longer translation invariant to float64's round-off (1e-6 of a few steps'
    motion in float32, 2e-15-5e-15 in float64, measured). And float32 and float64 differ by
    float32's round-off only (2e-7-1e-5 of the motion, measured)."""

    def run(dtype, offset=np.zeros(3), dv=0.0, steps=8):
        model, kw = _scene(option, dtype, offset)
        solver = we.Solver(model, **kw)
        a, b = _stirred(model, model.state()), model.state()
        u = np.random.default_rng(2).standard_normal((model.particle_count, 3))
        a.v.assign(a.v.numpy() + dv * u)
        for _ in range(steps):
            solver.step(a, b, 0.5 * model.stable_dt())
            a, b = b, a
        return a.x.numpy().astype(np.float64) - offset, a.F.numpy().astype(np.float64), model.particle_x0 - offset

    x, F, x0 = run(wp.float64)
    motion = np.abs(x - x0).max()
    assert motion > 0.01  # the block moved and deformed
    assert np.abs(F - np.eye(3)).max() > 1e-3
    once, twice = run(wp.float64, dv=1e-8)[0] - x, run(wp.float64, dv=2e-8)[0] - x
    assert np.abs(once).max() > 1e-10
    assert np.abs(twice - 2.0 * once).max() < 1e-5 * np.abs(once).max()
    x_moved, F_moved, _ = run(wp.float64, np.asarray(OFFSET))
    assert np.abs(x_moved - x).max() < 1e-12 * motion
    assert np.abs(F_moved - F).max() < 1e-12
    assert np.abs(run(wp.float32)[0] - x).max() < 1e-4 * motion


@pytest.mark.parametrize("option", OPTIONS)
@pytest.mark.parametrize("dtype, fused, taped", [(wp.float32, True, False), (wp.float64, False, False),
                                                 (wp.float64, True, True)], ids=["float32", "float64_unfused", "taped"])
def test_a_step_leaves_every_bit_of_state_in_as_it_was(option, dtype, fused, taped):
    model, kw = _scene(option, dtype, requires_grad=taped)
    solver = we.Solver(model, fused=fused, **kw)
    states = [_stirred(model, model.state()) for _ in range(4)]
    changed = []
    with wp.Tape() if taped else contextlib.nullcontext():
        for a, b in zip(states, states[1:]):
            before = _snapshot(a)
            solver.step(a, b, 0.5 * model.stable_dt())
            changed += _changed(before, _snapshot(a))
    assert changed == []
    seen = _snapshot(states[0])[0]
    for field in ("State.x_lo", "State.F_lo", "State.F_image", "State.alpha", "State.alpha_image", "State.F_p"):
        assert field in seen, field
    if taped:
        assert "State.x.grad" in seen


@pytest.mark.parametrize("option", OPTIONS)
def test_a_step_refuses_a_state_out_that_shares_an_array_with_state_in(option):
    """Two states of ``model.state()`` share no array. A shallow copy of ``state_in``
    (``copy.copy``) given as ``state_out``, or a state given one of ``state_in``'s arrays
    (``out.v = state_in.v``), passed the step's checks (only ``state_out is state_in`` was
    refused): the step wrote the arrays it read, and ``state_in`` came back holding the step's
    result. Refused naming the arrays shared, before any kernel runs."""
    model, kw = _scene(option, wp.float32)
    solver = we.Solver(model, **kw)
    a, b = _stirred(model, model.state()), model.state()
    mine = (we.Model, we.Solver)  # a state's arrays, not its model's
    assert {id(x) for x in _arrays(a, mine).values()}.isdisjoint(id(x) for x in _arrays(b, mine).values())
    dt = 0.5 * model.stable_dt()
    solver.step(a, b, dt)
    given = model.state()
    given.v = a.v
    before = _snapshot(a)
    for out, named in ((copy.copy(a), r"x, v, F, alpha, F_p, \.\.\. \(\d+ arrays\)"), (given, r"v")):
        with pytest.raises(ValueError, match=rf"^state_out is not allowed: it shares state_in's {named}"):
            solver.step(a, out, dt)
    assert _changed(before, _snapshot(a)) == []
    solver.step(b, a, dt)  # the pair as it was still steps


@pytest.mark.parametrize("option", OPTIONS)
def test_a_backward_pass_leaves_every_value_the_forward_steps_wrote(option):
    """The adjoints Warp generates replay the forward, atomic adds included: the tools' and
    static colliders' reaction rows a step reports (``State.reaction_force``,
    ``collider_force``) read 2-3x the forward's after ``tape.backward()`` (measured), as
    ``State.force`` did before ``replay.kept_through_backward``."""
    model, kw = _scene(option, wp.float64, requires_grad=True)
    solver = we.Solver(model, **kw)
    states = [_stirred(model, model.state()) for _ in range(4)]
    tape = wp.Tape()
    with tape:
        for a, b in zip(states, states[1:]):
            solver.step(a, b, 0.5 * model.stable_dt())
    values = {id(a): (f"{i}: {p}", a, a.numpy().tobytes()) for i, s in enumerate(states)
              for p, a in _arrays(s, skip=(we.Model, we.Solver)).items()}
    states[-1].x.grad.fill_(1.0)
    tape.backward()
    assert [p for p, a, bits in values.values() if a.numpy().tobytes() != bits] == []


@pytest.mark.parametrize("dtype", [wp.float32, wp.float64])
def test_the_calls_that_read_a_state_leave_every_bit_of_it_as_it_was(tmp_path, dtype):
    model, _ = _scene("keyframed_tools", dtype, requires_grad=True)
    solver = we.Solver(model)
    dt = 0.5 * model.stable_dt()
    a, b, state = _stirred(model, model.state()), model.state(), model.state()
    solver.step(a, b, dt)
    solver.step(b, state, dt)
    calls = {
        "reaction_forces": lambda: solver.reaction_forces(state),
        "collider_reactions": lambda: solver.collider_reactions(state),
        "record": lambda: (solver.record(state), solver.label(state), solver.runs_rest(state)),
        "save_state": lambda: checkpoint.save_state(tmp_path / "c.npz", model, state, step=2, frame=0),
        "UsdWriter.write_frame": lambda: _write_usd(tmp_path / "f.usdc", model, state),
        "simulate": lambda: we.simulate(model, 1, fps=1.0 / (2 * dt), substeps=2, state=state, solver=solver),
        # Taped in float64, untaped in float32: both paths, and float32 compiles no tool
        # integrator adjoint that only this test would load (4.5-5.3 s, measured).
        "Rollout.forward": lambda: Rollout(model, steps=2, dt=dt).forward(initial_state=state, taped=dtype == wp.float64),
        "State.assign": lambda: model.state().assign(state),
    }
    changed = {}
    for name, call in calls.items():
        before = _snapshot(state)
        call()
        changed[name] = _changed(before, _snapshot(state))
    assert changed == {name: [] for name in calls}


def _write_usd(path, model, state):
    with we.UsdWriter(str(path), model) as w:
        w.write_frame(0, state)


def test_a_float64_rollout_torch_and_checkpoint_stay_float64_and_resume_bit_for_bit(tmp_path):
    torch = pytest.importorskip("torch")
    import warp_esph.torch as wt

    model, _ = _scene("floor_images", wp.float64, requires_grad=True)
    rollout = Rollout(model, steps=4, dt=0.5 * model.stable_dt(), frames=[2, 4], checkpoint_every=2)
    x0 = torch.tensor(model.particle_x0, dtype=torch.float64, requires_grad=True)
    mu = torch.tensor([2000.0], dtype=torch.float64, requires_grad=True)
    out = wt.rollout_positions(rollout, {"mu": mu}, x0=x0)
    out[-1, :, 1].sum().backward()
    assert out.dtype == x0.grad.dtype == mu.grad.dtype == torch.float64
    assert _float32_arrays([rollout], [rollout.solver]) == []
    state = rollout.final_state()
    checkpoint.save_state(tmp_path / "s.npz", model, state, step=4, frame=1)
    loaded, _ = checkpoint.load_state(tmp_path / "s.npz", model)
    assert _float32_arrays([loaded]) == []
    for name in we.State.STATE_FIELDS:
        assert getattr(loaded, name).numpy().tobytes() == getattr(state, name).numpy().tobytes(), name


# Pairs of models that share no setting: each stepped in turn with the other must give the
# very states it gives alone, and the two must differ (so a shared kernel or cache built for
# the first would show). The fit weights are named, not "plain": were the biweight the
# default, "plain" and "biweight" would be one weight.
PAIRS = [(("poly6", wp.float64), ("biweight", wp.float32)), (("biweight", wp.float64), ("poly6", wp.float64)),
         (("curvature_corrected", wp.float64), ("plain", wp.float32)), (("floor_images", wp.float32), ("ghost_floor", wp.float64)),
         (("deformation_rest", wp.float32), ("hourglass", wp.float64)), (("pressure_spiky", wp.float64), ("pressure_energy", wp.float64)),
         (("pressure_isotropic", wp.float64), ("plain", wp.float32))]


@pytest.mark.parametrize("first, second", PAIRS, ids=[f"{a[0]}_{a[1].__name__}-{b[0]}_{b[1].__name__}" for a, b in PAIRS])
def test_two_models_stepped_in_turn_give_the_states_each_gives_alone(first, second):
    def make(option, dtype):
        model, kw = _scene(option, dtype)
        return model, we.Solver(model, **kw), [_stirred(model, model.state()), model.state()]

    def step(run):
        model, solver, (a, b) = run
        solver.step(a, b, 0.5 * model.stable_dt())
        run[2].reverse()

    def result(run):
        s = run[2][0]
        return s.x.numpy().astype(np.float64), s.F.numpy().astype(np.float64)

    alone = []
    for option, dtype in (first, second):
        run = make(option, dtype)
        for _ in range(4):
            step(run)
        alone.append(result(run))
    runs = [make(*first), make(*second)]
    for _ in range(4):
        for run in runs:
            step(run)
    for run, ref in zip(runs, alone):
        x, F = result(run)
        np.testing.assert_array_equal(x, ref[0])
        np.testing.assert_array_equal(F, ref[1])
    # Each setting took effect: the two differ by more than float32 round-off (a ghost floor
    # adds particles after the block's).
    n = min(len(alone[0][0]), len(alone[1][0]))
    assert np.abs(alone[0][0][:n] - alone[1][0][:n]).max() > 1e-6


# Solvers of other settings on one model: the model's caches (material structs, rest
# neighbourhoods, the replayed launches) serve both without one's settings reaching the other.
SOLVER_PAIRS = [("rest_model_auto", {}, {"fit": "linear"}),
                ("rest_model_auto", {"fit": "linear", "hourglass": 0.2}, {"fit": "curvature_corrected"}),
                ("floor_images", {"fit": "curvature_corrected"}, {}),
                ("deformation_rest", {}, {"fit": "curvature_corrected"}),
                ("plain", {"min_neighbors": 10}, {})]


@pytest.mark.parametrize("option, first, second", SOLVER_PAIRS,
                         ids=[f"{o}-{'-'.join(f'{k}={v}' for k, v in {**a, **b}.items())}" for o, a, b in SOLVER_PAIRS])
def test_two_solvers_of_one_model_stepped_in_turn_give_the_states_each_gives_alone(option, first, second):
    def run(settings, model=None):
        model = model or _scene(option, wp.float64)[0]
        return model, we.Solver(model, **settings), [_stirred(model, model.state()), model.state()]

    def step(model, solver, pair):
        solver.step(pair[0], pair[1], 0.5 * model.stable_dt())
        pair.reverse()

    alone = []
    for settings in (first, second):
        model, solver, pair = run(settings)
        for _ in range(4):
            step(model, solver, pair)
        alone.append(pair[0].x.numpy().copy())
    model = _scene(option, wp.float64)[0]
    runs = [run(first, model), run(second, model)]
    for _ in range(4):
        for m, solver, pair in runs:
            step(m, solver, pair)
    for (_, _, pair), ref in zip(runs, alone):
        np.testing.assert_array_equal(pair[0].x.numpy(), ref)
    assert np.abs(alone[0] - alone[1]).max() > 1e-6  # the settings differ in what they run
