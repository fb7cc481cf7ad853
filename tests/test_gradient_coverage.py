"""Float64 central differences for the step's kernel and option combinations that no other
gradient test takes: each at rest on its floor (F = I, every singular value repeated, the
contact law holding the block) and thrown into it (strained, sliding, pressed), at two steps
a hundred times apart, the larger one large enough that a jump in the loss would show, and
the hand-written adjoints against Warp's generated ones (``Solver.hand_adjoints``). (The plastic
block at rest on the slip ghost floor is ``test_gradients.py``'s ``AT_REST`` case, the same
rollout: ``CHECKED_ELSEWHERE``.)

Where the other combinations are checked (float64 central differences of a taped rollout):

- the fused linear fit with either elastic force, plasticity, pressure and viscosity,
  the stress models, the non-fused schedule, a force field: ``test_gradients.py``
  (``test_material_gradient...``, ``_OTHER_PATHS``; at rest on a floor, ``AT_REST``);
- the comparison models (``rest``, ``additive``) and the default elastic solver's rest model:
  ``test_gradients.py`` (``test_comparison_models...``, ``REST_CASES``, the hand-over);
- the curvature-corrected fit, the hourglass control, ``energy_spiky``, either fit weight
  on the incremental fits, the floor images, the guards' fades, keyed rows:
  ``test_gradients.py``; a pressure stiffness or viscosity of 0: ``SPH_AT_ZERO`` there;
- the ghost floor: ``test_ghost_floor.py``; the static colliders and the contact ramps:
  ``test_static_colliders.py``, ``test_friction.py``, ``test_smooth_loss.py``;
- tools (plane, box, sphere, capsule, cylinder, mesh; keyframes, pins, a particle floor):
  ``test_tools.py``; worlds: ``test_worlds.py`` (against separate tapes);
- the pair repulsion (``Material.pair_repulsion``) on a free block's merging layers, fused and
  not: ``test_gradients.py`` (``test_pair_repulsion...``); its hand-written adjoint against the
  generated one under each pair pressure force: ``test_adjoints.py``; the landing scan with it:
  ``test_smooth_loss.py``; on the ground, at rest and thrown: ``CASES`` here;
- the initial positions, deformation gradients and plastic strains and the plasticity
  parameters of a block flowing on the ground or a plane tool, a flowing block under moving
  tools, two bodies of different models pressed together, a plane tool and a sphere tool
  moved at a linear and an angular velocity: ``test_gradient_inputs.py``.

docs/method.md, "Which test checks each kernel's adjoint", has the same by kernel; the last test
here fails when a taped step launches a kernel that table does not name.
"""

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from taped_loss import random_weights, taped_gradients, taped_rollout_loss, untaped_rollout_loss
from warp_esph import tools
from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS


#: The fit weight a model gets only by name (poly6, the paper's eq. 7, since the biweight became
#: the default): every case but the ``*other_weight*`` ones runs the default, so without these
#: the other weight would have no central differences on the paths where the fit's weight enters.
(OTHER_FIT_WEIGHT,) = (w for w in FIT_WEIGHTS if w != DEFAULT_FIT_WEIGHT)

DT = 1.0e-3
STEPS = 8
DX = 0.02
ELASTIC = {"yield_stress": float("inf"), "flow_rate": 0.0, "hardening": 0.0}

