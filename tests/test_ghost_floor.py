"""The no-slip ghost floor (``SceneBuilder.add_particle_floor(ghost=True)``,
``warp_esph/sim/ghost_floor.py``): its fits, its forces and its gradients."""

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.sim import forces
from energy_fd import central_gradient, mover, stvk_energy
from taped_loss import random_weights, taped_rollout_loss

STEPS = 5
DT = 1.0e-3
SPACING = 0.02


def _model(params=None, velocity=None, dtype=wp.float64, requires_grad=True, slide=0.0):
    """A jittered block on a ghost floor, moving in shear over the floor (zero on the wall
    plane, half a spacing below the body's base) plus a stretch, so it yields within a few
    steps and every ghost's stencil moves; ``slide`` (m/s) adds a slide along x, fast
    enough that the stencils at the block's rim pass through the normaliser's switch
    (``ghost_floor.stencil_normaliser``: 4 / 8 / 12 of them at steps 3 / 4 / 5 at 2 m/s)."""
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "pressure_stiffness": 1.0,
         "viscosity": 2.0, "elastic_force": "variational"}
    p.update(params or {})
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.1, 0.06, 0.08), we.Material(density=1000.0, **p), name="block")
    b.add_particle_floor("block", margin=SPACING, ghost=True)
    model = b.finalize(dtype=dtype, requires_grad=requires_grad)
    model.particle_x0[:] += np.random.default_rng(5).normal(scale=1e-3 * SPACING, size=model.particle_x0.shape)
    x0 = model.particle_x0
    free = np.arange(model.particle_count) < model.particle_count - model.ghost_floor.count
    v = np.zeros_like(x0)
    plane = model.bodies[0].ghost_plane
    v[free] = (20.0 * (x0[free, 1:2] - plane) * np.array([1.0, 0.0, 0.3])
               + 10.0 * x0[free] * np.array([1.0, -0.5, 0.0]) + np.array([slide, 0.0, 0.0]))
    model.particle_v0 = v if velocity is None else velocity(model)
    return model


def _loss(model, weights, grad_of=(), hand_adjoints=True):
    solver = we.Solver(model)
    solver.hand_adjoints = hand_adjoints
    states = [model.state() for _ in range(STEPS + 1)]
    loss, tape = taped_rollout_loss(solver, states, DT, weights)
    if not grad_of:
        return loss.numpy()[0]
    tape.backward(loss)
    return loss.numpy()[0], {n: (states[0].v if n == "v0" else getattr(model, n)).grad.numpy().copy() for n in grad_of}


@pytest.fixture(scope="module")
def weights():
    return random_weights(_model().particle_count, 11)


NAMES = ("mu", "lam", "yield_stress", "flow_rate", "viscosity", "pressure_stiffness")


@pytest.mark.parametrize("slide", [0.0, 2.0])
def test_ghost_floor_gradients_match_central_differences(weights, slide):
    """float64 central differences of a rollout in shear over the ghost floor (from F = I),
    for every material parameter, with the hand-written adjoints of the fit and force and
    with Warp's generated ones (the ghosts' own kernels are Warp's in both); also sliding,
    with stencils switching on at the rim."""
    model = _model(slide=slide)
    _, grads = _loss(model, weights, NAMES)
    _, generated = _loss(_model(slide=slide), weights, NAMES, hand_adjoints=False)
    for name in NAMES:
        base = getattr(model.materials[0], name)
        eps = 1e-5 * abs(base)
        fd = (_loss(_model({name: base + eps}, slide=slide), weights)
              - _loss(_model({name: base - eps}, slide=slide), weights)) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4), name
        assert generated[name][0] == pytest.approx(grads[name][0], rel=1e-8), name


