"""The two elastic pair forces (``forces.py``): the paper's eqs. 10-13 and the variational
force, minus the gradient of the incremental fit's elastic energy.

What is asserted is physics: the variational force is exactly ``-dE/dx`` (the paper's is
not), its linear stiffness is symmetric with real frequencies (the paper's is not, and has
growing modes), and an undamped elastic body keeps its energy with it, while with the
paper's force it gains energy at a rate the time step does not change."""

import dataclasses

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from taped_loss import random_weights, taped_rollout_loss
from energy_fd import (central_gradient, continued_stvk_energy, corotated_energy, image_energy_share, image_heights,
                       mover, stvk_energy, stvk_psi)
from warp_esph import tools
from warp_esph.scenes import FIG8_PLASTIC_MIN_SCALE, FIGURE_SCENES, SCENES


SPACING = 0.02
# The bound on |f + dE/dx| / max |dE/dx| of a variational force against the central differences of its
# energy (float64, step 1e-7): their round-off, measured 0.8e-10 to 4.7e-10 over every case here. At 1e-6
# a force kernel handed h rounded to float32 (the fit's h float64) passed, 1.4e-8 to 3.8e-8 off.
FORCE_GRADIENT_RTOL = 1e-8


def _cube(shape, elastic_force, model="linear", dtype=wp.float64, fit_weight="poly6"):
    # No pressure, viscosity or gravity: the elastic force alone.
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, model=model, elastic_force=elastic_force)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, 0.0, 0.0), tuple(SPACING * k for k in shape), mat)
    return b.finalize(dtype=dtype)


@pytest.mark.parametrize("fused, fit, fit_weight", [(True, "linear", "poly6"), (False, "linear", "poly6"),
                                                  (False, "curvature_corrected", "poly6"), (True, "linear", "biweight"),
                                                  (False, "curvature_corrected", "biweight")])
def test_variational_force_is_minus_the_gradient_of_the_fit_energy(fused, fit, fit_weight):
    """At a deformed state (F up to 15 % from I, jittered positions), the force of every
    coordinate equals the central difference of ``E = sum V psi(dF(y) F)``, with ``dF``
    the step's own fit (read back from the solver) and psi St. Venant-Kirchhoff, for either
    fit. The paper's force at the same state is far from it: it is not the gradient of an
    energy. The hourglass control is off (``hourglass=0``): its energy is not the fit's (the
    default for this elastic cube, ``fit="auto"``, adds it; measured 0.58 % of the largest
    force here). With either fit weight (``SceneBuilder(fit_weight=)``)."""
    errors = {}
    for elastic_force in ("variational", "paper"):
        model = _cube((4, 4, 3), elastic_force, model="stvk", fit_weight=fit_weight)
        n = model.particle_count
        rng = np.random.default_rng(2)
        x0 = model.particle_x0 + rng.normal(scale=0.02 * SPACING, size=(n, 3))
        F0 = np.eye(3) + rng.uniform(-0.15, 0.15, size=(n, 3, 3))
        solver = we.Solver(model, fused=fused, fit=fit, hourglass=0.0)
        a, b = model.state(), model.state()
        a.x.assign(x0)
        a.F.assign(F0)
        moved = mover(solver, a, b)
        force = moved(0, 0.0).force.numpy().ravel().copy()
        dEdx = central_gradient(lambda k, d: stvk_energy(model, moved(k, d).F.numpy()), range(3 * n))
        assert sum(solver.guard_counts().values()) == 0
        errors[elastic_force] = np.abs(force + dEdx).max() / np.abs(dEdx).max()
    assert errors["variational"] < FORCE_GRADIENT_RTOL, errors
    assert errors["paper"] > 0.05, errors


def _rest_block(material_model):
    """A float64 4x4x3 block of a variational rest-model material without pressure, its
    particle count, the jitter's generator and its rest positions: the rest force tests' scene."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, model=material_model, elastic_force="variational",
                                 deformation="rest")
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING, 4 * SPACING, 3 * SPACING), mat)
    model = b.finalize(dtype=wp.float64)
    return model, model.particle_count, np.random.default_rng(2), model.particle_x0


@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
def test_rest_variational_force_is_minus_the_gradient_of_an_energy_of_the_positions(fit):
    """``Material(deformation="rest", elastic_force="variational")``: at a deformed,
    jittered state the force equals the central difference of ``E(x) = sum V psi(G(x))``,
    ``G`` the total fit against the rest neighbourhood (read back from the solver: the rest
    model's stored F), the paper's or the curvature-corrected one, and psi St. Venant-Kirchhoff. Unlike the incremental force's energy
    (``dF(y) F`` with the stored, path-dependent F), this one is a function of the positions
    alone: the force is conservative (docs/physics.md, "The energy of undamped elastic
    bodies")."""
    model, n, rng, X = _rest_block("stvk")
    x0 = X + 0.1 * X @ rng.uniform(-1.0, 1.0, size=(3, 3)).T + rng.normal(scale=0.05 * SPACING, size=(n, 3))
    solver = we.Solver(model, fit=fit)
    assert solver.fit == fit and solver.hourglass == 0.0
    a, b_, c = model.state(), model.state(), model.state()
    dt = 1.0e-9
    a.x.assign(x0)
    solver.step(a, b_, dt)  # b_: at x0 (to 1e-9), with F = G(x0)
    assert np.abs(b_.F.numpy() - np.eye(3)).max() > 0.05

    moved = mover(solver, b_, c, dt)
    force = moved(0, 0.0).force.numpy().ravel().copy()
    dEdx = central_gradient(lambda k, d: stvk_energy(model, moved(k, d).F.numpy()), range(3 * n))
    assert np.abs(force + dEdx).max() < FORCE_GRADIENT_RTOL * np.abs(dEdx).max()


@pytest.mark.parametrize("material_model", ["stvk", "hyperelastic"])
@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
def test_the_rest_force_through_inverted_fits_is_minus_the_gradient_of_the_continued_energy(fit, material_model):
    """Where the rest fit ``G`` inverts (a block mirrored through one axis and sheared), the rest
    model takes it and its energy continues through det = 0 (``comparison``'s
    ``inverted_stress``): the force equals the central difference of ``sum V psi~(G(x))``,
    ``psi~`` St. Venant-Kirchhoff's continued energy (``energy_fd.continued_stvk_psi``), not of
    St. Venant-Kirchhoff's own, even in the reflection (``hyperelastic``: twice both). Before, an
    inverted fit kept the last ``F`` (here ``I``: no force at all), a stress that is the gradient
    of no energy."""
    scale = 2.0 if material_model == "hyperelastic" else 1.0
    model, n, rng, X = _rest_block(material_model)
    x0 = X @ (np.diag([1.0, 1.0, -0.5]) + 0.1 * rng.uniform(-1.0, 1.0, size=(3, 3))).T
    x0 += rng.normal(scale=0.03 * SPACING, size=(n, 3))
    solver = we.Solver(model, fit=fit)
    a, b_, c = model.state(), model.state(), model.state()
    dt = 1.0e-9
    a.x.assign(x0)
    solver.step(a, b_, dt)
    det = np.linalg.det(b_.F.numpy())
    assert (det < -0.05).all()  # every fit inverted, none near det = 0 (where psi~ has a kink)

    moved = mover(solver, b_, c, dt)
    force = moved(0, 0.0).force.numpy().ravel().copy()
    dEdx = scale * central_gradient(lambda k, d: continued_stvk_energy(model, moved(k, d).F.numpy()), range(3 * n))
    assert np.abs(force + dEdx).max() < FORCE_GRADIENT_RTOL * np.abs(dEdx).max()
    even = scale * central_gradient(lambda k, d: stvk_energy(model, moved(k, d).F.numpy()), range(3 * n))
    assert np.abs(force + even).max() > 0.1 * np.abs(even).max()


@pytest.mark.parametrize("material_model", ["linear", "non_newtonian"])
@pytest.mark.parametrize("case", ["incremental fused", "incremental", "rest", "rest inverted"])
def test_the_force_of_a_linear_material_that_cannot_flow_is_minus_the_gradient_of_the_corotated_energy(
        case, material_model):
    """A ``linear`` or ``non_newtonian`` material on the variational force that cannot flow
    (``yield_stress = inf``) takes the corotated stress (``forces.corotated_stress``): its force
    equals the central difference of ``sum V psi(F)``, ``psi`` the corotated energy
    (``energy_fd.corotated_psi``), of the incremental fit ``dF(y) F`` (``F`` up to 15 % from
    ``I``, fused and not) and of the rest model's total fit, strained 10 % and inverted
    through one axis (the corotated energy is smooth through det = 0 in the signed singular
    values: no continuation). Before, these materials took eq. 9's ``U diag(s o P^) V^T``,
    the gradient of no energy beyond small strain: measured 18 % (incremental), 11 % (rest) and
    64 % (inverted, its energy then continued as ``stvk``'s is) off the largest force."""
    rest = case.startswith("rest")
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, model=material_model,
                                 elastic_force="variational", deformation="rest" if rest else "incremental")
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING, 4 * SPACING, 3 * SPACING), mat)
    model = b.finalize(dtype=wp.float64)
    n = model.particle_count
    rng = np.random.default_rng(2)
    X = model.particle_x0
    solver = we.Solver(model, fit="linear", hourglass=0.0, fused=case == "incremental fused")
    a, b_, c = model.state(), model.state(), model.state()
    dt = 1.0e-9
    if rest:
        strain = np.diag([1.0, 1.0, -0.5]) if case == "rest inverted" else np.eye(3)
        x0 = X @ (strain + 0.1 * rng.uniform(-1.0, 1.0, size=(3, 3))).T + rng.normal(scale=0.03 * SPACING, size=(n, 3))
        a.x.assign(x0)
        solver.step(a, b_, dt)  # b_: at x0 (to 1e-9), with F = G(x0)
        a = b_
        det = np.linalg.det(a.F.numpy())
        assert (det < -0.05).all() if case == "rest inverted" else (det > 0.5).all()
    else:
        a.x.assign(X + rng.normal(scale=0.02 * SPACING, size=(n, 3)))
        a.F.assign(np.eye(3) + rng.uniform(-0.15, 0.15, size=(n, 3, 3)))
    moved = mover(solver, a, c, dt)
    force = moved(0, 0.0).force.numpy().ravel().copy()
    dEdx = central_gradient(lambda k, d: corotated_energy(model, moved(k, d).F.numpy()), range(3 * n))
    assert sum(v for k, v in solver.guard_counts().items() if k != "inverted") == 0
    assert np.abs(force + dEdx).max() < FORCE_GRADIENT_RTOL * np.abs(dEdx).max(), np.abs(force + dEdx).max() / np.abs(dEdx).max()


@pytest.mark.parametrize("fused", [True, False])
def test_only_materials_that_cannot_flow_take_the_corotated_stress(fused):
    """The stress a step writes (``State.stress``) of ``F = U diag(s) V^T`` (the flowed ``F``,
    up to 15 % from ``I``): a ``linear`` or ``non_newtonian`` material on the variational force
    that cannot flow (``yield_stress = inf``, or ``flow_rate = 0``) takes the corotated stress
    ``U diag(P^) V^T``, ``P^ = 2 mu (s - 1) + lam sum(s - 1)``; one that can flow (finite yield
    stress and a flow rate; not reached here) and one on the paper's force keep eq. 9's
    ``U diag(s o P^) V^T``, as before (docs/physics.md, "Choices")."""
    cases = {
        "elastic": ({}, True),
        "flow rate 0": ({"yield_stress": 1.0e9, "flow_rate": 0.0}, True),
        "non_newtonian elastic": ({"model": "non_newtonian"}, True),
        "can flow": ({"yield_stress": 1.0e9, "flow_rate": 50.0}, False),
        "paper force": ({"elastic_force": "paper"}, False),
    }
    rng = np.random.default_rng(4)
    for name, (options, corotated) in cases.items():
        mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, **options)
        b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
        b.add_box((0.0, 0.0, 0.0), (3 * SPACING,) * 3, mat)
        model = b.finalize(dtype=wp.float64)
        n = model.particle_count
        solver = we.Solver(model, fit="linear", fused=fused)
        a, c = model.state(), model.state()
        a.F.assign(np.eye(3) + rng.uniform(-0.15, 0.15, size=(n, 3, 3)))
        solver.step(a, c, 1.0e-9)
        F = c.F_flowed.numpy()
        U, s, Vt = np.linalg.svd(F)
        assert (np.linalg.det(F) > 0).all()
        p_hat = 2.0 * mat.mu * (s - 1.0) + mat.lam * (s - 1.0).sum(axis=1, keepdims=True)
        expected = np.einsum("nij,nj,njk->nik", U, p_hat if corotated else s * p_hat, Vt)
        other = np.einsum("nij,nj,njk->nik", U, s * p_hat if corotated else p_hat, Vt)
        P = c.stress.numpy()
        assert np.abs(P - expected).max() < 1e-9 * np.abs(expected).max(), name
        assert np.abs(P - other).max() > 0.02 * np.abs(expected).max(), name


def _pressure_energy(model, x) -> float:
    """The clamped SPH pressure energy of the default ``energy_spiky`` force at ``x``:
    ``sum m k_p (ln(rho / rho0) + rho0 / rho - 1)`` where ``rho > rho0``, ``rho`` the spiky
    density sum, ``rho0`` its value in the initial configuration."""
    h = model.support_radius
    m = model.particle_mass.numpy().astype(np.float64)

    def rho(y):
        r = np.sqrt(((y[:, None, :] - y[None, :, :]) ** 2).sum(-1))
        return (m[None, :] * 15.0 / (np.pi * h**6) * np.clip(h - r, 0.0, None) ** 3).sum(1)

    r, r0 = rho(np.asarray(x, dtype=np.float64)), rho(model.particle_x0.astype(np.float64))
    k_p = model.materials[0].pressure_stiffness
    return float((m * np.where(r > r0, k_p * (np.log(r / r0) + r0 / r - 1.0), 0.0)).sum())