#: name -> (material options, ``Solver`` options, ``SceneBuilder`` options, floor). ``corotated*``:
#: an elastic linear (or non-Newtonian) material on the variational force takes the corotated
#: stress (``forces.corotated_stress``) on the incremental fits, fused, not fused and corrected;
#: ``default_elastic*``: what ``Solver(model)`` runs for an elastic model (the rest model with
#: the corrected total fit and the hourglass control), also with the other fit weight
#: (``OTHER_FIT_WEIGHT``); the other weight on the rest and additive materials, the ghost floor
#: and the non-fused floor images; the hourglass control beside the paper's force, the floor
#: images and the ghost floor; the ``energy`` and
#: ``spiky`` pressure forces on the non-fused schedule (one unclamped); a block held on a mesh
#: tool and on a cylinder tool standing on its axis; an elastic block (the corotated stress, with
#: the ghosts in its linear fit) on a no-slip and on a slip ghost floor, a plastic one on the slip
#: floor, and an elastic block (the default solver's rest model) on a pinned particle floor, the
#: combinations the audit of docs/method.md, "Which test checks each kernel's adjoint", found no
#: float64 central difference passing through; a plastic block on an elastic particle floor and
#: on a capsule tool standing on its axis, which one test each passed through; a compression
#: field beside the floor images and on the default elastic solver (two tests passed through a field);
#: the yield test with the SPH pressure's stress (``Solver(yield_with_pressure=True)``), whose own
#: tests are in ``test_yield_with_pressure.py``; the ``isotropic`` pressure force (the default
#: solver, which runs it on the unfused schedule); the pair repulsion (``Material.pair_repulsion``,
#: a pair started 0.3 dx apart, inside its range: ``_model``), fused and not, whose central
#: differences in ``test_gradients.py`` take a free block's merging layers alone; the frictionless
#: imaged ground (``friction = 0``: the images move with their particles over the step, in both fits,
#: the images' own fits and the SPH viscosity), the linear fit fused and the corrected one.
CASES = {
    "corotated": (ELASTIC, {"fit": "linear"}, {}, "ground"),
    "corotated_unfused": (ELASTIC, {"fit": "linear", "fused": False}, {}, "ground"),
    "corotated_non_newtonian": ({**ELASTIC, "model": "non_newtonian"}, {"fit": "linear"}, {}, "ground"),
    "corotated_corrected": (ELASTIC, {"fit": "curvature_corrected"}, {}, "ground"),
    "default_elastic": (ELASTIC, {}, {}, "ground"),
    "default_elastic_other_weight": (ELASTIC, {}, {"fit_weight": OTHER_FIT_WEIGHT}, "ground"),
    "other_weight_rest_variational": ({"deformation": "rest", "elastic_force": "variational"}, {},
                                      {"fit_weight": OTHER_FIT_WEIGHT}, "ground"),
    "other_weight_rest_paper": ({"deformation": "rest"}, {}, {"fit_weight": OTHER_FIT_WEIGHT}, "ground"),
    "other_weight_additive": ({"deformation": "additive"}, {}, {"fit_weight": OTHER_FIT_WEIGHT}, "ground"),
    "other_weight_ghost_floor": ({}, {}, {"fit_weight": OTHER_FIT_WEIGHT}, "ghost"),
    "other_weight_unfused_images": ({}, {"fused": False}, {"fit_weight": OTHER_FIT_WEIGHT}, "images"),
    "hourglass_paper": ({"elastic_force": "paper"}, {"hourglass": 0.5}, {}, "ground"),
    "hourglass_images": ({}, {"hourglass": 0.5}, {}, "images"),
    "hourglass_ghost_floor": ({}, {"hourglass": 0.5}, {}, "ghost"),
    "energy_unfused": ({"pressure_force": "energy"}, {"fused": False}, {}, "ground"),
    "spiky_unfused_unclamped": ({"pressure_force": "spiky", "clamp_pressure": False}, {"fused": False}, {}, "ground"),
    "mesh_tool": ({}, {}, {}, "mesh"),
    "cylinder_tool": ({}, {}, {}, "cylinder"),
    "ghost_floor_elastic": (ELASTIC, {}, {}, "ghost"),
    "ghost_slip_floor": ({}, {}, {}, "ghost_slip"),
    "ghost_slip_floor_elastic": (ELASTIC, {}, {}, "ghost_slip"),
    "pinned_floor_elastic": (ELASTIC, {}, {}, "pinned"),
    "elastic_pinned_floor": ({}, {}, {}, "pinned_elastic"),
    "capsule_tool": ({}, {}, {}, "capsule"),
    "field_images": ({}, {}, {}, "images_field"),
    "frictionless_images": ({}, {}, {}, "images_frictionless"),
    "frictionless_images_corrected": ({}, {"fit": "curvature_corrected"}, {}, "images_frictionless"),
    "field_default_elastic": (ELASTIC, {}, {}, "ground_field"),
    "yield_with_pressure": ({}, {"yield_with_pressure": True}, {}, "ground"),
    "isotropic_pressure": ({"pressure_force": "isotropic"}, {}, {}, "ground"),
    "pair_repulsion": ({"pair_repulsion": 2.0}, {}, {}, "ground"),
    "pair_repulsion_unfused": ({"pair_repulsion": 2.0}, {"fused": False}, {}, "ground"),
}


