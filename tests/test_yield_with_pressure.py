"""``Solver(yield_with_pressure=True)``: the yield test adds each particle's SPH pressure stress
(the virial of its pressure pair forces over its volume) to the elastic stress of ``F``
(docs/physics.md, "Still open", the SPH pressure's load the yield test does not see)."""

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from taped_loss import random_weights, taped_gradients, taped_rollout_loss
from warp_esph.sim import pressure

DX = 0.02
DT = 4.0e-4


def _block(dtype=wp.float64, requires_grad=False, squeeze=0.99, **params):
    """A 4 x 4 x 4 block on the ground whose particles start squeezed vertically by ``squeeze``
    about its centre (so its SPH density is above the rest density the builder took, and its
    surface particles' pressure pushes more vertically than sideways), at rest."""
    p = {"mu": 2.0e3, "lam": 3.0e3, "yield_stress": 40.0, "flow_rate": 100.0, "hardening": 0.0,
         "pressure_stiffness": 20.0, "viscosity": 0.0, **params}
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.1, 0.0), (4 * DX, 4 * DX, 4 * DX), we.Material(density=1000.0, **p), name="block")
    b.add_ground(0.0)
    model = b.finalize(dtype=dtype, requires_grad=requires_grad)
    x0 = model.particle_x0
    c = x0.mean(axis=0)
    x0[:, 1] = c[1] + squeeze * (x0[:, 1] - c[1])
    model.particle_x0 = x0 + np.random.default_rng(3).normal(scale=1e-3 * DX, size=x0.shape)
    return model


def _strained(model, state, stretch):
    """``state.F`` set to ``diag(1, stretch, 1)`` for every particle (an elastic vertical strain)."""
    F = np.tile(np.diag([1.0, stretch, 1.0]), (model.particle_count, 1, 1))
    state.F.assign(F.astype(state.F.numpy().dtype))


def test_pressure_stress_is_the_virial_of_the_pressure_forces():
    """The stress the yield test reads, times each particle's volume ``m / rho`` and summed, is
    minus the virial ``sum_i f_i (x) x_i`` of ``pressure.py``'s pressure forces on the same state
    (float64, to 1e-10 of its largest entry); it is compressive (the squeezed block's pressure
    pushes) and larger vertically, the direction of the squeeze."""
    model = _block()
    solver = we.Solver(model, yield_with_pressure=True)
    a, b = model.state(), model.state()
    solver.step(a, b, DT)
    sigma = solver.scratch.pressure_stress.numpy()
    V = model.particle_mass.numpy() / b.density.numpy()
    b.force.zero_()
    pressure.launch_pressure_forces(model, a, b, False)
    f = b.force.numpy()
    virial = -np.einsum("ia,ib->ab", f, a.x.numpy())
    total = np.einsum("i,iab->ab", V, sigma)
    assert np.abs(virial).max() > 0.0
    np.testing.assert_allclose(total, virial, rtol=0.0, atol=1e-10 * np.abs(virial).max())
    assert np.trace(total) < 0.0 and total[1, 1] < total[0, 0] and total[1, 1] < total[2, 2]


def test_the_yield_test_sees_the_pressure_deviator():
    """One step of the squeezed block with ``F = diag(1, 0.99, 1)``: its elastic deviatoric
    stress ``|2 mu dev(sigma)|`` (32.7 Pa) is under the yield stress (40 Pa), so without the
    option no particle flows; with it a particle flows exactly where the elastic deviator plus
    its pressure stress's deviator exceeds the yield stress (recomputed here in NumPy from the
    stress the step read), some do and some do not, at the rate that combined norm sets (read
    back from its hardening), and a flowed particle's vertical stretch relaxes toward 1."""
    mu, Y, stretch = 2.0e3, 40.0, 0.99
    s = np.array([1.0, stretch, 1.0])
    elastic = 2.0 * mu * np.linalg.norm(s - s.mean())
    assert elastic < Y
    alphas = {}
    for option in (False, True):
        model = _block()
        solver = we.Solver(model, yield_with_pressure=option, fused=False)
        a, b = model.state(), model.state()
        _strained(model, a, stretch)
        solver.step(a, b, DT)
        alphas[option] = b.alpha.numpy()
        if option:
            D = solver.scratch.pressure_stress.numpy()
            D = D - np.einsum("iaa->i", D)[:, None, None] / 3.0 * np.eye(3)
            dev = np.diag(2.0 * mu * (s - s.mean()))
            combined = np.linalg.norm(dev[None] + D, axis=(1, 2))
            Fy = b.F_flowed.numpy()[:, 1, 1]
    assert (alphas[False] == 0.0).all()
    flowed = alphas[True] > 0.0
    assert flowed.any() and not flowed.all()
    np.testing.assert_array_equal(flowed, combined > Y)
    assert (Fy[flowed] > stretch).all() and (Fy[~flowed] == stretch).all()
    # The norm the test read, not only its side of Y: a flowed particle's hardening is
    # gamma |dev ln s| (K = 0), gamma = nu_f dt (|s| - Y) / |s| (_block's flow rate 100/s).
    # Measured 6e-14 off; a test with half the cross term 4 mu tr(V_L D) flowed the same
    # particles, 12 % off here.
    gamma = alphas[True][flowed] / (abs(np.log(stretch)) * np.sqrt(2.0 / 3.0))
    tested = Y / (1.0 - gamma / (100.0 * DT))
    err = np.abs(tested / combined[flowed] - 1.0).max()
    assert err < 1e-12, err