def test_a_block_of_the_default_material_released_from_a_stretch_keeps_its_energy():
    """The default material (``Material.from_young(2e5, 0.3)``: ``linear``, variational force,
    default SPH pressure) as a 4^3 block (1 cm, float64, no gravity) released from a 10 %
    uniform stretch, on the default solver (the rest model), at half the stable step: its
    energy (kinetic, with the mean of the half-step velocities, plus the corotated elastic
    and the pressure energy) stays within 2 % of its start over 0.17 s (measured 0.35 %, the
    0.9 % of docs/physics.md being over 10 frames: the O(dt^2) offset of the sampled energy;
    3.6 % at the stable step over 1.33 s, as ``stvk``'s
    3.7 %). Before, the ``linear`` stress was eq. 9's ``U diag(s o P^) V^T``, the gradient of no
    energy beyond small strain: on this conservative scheme the block gained energy, 26 %
    within these 0.17 s; at the stable step it went on to invert its rest fits and
    diverge at 0.97 s."""
    mat = we.Material.from_young(2.0e5, 0.3)
    b = we.SceneBuilder(spacing=0.01, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.04, 0.04, 0.04), mat)
    model = b.finalize(dtype=wp.float64)
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    x = a.x.numpy()
    a.x.assign(x.mean(axis=0) + 1.1 * (x - x.mean(axis=0)))
    m = model.particle_mass.numpy()[:, None]
    frame = 1.0 / 30.0
    sub = int(np.ceil(2.0 * frame / model.stable_dt(hourglass=solver.hourglass)))
    dt = frame / sub

    def energy(state, v):
        return (0.5 * float((m * v * v).sum()) + corotated_energy(model, solver.start_deformation(state))
                + _pressure_energy(model, state.x.numpy()))

    e0 = energy(a, np.zeros_like(x))
    relative = []
    for _ in range(5):
        for _ in range(sub - 1):
            solver.step(a, c, dt)
            a, c = c, a
        v_before = a.v.numpy()
        solver.step(a, c, dt)
        relative.append(energy(a, 0.5 * (v_before + c.v.numpy())) / e0 - 1.0)
        a, c = c, a
    assert solver.rest_model and solver.guard_counts()["inverted"] == 0
    assert np.abs(relative).max() < 0.02, relative


def test_a_ball_thrown_hard_onto_a_plane_keeps_its_energy_on_the_rest_model():
    """An undamped St. Venant-Kirchhoff ball (136 particles) thrown at 6 m/s (0.37 of its P-wave
    speed) onto a frictionless static plane, on the default solver (the rest model): the impact
    crushes the layers at the contact through zero thickness and their rest fits invert. Its
    energy (kinetic plus the continued elastic energy, ``continued_stvk_energy``) never rises
    above what it was thrown with (the contact only removes energy) and it bounces off. Before,
    an inverted rest fit kept its last ``F``, a frozen stress whose force is the gradient of no
    energy: the ball's kinetic energy rose 870-fold within 44 steps (docs/physics.md, the rest
    model's Limits)."""
    dx, speed = 0.01, 6.0
    mat = we.Material.from_young(2.0e5, 0.3, density=1000.0, pressure_stiffness=0.0, model="stvk",
                                 elastic_force="variational", viscosity=0.0)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0))
    b.add_sphere((0.0, 0.0, 0.0), 0.03, mat, velocity=(-speed, 0.0, 0.0))
    b.add_plane((1.0, 0.0, 0.0), -0.03 - 0.2 * dx, friction=0.0)
    model = b.finalize()
    solver = we.Solver(model)
    assert solver.rest_model
    dt = model.stable_dt(hourglass=solver.hourglass)
    mass = model.particle_mass.numpy().astype(np.float64)
    E0 = 0.5 * mass.sum() * speed**2
    a, c = model.state(), model.state()
    energy = []
    for _ in range(250):
        solver.step(a, c, dt)
        a, c = c, a
        v = a.v.numpy().astype(np.float64)
        energy.append(0.5 * float((mass[:, None] * v * v).sum()) + continued_stvk_energy(model, a.F.numpy()))
    assert solver.guard_counts()["inverted"] > 0
    assert np.isfinite(energy).all() and max(energy) < 1.02 * E0, max(energy) / E0
    assert (mass * a.v.numpy()[:, 0]).sum() / mass.sum() > 0.3 * speed


def test_a_ball_struck_by_a_moving_plane_tool_keeps_its_energy_after_the_tool_leaves():
    """An undamped St. Venant-Kirchhoff ball (136 particles, E = 200 kPa) at rest, struck by a
    frictionless plane tool moving at 4 m/s (0.24 of its P-wave speed), on the default solver:
    with a tool in the scene that is the rest model now. Once the tool has left it (no reaction
    on it), the ball's energy (kinetic plus the continued elastic energy, some of its rest fits
    having inverted at the strike) stays within 1 % of what it left with over the next ~8
    breathing periods (measured: within 0.49 %, +0.21 % at the end). Before, a tool kept the
    default on the incremental composition, whose energy rose 3.4 % over the same steps (its
    drift; docs/physics.md, the rest model's Limits)."""
    dx, speed = 0.01, 4.0
    mat = we.Material.from_young(2.0e5, 0.3, density=1000.0, pressure_stiffness=0.0, model="stvk",
                                 elastic_force="variational", viscosity=0.0)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0))
    b.add_sphere((0.0, 0.0, 0.0), 0.03, mat)
    # The ball's leftmost particles sit at x = -0.025; the tool starts 0.2 spacing short of them.
    b.add_tool("plane", normal=(1.0, 0.0, 0.0), friction=0.0, name="bat",
               motion=tools.Velocity((speed, 0.0, 0.0), position=(-0.025 - 0.2 * dx, 0.0, 0.0)))
    model = b.finalize()
    solver = we.Solver(model)
    assert solver.rest_model
    dt = model.stable_dt(hourglass=solver.hourglass)
    mass = model.particle_mass.numpy().astype(np.float64)
    a, c = model.state(), model.state()
    energy, left = [], None
    for k in range(400):
        solver.step(a, c, dt)
        a, c = c, a
        touching = np.abs(solver.reaction_forces(a)["bat"][0]).max() > 0.0
        if touching:
            left = None
        elif left is None and k > 0:
            left = k
        v = a.v.numpy().astype(np.float64)
        energy.append(0.5 * float((mass[:, None] * v * v).sum()) + continued_stvk_energy(model, a.F.numpy()))
    assert solver.guard_counts()["inverted"] > 0  # the strike inverted rest fits
    assert left is not None and left < 200, left  # the tool struck the ball, which left it
    assert (mass * a.v.numpy()[:, 0]).sum() / mass.sum() > 1.5 * speed  # bounced off the tool
    after = np.array(energy[left + 2:]) / energy[left + 2]
    assert np.abs(after - 1.0).max() < 0.01, (after.min(), after.max())


def _linear_stiffness(model, fused, fit=None):
    """K = -df/du at rest, with F the solver's own fit of the displacement u."""
    n = model.particle_count
    solver = we.Solver(model, fused=fused, fit=fit)
    a, b, c = model.state(), model.state(), model.state()
    dt, eps = 1.0e-9, 1.0e-7

    def force(u):
        a.v.assign(u / dt)  # one step moves every particle by u and fits F = I + G u
        solver.step(a, b, dt)
        b.v.zero_()
        solver.step(b, c, dt)
        return c.force.numpy().ravel().copy()

    K = np.zeros((3 * n, 3 * n))
    for k in range(3 * n):
        u = np.zeros((n, 3))
        u.flat[k] = eps
        K[:, k] = -(force(u) - force(-u)) / (2 * eps)
    return K


@pytest.mark.parametrize("fused", [True, False])
def test_linear_stiffness_is_symmetric_only_for_the_variational_force(fused):
    """Small vibrations about rest obey M u'' = -K u. The variational K is symmetric
    (measured 4e-10 relative), so every frequency is real. The paper's is 12 % asymmetric
    on this 4^3 cube: complex frequencies, one growing as exp(1.41 t) (measured; on a 5^3
    cube, at 2.9 x the cost, 12 % and exp(2.85 t))."""
    rates, asym = {}, {}
    for elastic_force in ("variational", "paper"):
        model = _cube((4, 4, 4), elastic_force)
        K = _linear_stiffness(model, fused)
        m = np.repeat(model.particle_mass.numpy(), 3)
        asym[elastic_force] = np.abs(K - K.T).max() / np.abs(K).max()
        omega = np.sqrt(np.linalg.eigvals(K / m[:, None]).astype(complex))
        rates[elastic_force] = np.abs(omega.imag).max()
        omega_max = np.abs(omega).max()
    assert asym["variational"] < 1e-8, asym
    assert rates["variational"] < 1e-6 * omega_max, rates
    assert asym["paper"] > 0.05, asym
    assert rates["paper"] > 1.0, rates


def _vibrate(elastic_force, dt_factor, duration, stop_at=None, fit=None, deformation="incremental", hourglass=None,
             jitter=0.0, rate=5.0):
    """A 6^3 cube set breathing (v = rate (x - c), ``rate`` in 1/s), undamped; the largest
    kinetic energy reached over ``duration``, relative to the initial one, and when it passed
    ``stop_at`` (``fit``, ``hourglass``: ``Solver(fit=..., hourglass=...)``, None the default;
    ``jitter``: the standard deviation in m/s of a random velocity, seed 0, added to the
    breathing)."""
    mat = we.Material.from_young(2.0e5, 0.3, elastic_force=elastic_force, deformation=deformation)  # default SPH pressure
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (6 * SPACING,) * 3, mat)
    model = b.finalize()
    a, c = model.state(), model.state()
    x = a.x.numpy()
    v0 = rate * (x - x.mean(axis=0)) + jitter * np.random.default_rng(0).standard_normal(x.shape)
    a.v.assign(v0)
    mass = model.particle_mass.numpy()[:, None]
    ke0 = 0.5 * (mass * v0**2).sum()
    solver = we.Solver(model, fit=fit, hourglass=hourglass)
    dt = model.stable_dt(hourglass=solver.hourglass) * dt_factor
    peak = 0.0
    for k in range(int(duration / dt)):
        solver.step(a, c, dt)
        a, c = c, a
        if k % 20 == 0:
            peak = max(peak, 0.5 * (mass * a.v.numpy() ** 2).sum() / ke0)
            if stop_at is not None and peak > stop_at:
                return peak, k * dt
    return peak, None


# Four runs, each its own test so that parallel workers share them (together they are the
# suite's second-longest test).
@pytest.mark.parametrize("run", ["variational linear fit, stable step", "default, stable step",
                                 "conservative rest variant, stable step", "paper force, stable and half step"])
def test_undamped_elastic_body_keeps_its_energy_only_with_the_variational_force(run):
    """Measured: the variational cube's kinetic energy never exceeds its initial value
    (peak 1.00001 in 1.5 s); the paper's passes 10x it after 2.49 s at the stable step and
    2.95 s at half of it (1.5x after 2.24 and 2.57 s, 3x after 2.40 and 2.75 s; measured at
    5a7a948; an older tree read 2.42 s and 1.71 s, and 1.91 s at a quarter): a flutter of the
    force, not a time-step instability, which a smaller step would delay by far more or
    remove. The half step now postpones it by 18 % of the bound's 25 %.

    The onset time itself is not a property of the force: the flutter grows from rounding-level
    asymmetries, so it moves with anything that changes them. With rows of the paper's 30
    nearest it was 1.74 s and 1.59 s; the wide rows that reach h sigma_max(F) give each
    particle every neighbour inside its support and move it to the spread above. So the test
    asks only that halving the step does not postpone it (by more than the scatter between
    step sizes). To reach it in fewer steps the paper's runs start with a random velocity (seed
    0) on top of the breathing, now 0.3 m/s (77 % of the start's kinetic energy, 0.1 m/s 26 %:
    the cube vibrates at random more than it breathes, which the variational force in the
    paper's place still keeps, below), and stop at 3x (the times in the code below); measured from 0.03 m/s (3 % of the kinetic energy) on an older tree, it passed
    10x after 1.33 s at the stable step and 1.28 s at half of it (0.1 m/s: 1.08 and 1.12 s;
    0.01 m/s: 1.55 and 1.76 s), where the variational force (default fit) from a 0.01 m/s
    start still peaks at 1.00001 over 3 s at both steps.

    The variational force's own gain is the drift of the incremental composition F <- dF F
    (docs/physics.md, "The energy of undamped elastic bodies"): it goes as dt^2, with either
    fit; the rest-configuration variational force keeps the energy at the stable step
    (tests/test_validation_suite.py). Measured peaks over 1.5 /
    3 s at the stable step: the paper's linear fit 1.002 / 1.21 (pressure off: 1.27 / 1.79),
    the incremental composition with this elastic cube's solver settings (curvature-corrected
    fit, hourglass control 0.05) 1.07 / 1.52 (pressure off: 1.09 / 1.52); at half the step
    1.00000 and 1.00001 over 3 s. Measured again at 9b79470, that composition (curvature-corrected
    fit, control 0.05, stable step) from this breathing (rate 5/s) peaks at 1.000009 over 1.5 s,
    1.006 at 1.75 s, 1.11 at 2 s and 1.46 at 3 s. So the linear fit is held to the stable step
    over 1.5 s, as before, and the two runs held against that composition breathe faster (rate
    17/s), where it shows its gain sooner: measured at af3ef49, peak 1.89 by 1 s and 6.07 over
    1.25 s (with 1e-4 m/s of random velocity, seeds 1 and 2: 1.17 and 1.32 by 1 s; in float64
    15.9 by 1 s). Its onset is erratic in the rate: 1.05 by 0.5 s at 15/s (J within 0.89-1.23;
    at half the step 1.000002 over 1 s, so a drift of the step), but not by 1.3 s with 0.03
    m/s of random velocity added; none by 1 s at 13/s; 1.03-1.10 by 1-1.25 s at 16, 20 and
    22/s. 17/s is the rate whose gain came by 1 s under every perturbation tried. The default (``fit="auto"``) runs this elastic cube on the
    conservative rest model (``Solver.rest_model``), which peaks at 1.000003 over 1.5 s at
    rate 17/s (at rate 5/s 1.000009 over 1.5 and 3 s at the stable step, 1.000005 at half of
    it): it is held to the stable step over 1 s. The incremental composition it would fall
    back to (``Model.auto_runs_rest`` forced False) reached 6.07 over 1.25 s at af3ef49, at the
    full wave limit; since that path's stable step is half of it (``CORRECTED_INCREMENTAL_STEP``)
    the fallback runs at its own step and peaks at 0.99999999 over 1.25 s and over 0.6 s
    (measured at 86fec9d1): the case holds the default's energy at its stable step, not which
    model runs (``Solver.rest_model``'s tests do). The comparison's
    conservative variant, the same pieces against the rest neighbourhood
    (``deformation="rest"``, corrected fit, control 0.05), peaks at 1.000003 over 1.5 s at rate
    17/s (at rate 5/s 1.00001 over 1.5 and 3 s, the linear rest fit too): it is held to the
    stable step over 1 s, where the same pieces on the incremental composition reach 1.09 (poly6:
    1.26)."""
    if run.startswith("variational"):
        peak, _ = _vibrate("variational", 1.0, 1.5, fit="linear")
        assert peak < 1.01
    elif run.startswith("default"):
        # 1 s (was 1.25 s), the suite's cost: measured at 86fec9d1, the same pieces on the
        # incremental composition at this step (the full wave limit, twice theirs) peak at 1.055
        # from 0.26 s on (1.09 by 1 s, 1.60 by 1.25 s); with poly6 at 1.000000 to 0.84 s, then
        # 1.26 by 0.97 s and 4.09 by 1.25 s, so not shorter.
        peak, _ = _vibrate("variational", 1.0, 1.0, rate=17.0)
        assert peak < 1.01
    elif run.startswith("conservative"):
        # 1 s (was 1.25 s): the same pieces on the incremental composition (the mutation)
        # at this step peak at 1.055 from 0.26 s on, with poly6 1.26 by 0.97 s, as above.
        peak, _ = _vibrate("variational", 1.0, 1.0, fit="curvature_corrected", deformation="rest", hourglass=0.05,
                           rate=17.0)
        assert peak < 1.001
    else:
        # Seeded, the flutter's onset is set by its growth rate, not by when rounding first
        # excites it, and comes about twice as soon (half the steps). Measured at 86fec9d1
        # from 0.03 m/s: 3x after 1.71 and 1.25 s, 10x after 2.20 and 1.68 s; from 0.1 m/s
        # 3x after 1.30 and 1.00 s (10x 1.72 and 1.44 s; with poly6 3x after 0.84 and 0.91 s,
        # 10x after 1.08 and 1.12 s). From 0.3 m/s, which this reads (the suite's cost: about
        # two thirds of the steps of 0.1 m/s, 0.72 + 2 x 0.71 s of step against 1.30 + 2 x
        # 1.00 s), 3x after 0.72 and 0.71 s (measured at 2a8dfb3b), where
        # the variational force (default fit) in its place peaks at 1.00000003 over 3 s at
        # the stable step: no onset. 3x is twice the largest gain the variational force's
        # composition drift reached over 3 s (1.52, above).
        _, t_full = _vibrate("paper", 1.0, 3.0, stop_at=3.0, jitter=0.3)
        _, t_half = _vibrate("paper", 0.5, 3.0, stop_at=3.0, jitter=0.3)
        assert t_full is not None and t_half is not None, "the paper's force gains energy"
        assert t_half < 1.25 * t_full, (t_full, t_half)