def _model(case, scene, params=None, worlds=1, world1=None):
    """A 4 x 3 x 3 block (36 particles, jittered by 1e-3 dx) whose bottom layer lies on the
    case's floor at y = 0.01: ``rest``, from rest (F = I, v = 0) under gravity; ``thrown``, with
    a stretching and squeezing velocity field, a slide along x and a push into the floor."""
    options, _solver, builder, floor = CASES[case]
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "hardening": 200.0, "pressure_stiffness": 1.0,
         "viscosity": 2.0, **options, **(params or {})}
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0), **builder)
    b.add_box((0.0, 0.03, 0.0), (4 * DX, 3 * DX, 3 * DX), we.Material(density=1000.0, **p), name="block")
    if floor in ("ghost", "ghost_slip"):
        b.add_particle_floor("block", margin=DX, ghost=True, slip=floor == "ghost_slip")
    elif floor in ("pinned", "pinned_elastic"):
        b.add_particle_floor("block", margin=DX, layers=1, elastic=floor == "pinned_elastic")
    elif floor == "mesh":
        b.add_tool("mesh", mesh=tools.box_mesh((0.1, 0.01, 0.1)), position=(0.0, 0.0, 0.0), friction=0.5, name="floor")
    elif floor == "cylinder":
        b.add_tool("cylinder", radius=0.05, half_height=0.05, position=(0.0, -0.04, 0.0), friction=0.5, name="floor")
    elif floor == "capsule":
        # Standing on its axis: the block's middle rests on its round cap.
        b.add_tool("capsule", radius=0.05, half_height=0.02, position=(0.0, -0.059, 0.0), friction=0.5, name="floor")
    else:
        b.add_ground(0.01, friction=0.0 if floor == "images_frictionless" else 0.5, images=floor.startswith("images"))
    if floor.endswith("_field"):
        # A horizontal squeeze towards the block's axis, on from the start.
        b.add_compression_field((0.0, 0.0, 0.0), 50.0)
    model = b.finalize(dtype=wp.float64, requires_grad=True, worlds=worlds)
    if world1 is not None:
        # World 1's material differs from world 0's (stiffer, yielding later).
        model.set_material(0, we.Material(density=1000.0, **{**p, **world1}), world=1)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    if p.get("pair_repulsion"):
        # Particle 1 starts 0.3 dx from particle 0, inside the repulsion's range (h / 4 = 0.5 dx):
        # a block on its lattice has no pair there, and the option would add nothing.
        x0 = model.particle_x0
        d = x0[1] - x0[0]
        x0[1] = x0[0] + 0.3 * DX * d / np.linalg.norm(d)
        model.particle_x0 = x0
    if scene == "thrown":
        x0 = model.particle_x0
        model.particle_v0 = (10.0 * (x0 - x0.mean(axis=0)) * np.array([1.0, -0.5, 0.0]) + np.array([0.2, -0.3, 0.0])
                             + np.random.default_rng(11).normal(scale=0.02, size=x0.shape))
    return model


def _loss(case, model, w, grad_of=None, hand_adjoints=True):
    solver = we.Solver(model, **CASES[case][1])
    solver.hand_adjoints = hand_adjoints
    if grad_of is None:  # a central difference's run: no tape, on the taped run's kernels (no twins compiled)
        return untaped_rollout_loss(solver, model.state(requires_grad=False), DT, STEPS, w, forward_only=False)
    states = [model.state() for _ in range(STEPS + 1)]
    loss, tape = taped_rollout_loss(solver, states, DT, w)
    if grad_of is None:
        return loss.numpy()[0]
    grads = taped_gradients(model, states, loss, tape, grad_of)
    return grads, solver, states


#: (case, scene) pairs whose rollout another test already checks to the bit: the plastic block at
#: rest on the slip ghost floor is ``test_gradients.py``'s ``AT_REST["ghost_floor_slip"]`` (the same
#: model, steps and weights: its loss and its taped ``lam`` and ``v0`` gradients are equal to the
#: bit, measured), whose central differences are these and more; the hand-written adjoints at rest
#: with ghosts in the fits are checked against the generated ones here on ``hourglass_ghost_floor``
#: and ``ghost_slip_floor_elastic`` (the slip floor's own kernels are Warp's in both runs).
CHECKED_ELSEWHERE = {("ghost_slip_floor", "rest")}


@pytest.mark.parametrize("case, scene", [(case, scene) for case in sorted(CASES) for scene in ("rest", "thrown")
                                         if (case, scene) not in CHECKED_ELSEWHERE])