def test_without_sph_pressure_the_option_changes_nothing():
    """With no SPH pressure or viscosity (``pressure_stiffness = 0``) the pressure stress is 0
    and a flowing block's ``F`` and hardening over 5 steps are those of the paper's test to the
    bit (the same non-fused kernels otherwise)."""
    out = {}
    for option in (False, True):
        model = _block(wp.float32, pressure_stiffness=0.0, yield_stress=5.0)
        solver = we.Solver(model, yield_with_pressure=option, fused=False)
        a, b = model.state(), model.state()
        _strained(model, a, 0.97)
        for _ in range(5):
            solver.step(a, b, DT)
            a, b = b, a
        out[option] = (a.F.numpy(), a.alpha.numpy())
    assert (out[True][1] > 0.0).all()
    np.testing.assert_array_equal(out[True][0], out[False][0])
    np.testing.assert_array_equal(out[True][1], out[False][1])


def test_yield_with_pressure_refuses_a_non_bool_and_a_comparison_model():
    """A value other than True or False, and the option beside a comparison deformation model
    (whose constitutive update has no such test), are refused by name."""
    model = _block(wp.float32)
    with pytest.raises(ValueError, match="yield_with_pressure = 1 is not allowed: must be True or False"):
        we.Solver(model, yield_with_pressure=1)
    model = _block(wp.float32, deformation="rest")
    with pytest.raises(ValueError, match="yield_with_pressure = True is not allowed with a comparison deformation"):
        we.Solver(model, yield_with_pressure=True)
    we.Solver(model)


GRAD_DT = 2.0e-4


@wp.kernel(module="unique")
def hardening_loss(alpha: wp.array(dtype=wp.float64), w: wp.array(dtype=wp.float64), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, w[i] * alpha[i])


def _loss(params, grad_of=None, v_delta=0.0, option=True):
    model = _block(requires_grad=True, squeeze=1.0, **params)
    x0 = model.particle_x0
    # A vertical squeeze (the pressure builds) with a slide and noise, so every particle moves.
    model.particle_v0 = (-20.0 * (x0 - x0.mean(axis=0)) * np.array([0.0, 1.0, 0.0]) + np.array([0.1, 0.0, 0.0])
                         + np.random.default_rng(11).normal(scale=0.02, size=x0.shape))
    model.particle_v0[0, 0] += v_delta
    solver = we.Solver(model, yield_with_pressure=option)
    states = [model.state() for _ in range(7)]
    loss, tape = taped_rollout_loss(solver, states, GRAD_DT, random_weights(model.particle_count, 2))
    # The hardening too, weighted so that it outweighs the positions: over six steps the flow
    # moves the particles by too little for a wrong adjoint of the yield test to show in them.
    w = wp.array(1.0e4 * np.random.default_rng(4).normal(size=model.particle_count), dtype=wp.float64)
    with tape:
        wp.launch(hardening_loss, model.particle_count, [states[-1].alpha, w], [loss])
    if grad_of is None:
        return loss.numpy()[0], states[-1].alpha.numpy()
    return taped_gradients(model, states, loss, tape, grad_of)