@pytest.mark.parametrize("fused", [True, False])
def test_the_papers_force_is_eqs_10_to_13_summed_in_numpy(fused):
    """The paper's force at a deformed, jittered state (``F`` up to 15 % from ``I``) is eqs. 10-13
    summed over each particle's row in NumPy, ``g_ij = V_i V_j P*_i grad W(F_i^-1 (x_j - x_i))``
    added to ``j`` and taken from ``i``, with the stress and ``F`` the step read and eq. 12's
    gradient ``-c cos(pi r / 2h) r / |r|`` (``smoothing.elastic_kernel_constant``); measured
    6.6e-16 of the largest force. The other tests of this file ask only that it is not the
    variational force: a paper's force 10 % too large (``forces.elastic_pair_force``) passed the
    four of them tried and the 53 of tests/test_shared_formulas.py and tests/test_physics.py
    that ran."""
    from warp_esph.sim.smoothing import elastic_kernel_constant

    model = _cube((3, 3, 3), "paper")
    n, h = model.particle_count, model.support_radius
    rng = np.random.default_rng(5)
    solver = we.Solver(model, fused=fused, hourglass=0.0)
    a, c = model.state(), model.state()
    x = model.particle_x0 + rng.normal(scale=0.02 * SPACING, size=(n, 3))
    a.x.assign(x)
    a.F.assign(np.eye(3) + rng.uniform(-0.15, 0.15, size=(n, 3, 3)))
    solver.step(a, c, 1.0e-9)
    P, F_inv, V = c.stress.numpy(), np.linalg.inv(c.F_flowed.numpy()), model.particle_volume.numpy()
    nbr, count = c.neighbors.numpy(), c.neighbor_count.numpy()
    f = np.zeros((n, 3))
    for i in range(n):
        for j in nbr[i, : count[i]]:
            r = F_inv[i] @ (x[j] - x[i])
            rl = np.linalg.norm(r)
            if 0.0 < rl < h:
                g = V[i] * V[j] * P[i] @ (-elastic_kernel_constant(h) * np.cos(np.pi * rl / (2.0 * h)) * r / rl)
                f[j] += g
                f[i] -= g
    assert np.abs(f).max() > 0.0
    err = np.abs(c.force.numpy() - f).max() / np.abs(f).max()
    assert err < 1e-13, err


@pytest.mark.parametrize("fused", [True, False])
def test_guarded_particles_apply_no_variational_force(fused):
    """A one-layer sheet: every fit is ill-conditioned or has too few neighbours, so every F is kept whatever the
    positions do, the energy has no gradient and the variational force is zero; the paper's
    force still acts on the stressed sheet (its stress comes from the stored F)."""
    forces = {}
    for elastic_force in ("variational", "paper"):
        model = _cube((5, 5, 1), elastic_force)
        solver = we.Solver(model, fused=fused)
        a, b = model.state(), model.state()
        a.F.assign(np.tile(np.diag([1.1, 0.95, 1.0]), (model.particle_count, 1, 1)))
        solver.step(a, b, 1.0e-5)
        counts = solver.guard_counts()
        assert counts["ill_conditioned"] + counts["few_neighbors"] == model.particle_count
        forces[elastic_force] = np.abs(b.force.numpy()).max()
    assert forces["variational"] == 0.0
    assert forces["paper"] > 0.0


@pytest.mark.parametrize("elastic_force", ["variational", "paper"])
def test_guarded_rest_neighbourhoods_keep_their_f(elastic_force):
    """The rest model on a one-layer sheet: every rest neighbourhood is ill-conditioned, so
    its F is kept (counted) instead of a singular fit, and the variational force, which has
    no energy gradient there, is zero."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, elastic_force=elastic_force, deformation="rest")
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (5 * SPACING, 5 * SPACING, SPACING), mat)
    model = b.finalize(dtype=wp.float64)
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    F0 = np.tile(np.diag([1.1, 0.95, 1.0]), (model.particle_count, 1, 1))
    a.F.assign(F0)
    a.v.assign(np.random.default_rng(0).normal(scale=0.01, size=(model.particle_count, 3)))
    solver.step(a, c, 1.0e-5)
    counts = solver.guard_counts()
    assert counts["ill_conditioned"] + counts["few_neighbors"] == model.particle_count
    assert np.isfinite(c.x.numpy()).all()
    assert np.array_equal(c.F.numpy(), F0)
    if elastic_force == "variational":
        assert np.abs(c.force.numpy()).max() == 0.0


@pytest.mark.parametrize("fit", ["auto", "explicit rest"])
def test_the_rest_models_guard_follows_the_solvers_thresholds(fit):
    """A two-layer 8x8 plate: with ``Solver(min_neighbors=20)`` no particle has that many rest
    neighbours, so the rest model keeps every F (counted), as the incremental fit does (the
    guard was evaluated once with the default thresholds: it fitted every F); the
    default solver on the same model still fits (the model's default rest guard is not
    changed by the other solver's thresholds)."""
    deformation = "rest" if fit == "explicit rest" else "incremental"
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, deformation=deformation)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (8 * SPACING, 8 * SPACING, 2 * SPACING), mat)
    model = b.finalize(dtype=wp.float64)
    F0 = np.tile(np.diag([1.1, 0.95, 1.0]), (model.particle_count, 1, 1))
    few = {}
    for min_neighbors in (20, we.Solver(model).min_neighbors, 20):
        solver = we.Solver(model, min_neighbors=min_neighbors)
        assert fit != "auto" or solver.rest_model
        a, c = model.state(), model.state()
        a.F.assign(F0)
        solver.step(a, c, 1.0e-5)
        few[min_neighbors] = solver.guard_counts()["few_neighbors"]
        if min_neighbors == 20:
            assert np.array_equal(c.F.numpy(), F0)
    assert few == {20: model.particle_count, 6: 0}, few
    # max_condition reaches it too: no rest neighbourhood of the plate passes cond(A) <= 1.01.
    solver = we.Solver(model, max_condition=1.01)
    solver.step(model.state(), model.state(), 1.0e-5)
    assert solver.guard_counts()["ill_conditioned"] > 0


def test_the_rest_guard_of_a_solvers_thresholds_is_that_of_the_rest_neighbourhoods_it_guards():
    """``Model.rest_guard_for`` evaluates a solver's own thresholds at its first step, on the
    rest neighbourhoods the solver runs against (built from ``particle_x0`` when it was made).
    It searched ``particle_x0`` as it was then: moved apart by 3 x after the solver was made,
    every particle of a 4^3 block was guarded for ``min_neighbors=7`` (no F fitted, no elastic
    force) while its rest neighbourhood held 7 to 29, where the default thresholds fitted
    every F of the same neighbourhoods."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64)
    solvers = {k: we.Solver(model, min_neighbors=k) for k in (6, 7)}
    assert all(s.rest_model for s in solvers.values())
    assert model.rest_count.numpy().min() >= 7
    model.particle_x0 = model.particle_x0 * 3.0
    for k, solver in solvers.items():
        solver.step(model.state(), model.state(), 1.0e-5)
        assert solver.guard_counts()["few_neighbors"] == 0, k


def test_the_rest_model_fits_whole_where_the_incremental_fit_fades_an_ill_conditioned_one():
    """Float64, a plate of two 6 x 6 layers 0.17 spacings apart, whose every fit has ``cond(A)``
    between 29 and 36 (the poly6 moments at ``h = 2 dx``; the weight is named, as with the
    biweight the rest model's guard fires here too): past ``max_condition`` (20), short of
    the switch at twice it. The rest model reads the guard's switch alone (``Model.rest_guard``
    0 for all) and fits a 1 % stretch of the positions whole; the incremental fit takes 0.14 to
    0.54 of the same stretch made over a step, the fade of ``guards.guard_scale``
    (docs/physics.md, the rest model's "Limits"; docs/method.md §2)."""
    g = np.arange(6) * SPACING
    grid = np.meshgrid(g, g, [0.0, 0.17 * SPACING], indexing="ij")
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0), fit_weight="poly6")
    b.add_particles(np.stack([c.ravel() for c in grid], 1), mat)
    model = b.finalize(dtype=wp.float64)
    stretch = np.diag([1.01, 1.0, 1.0])
    rest = we.Solver(model)
    assert rest.rest_model
    a, c = model.state(), model.state()
    a.x.assign(model.particle_x0 @ stretch.T)
    rest.step(a, c, 1e-9)  # the positions barely move: F is the fit of the stretch
    assert not model.rest_guard.numpy().any()
    assert np.abs(c.F.numpy() - stretch).max() < 1e-12
    incremental = we.Solver(model, fit="linear")
    a, c = model.state(), model.state()
    dt = 1e-4
    a.v.assign(model.particle_x0 @ (stretch - np.eye(3)).T / dt)
    incremental.step(a, c, dt)
    share = (c.F.numpy()[:, 0, 0] - 1.0) / 0.01
    assert 0.1 < share.min() and share.max() < 0.6
    assert sum(incremental.guard_counts().values()) == 0