@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
def test_gradients_of_the_remaining_step_options_match_central_differences(case, scene):
    """The tape's gradient in a material parameter (``lam`` at rest, where the stress is near
    0 and ``mu`` reaches the loss by 1e-10 only; ``mu`` thrown) and in the initial velocity of
    the lowest particle along x against float64 central differences at a relative step of
    1e-3 and 1e-5 (1e-4 and 1e-6 m/s), within 1e-4 (measured: within 5e-6 at the larger steps,
    the loss's curvature, and 3e-5 at the smaller, its round-off); the hand-written adjoints
    give the generated ones' gradients to 1e-8 (measured: 5e-15 of the largest)."""
    model = _model(case, scene)
    w = random_weights(model.particle_count, 2)
    name = "lam" if scene == "rest" else "mu"
    grads, solver, states = _loss(case, model, w, (name, "v0"))
    generated = _loss(case, _model(case, scene), w, (name, "v0"), hand_adjoints=False)[0]
    for n in (name, "v0"):
        np.testing.assert_allclose(grads[n], generated[n], rtol=1e-8, atol=1e-12 * np.abs(generated[n]).max())
    # The case runs what its name says (its fit weight too), and the floor holds the block.
    assert model.fit_weight == (OTHER_FIT_WEIGHT if "other_weight" in case else DEFAULT_FIT_WEIGHT)
    floor = CASES[case][3]
    if case.startswith("pair_repulsion"):
        off = _model(case, scene)
        off.set_materials([mt.replace(pair_repulsion=0.0) for mt in off.materials])
        assert _loss(case, off, w) != _loss(case, _model(case, scene), w), "the repulsion acts"
    if case.startswith("default_elastic"):
        assert solver.rest_model and solver.fit == "curvature_corrected" and solver.hourglass > 0.0
    if floor in ("mesh", "cylinder", "capsule"):
        assert np.abs(states[-1].reaction_force.numpy()).max() > 0.0
    elif not floor.startswith(("ghost", "pinned")):
        assert np.abs(states[-1].collider_force.numpy()).max() > 0.0
    base = getattr(model.materials[0], name)
    # One model for the central differences' runs (a run from a model another run left, its
    # materials set, is a new one's to the bit): the parameter set in each material made with
    # it (an elastic particle floor's material is a copy of the block's), then put back.
    m = _model(case, scene)
    materials = list(m.materials)

    def loss_at(value):
        m.set_materials([mt.replace(**{name: value}) if getattr(mt, name) == base else mt for mt in materials])
        return _loss(case, m, w)

    for rel in (1e-3, 1e-5):
        eps = rel * base
        fd = (loss_at(base + eps) - loss_at(base - eps)) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        # (Summed over the materials: an elastic particle floor's is a copy of the block's, made
        # with the same parameter.)
        assert grads[name].sum() == pytest.approx(fd, rel=1e-4, abs=0.0), (name, rel)
    m.set_materials(materials)
    i = int(np.argmin(model.particle_x0[:36, 1]))
    v0 = m.particle_v0.copy()
    for eps in (1e-4, 1e-6):
        def loss_with(delta):
            m.particle_v0 = v0.copy()
            m.particle_v0[i, 0] += delta
            return _loss(case, m, w)

        fd = (loss_with(eps) - loss_with(-eps)) / (2 * eps)
        assert abs(fd) > 1e-9
        assert grads["v0"][i, 0] == pytest.approx(fd, rel=1e-4, abs=1e-9), eps


@pytest.mark.parametrize("scene", ["rest", "thrown"])
def test_the_isotropic_pressures_stiffness_gradient_matches_central_differences(scene):
    """``pressure_force = "isotropic"``: the pair kernel carries no pressure of it, so ``k_p``
    reaches the loss through ``pressure.isotropic_pressure_forces`` alone, and its taped gradient
    (Warp's generated adjoint of that kernel) is its float64 central difference at relative steps
    1e-3 and 1e-5 within 1e-4, at rest (F = I, pressed by its weight) and thrown into the ground."""
    case = "isotropic_pressure"
    model = _model(case, scene, {"pressure_stiffness": 10.0})
    w = random_weights(model.particle_count, 2)
    grads = _loss(case, model, w, ("pressure_stiffness",))[0]
    base = 10.0
    for rel in (1e-3, 1e-5):
        eps = rel * base
        fd = (_loss(case, _model(case, scene, {"pressure_stiffness": base + eps}), w)
              - _loss(case, _model(case, scene, {"pressure_stiffness": base - eps}), w)) / (2 * eps)
        assert abs(fd) > 1e-12, "the loss does not reach k_p"
        assert grads["pressure_stiffness"].sum() == pytest.approx(fd, rel=1e-4), rel