def test_gradient_through_the_pressure_in_the_yield_test_matches_central_differences():
    """The tape's gradient of a 6-step squeezed, flowing block's loss (its positions and, more,
    its hardening) in the pressure stiffness,
    the yield stress and the first particle's initial velocity against float64 central
    differences at relative steps 1e-3 and 1e-5, within 1e-4. Some particles flow and some do
    not, and the hardening differs from the paper's test's on the same run: the gradient passes
    through the pressure's part of the test."""
    params = {"pressure_stiffness": 200.0, "yield_stress": 300.0}
    grads = _loss(params, ("pressure_stiffness", "yield_stress", "v0"))
    _, alpha = _loss(params)
    assert (alpha > 0.0).any() and not (alpha > 0.0).all()
    assert np.abs(alpha - _loss(params, option=False)[1]).max() > 1e-3 * alpha.max()
    for name in ("pressure_stiffness", "yield_stress"):
        base = params[name]
        for rel in (1e-3, 1e-5):
            eps = rel * base
            fd = (_loss({**params, name: base + eps})[0] - _loss({**params, name: base - eps})[0]) / (2 * eps)
            assert abs(fd) > 1e-12, name
            assert grads[name].sum() == pytest.approx(fd, rel=1e-4), (name, rel)
    for eps in (1e-4, 1e-6):
        fd = (_loss(params, v_delta=eps)[0] - _loss(params, v_delta=-eps)[0]) / (2 * eps)
        assert grads["v0"][0, 0] == pytest.approx(fd, rel=1e-4, abs=1e-9), eps


def test_a_solver_of_the_option_says_its_taped_step_runs_the_differentiable_kernels():
    """``fast_under_tape()`` (what ``Rollout`` reads to run its untaped forward on the kernels
    the tape records) said True for ``Solver(yield_with_pressure=True)`` on a model with
    gradients, whose steps never take the fused kernels; the same solver without the option
    does take them."""
    model = _block(wp.float32, requires_grad=True)
    assert we.Solver(model).fast_under_tape()
    assert not we.Solver(model, yield_with_pressure=True).fast_under_tape()


def test_worlds_beside_a_ghost_floor_are_not_told_they_differ_from_their_separate_runs():
    """A world beside a ghost floor is warned that alone it runs the fused kernels; with
    ``yield_with_pressure`` no world alone runs them (the option runs the non-fused ones), so
    the warning, and its advice to compare with ``fused=False`` runs, said what is not so. The
    world's run is its separate run's under the same option to the bit."""
    import warnings

    from warp_esph.builder import finalize_worlds

    def world(ghost):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.04, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name="paste",
                  velocity=(0.1, 0.0, 0.0))
        b.add_particle_floor("paste", margin=0.02, layers=2, ghost=ghost)
        b.add_ground(friction=0.5)
        return b

    model = finalize_worlds([world(True), world(False)], dtype=wp.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver = we.Solver(model, yield_with_pressure=True)
    steps = dict(fps=30.0, dt=1.0 / 30.0 / 80.0, progress=False)
    x = we.simulate(model, 1, solver=solver, **steps).x.numpy()
    alone = world(False).finalize(dtype=wp.float64)
    x1 = we.simulate(alone, 1, solver=we.Solver(alone, yield_with_pressure=True), **steps).x.numpy()
    np.testing.assert_array_equal(x[model.world_particles(1)], x1)


def test_the_option_is_refused_beside_floor_images_whose_pressure_it_leaves_out():
    """The floor images' pressure (``add_ground(images=True)``) carries a resting body's weight
    but is not in the stress the yield test reads, so a bottom particle's pressure stress lacks
    the floor's vertical push: measured on a 4 x 4 x 4 block settled on them, its bottom layer
    read -622 Pa sideways and -248 Pa vertically, a deviator of 361 Pa against a 40 Pa yield
    stress, though the images carried all its weight. Refused naming the option and the floor;
    the plain ground and a particle floor, whose pairs are in the stress, are taken."""
    def model(floor):
        b = we.SceneBuilder(spacing=DX)
        b.add_box((0.0, 0.05, 0.0), (4 * DX,) * 3, we.Material(mu=2e3, lam=3e3, yield_stress=40.0, flow_rate=100.0,
                                                               pressure_stiffness=20.0), name="block")
        if floor == "particles":
            b.add_particle_floor("block", margin=DX, layers=2)
        b.add_ground(0.0, images=floor == "images")
        return b.finalize(dtype=wp.float64)

    with pytest.raises(ValueError, match=r"^yield_with_pressure = True is not allowed with floor images "
                                         r"\(add_ground\(images=True\)\): their pressure, .* is not in the stress"):
        we.Solver(model("images"), yield_with_pressure=True)
    we.Solver(model("images"))
    for floor in ("ground", "particles"):
        we.Solver(model(floor), yield_with_pressure=True)