@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
@pytest.mark.parametrize("yield_stress, flows", [(0.0, False), (1.0e9, False), (100.0, True)])
def test_the_rest_model_keeps_its_plastic_f_exactly_where_nothing_flows(yield_stress, flows):
    """Float32, a stretched 4x4x3 block of the rest model ringing for 60 steps: where no flow
    changes ``F`` (elastic, or a yield stress far above the stress), ``F_p`` stays ``I`` bit
    for bit. It was rewritten ``F_e^-1 (F F_p)`` every step, whose round-off walked it (a
    1.7e-6 here; 3e-4 over a period of the 4-thick beam, whose largest strain is 1.4e-3), and an
    undamped or relaxing body crept with its rest shape (docs/physics.md, "The energy of
    undamped elastic bodies"). Where the flow acts, ``F_p`` takes it."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, elastic_force="variational", deformation="rest",
                                 yield_stress=yield_stress, flow_rate=1.0e3 if yield_stress else 0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING, 4 * SPACING, 3 * SPACING), mat)
    model = b.finalize(dtype=wp.float32)
    solver = we.Solver(model, fit="curvature_corrected", hourglass=0.05)
    a, c = model.state(), model.state()
    a.x.assign(model.particle_x0 * np.array([1.05, 0.98, 1.0], dtype=np.float32))
    dt = model.stable_dt(hourglass=solver.hourglass)
    for _ in range(60):
        solver.step(a, c, dt)
        a, c = c, a
    Fp = a.F_p.numpy()
    assert np.isfinite(a.x.numpy()).all()
    if flows:
        assert np.abs(Fp - np.eye(3)).max() > 1e-3
    else:
        assert np.array_equal(Fp, np.tile(np.eye(3, dtype=np.float32), (model.particle_count, 1, 1)))


def test_elastic_force_is_read_from_scene_files_and_presets(tmp_path):
    from warp_esph import scenes

    path = tmp_path / "s.toml"
    path.write_text('[materials.m]\npreset = "rubber"\nelastic_force = "variational"\n'
                    '[[bodies]]\nshape = "box"\nmaterial = "m"\ncenter = [0, 0.5, 0]\nsize = [0.2, 0.2, 0.2]\n')
    material = scenes.load_scene_file(str(path)).builder._materials[0]
    assert material.elastic_force == "variational" and material.viscosity == we.Material.preset("rubber").viscosity
    path.write_text('[materials.m]\npreset = "rubber"\nelastic_force = "exact"\n'
                    '[[bodies]]\nshape = "box"\nmaterial = "m"\ncenter = [0, 0.5, 0]\nsize = [0.2, 0.2, 0.2]\n')
    with pytest.raises(ValueError, match=r"\[materials\.m\]: elastic_force = 'exact' is not allowed"):
        scenes.load_scene_file(str(path))


def test_a_preset_given_a_comparison_model_gets_that_models_default_force():
    """The presets leave ``elastic_force`` to its default, which depends on ``deformation``
    (the comparison models' is the paper's): overriding ``deformation`` alone gives the
    force ``Material(...)`` would. It kept the incremental model's ``"variational"``, so
    ``deformation="additive"`` was refused for a force no one asked for."""
    for deformation in ("rest", "additive"):
        mat = we.Material.preset("rubber", deformation=deformation)
        assert mat.elastic_force == "paper"
        assert mat == we.Material(**{**dataclasses.asdict(we.Material.preset("rubber")), "deformation": deformation,
                                     "elastic_force": None})
    assert we.Material.preset("rubber", deformation="rest", elastic_force="variational").elastic_force == "variational"
    assert we.Material.preset("rubber", deformation="incremental").elastic_force == "variational"


def test_replace_of_a_defaulted_force_follows_a_new_deformation_and_a_given_one_stays():
    """``Material.replace(deformation=...)`` kept the resolved ``"variational"`` of a force left
    to its default: ``preset("rubber").replace(deformation="additive")`` was refused for a force
    no one gave, and ``deformation="rest"`` ran the variational force where ``Material(...)``
    gives the paper's. A defaulted force now follows the deformation, also after other
    replaces; a given one is kept (and refused with ``"additive"``). Whether it was given is
    no field: equality, hash, repr and ``asdict`` are the resolved values', and pickling keeps it."""
    import copy
    import pickle

    rubber = we.Material.preset("rubber")
    assert rubber.replace(deformation="additive").elastic_force == "paper"
    assert rubber.replace(mu=2e5).replace(deformation="rest").elastic_force == "paper"
    assert rubber.replace(deformation="rest").replace(deformation="incremental").elastic_force == "variational"
    assert we.Material.preset("rubber", mu=2e5).replace(deformation="additive").elastic_force == "paper"
    assert pickle.loads(pickle.dumps(rubber)).replace(deformation="rest").elastic_force == "paper"
    assert copy.deepcopy(rubber).replace(deformation="rest").elastic_force == "paper"
    given = we.Material(mu=1e4, lam=1e4, elastic_force="variational")
    defaulted = we.Material(mu=1e4, lam=1e4)
    assert given == defaulted and hash(given) == hash(defaulted) and repr(given) == repr(defaulted)
    assert dataclasses.asdict(given) == dataclasses.asdict(defaulted)
    assert given.replace(deformation="rest").elastic_force == "variational"
    assert pickle.loads(pickle.dumps(given)).replace(deformation="rest").elastic_force == "variational"
    with pytest.raises(ValueError, match=r"^Material\.elastic_force = 'variational' is not allowed with deformation = "
                                         r"'additive': .*, or elastic_force = 'paper'$"):
        given.replace(deformation="additive")
    assert given.replace(deformation="additive", elastic_force="paper").elastic_force == "paper"
    paper = we.Material.preset("rubber", elastic_force="paper")
    assert paper.replace(deformation="incremental").elastic_force == "paper"


def test_a_scene_file_preset_keeps_its_force_defaulted(tmp_path):
    """A scene file's preset with another field changed left the preset's force as if given:
    its ``replace(deformation="rest")`` kept ``"variational"``."""
    from warp_esph import scenes

    path = tmp_path / "s.toml"
    path.write_text('[materials.m]\npreset = "rubber"\nmu = 2e5\n'
                    '[[bodies]]\nshape = "box"\nmaterial = "m"\ncenter = [0, 0.5, 0]\nsize = [0.2, 0.2, 0.2]\n')
    material = scenes.load_scene_file(str(path)).builder._materials[0]
    assert material.elastic_force == "variational"
    assert material.replace(deformation="rest").elastic_force == "paper"


@pytest.mark.parametrize("name", SCENES)
def test_a_built_in_scenes_material_follows_a_new_deformation_as_a_users_would(name):
    """three_cylinders and lab_fig8_plates named the default force (``elastic_force="variational"``),
    so their materials counted as given: ``replace(deformation="additive")`` was refused where the
    same material built with the default gets the paper force. Every scene but the figures'
    leaves it defaulted; the figure scenes ask for the paper's, which a new deformation keeps."""
    force = "paper" if name in FIGURE_SCENES else None
    # The scene function: its bodies' resolution is not the point (Fig. 8 refuses its very
    # plastic cubes below FIG8_PLASTIC_MIN_SCALE).
    materials = SCENES[name](scale=FIG8_PLASTIC_MIN_SCALE if name == "fig8_comparison" else 0.3).builder._materials
    assert materials
    for m in materials:
        users = we.Material(**{**dataclasses.asdict(m), "elastic_force": force})
        assert m == users
        for deformation in ("rest", "additive", "incremental"):
            assert m.replace(deformation=deformation) == users.replace(deformation=deformation), (m, deformation)
        if force is None:
            assert m.elastic_force == "variational" and m.replace(deformation="additive").elastic_force == "paper"
        else:
            assert m.replace(deformation="incremental").elastic_force == "paper"


def test_a_scene_file_preset_given_a_comparison_model_gets_that_models_default_force(tmp_path):
    """The same rule in a scene file's ``[materials]`` table: ``preset`` and ``deformation``
    without ``elastic_force`` is the comparison model's default force, ``"paper"``."""
    from warp_esph import scenes

    path = tmp_path / "s.toml"
    path.write_text('[materials.m]\npreset = "rubber"\ndeformation = "additive"\n'
                    '[[bodies]]\nshape = "box"\nmaterial = "m"\ncenter = [0, 0.5, 0]\nsize = [0.2, 0.2, 0.2]\n')
    material = scenes.load_scene_file(str(path)).builder._materials[0]
    assert material == we.Material.preset("rubber", deformation="additive")
    assert material.elastic_force == "paper"


def test_rubber_ball_bounces_and_settles_in_its_shape():
    """The rubber preset (variational force) in the rubber_bounce scene, at 0.6 of its
    resolution: after the bounce the ball settles on the ground in its rest shape (its
    principal second moments about the centroid within 5 % of the start's: it sags and
    spreads a little where it rests).

    Since static friction holds (the friction fix of docs/physics.md) the ball keeps
    rocking on its flattened contact patch: the rocking is nearly rigid, which the central
    SPH viscosity leaves alone, and the floor has no rolling resistance. It is physical, not
    the contact law (docs/tools.md, "Rocking on the contact patch"): nothing feeds it (on the
    spiky pressure force it decayed at the same rate at half the step and ten times the
    viscosity damped it 2.3 times faster; under the default energy_spiky force it decays about
    7 x more slowly, an e-fold in 9.6 s, not yet explained). How much of it is left at 4 s is chaotic: over the unjittered start and three
    starts jittered by 1e-5 m (0.04 % of the spacing), the internal kinetic energy at 4 s
    (mean ``|v - v_mean|^2 / 2``) is 5.0e-5 to 5.5e-4 J/kg with the spiky pressure force and
    1.2e-4 to 4.5e-4 with the energy force, the centroid's speed 0.012-0.036 / 0.013-0.033 m/s
    (docs/physics.md, the SPH pressure): the earlier bounds on these (1e-4 J/kg, 0.03 m/s)
    held for one realization only. So the bounds are on the deformation's kinetic energy, the
    rigid rotation about the centroid removed (measured 3.0e-6 to 3.2e-5 / 6.7e-6 to 3.8e-5
    J/kg on the incremental composition), on the shape by its principal second moments
    (0.966-1.006 / 0.972-1.016 of the start's; the axis extents of a turned lattice sphere
    change by up to 15 %), on the centroid's drift (at most 0.012 m) and on its speed with room
    for the rocking. On the rest model, the default for this elastic ball, the deformation's
    kinetic energy at 4 s is as chaotic: over the same four starts 1.7e-5 to 5.3e-4 J/kg with
    eq. 9's stress (the centroid's speed 0.011-0.069 m/s) and 9.2e-6 to 1.6e-3 J/kg with the
    corotated stress it takes now (0.015-0.064 m/s), from 1e-2 to 3e-2 J/kg at 2 s either way;
    the shape within 0.989-1.005 of the start's. The bounds sit above those spreads: one
    realization of eq. 9 already broke the earlier 1e-4 J/kg and 0.06 m/s."""
    from warp_esph.scenes import get_scene

    scene = get_scene("rubber_bounce", scale=0.6)
    model = scene.builder.finalize()
    assert model.materials[0].elastic_force == "variational"
    a, c = model.state(), model.state()
    solver = we.Solver(model)
    dt = model.stable_dt()
    bounced = False
    for k in range(int(4.0 / dt)):
        solver.step(a, c, dt)
        a, c = c, a
        if k % 50 == 0:
            bounced |= bool(a.v.numpy()[:, 1].mean() > 0.5)
    x, v = a.x.numpy().astype(np.float64), a.v.numpy().astype(np.float64)
    r = x - x.mean(axis=0)
    u = v - v.mean(axis=0)
    inertia = (r * r).sum() * np.eye(3) - r.T @ r
    omega = np.linalg.solve(inertia, np.cross(r, u).sum(axis=0))
    deformation = 0.5 * ((u - np.cross(omega, r)) ** 2).sum(axis=1).mean()
    r0 = model.particle_x0 - model.particle_x0.mean(axis=0)
    moments = np.linalg.eigvalsh(r.T @ r) / np.linalg.eigvalsh(r0.T @ r0)
    assert bounced
    assert deformation < 3e-3, deformation
    assert np.abs(v.mean(axis=0)).max() < 0.08
    centroid_drift = np.abs(x.mean(axis=0) - model.particle_x0.mean(axis=0))[[0, 2]].max()
    assert centroid_drift < 0.02
    np.testing.assert_allclose(moments, 1.0, atol=0.05)
    assert x[:, 1].min() > -0.005


def _image_energy(model, x, y, F, rows, fit="linear"):
    """``sum_i V psi(dF_g(y) F_i)`` over the floor images ``g_i`` within ``h`` of the plane
    (``_image_fits``)."""
    Fg, near = _image_fits(model, x, y, F, rows, fit)
    psi = stvk_psi(model, Fg)
    return float((model.particle_volume.numpy() * np.where(near, psi, 0.0)).sum())


def _image_fits(model, x, y, F, rows, fit="linear"):
    """``dF_g(y) F_i`` of the floor images ``g_i`` (plane y = 0; mirrors, about
    half a spacing deep near the plane, ``image_heights``) of the particles within ``h`` of the plane: each image's fit over
    the particles near it (end positions ``y``) and the images of ``i``'s row ``rows[i]`` (at
    rest; each weighed as the pair of its particle and ``i``), with the particle's ``F``
    (docs/physics.md, "The ground collider's thin-layer strength");
    ``fit="curvature_corrected"``: the image's fit with the mixed quadratic terms projected out (``curvature.py``: ``dF = B~ A~^-1``, ``A~ = A - C K``, ``B~ = B - E K``,
    ``K = (D + eps I)^-1 C^T``, dropped where ``det A~ <= 0.1 det A``)."""
    h = model.support_radius
    c6 = 315.0 / (64.0 * np.pi * h**9)
    power = {"poly6": 3, "biweight": 2}[model.fit_weight]  # the fit's weight (its constant cancels)
    g = x.copy()
    g[:, 1] = image_heights(x[:, 1], model.spacing)
    Fg = np.tile(np.eye(3), (len(x), 1, 1))
    near = np.flatnonzero(x[:, 1] < h)
    # Every near image at once (the central differences call this hundreds of times): its
    # points are all particles, then its row's images padded to the longest row (weight 0).
    width = max(len(rows[i]) for i in near)
    row = np.zeros((len(near), width), dtype=int)
    live = np.zeros((len(near), width), dtype=bool)
    for k, i in enumerate(near):
        row[k, : len(rows[i])], live[k, : len(rows[i])] = rows[i], True
    gi = g[near][:, None, :]
    pts = np.concatenate([np.broadcast_to(x, (len(near), *x.shape)), g[row]], axis=1)
    ends = np.concatenate([np.broadcast_to(y, (len(near), *y.shape)), g[row]], axis=1)
    pair = np.concatenate([x[None, :, :] - gi, x[row] - x[near][:, None, :]], axis=1)  # an image pair weighs as its particles' pair
    mask = np.concatenate([np.ones((len(near), len(x)), dtype=bool), live], axis=1)
    d, e = pts - gi, ends - gi
    w = np.where(mask, c6 * np.clip(h * h - (pair * pair).sum(2), 0.0, None) ** power, 0.0)
    q = np.stack([d[..., 0] * d[..., 1], d[..., 0] * d[..., 2], d[..., 1] * d[..., 2]], axis=2) / h
    A = np.einsum("mn,mni,mnj->mij", w, d, d)
    B = np.einsum("mn,mni,mnj->mij", w, e, d)
    if fit == "curvature_corrected":
        C = np.einsum("mn,mni,mnj->mij", w, d, q)
        D = np.einsum("mn,mni,mnj->mij", w, q, q)
        E = np.einsum("mn,mni,mnj->mij", w, e, q)
        K = np.linalg.inv(D + 1e-4 * np.trace(A, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)) @ C.transpose(0, 2, 1)
        At = A - C @ K
        keep = (np.linalg.det(At) > 0.1 * np.linalg.det(A))[:, None, None]
        A, B = np.where(keep, At, A), np.where(keep, B - E @ K, B)
    Fg[near] = B @ np.linalg.inv(A) @ F[near]
    return Fg, x[:, 1] < h