def test_ghost_floor_initial_velocity_gradient(weights):
    """The same rollout's gradient in the initial velocity of particles in the lowest layer
    (whose fits hold ghosts) and of one above, against central differences."""
    model = _model()
    _, grads = _loss(model, weights, ("v0",))
    x0 = model.particle_x0
    low = np.flatnonzero(np.abs(x0[:, 1] - x0[:, 1][x0[:, 1] > 0].min()) < 0.2 * SPACING)
    for i, c in ((int(low[len(low) // 2]), 0), (int(low[3]), 1), (int(np.argmax(x0[:, 1])), 2)):
        def loss_with(delta):
            def velocity(m):
                v = _model().particle_v0.copy()
                v[i, c] += delta
                return v
            return _loss(_model(velocity=velocity), weights)
        fd = (loss_with(1e-6) - loss_with(-1e-6)) / 2e-6
        assert grads["v0"][i, c] == pytest.approx(fd, rel=1e-4, abs=1e-9)


def test_ghost_floor_force_is_minus_the_gradient_of_the_free_particles_fit_energy():
    """At a deformed state (F up to 15 % from I, jittered positions) on a ghost floor, the
    force on every coordinate of every free particle equals the central difference of
    ``E = sum V psi(dF(y) F)`` over the free particles (the floor's volume is 0), the fits
    holding the ghosts that follow the free particles' displacements (``dF`` read back from
    the solver): the hand-over is the ghosts' share of the gradient. Without it the force is
    far off. The hand-over is a set of equal and opposite pairs: the forces of all particles,
    floor included, sum to zero, so the pinned floor's reaction is the force the wall puts
    on the material."""
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, model="stvk", elastic_force="variational")
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), mat, name="block")
    b.add_particle_floor("block", margin=0.0, ghost=True)
    model = b.finalize(dtype=wp.float64)
    n, nf = model.particle_count, model.ghost_floor.count
    free = np.arange(n) < n - nf
    rng = np.random.default_rng(2)
    x0 = model.particle_x0.copy()
    x0[free] += rng.normal(scale=0.02 * SPACING, size=(free.sum(), 3))
    F0 = np.eye(3) + rng.uniform(-0.15, 0.15, size=(n, 3, 3))
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    a.x.assign(x0)
    a.F.assign(F0)
    moved = mover(solver, a, c)
    force = moved(0, 0.0).force.numpy().copy()
    assert c.ghost_count.numpy().max() > 0
    # The same stage without the hand-over: the free particles' own fit forces only.
    c.force.zero_()
    forces.launch_elastic_forces(model, a, c, False)
    bare = c.force.numpy().ravel().copy()
    assert np.abs(force.sum(axis=0)).max() < 1e-9 * np.abs(force).max()
    coords = np.flatnonzero(np.repeat(free, 3))
    dEdx = central_gradient(lambda k, d: stvk_energy(model, moved(k, d).F.numpy()), coords)
    assert sum(solver.guard_counts().values()) == 0
    err = np.abs(force.ravel()[coords] + dEdx).max() / np.abs(dEdx).max()
    assert err < 1e-6, err
    assert np.abs(bare[coords] + dEdx).max() / np.abs(dEdx).max() > 0.05


@pytest.mark.parametrize("change, pattern", [
    ({"fit": "curvature_corrected"}, r"fit = 'curvature_corrected' is not allowed with a ghost floor"),
    ({"elastic_force": "paper"}, r"Material.elastic_force = \['paper'\] is not allowed with a ghost floor"),
    ({"deformation": "rest"}, r"Material.elastic_force|Material.deformation 'rest' or 'additive' is not allowed with a ghost floor"),
    ({"images": True}, r"add_ground\(images=True\) is not allowed with a ghost floor"),
])
def test_ghost_floor_refuses_what_it_does_not_support(change, pattern):
    """Before any kernel runs, naming what is refused and what is allowed."""
    p = {"elastic_force": change.get("elastic_force", "variational")}
    if "deformation" in change:
        p["deformation"] = change["deformation"]
    b = we.SceneBuilder(spacing=SPACING)
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), we.Material(mu=1e4, lam=1e4, **p), name="block")
    b.add_particle_floor("block", margin=0.0, ghost=True)
    if change.get("images"):
        b.add_ground(-0.05, images=True)
    model = b.finalize()
    with pytest.raises(ValueError, match=pattern):
        we.Solver(model, fit=change.get("fit"))


def test_ghost_floor_builder_refuses_an_elastic_ghost_and_a_non_bool():
    b = we.SceneBuilder(spacing=SPACING)
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), we.Material(mu=1e4, lam=1e4), name="block")
    with pytest.raises(ValueError, match=r"elastic = True is not allowed with ghost = True"):
        b.add_particle_floor("block", margin=0.0, ghost=True, elastic=True)
    with pytest.raises(ValueError, match=r"ghost = 'yes' is not allowed: must be True or False"):
        b.add_particle_floor("block", margin=0.0, ghost="yes")


def test_ghost_floor_elastic_block_at_rest_stays_at_rest_and_auto_fit_is_linear():
    """An elastic block (``fit="auto"`` would pick the curvature-corrected fit; with a ghost
    floor it is the linear one) resting without gravity on the ghost floor keeps its state:
    the ghosts of a body at rest are at rest (float64, 200 steps)."""
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), we.Material.from_young(1e5, 0.3, elastic_force="variational"),
              name="block")
    b.add_particle_floor("block", margin=SPACING, ghost=True)
    model = b.finalize(dtype=wp.float64)
    solver = we.Solver(model)
    assert solver.fit == "linear"
    a, c = model.state(), model.state()
    for _ in range(200):
        solver.step(a, c, 0.5 * model.stable_dt())
        a, c = c, a
    assert np.abs(a.v.numpy()).max() < 1e-12
    assert np.abs(a.F.numpy() - np.eye(3)).max() < 1e-12