def test_the_isotropic_pressures_stiffness_gradient_from_zero_matches_forward_differences():
    """``pressure_force = "isotropic"`` with ``k_p = 0``, where a fit may start it (every
    pressure then 0): the taped gradient in ``k_p`` is its float64 forward difference at
    ``k_p`` = 1e-4 and 1e-6 within 1e-3, not 0 (the step runs the SPH terms under a tape for
    that slope, docs/method.md §6), thrown into the ground where particles are compressed."""
    case, scene = "isotropic_pressure", "thrown"
    model = _model(case, scene, {"pressure_stiffness": 0.0})
    w = random_weights(model.particle_count, 2)
    grads = _loss(case, model, w, ("pressure_stiffness",))[0]
    base = _loss(case, _model(case, scene, {"pressure_stiffness": 0.0}), w)
    for eps in (1e-4, 1e-6):
        fd = (_loss(case, _model(case, scene, {"pressure_stiffness": eps}), w) - base) / eps
        assert abs(fd) > 1e-12, "the loss does not reach k_p"
        assert grads["pressure_stiffness"].sum() == pytest.approx(fd, rel=1e-3), eps


#: Taped steps (each scene with a compression field) whose launches together are every kernel of
#: docs/method.md's coverage table but the rest model's hand-over and hand-back (a step that
#: switches models): (case of ``CASES``, material options, ``Solver`` options or None for the
#: case's, hand-written adjoints).
_TABLE_SCENES = [
    ("other_weight_ghost_floor", None, None, True),
    ("default_elastic", None, None, True),
    ("default_elastic", None, None, False),
    ("hourglass_images", None, None, True),
    ("hourglass_images", None, None, False),
    ("hourglass_paper", None, None, True),
    ("corotated_corrected", None, None, True),
    ("mesh_tool", None, None, True),
    ("corotated", {"deformation": "additive", **ELASTIC}, {}, False),
    ("yield_with_pressure", None, None, True),
    ("isotropic_pressure", None, None, True),
]


def _table_kernels() -> set:
    """The kernels docs/method.md's table names (its rows' first cells and the adjoints named
    in the second), as ``file.function``."""
    import pathlib
    import re

    text = (pathlib.Path(__file__).resolve().parent.parent / "docs" / "method.md").read_text()
    section = text.split("### Which test checks each kernel's adjoint", 1)[1].split("\n## ", 1)[0]
    rows = [line.split(" | ")[:2] for line in section.splitlines() if line.startswith("| `")]
    return {name for cells in rows for cell in cells for name in re.findall(r"`([a-z_]+\.(?!py`)[a-z_]+)`", cell)}


@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
def test_every_kernel_of_a_taped_step_is_in_the_coverage_table():
    """Two taped float64 steps (and their backward pass) of each of ``_TABLE_SCENES`` launch only
    kernels docs/method.md's coverage table names: a new kernel on the step's path needs a
    float64 central-difference test and its row there. Each kernel the table names exists
    (``def <function>(`` in ``warp_esph/sim/<file>.py`` or ``warp_esph/<file>.py``)."""
    import pathlib

    from kernel_log import launched_kernels
    from warp_esph.sim.fields import CompressionField

    named = _table_kernels()
    launched = set()
    for case, options, solver_options, hand in _TABLE_SCENES:
        model = _model(case, "thrown", options)
        model.force_fields.append(CompressionField((0.0, 0.0, 0.0), 10.0))
        log = set()
        with launched_kernels(log):
            solver = we.Solver(model, **(CASES[case][1] if solver_options is None else solver_options))
            solver.hand_adjoints = hand
            # Two steps: the second checks the neighbour lists' skin (neighbors.displacement_bounds).
            states = [model.state() for _ in range(3)]
            loss, tape = taped_rollout_loss(solver, states, DT, random_weights(model.particle_count, 2))
            tape.backward(loss)
        assert np.isfinite(states[0].v.grad.numpy()).all() and np.abs(states[0].v.grad.numpy()).max() > 0.0
        launched |= {name for name, _ in log if not name.startswith("taped_loss.")}
    missing = sorted(launched - named)
    assert not missing, f"kernels on the taped step without a row in docs/method.md's coverage table: {missing}"
    # The scenes reach every row but the two named above, so a kernel the step stops launching shows.
    assert named - launched == {"comparison.rest_handover", "comparison.rest_handback"}, sorted(named - launched)
    root = pathlib.Path(__file__).resolve().parent.parent / "warp_esph"
    for name in named:
        stem, function = name.split(".")
        source = root / "sim" / f"{stem}.py"
        source = source if source.exists() else root / f"{stem}.py"
        assert f"def {function}(" in source.read_text(), name