def _deformed_cube_on_the_imaged_ground(base, friction, fit_weight):
    """A float64 4x4x3 ``stvk`` cube without pressure or gravity on ``add_ground(friction=...,
    images=True)``, its bottom layer ``base`` spacings above the plane: the model, its positions
    jittered by 0.02 dx and an ``F`` up to 15 % from I (seed 2)."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, model="stvk")
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, (base + 1.5) * SPACING, 0.0), (4 * SPACING, 4 * SPACING, 3 * SPACING), mat)
    b.add_ground(0.0, friction=friction, images=True)
    model = b.finalize(dtype=wp.float64)
    n = model.particle_count
    rng = np.random.default_rng(2)
    x0 = model.particle_x0 + rng.normal(scale=0.02 * SPACING, size=(n, 3))
    assert (x0[:, 1].min() > 0.5 * SPACING) == (base > 0.5)  # whether the images are exact mirrors
    return model, x0, np.eye(3) + rng.uniform(-0.15, 0.15, size=(n, 3, 3))


@pytest.mark.parametrize("fused, base, fit, fit_weight", [
    (True, 0.6, "linear", "poly6"), (False, 0.6, "linear", "poly6"), (True, 0.2, "linear", "poly6"),
    (False, 0.6, "curvature_corrected", "poly6"), (False, 0.2, "curvature_corrected", "poly6"),
    (True, 0.2, "linear", "biweight"), (False, 0.2, "curvature_corrected", "biweight")])
def test_variational_force_with_floor_images_is_minus_the_gradient_of_the_fit_energy(fused, base, fit, fit_weight):
    """``add_ground(images=True)``: a cube whose bottom layer stands ``base`` spacings above the
    plane (0.2: below half a spacing, where the images stop being mirrors), ``F`` up to 15 %
    from I, jittered. Its elastic force equals the central difference of ``sum V
    psi(dF(y) F)`` over the particles (their fits hold the images, at rest over the step; dF
    read back from the solver) plus the same over the images within ``h`` of a particle, each
    with its particle's ``F`` and its own fit (in numpy). Measured 1.7e-10 relative on either
    schedule, 1.4e-10 with the bottom layer below half a spacing (0.15 with the images' energy
    left out of the sum). The same with the curvature-corrected fit (``curvature.py``), whose
    images enter its moments and the images' energy likewise; and with the biweight fit weight
    (``SceneBuilder(fit_weight="biweight")``) in the fits, the particles' and the images'."""
    model, x0, F0 = _deformed_cube_on_the_imaged_ground(base, 0.5, fit_weight)
    n = model.particle_count
    solver = we.Solver(model, fused=fused, fit=fit, hourglass=0.0)
    a, c = model.state(), model.state()
    a.x.assign(x0)
    a.F.assign(F0)
    a.F_image.assign(F0)  # each image's own F (State.F_image): its particle's, as the numpy energy has it
    moved = mover(solver, a, c)

    def energy(k, delta):
        s = moved(k, delta)
        y = x0.copy()
        y.flat[k] += delta
        V = model.particle_volume.numpy()
        return float((V * stvk_psi(model, s.F.numpy())).sum()) + _image_energy(model, x0, y, F0, rows, fit)

    first = moved(0, 0.0)
    force = first.force.numpy().ravel().copy()
    nbr, count = first.neighbors.numpy(), first.neighbor_count.numpy()
    rows = [nbr[i, : count[i]] for i in range(n)]
    dEdx = central_gradient(energy, range(3 * n))
    assert sum(solver.guard_counts().values()) == 0
    err = np.abs(force + dEdx).max() / np.abs(dEdx).max()
    assert err < FORCE_GRADIENT_RTOL, err


@pytest.mark.parametrize("fused, base, fit, image_jitter", [
    (False, 0.6, "linear", 0.0), (True, 0.6, "linear", 0.0), (False, 0.2, "linear", 0.0), (True, 0.2, "linear", 0.0),
    (False, 0.6, "curvature_corrected", 0.0), (False, 0.2, "curvature_corrected", 0.0),
    (False, 0.6, "linear", 3e-4), (True, 0.6, "linear", 3e-4), (False, 0.6, "curvature_corrected", 3e-4)])
def test_the_frictionless_imaged_grounds_force_is_minus_the_gradient_of_half_the_particles_and_images_energies(
        fused, base, fit, image_jitter):
    """``add_ground(friction=0, images=True)``: the images move with their particles (``g(x)``,
    Jacobian ``J``). A cube whose bottom layer stands ``base`` spacings above the plane, ``F`` up
    to 15 % from I, each image's F its particle's mirrored, jittered: its elastic force against
    the central difference of ``sum V psi(F)`` over the particles, each within ``h`` of the plane
    counted as ``1/2 (psi(F_i) + psi(F_g))`` with its image's F after the step (the images moving
    by ``J`` in the differences). The force is that energy's gradient (``forces.image_energy_share``,
    ``forces.moving_image_forces``: every image's reaction sent to its particle through ``J``,
    the images' F their own fit's, ``deformation.floor_image_share``) on either schedule and fit:
    measured 3.1-3.3e-10 relative with the linear fit, 7.0-7.2e-10 with the corrected one, from
    half a spacing up (the images mirrors) and below it (0.2). Before, below half a spacing
    the force was not this gradient: 0.36 (the linear fit) and 0.39 (the corrected) off, the
    images' reactions on the floor and their F blended towards their particles' (docs/physics.md,
    "The frictionless imaged ground below half a spacing"). The image's share fades from 1/2 to 0
    over the last half spacing under ``h`` (``forces.image_energy_share``; the cube's second layer
    at ``base`` 0.6 stands there), so with the images' F no mirrors (``image_jitter``: each
    entry moved by up to that) the share's slope pushes that layer by ``c' (psi_g - psi)``
    (``forces.image_share_force``): measured 1.9e-10 (linear, either schedule) and 1.7e-10
    (corrected); without that force 1.6e-4 / 1.2e-4 off, and so at the parent, the share 1/2 up
    to ``h``. Its energy difference is the trapezoid's (``forces.image_energy_difference``),
    whose error is third order in the images' F's distance from the mirror: 5.7e-9 with 1e-3,
    5.6e-6 with 1e-2 (measured)."""
    model, x0, F0 = _deformed_cube_on_the_imaged_ground(base, 0.0, "biweight")
    n = model.particle_count
    R = np.diag([1.0, -1.0, 1.0])
    solver = we.Solver(model, fused=fused, fit=fit, hourglass=0.0)
    a, c = model.state(), model.state()
    a.x.assign(x0)
    a.F.assign(F0)
    jitter = np.random.default_rng(4).uniform(-image_jitter, image_jitter, size=F0.shape)
    a.F_image.assign(R @ F0 @ R + jitter)
    moved = mover(solver, a, c)
    h = model.support_radius
    near = x0[:, 1] < h
    fading = (x0[:, 1] > h - 0.5 * SPACING) & near
    V = model.particle_volume.numpy()

    def energy(k, delta):
        s = moved(k, delta)
        psi, psi_g = stvk_psi(model, s.F.numpy()), stvk_psi(model, s.F_image.numpy())
        share = image_energy_share(s.x.numpy()[:, 1], h, SPACING)
        return float((V * ((1.0 - share) * psi + share * psi_g)).sum())

    force = moved(0, 0.0).force.numpy().ravel().copy()
    dEdx = central_gradient(energy, range(3 * n))
    assert sum(solver.guard_counts().values()) == 0
    assert near.sum() >= 24  # not vacuous: two layers within h, their images in the sum
    assert fading.sum() >= 12 or base < 0.5  # not vacuous: a layer where the image's share fades
    err = np.abs(force + dEdx).max() / np.abs(dEdx).max()
    print(f"fused {fused}, base {base}, jitter {image_jitter}: |f + dE/dx| / max |dE/dx| = {err:.3g}")
    assert err < FORCE_GRADIENT_RTOL, err


@pytest.mark.parametrize("fused, fit", [(True, "linear"), (False, "linear"), (False, "curvature_corrected")])
def test_the_frictionless_imaged_grounds_force_is_continuous_where_a_particle_crosses_h(fused, fit):
    """Beyond ``h`` a moving image carries its particle's F mirrored and no energy; inside, its
    own fit's F, which is no mirror of its particle's where a partner was on the depth ramp. The
    image's share fades to 0 at ``h`` with its slope (``forces.image_energy_share``,
    ``forces.image_share_force``), so the force is continuous where a particle crosses ``h``.
    The cube of the test above (``base`` 0.6), the images' F their particles' mirrored moved by
    up to 1e-3, one particle of its second layer set ``1e-9`` spacings under and over ``h``: the
    forces on every particle differ by 9.4e-10 of their largest (either linear schedule; 7.1e-10
    corrected); with the share 1/2 up to ``h`` (before) by 4.1e-4 (3.3e-4) (docs/physics.md,
    "Where a particle crosses ``h``")."""
    model, x0, F0 = _deformed_cube_on_the_imaged_ground(0.6, 0.0, "biweight")
    R = np.diag([1.0, -1.0, 1.0])
    h = model.support_radius
    p = int(np.flatnonzero(np.abs(x0[:, 1] - 1.6 * SPACING) < 0.2 * SPACING)[5])
    solver = we.Solver(model, fused=fused, fit=fit, hourglass=0.0)
    a, c = model.state(), model.state()
    a.F.assign(F0)
    a.F_image.assign(R @ F0 @ R + np.random.default_rng(4).uniform(-1e-3, 1e-3, size=F0.shape))
    forces = []
    for side in (-1.0, 1.0):
        x = x0.copy()
        x[p, 1] = h + side * 1e-9 * SPACING
        a.x.assign(x)
        solver.step(a, c, 1.0e-9)
        forces.append(c.force.numpy().copy())
    assert sum(solver.guard_counts().values()) == 0
    jump = np.abs(forces[1] - forces[0]).max() / np.abs(forces[0]).max()
    print(f"fused {fused}, {fit}: the force's jump across h {jump:.3g} of its largest")
    assert jump < 1e-6, jump


@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
def test_floor_images_store_the_update_of_the_fit_their_energy_is_of(fit):
    """Each floor image's own F after a step (``State.F_image``) is ``dF_g F_g`` of the fit its
    energy is of (``_image_fits``, the numpy fit of the test above), where the image is its
    own (``State.image_share`` 1): so the work of that energy is stored where the next step
    reads it. The corrected fit's images first updated their F by their linear fit (measured:
    the stored F then differed from its energy's fit by up to 0.017 here, in a random motion
    of 2 % of a spacing; docs/physics.md, "The corrected fit's own image update")."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, model="stvk")
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 2.0 * SPACING, 0.0), (4 * SPACING, 4 * SPACING, 3 * SPACING), mat)  # bottom layer dx/2 up
    b.add_ground(0.0, images=True)
    model = b.finalize(dtype=wp.float64)
    n = model.particle_count
    rng = np.random.default_rng(3)
    x0 = model.particle_x0 + rng.normal(scale=0.02 * SPACING, size=(n, 3))
    F0 = np.eye(3) + rng.uniform(-0.15, 0.15, size=(n, 3, 3))
    dt = 1.0e-4
    solver = we.Solver(model, fit=fit, hourglass=0.0)
    a, c = model.state(), model.state()
    a.x.assign(x0)
    a.v.assign(rng.normal(scale=0.02 * SPACING / dt, size=(n, 3)))
    a.F.assign(F0)
    a.F_image.assign(F0)
    solver.step(a, c, dt)
    assert sum(solver.guard_counts().values()) == 0
    nbr, count = c.neighbors.numpy(), c.neighbor_count.numpy()
    rows = [nbr[i, : count[i]] for i in range(n)]
    Fg, near = _image_fits(model, x0, c.x.numpy(), F0, rows, fit)
    own = near & (c.image_share.numpy() == 1.0)
    assert own.sum() >= 12
    np.testing.assert_allclose(c.F_image.numpy()[own], Fg[own], rtol=0, atol=1e-11)


def test_an_elastic_particle_floor_keeps_its_bodys_force_defaulted_or_given():
    """``add_particle_floor(elastic=True)``'s own material (the body's without a yield stress)
    was built with ``dataclasses.replace``, which marked a defaulted force as given: its
    ``replace(deformation="rest")`` kept ``"variational"`` where the body's material follows
    the comparison model's default, ``"paper"``."""
    for force, want in ((None, "paper"), ("variational", "variational")):
        b = we.SceneBuilder(spacing=0.05)
        b.add_box((0.0, 0.2, 0.0), (0.15, 0.15, 0.15),
                  we.Material(mu=1e4, lam=1e4, yield_stress=100.0, flow_rate=10.0, elastic_force=force), name="blk")
        b.add_particle_floor("blk", margin=0.1, elastic=True)
        floor = b._materials[1]
        assert floor.yield_stress == float("inf") and floor.elastic_force == "variational"
        assert floor.replace(deformation="rest").elastic_force == want


def _sheared_block_flowing(steps, yield_stress=50.0):
    """A 4^3 float64 block of a material elastic until its ``flow_rate`` is set, sheared by 0.2
    (positions and ``F``), stepped ``steps`` times by the default solver with ``flow_rate``
    1e4 (the incremental composition: it flows, unless ``yield_stress`` is above its stress);
    ``(model, solver, state, spare, dt)``."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, yield_stress=yield_stress, flow_rate=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64)
    solver = we.Solver(model)
    assert solver.rest_model and solver.fit == "curvature_corrected"
    dt = 0.5 * model.stable_dt()
    a, c = model.state(), model.state()
    shear = np.eye(3)
    shear[0, 1] = 0.2
    x0 = model.particle_x0
    a.x.assign((x0 - x0.mean(0)) @ shear.T + x0.mean(0))
    a.F.assign(np.tile(shear, (model.particle_count, 1, 1)))
    model.flow_rate.assign(np.array([1.0e4]))
    for _ in range(steps):
        solver.step(a, c, dt)
        a, c = c, a
        assert not solver.rest_model and a.rest_model is False
    return model, solver, a, c, dt


def test_auto_runs_the_rest_model_for_elastic_bodies_and_hands_f_over_where_it_did_not_flow():
    """``fit="auto"`` on a model that cannot flow runs the rest-configuration model
    (``Solver.rest_model``); a parameter that makes it flow turns it to the incremental
    composition, and back where the body did not flow (``State.alpha`` 0): the stored ``F`` is
    handed over (``F_p = F^-1 G(x)``, ``comparison.rest_handover``)."""
    model, solver, a, c, dt = _sheared_block_flowing(20, yield_stress=1.0e6)
    assert a.flowed is None and not a.alpha.numpy().any()
    stored = a.F.numpy()
    model.flow_rate.assign(np.array([0.0]))
    solver.step(a, c, dt)
    assert solver.rest_model and c.rest_model is True and c.flowed is False
    assert solver.label() == f"rest curvature_corrected c={we.model.AUTO_HOURGLASS:g}"
    assert np.abs(c.F.numpy() - stored).max() < 0.02


def test_auto_keeps_the_incremental_composition_for_a_body_that_flowed():
    """A body that flowed (``State.alpha`` > 0) and is then made elastic is not handed over to
    the rest model: its rest neighbourhoods no longer describe it, and the automatic solver runs
    on with the incremental composition, the fit and control the parameters chose, the same
    steps bit for bit as a solver of that fit (``Solver.record``, ``label`` say so). The choice
    is carried by the states (``State.flowed``) and holds for the rest of the run."""
    model, solver, a, c, dt = _sheared_block_flowing(20)
    assert a.alpha.numpy().max() > 0.0
    model.flow_rate.assign(np.array([0.0]))
    fixed = we.Solver(model, fit="curvature_corrected", hourglass=we.model.AUTO_HOURGLASS)
    b, d = model.state(), model.state()
    b.assign(a)
    for _ in range(5):
        solver.step(a, c, dt)
        a, c = c, a
        fixed.step(b, d, dt)
        b, d = d, b
        assert not solver.runs_rest(a) and a.rest_model is False and a.flowed is True
    assert solver.record(a)["rest_model"] is False
    assert solver.label(a) == fixed.label(b) == f"incremental curvature_corrected c={we.model.AUTO_HOURGLASS:g}"
    np.testing.assert_array_equal(a.x.numpy(), b.x.numpy())
    np.testing.assert_array_equal(a.F.numpy(), b.F.numpy())


def _elastic_block_and_a_flowed_start(requires_grad=False):
    """A 3^3 float64 block of an elastic material on the default solver (the rest model), and a
    state an incremental step wrote whose body flowed (``State.rest_model`` False, ``alpha`` >
    0): from it the solver keeps the incremental composition."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (3 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64, requires_grad=requires_grad)
    flowed = model.state(requires_grad=requires_grad)
    flowed.alpha.fill_(0.01)
    flowed.rest_model = False
    return model, flowed


def test_a_solvers_record_follows_the_state_it_is_given_not_the_run_it_stepped_last():
    """One solver steps two rollouts (segments of 2 steps): A from a flowed start (the
    incremental composition), B from a new state (the rest model); A's backward pass replays its
    segments after B ran. The step wrote what ran on the states only, so ``record(state)`` and
    ``label(state)`` of each rollout's last state say what that rollout ran, and ``record()``
    what a step from a new state runs. Before, ``record()`` said what the step the solver ran
    last ran, A's replay of its first segment: the incremental composition, while B's run, the
    latest forward, ran the rest model."""
    from warp_esph.rollout import Rollout

    model, flowed = _elastic_block_and_a_flowed_start(requires_grad=True)
    solver = we.Solver(model)
    dt = 0.5 * model.stable_dt()
    a = Rollout(model, 4, dt, frames=[4], checkpoint_every=2, solver=solver)
    b = Rollout(model, 4, dt, frames=[4], checkpoint_every=2, solver=solver)
    a.forward(initial_state=flowed)
    b.forward()
    a.backward([np.ones((model.particle_count, 3))])
    ran_a, ran_b = a.final_state(), b.final_state()
    assert (ran_a.rest_model, ran_a.flowed, ran_b.rest_model) == (False, True, True)
    assert solver.record()["rest_model"] is True and solver.rest_model
    assert solver.record(ran_a)["rest_model"] is False and solver.record(ran_b)["rest_model"] is True
    c = we.model.AUTO_HOURGLASS
    assert (solver.label(ran_a), solver.label(ran_b)) == (f"incremental curvature_corrected c={c:g}",
                                                          f"rest curvature_corrected c={c:g}")
    assert solver.runs_rest(flowed) is False and solver.runs_rest(model.state()) is True
    with pytest.raises(ValueError, match=r"^state = .* is not allowed"):
        solver.record("not a state")


def test_what_a_solver_runs_from_a_state_refuses_what_is_no_state_of_its_model_whatever_it_runs():
    """``runs_rest(state)``, ``record(state)`` and ``label(state)`` checked ``state`` only where
    the parameters chose the rest model: a solver of the incremental composition (a fixed fit,
    or ``"auto"`` on a material that flows) answered for a string, or for another model's
    state, as for a state of its own."""
    model, _ = _elastic_block_and_a_flowed_start()
    other = we.SceneBuilder(spacing=SPACING)
    other.add_box((0.0, 0.0, 0.0), (2 * SPACING,) * 3, we.Material.from_young(2.0e5, 0.3))
    foreign = other.finalize(dtype=wp.float64).state()
    for solver in (we.Solver(model), we.Solver(model, fit="linear")):
        for bad in ("not a state", foreign):
            for ask in (solver.runs_rest, solver.record, solver.label):
                with pytest.raises(ValueError, match=r"^state (= .* is not allowed|does not belong to this model)"):
                    ask(bad)
        assert solver.runs_rest(model.state()) is solver.rest_model


def test_the_inverted_fits_advice_reads_what_runs_from_the_diverged_state():
    """``simulate``'s divergence advice blames the rest model's inverted fits only where a step
    from the state the diverging step wrote runs the rest model (``rest_inversions(solver,
    state)``): the incremental composition, kept for a flowed body, counts its own inverted fits
    in the same guard count. It read the solver's record of its last step before, which the
    step no longer writes."""
    from warp_esph.simulate import divergence_advice, rest_inversions

    model, flowed = _elastic_block_and_a_flowed_start()
    solver = we.Solver(model)
    counts = np.zeros(solver.scratch.counters.shape[0], dtype=np.int32)
    counts[list(solver.guard_counts()).index("inverted")] = 7
    solver.scratch.counters.assign(counts)
    assert rest_inversions(solver, flowed) == 0 and rest_inversions(solver, model.state()) == 7
    assert "inverted in 7" not in divergence_advice(model, solver.hourglass, solver=solver, state=flowed)
    assert "inverted in 7" in divergence_advice(model, solver.hourglass, solver=solver, state=model.state())


def _solver_facts(solver) -> dict:
    """The solver's attributes that are not Warp arrays, copied where mutable (the step counter,
    a count of work as ``guard_counts`` is, left out)."""
    out = {}
    for k, v in vars(solver).items():
        if isinstance(v, wp.array) or k == "step_count":
            continue
        out[k] = v.copy() if isinstance(v, (np.ndarray, set, dict, list)) else v
    return out


def test_a_step_writes_state_out_only_not_the_solver():
    """``Solver.step`` reads ``state_in`` and writes ``state_out``: after its first step (which
    takes what it builds once), steps from other states leave the solver's attributes as they
    were, also where those steps run another model (a flowed body keeps the incremental
    composition, a new state runs the rest model). Before, each step wrote what it ran on the
    solver (``rest_model``, ``_kept_incremental``), so the solver described whichever state it
    stepped last."""
    model, flowed = _elastic_block_and_a_flowed_start()
    solver = we.Solver(model)
    dt = 0.5 * model.stable_dt()
    fresh, out, kept, again = model.state(), model.state(), model.state(), model.state()
    solver.step(fresh, out, dt)
    before = _solver_facts(solver)
    for state_in, state_out in ((flowed, kept), (out, again), (kept, fresh)):
        solver.step(state_in, state_out, dt)
        after = _solver_facts(solver)
        assert before.keys() == after.keys(), set(before) ^ set(after)
        changed = [k for k in before if not (before[k] is after[k] or (np.array_equal(before[k], after[k])
                                                                       if isinstance(before[k], np.ndarray)
                                                                       else before[k] == after[k]))]
        assert not changed, {k: (before[k], after[k]) for k in changed}
    assert (out.rest_model, kept.rest_model, again.rest_model, fresh.rest_model) == (True, False, True, False)
    assert solver.step_count == 4


def test_a_run_from_a_flowed_state_records_the_incremental_composition_from_its_start():
    """``simulate`` tells a writer what its solver runs (``Solver.record``, ``label``) before the
    first step and before each frame, with the state it writes next (``state=``): from a state
    whose body flowed, made elastic, that is the incremental composition, not the rest model
    the parameters alone would choose (``record()`` without the state)."""
    from warp_esph.simulate import simulate

    model, _, a, c, dt = _sheared_block_flowing(5)
    model.flow_rate.assign(np.array([0.0]))

    class Writer:
        told = []

        def record_solver(self, solver, frame=None, state=None):
            self.told.append((frame, solver.record(state)["rest_model"], solver.label(state)))

        def write_frame(self, frame, state):
            pass

    class Stateless(Writer):
        told = []

        def record_solver(self, solver, frame=None):
            self.told.append((frame, solver.record()["rest_model"], solver.label()))

    for writer in (Writer, Stateless):
        simulate(model, 1, fps=1.0 / (3 * dt), dt=dt, writer=writer(), progress=False, solver=we.Solver(model), state=a)
    label = f"incremental curvature_corrected c={we.model.AUTO_HOURGLASS:g}"
    assert Writer.told == [(None, False, label), (0, False, label), (1, False, label)]
    # Without the state: what a step from a new state runs, as record() says.
    rest = f"rest curvature_corrected c={we.model.AUTO_HOURGLASS:g}"
    assert Stateless.told == [(None, True, rest), (0, True, rest), (1, True, rest)]


def _slump_block(ground: float):
    """A 4x4x6 block (yield 30 Pa, ``flow_rate`` 200) standing on the ground at ``ground``, float64."""
    mat = we.Material(density=1000.0, mu=3e3, lam=4e3, yield_stress=30.0, flow_rate=200.0)
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.0, 0.0), (0.08, 0.12, 0.08), mat)
    b.add_ground(ground, friction=0.5)
    return b.finalize(dtype=wp.float64)


def test_a_slumped_body_made_elastic_stays_at_rest():
    """A 4x4x6 block slumped on the ground for 0.4 s (``flow_rate`` 200, yield 30 Pa), then set
    (``flow_rate = 0``, as a callback or a fit's parameter crossing zero does): handed over to
    the rest model, 15 of its 96 rest fits inverted every step (rest neighbourhoods its flow had
    left), its top rose 3.3 mm in 0.1 s and its kinetic energy grew from 1.6e-4 J to 0.13 J,
    120 x the incremental composition's 1.1e-3 J. It now keeps the incremental composition."""
    model = _slump_block(-0.07)
    solver = we.Solver(model)
    # Both runs at the step of the corrected incremental fit (half the wave limit, with the
    # control's), which the flowed body keeps after the hand-over and the second solver runs.
    dt = model.stable_dt(hourglass=0.05, fit="curvature_corrected")
    a, c = model.state(), model.state()
    for _ in range(int(0.4 / dt)):
        solver.step(a, c, dt)
        a, c = c, a
    model.flow_rate.assign(np.array([0.0]))
    start = model.state()
    start.assign(a)
    top0 = start.x.numpy()[:, 1].max()
    ran = {}
    for label, s in (("default", solver), ("incremental", we.Solver(model, fit="curvature_corrected", hourglass=0.05))):
        s.reset_counts()
        a.assign(start)
        for _ in range(int(0.1 / dt)):
            s.step(a, c, dt)
            a, c = c, a
        v = a.v.numpy()
        ran[label] = (0.5 * (model.particle_mass.numpy() * (v * v).sum(axis=1)).sum(), a.x.numpy()[:, 1].max() - top0,
                      s.guard_counts()["inverted"])
    (energy, rise, inverted), (energy_incremental, _, _) = ran["default"], ran["incremental"]
    assert energy < 2.0 * energy_incremental, ran
    assert rise < 5e-4 and inverted == 0, ran