@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
def test_the_central_differences_untaped_runs_are_the_taped_runs_to_the_bit():
    """The central differences here and in the other gradient tests run their rollouts without
    a tape (``taped_loss.untaped_rollout_loss``: two states in turn, no gradient arrays), so
    the loss they difference must be the taped rollout's, the function the tape's gradient is
    of: to the bit, thrown, on each of ``_TABLE_SCENES`` (whose taped steps together launch
    every kernel of docs/method.md's coverage table but the rest model's hand-over), from a
    pressure stiffness of 0 (``isotropic_pressure``: under a tape the SPH terms run there
    too) and with two worlds."""
    runs = [(case, options, solver_options, {}, 1) for case, options, solver_options, _hand in _TABLE_SCENES]
    runs += [("isotropic_pressure", None, None, {"pressure_stiffness": 0.0}, 1), ("hourglass_paper", None, None, {}, 2)]
    for case, options, solver_options, params, worlds in runs:
        values = []
        for taped in (True, False):
            model = _model(case, "thrown", {**(options or {}), **params}, worlds=worlds,
                           world1={"mu": 1.4e3} if worlds > 1 else None)
            solver = we.Solver(model, **(CASES[case][1] if solver_options is None else solver_options))
            w = random_weights(model.particle_count, 2)
            if taped:
                values.append(taped_rollout_loss(solver, [model.state() for _ in range(STEPS + 1)], DT, w)[0].numpy()[0])
            else:
                values.append(untaped_rollout_loss(solver, model.state(requires_grad=False), DT, STEPS, w))
        assert values[0] == values[1], (case, params, worlds, values)


#: Step paths the worlds' other gradient tests (``test_worlds.py``: the fused linear fit on the
#: ground, the default elastic solver's rest model beside tools) do not take, each with two worlds.
WORLD_CASES = ["corotated_unfused", "hourglass_paper", "hourglass_images", "other_weight_ghost_floor", "corotated_corrected",
               "other_weight_rest_paper", "other_weight_additive", "pinned_floor_elastic"]


@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
@pytest.mark.parametrize("case", WORLD_CASES)
def test_each_worlds_mu_gradient_on_the_other_step_paths_matches_central_differences(case):
    """Two worlds of different materials in one model (``finalize(worlds=2)``), thrown onto
    their floor: the tape's gradient in each world's own ``mu`` (its entry of ``Model.mu``) is
    the central difference of the loss in that world's ``mu`` alone (``set_material(...,
    world=w)``), at relative steps of 1e-3 and 1e-5, within 1e-4. A per-world index read wrong
    by a kernel or its adjoint (a material or a particle of world 0 for world 1's) moves the
    gradient to the other world's entry."""
    world1 = {"mu": 1.4e3, "lam": 2.0e3, "yield_stress": 14.0}
    model = _model(case, "thrown", worlds=2, world1=world1)
    assert model.world_count == 2
    assert model.fit_weight == (OTHER_FIT_WEIGHT if "other_weight" in case else DEFAULT_FIT_WEIGHT)
    w = random_weights(model.particle_count, 2)
    grads = _loss(case, model, w, ("mu",))[0]["mu"]
    first = model.world_material_start
    for world, mu in ((0, 1.0e3), (1, world1["mu"])):
        m = _model(case, "thrown", worlds=2, world1=world1)  # one model for the world's runs, its material set in each

        def loss_with(delta):
            options = {**CASES[case][0], **(world1 if world else {}), "mu": mu + delta}
            p = {"lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "hardening": 200.0, "pressure_stiffness": 1.0,
                 "viscosity": 2.0, **options}
            m.set_material(0, we.Material(density=1000.0, **p), world=world)
            return _loss(case, m, w)

        g = grads[first[world]]
        for rel in (1e-3, 1e-5):
            eps = rel * mu
            fd = (loss_with(eps) - loss_with(-eps)) / (2 * eps)
            assert abs(fd) > 1e-11, (world, rel)
            assert g == pytest.approx(fd, rel=1e-4), (world, rel)