def test_auto_runs_the_rest_model_with_tools_pins_and_the_ground():
    """Tools, pins and the ground leave the elastic block on the rest model; an explicit fit
    runs the incremental composition (``Model.may_run_rest``). Before, a tool kept ``auto`` on
    the incremental composition (a sphere pressed into a block diverged on the rest model
    until an inverted rest fit's energy was continued through det = 0; docs/physics.md, the
    rest model's Limits)."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)

    def block(**extra):
        b = we.SceneBuilder(spacing=SPACING)
        b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat, name="block")
        b.add_ground(-3 * SPACING)
        if extra.get("pin"):
            b.pin(body="block", where=lambda x: x[:, 1] < 0.5 * SPACING)
        if extra.get("tool"):
            b.add_tool("sphere", radius=SPACING, position=(1.0, 1.0, 1.0), name="far")
        return b.finalize()

    assert we.Solver(block()).rest_model and we.Solver(block(pin=True)).rest_model
    tooled = block(tool=True)
    assert tooled.may_run_rest() and we.Solver(tooled).rest_model
    assert we.Solver(tooled).fit == "curvature_corrected" and we.Solver(tooled).hourglass == 0.05
    assert not we.Solver(block(), fit="curvature_corrected").rest_model


@pytest.mark.parametrize("flows", [False, True])
def test_the_rest_models_hand_over_survives_a_checkpoint_and_a_copy(tmp_path, flows):
    """Which model wrote a state (``State.rest_model``) and whether its body flowed
    (``State.flowed``, from ``alpha`` in a checkpoint) travel with it, so a run resumed from a
    checkpoint, or from ``State.assign``'s copy, hands ``F`` over where the uninterrupted run
    does (a body that did not flow) and keeps the incremental composition where it does (one
    that flowed): the same next state, bit for bit."""
    from warp_esph.checkpoint import load_state, save_state

    model, solver, a, c, dt = _sheared_block_flowing(5, yield_stress=50.0 if flows else 1.0e6)
    path = save_state(tmp_path / "flowed.npz", model, a, step=5, frame=0)
    copy = model.state()
    copy.assign(a)
    resumed, _ = load_state(path, model)  # sets the checkpoint's parameters: flowing
    model.flow_rate.assign(np.array([0.0]))
    assert resumed.rest_model is False and copy.rest_model is False and resumed.flowed is flows
    outs = []
    for start in (a, resumed, copy):
        out = model.state()
        solver.step(start, out, dt)
        assert out.rest_model is not flows and out.flowed is flows
        outs.append(out.F.numpy())
    np.testing.assert_array_equal(outs[1], outs[0])
    np.testing.assert_array_equal(outs[2], outs[0])


def test_a_checkpoint_of_a_flowed_body_records_the_incremental_composition_it_ran(tmp_path):
    """A body that flowed, made elastic, runs the incremental composition under the default
    solver, the same steps as a solver of its fit and control: its checkpoint records
    ``rest_model`` False, and either solver resumes the other's run. Before, it recorded
    ``rest_model = True`` (the parameters' choice) and the resume under the solver of the fit
    and control was refused, 'the run it continues had rest_model = True'."""
    from warp_esph.checkpoint import load_state, save_state

    model, solver, a, c, dt = _sheared_block_flowing(5)
    model.flow_rate.assign(np.array([0.0]))
    solver.step(a, c, dt)
    assert c.rest_model is False and c.flowed is True
    fixed = we.Solver(model, fit="curvature_corrected", hourglass=we.model.AUTO_HOURGLASS)
    for name, writer in (("auto", solver), ("fixed", fixed)):
        path = save_state(tmp_path / f"{name}.npz", model, c, step=6, frame=0, solver=writer)
        assert load_state(path, model)[1]["solver"]["rest_model"] is False
        for reader in (we.Solver(model), fixed):
            load_state(path, model, solver=reader)
    path = save_state(tmp_path / "auto.npz", model, c, step=6, frame=0, solver=solver)
    with pytest.raises(ValueError, match=r"had fit = 'curvature_corrected', this solver fit = 'linear'"):
        load_state(path, model, solver=we.Solver(model, fit="linear"))


def test_checkpoints_and_fit_json_say_what_solver_runs_rest_says_of_each_start(tmp_path):
    """A checkpoint's ``solver.rest_model`` (``checkpoint.solver_settings``, written by
    ``save_state`` and compared by ``load_state``) and fit.json's (``solvers_record`` with
    ``flowed_starts``) each worked out whether a step from a state runs the rest model in words
    of their own; they ask ``Solver.runs_rest`` (``sim.solver.keeps_incremental``) now, and say
    what it says for a new state, one a rest step wrote, and ones an incremental step wrote
    whose body did not flow and did: True, True, True, False."""
    from warp_esph.checkpoint import load_state, save_state, solver_settings
    from warp_esph.fit import fit
    from warp_esph.losses import PositionLoss

    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, yield_stress=50.0, flow_rate=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (3 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    dt = 0.5 * model.stable_dt()
    shear = np.eye(3)
    shear[0, 1] = 0.2
    x0 = model.particle_x0

    def sheared():
        s = model.state()
        s.x.assign((x0 - x0.mean(0)) @ shear.T + x0.mean(0))
        s.F.assign(np.tile(shear, (model.particle_count, 1, 1)))
        return s

    def stepped(yield_stress, flow_rate, steps):
        model.yield_stress.assign(np.array([yield_stress]))
        model.flow_rate.assign(np.array([flow_rate]))
        solver, a, c = we.Solver(model), sheared(), model.state()
        for _ in range(steps):
            solver.step(a, c, dt)
            a, c = c, a
        model.yield_stress.assign(np.array([50.0]))
        model.flow_rate.assign(np.array([0.0]))  # elastic: the parameters choose the rest model
        return a

    starts = {"new": model.state(), "rest": stepped(50.0, 0.0, 1), "unflowed": stepped(1.0e6, 1.0e4, 3),
              "flowed": stepped(50.0, 1.0e4, 3)}
    assert starts["rest"].rest_model is True and starts["unflowed"].rest_model is False
    assert not starts["unflowed"].alpha.numpy().any() and starts["flowed"].alpha.numpy().max() > 0.0
    loss = PositionLoss({1: x0.astype(np.float64)})
    for k, (name, start) in enumerate(starts.items()):
        solver = we.Solver(model)
        runs = solver.runs_rest(start)
        assert runs is (name != "flowed"), name
        assert solver_settings(solver, start)["rest_model"] is runs, name
        path = save_state(tmp_path / f"{name}.npz", model, start, step=k, frame=0, solver=solver)
        resumed, meta = load_state(path, model, solver=we.Solver(model))  # refused where the two disagree
        assert meta["solver"]["rest_model"] is runs and we.Solver(model).runs_rest(resumed) is runs, name
        r = fit(model, loss, ["mu"], initial={"initial_state": start}, steps=1, dt=dt, iterations=0, progress=False,
                diagnostics=False)
        assert r.to_dict()["solver"]["rest_model"] is runs and r.flowed_starts == [not runs], name


def test_a_hardening_set_by_hand_after_the_step_that_wrote_flowed_false_counts(tmp_path):
    """A step trusted ``State.flowed`` where it was set: a state a rest step wrote, or a
    checkpoint of an unflowed run loaded, says False, and an ``alpha`` set by hand after that
    (``state.alpha.fill_``) was not read: the next hand-over gave the flowed body to the rest
    model, whose rest neighbourhoods no longer describe it. False is read again at the hand-over
    now (True, which a step never undoes, is still taken as it stands), on the package's paths:
    a rollout's ``initial_state`` (with ``F0``, which hands over), a fit's start (its
    ``flowed_starts`` and fit.json) and a loaded checkpoint."""
    from warp_esph.checkpoint import load_state, save_state
    from warp_esph.fit import fit
    from warp_esph.losses import PositionLoss
    from warp_esph.rollout import Rollout

    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, yield_stress=1.0e6, flow_rate=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (3 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    # 0.4, under the half a flowed start keeps (Model.stable_dt(state=)) at the fit's stiffer
    # second point too (mu 1.1 x), which the fit below tries where its start's loss is 0.
    dt = 0.4 * model.stable_dt()
    solver = we.Solver(model)
    first, rest, spare = model.state(), model.state(), model.state()
    we.Solver(model, fit="linear").step(model.state(), first, dt)
    solver.step(first, rest, dt)  # handed over to the rest model: it had not flowed
    assert rest.rest_model is True and rest.flowed is False
    rest.alpha.fill_(0.01)  # by hand, after the step
    assert solver.runs_rest(rest)  # no hand-over from a rest step's state: the rest model goes on
    # A rollout from it with F0 hands it over: the body has flowed, so it is not.
    rollout = Rollout(model, 2, dt)
    rollout.forward(initial_state=rest, F0=np.eye(3))
    assert rollout.final_state().rest_model is False and rollout.final_state().flowed is True
    r = fit(model, PositionLoss({2: model.particle_x0.astype(np.float64)}), ["mu"], steps=2, dt=dt, iterations=0,
            initial={"initial_state": rest, "F0": np.eye(3)}, progress=False, diagnostics=False)
    assert r.flowed_starts == [True] and r.to_dict()["solver"]["rest_model"] is False
    # A checkpoint of a run the incremental composition wrote, unflowed: loaded, it says False.
    model.flow_rate.assign(np.array([1.0e4]))
    incremental = model.state()
    solver.step(model.state(), incremental, dt)
    assert incremental.rest_model is False and not incremental.alpha.numpy().any()
    path = save_state(tmp_path / "unflowed.npz", model, incremental, step=1, frame=0)
    model.flow_rate.assign(np.array([0.0]))
    resumed, _ = load_state(path, model)
    model.flow_rate.assign(np.array([0.0]))  # the checkpoint's parameters were flowing
    assert resumed.flowed is False and solver.runs_rest(resumed)
    resumed.alpha.fill_(0.01)
    assert not solver.runs_rest(resumed)
    solver.step(resumed, spare, dt)
    assert spare.rest_model is False and spare.flowed is True


def test_a_checkpoint_written_before_the_rest_model_hands_f_over_when_resumed(tmp_path):
    """A checkpoint written before ``fit="auto"`` ran the rest model has no ``rest_model`` in
    its metadata, and every step then ran the incremental composition: resumed by the default
    solver it hands ``F`` over as a state the incremental composition wrote does (read as None
    before, the flowed block sprang to the rest fit of its sheared positions in one step)."""
    import json

    from warp_esph.checkpoint import load_state, save_state

    def written_before(state, name, step):
        """A checkpoint of ``state`` as written before: its metadata without ``rest_model``."""
        with np.load(save_state(tmp_path / f"{name}_new.npz", model, state, step=step, frame=0)) as data:
            arrays = {k: data[k] for k in data.files}
        meta = json.loads(arrays["meta"].tobytes().decode())
        del meta["rest_model"]
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        np.savez(tmp_path / f"{name}.npz", **arrays)
        return tmp_path / f"{name}.npz"

    model, solver, a, c, dt = _sheared_block_flowing(5)
    old, _ = load_state(written_before(a, "old", 5), model)
    model.flow_rate.assign(np.array([0.0]))
    assert old.rest_model is False
    outs = []
    for start in (a, old):
        out = model.state()
        solver.step(start, out, dt)
        outs.append(out.F.numpy())
    np.testing.assert_array_equal(outs[1], outs[0])
    # A checkpoint of a state no step wrote (step 0) is a new state's start, as before.
    assert load_state(written_before(model.state(), "old0", 0), model)[0].rest_model is None


def test_a_rollouts_given_f0_is_the_strain_the_rest_model_starts_from():
    """``Rollout.forward(F0=...)`` gives the body's strain: the rest model takes it over
    (``F_p = F0^-1 G(x0)``, as after an incremental step). Before, the start was a new state's,
    ``F0`` set the first step's stress only and the next ``F`` was the rest fit of the
    unmoved positions: a 4^3 block released from a 20 % stretch kept its stretched shape
    (``F`` 0.999 after 30 steps, kinetic energy 0.0022 J) where the incremental composition
    recoils (0.894, 0.105 J)."""
    from warp_esph.rollout import Rollout

    def block():
        b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
        b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, we.Material(density=1000.0, mu=1e4, lam=1.5e4))
        return b.finalize(dtype=wp.float64, requires_grad=True)

    stretch = np.diag([1.2, 1.2 ** -0.5, 1.2 ** -0.5])
    ran = {}
    for label, options in (("default", {}), ("incremental", {"fit": "curvature_corrected", "hourglass": 0.05})):
        model = block()
        rollout = Rollout(model, 30, 0.5 * model.stable_dt(), solver=we.Solver(model, **options))
        rollout.forward(F0=stretch)
        assert rollout.solver.rest_model == (label == "default")
        end = rollout.final_state()
        v = end.v.numpy()
        ran[label] = (0.5 * (model.particle_mass.numpy() * (v * v).sum(axis=1)).sum(), end.F.numpy()[:, 0, 0].mean())
    (energy, stretched), (energy_incremental, stretched_incremental) = ran["default"], ran["incremental"]
    assert energy == pytest.approx(energy_incremental, rel=0.15), ran
    assert stretched == pytest.approx(stretched_incremental, abs=0.01), ran


def test_a_solver_made_after_particle_x0_changed_takes_the_rest_configuration_as_it_is_now():
    """The rest neighbourhoods are the model's, built when a solver first runs the rest model:
    a solver made after ``particle_x0`` changed (a body scaled by 2 %, at rest, as a jitter
    or a moved body is) runs against the positions as they are now. Before, the ones an
    earlier solver saw were kept, and the new unstressed body sprang back to them (0.48 m/s
    in 20 steps; the incremental composition: 2e-14)."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64)
    assert we.Solver(model).rest_model
    model.particle_x0 = model.particle_x0 * 1.02
    model.compute_rest_density()
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    dt = 0.5 * model.stable_dt()
    for _ in range(20):
        solver.step(a, c, dt)
        a, c = c, a
    assert a.rest_model
    assert np.abs(a.v.numpy()).max() < 1e-10
    assert np.abs(a.F.numpy() - np.eye(3)).max() < 1e-10


def test_a_solver_made_after_particle_x0_changed_fits_against_the_new_rest_moments():
    """The rest moments (``Model.rest_moments``: ``A~^-1`` and ``K`` of the rest offsets, the
    same every step) are evaluated once, so they are dropped with the rest neighbourhoods
    when ``particle_x0`` changes: a solver made after the body was scaled by 2 % fits a
    stretch of the new rest positions exactly, with the moments a model built at them has.
    Kept, the fit mixed the new offsets with the old moments (``F`` off the stretch by 6e-4,
    against 2e-17)."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64)
    solver = we.Solver(model)
    assert solver.rest_model
    a, c = model.state(), model.state()
    solver.step(a, c, 1e-6)
    before = model.rest_moments(True)[0].numpy().copy()
    model.particle_x0 = model.particle_x0 * 1.02
    model.compute_rest_density()
    solver = we.Solver(model)
    stretch = np.diag([1.01, 1.0, 1.0])
    a, c = model.state(), model.state()
    a.x.assign(model.particle_x0 @ stretch.T)
    solver.step(a, c, 1e-9)  # the positions barely move: F is the fit of the stretch
    fresh = b.finalize(dtype=wp.float64)
    fresh.particle_x0 = model.particle_x0.copy()
    fresh.compute_rest_density()
    assert we.Solver(fresh).rest_model
    now = model.rest_moments(True)[0].numpy()
    assert np.abs(now - before).max() > 0.01 * np.abs(before).max()
    np.testing.assert_array_equal(now, fresh.rest_moments(True)[0].numpy())
    free = model.rest_guard.numpy() == 0
    assert free.sum() > 0
    assert np.abs(c.F.numpy()[free] - stretch).max() < 1e-9


def test_the_rest_moments_follow_the_models_fit_weight():
    """The rest moments (``Model.rest_moments``) are sums over the rest offsets with the fit's
    weights, so a model whose ``fit_weight`` changes after a rest step fits with the new
    weight's moments: a 5 % stretch is fitted as it is by a model built with that weight. Kept
    (cached by the fit alone), the new weight's displacement moments met the old weight's
    ``A~^-1`` and the stretch was fitted as 1.000003 (the weights' normalisations differ)."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)

    def model(weight):
        b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0), fit_weight=weight)
        b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
        return b.finalize(dtype=wp.float64)

    stretch = np.diag([1.05, 1.0, 1.0])

    def fitted(m):
        solver = we.Solver(m)
        assert solver.rest_model
        a, c = m.state(), m.state()
        a.x.assign(m.particle_x0 @ stretch.T)
        solver.step(a, c, 1e-9)  # the positions barely move: F is the fit of the stretch
        return c.F.numpy()

    m = model("poly6")
    fitted(m)
    m.fit_weight = "biweight"
    F = fitted(m)
    free = m.rest_guard.numpy() == 0
    assert free.sum() > 0
    assert np.abs(F[free] - stretch).max() < 1e-9
    np.testing.assert_allclose(F, fitted(model("biweight")), rtol=0.0, atol=1e-12)


def test_a_solver_keeps_its_rest_configuration_when_a_later_solver_takes_a_new_one():
    """Each solver keeps the rest neighbourhoods it was made with (``Solver.rest_set``): a
    solver made before ``particle_x0`` changed (a 4^3 block scaled by 2 %) runs its body at
    rest from the old positions, the same after another solver made since has the model build
    new ones. Before, the model's arrays switched under the first solver, whose body then
    sprang towards the new shape (0.48 m/s in 20 steps, from 1e-14)."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64)
    first = we.Solver(model)
    old = model.state()
    model.particle_x0 = model.particle_x0 * 1.02
    model.compute_rest_density()
    dt = 0.5 * model.stable_dt()

    def speed(solver, start):
        a, c = model.state(), model.state()
        a.assign(start)
        for _ in range(20):
            solver.step(a, c, dt)
            a, c = c, a
        assert a.rest_model
        return np.abs(a.v.numpy()).max()

    assert speed(first, old) < 1e-10
    later = we.Solver(model)
    assert speed(first, old) < 1e-10
    # The later solver's rest configuration is the scaled one: the old positions spring out.
    assert speed(later, old) > 0.1
    assert speed(later, model.state()) < 1e-10


def test_the_hand_over_takes_f_p_as_a_new_states_where_the_rest_fit_is_inverted():
    """An incremental step does not write ``F_p``, so a state it wrote holds what that buffer
    last held: in a loop of two reused states, the ``F_p`` an earlier rest-model period left;
    in a rollout's states, ``I``. Where the rest fit ``G`` of a particle is inverted (its rest
    neighbourhood mirrored: a body folded through itself while it flowed) no hand-over
    ``F^-1 G`` exists, and the hand-over now gives such a particle a new state's ``F_p = I``.
    Before, it kept the buffer's value, which entered the rest force at once: two states equal
    in every field an incremental step writes stepped to different velocities."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64)
    solver = we.Solver(model)
    n = model.particle_count
    x0 = model.particle_x0
    mirrored = (x0 - x0.mean(0)) * np.array([-1.0, 1.0, 1.0]) + x0.mean(0)
    stretch = np.diag([1.05, 1.0, 1.0])
    left = np.diag([1.1, 1.0 / 1.1, 1.0])  # an earlier rest period's F_p
    outs = []
    for Fp in (np.eye(3), left):
        start, out = model.state(), model.state()
        start.x.assign(mirrored)
        start.F.assign(np.tile(stretch, (n, 1, 1)))
        start.F_p.assign(np.tile(Fp, (n, 1, 1)))
        start.rest_model = False  # as an incremental step wrote it
        solver.step(start, out, 0.5 * model.stable_dt())
        assert solver.rest_model and out.rest_model
        assert solver.guard_counts()["inverted"] > 0
        outs.append(out)
    np.testing.assert_array_equal(outs[1].v.numpy(), outs[0].v.numpy())
    np.testing.assert_array_equal(outs[1].F_p.numpy(), np.tile(np.eye(3), (n, 1, 1)))
    assert np.abs(outs[0].v.numpy()).max() > 1e-3  # the stretch's stress moves the body


def test_a_solver_keeps_the_moments_of_its_rest_configuration():
    """A solver's rest set carries its moments (``Solver.rest_set``, ``Model.rest_moments(curved,
    rest)``): a solver made before ``particle_x0`` changed (a 4^3 block scaled by 2 %) fits a
    1 % stretch of its old rest positions exactly after a later solver had the model build the
    new rest set and its moments, and the later solver fits a stretch of the new ones exactly.
    Before, the first solver's fit of the old offsets read the model's new moments (``F`` off the
    stretch by 6e-4)."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64)
    stretch = np.diag([1.01, 1.0, 1.0])

    def fit_error(solver, x):
        a, c = model.state(), model.state()
        a.x.assign(x @ stretch.T)
        solver.step(a, c, 1e-9)  # the positions barely move: F is the fit of the stretch
        assert c.rest_model
        free = solver.rest_set()[3].numpy() == 0
        assert free.sum() > 0
        return np.abs(c.F.numpy()[free] - stretch).max()

    first = we.Solver(model)
    old = model.particle_x0.copy()
    assert fit_error(first, old) < 1e-9
    model.particle_x0 = model.particle_x0 * 1.02
    model.compute_rest_density()
    later = we.Solver(model)
    assert fit_error(later, model.particle_x0) < 1e-9
    assert fit_error(first, old) < 1e-9


def _scaled_block(requires_grad=False, flow_rate=0.0):
    """A 4^3 elastic block (flowing where ``flow_rate`` > 0), no gravity, float64."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, yield_stress=1.0e3, flow_rate=flow_rate)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    return b.finalize(dtype=wp.float64, requires_grad=requires_grad)


def _scale_by_2_percent(model):
    model.particle_x0 = model.particle_x0 * 1.02
    model.compute_rest_density()


def test_a_solver_first_choosing_the_rest_model_after_particle_x0_changed_takes_the_new_rest_configuration():
    """A solver made while the block could flow has no rest configuration yet; after the block
    is scaled by 2 % and made elastic it takes one when it first runs the rest model: the
    positions as they are then, as its hourglass control does, whether or not another solver
    had the model build a set before. Before, it took the model's set of the old positions
    where one had been built: the new, unstressed block sprang back (0.48 m/s in 20 steps; without the
    earlier solver 1e-14)."""
    speeds = []
    for earlier in (False, True):
        model = _scaled_block()
        if earlier:
            assert we.Solver(model).rest_model  # has the model build its rest set
        model.flow_rate.assign(np.array([1.0e4]))
        solver = we.Solver(model)
        assert not solver.rest_model
        _scale_by_2_percent(model)
        model.flow_rate.assign(np.array([0.0]))
        a, c = model.state(), model.state()
        dt = 0.5 * model.stable_dt()
        for _ in range(20):
            solver.step(a, c, dt)
            a, c = c, a
        assert a.rest_model
        speeds.append(np.abs(a.v.numpy()).max())
    assert max(speeds) < 1e-10, speeds


def test_a_rollout_reused_after_particle_x0_changed_runs_as_a_new_one():
    """A ``Rollout`` starts each forward from ``particle_x0`` as it is then, so after the block is
    scaled by 2 % its solver takes the new rest configuration, and the block stays at rest as in
    a new rollout. Before, its solver kept the rest set of the old shape: 0.48 m/s in 20 steps
    (a new rollout: 1e-14)."""
    from warp_esph.rollout import Rollout

    model = _scaled_block(requires_grad=True)
    rollout = Rollout(model, 20, 0.5 * model.stable_dt())
    rollout.forward()
    assert rollout.solver.rest_model
    _scale_by_2_percent(model)
    rollout.forward()
    assert np.abs(rollout.final_state().v.numpy()).max() < 1e-10
    np.testing.assert_array_equal(rollout.positions(),
                                  Rollout(model, 20, 0.5 * model.stable_dt()).forward())


def _pushed_through_flowing(fused=True):
    """An elastic 4^3 block whose corner particle 0 starts pushed through the block: the rest
    model's first step takes its inverted rest fit; then a yield stress and flow rate make the
    material flow, and ``(model, solver, state)`` run on with the incremental composition."""
    mat = we.Material(mu=1e3, lam=1.5e3, density=1000.0, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (4 * SPACING,) * 3, mat)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    a, c = model.state(), model.state()
    x = model.particle_x0.copy()
    x[0] += SPACING
    a.x.assign(x)
    we.Solver(model).step(a, c, 2e-4)
    assert c.rest_model is True and np.linalg.det(c.F.numpy()[0]) < -1.0
    model.yield_stress.assign(np.array([1e5]))
    model.flow_rate.assign(np.array([10.0]))
    solver = we.Solver(model, fit="linear", fused=fused)
    return model, solver, c


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "unfused"])
def test_an_inverted_rest_fit_handed_back_to_the_incremental_composition_follows_the_body(fused):
    """A parameter that makes a material flow turns the step from the rest model to the
    incremental composition ``F <- dF F``, which keeps the last ``F`` where a step would
    invert it (paper §4): from a rest fit taken inverted every step was such a step, and the
    particle's ``F`` stayed the inverted fit for the rest of the run, whatever the body did
    (counted inverted at every step). The step hands it back as ``-F``, a mirror image of the
    same stretches (``comparison.rest_handback``), which the composition follows."""
    model, solver, a = _pushed_through_flowing(fused)
    c = model.state()
    handed = np.linalg.svd(a.F.numpy()[0], compute_uv=False)
    # What the first step sees (simulate's DivergenceMonitor bounds the start's energy by it).
    np.testing.assert_array_equal(solver.start_deformation(a)[0], -a.F.numpy()[0])
    inverted = solver.guard_counts()["inverted"]
    Fs = []
    for _ in range(10):
        solver.step(a, c, 2e-4)
        a, c = c, a
        assert not solver.rest_model and a.rest_model is False
        Fs.append(a.F.numpy()[0])
    assert solver.guard_counts()["inverted"] == inverted
    assert np.linalg.det(Fs[0]) > 1.0 and np.abs(np.linalg.svd(Fs[0], compute_uv=False) - handed).max() < 0.05
    assert np.abs(Fs[-1] - Fs[0]).max() > 1e-4  # kept, it was the inverted fit to the bit


@pytest.mark.parametrize("hand", [True, False], ids=["hand_written", "generated"])
def test_the_gradient_through_the_hand_back_of_an_inverted_rest_fit_matches_central_differences(hand):
    """Three taped incremental steps from a state a rest step wrote whose fit of particle 0 is
    inverted (``_pushed_through_flowing``; its singular values ``(1.92, 1, -1)``, where a
    mirror along the smallest one would jump): the gradient in that ``F`` goes back through
    the hand-back ``-F`` (``comparison.rest_handback``), with the hand-written adjoints of the
    step and Warp's generated ones, against float64 central differences; and in ``x``."""
    weights = random_weights(64, 7)

    def loss_of(dF=None, dx=None, grad=False):
        model, solver, start = _pushed_through_flowing()
        solver.hand_adjoints = hand
        states = [model.state() for _ in range(4)]
        states[0].assign(start)
        F, x = start.F.numpy(), start.x.numpy()
        if dF is not None:
            F[0][dF[:2]] += dF[2]
        if dx is not None:
            x[dx[0], dx[1]] += dx[2]
        states[0].F.assign(F)
        states[0].x.assign(x)
        loss, tape = taped_rollout_loss(solver, states, 2e-4, weights)
        if not grad:
            return loss.numpy()[0]
        tape.backward(loss)
        return states[0].F.grad.numpy()[0], states[0].x.grad.numpy()[0]

    gF, gx = loss_of(grad=True)
    # F's step is 1e-4: at 1e-6 the loss's (0.17) roundoff, ~4e-11 in the quotient, is 1e-4 of
    # the smallest entry (5.06e-7; 7.6e-6 at 1e-5), while 1e-4's truncation stays below 1e-6.
    eps = 1e-4
    for a, b in [(0, 0), (0, 2), (1, 2), (2, 1)]:
        fd = (loss_of(dF=(a, b, eps)) - loss_of(dF=(a, b, -eps))) / (2 * eps)
        assert abs(fd) > 1e-8, (a, b)
        assert gF[a, b] == pytest.approx(fd, rel=1e-5, abs=0.0), (a, b)
    eps = 1e-6
    for c in range(3):
        fd = (loss_of(dx=(0, c, eps)) - loss_of(dx=(0, c, -eps))) / (2 * eps)
        assert gx[c] == pytest.approx(fd, rel=1e-5, abs=0.0), c


@pytest.mark.parametrize("fused", [True, False])
def test_the_variational_forces_virial_is_the_particles_stress_on_any_packing(fused):
    """The mean stress theorem for the variational force: its virial ``-sum_k x_k (x) f_k``
    equals ``sum_i V_i P_i F_i^T`` (``V_i J_i`` times each particle's Cauchy stress, the stress
    its yield test reads) to round-off, on a jittered packing with scattered ``F`` as on a
    lattice, because each particle's energy turns with a global affine map of the positions
    (its fit reproduces one exactly). So a disordered packing does not carry less than its
    particles hold (docs/physics.md, "What the rested pile's forces carry"). The paper's eqs.
    10-13 carry 0.74 of it on a lattice (their kernel gradient's moment) and 1.1-1.25 of it
    jittered."""
    rel = {}
    for elastic_force in ("variational", "paper"):
        model = _cube((5, 4, 4), elastic_force, model="stvk", fit_weight="biweight")
        n = model.particle_count
        rng = np.random.default_rng(5)
        # Jittered by 0.1 spacing: at 0.2 a corner's count falls to the guard's fade (a faded fit
        # holds a stress it applies only in part; measured 16 % of the sum off).
        x0 = model.particle_x0 + rng.normal(scale=0.1 * SPACING, size=(n, 3))
        F0 = np.eye(3) + rng.uniform(-0.05, 0.05, size=(n, 3, 3))
        # The incremental fit: "auto" would run this elastic cube's rest-configuration model.
        solver = we.Solver(model, fused=fused, fit="linear", hourglass=0.0)
        a, b = model.state(), model.state()
        a.x.assign(x0)
        a.F.assign(F0)
        out = mover(solver, a, b)(0, 0.0)
        assert not out.guard.numpy().any()  # a guarded particle holds a stress it does not apply
        f = out.force.numpy()
        virial = -np.einsum("ka,kb->ab", x0, f)
        P, F = out.stress.numpy(), out.F_flowed.numpy()
        held = np.einsum("k,kab,kcb->ac", model.particle_volume.numpy(), P, F)
        rel[elastic_force] = np.abs(virial - held).max() / np.abs(held).max()
    assert rel["variational"] < 1e-12, rel
    assert rel["paper"] > 0.1, rel
