"""The no-slip ghost floor (``SceneBuilder.add_particle_floor(ghost=True)``,
``warp_esph/sim/ghost_floor.py``): its fits, its forces and its gradients."""

import contextlib

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.sim import forces
from energy_fd import central_gradient, mover, stvk_energy
from taped_loss import random_weights, taped_gradients, taped_rollout_loss, untaped_rollout_loss

STEPS = 5
DT = 1.0e-3
SPACING = 0.02


def _model(params=None, velocity=None, dtype=wp.float64, requires_grad=True, slide=0.0, slip=False):
    """A jittered block on a ghost floor, moving in shear over the floor (zero on the wall
    plane, half a spacing below the body's base) plus a stretch, so it yields within a few
    steps and every ghost's stencil moves; ``slide`` (m/s) adds a slide along x, fast
    enough that the stencils at the block's rim pass through the normaliser's switch
    (``ghost_floor.stencil_normaliser``: 4 / 8 / 12 of them at steps 3 / 4 / 5 at 2 m/s);
    ``slip``: the frictionless ghost floor."""
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "pressure_stiffness": 1.0,
         "viscosity": 2.0, "elastic_force": "variational"}
    p.update(params or {})
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (0.1, 0.06, 0.08), we.Material(density=1000.0, **p), name="block")
    b.add_particle_floor("block", margin=SPACING, ghost=True, slip=slip)
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
    if not grad_of and hand_adjoints:  # a central difference's run: no tape
        return untaped_rollout_loss(solver, model.state(requires_grad=False), DT, STEPS, weights)
    states = [model.state() for _ in range(STEPS + 1)]
    loss, tape = taped_rollout_loss(solver, states, DT, weights)
    if not grad_of:
        return loss.numpy()[0]
    return loss.numpy()[0], taped_gradients(model, states, loss, tape, grad_of)


@pytest.fixture(scope="module")
def weights():
    return random_weights(_model().particle_count, 11)


NAMES = ("mu", "lam", "yield_stress", "flow_rate", "viscosity", "pressure_stiffness")


@pytest.mark.parametrize("slide, slip", [(0.0, False), (2.0, False), (2.0, True)])
def test_ghost_floor_gradients_match_central_differences(weights, slide, slip):
    """float64 central differences of a rollout in shear over the ghost floor (from F = I),
    for every material parameter, with the hand-written adjoints of the fit and force and
    with Warp's generated ones (the ghosts' own kernels are Warp's in both); also sliding,
    with stencils switching on at the rim, and on the slip floor."""
    model = _model(slide=slide, slip=slip)
    loss, grads = _loss(model, weights, NAMES)
    # The central differences' runs, untaped, difference the taped rollout's loss: to the bit.
    assert _loss(_model(slide=slide, slip=slip), weights) == loss
    _, generated = _loss(_model(slide=slide, slip=slip), weights, NAMES, hand_adjoints=False)
    for name in NAMES:
        base = getattr(model.materials[0], name)
        eps = 1e-5 * abs(base)
        fd = (_loss(_model({name: base + eps}, slide=slide, slip=slip), weights)
              - _loss(_model({name: base - eps}, slide=slide, slip=slip), weights)) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4), name
        assert generated[name][0] == pytest.approx(grads[name][0], rel=1e-8, abs=0.0), name


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


@pytest.mark.parametrize("slip, margin", [(False, 0.0), (True, 0.0), (True, SPACING)])
def test_ghost_floor_force_is_minus_the_gradient_of_the_free_particles_fit_energy(slip, margin):
    """At a deformed state (F up to 15 % from I, jittered positions) on a ghost floor, the
    force on every coordinate of every free particle equals the central difference of
    ``E = sum V psi(dF(y) F)`` over the free particles (the floor's volume is 0), the fits
    holding the ghosts that follow the free particles' displacements (``dF`` read back from
    the solver): the hand-over is the ghosts' share of the gradient. Without it the force is
    far off. The hand-over is a set of equal and opposite pairs: the forces of all particles,
    floor included, sum to zero, so the pinned floor's reaction is the force the wall puts
    on the material. The same on the slip floor, and on a slip floor a spacing wider than the
    block, whose 24 ghosts past its rim fill part of their stencils (``stencil_fill``, 0 < fill
    < 1: the hand-over's ``f_kj P f_k``); with no margin no ghost fills, and without that term
    of the hand-over the force was 0.055 of the largest off (measured)."""
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, model="stvk", elastic_force="variational")
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), mat, name="block")
    b.add_particle_floor("block", margin=margin, ghost=True, slip=slip)
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
    fill = c.ghost_fill.numpy().sum(axis=1)
    assert ((fill > 1e-6) & (fill < 1.0 - 1e-6)).sum() == (24 if margin else 0), fill
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


def test_slip_ghost_positions_at_the_rim_have_the_gradient_of_their_central_differences():
    """The ghosts' positions after one step, ``sum w . ghost_y`` (random ``w``), against
    float64 central differences in every coordinate of every free particle's start, on a slip
    floor a spacing wider than a jittered block moving along it at random: its 24 ghosts past
    the rim fill part of their stencils (``stencil_fill``, 0 < fill < 1), so their positions
    hang on the fill's partial weights (the stencil's total through ``1 - total / N``, the
    support-wide Shepard weights). Within 1e-6 of the largest (measured: 2.2e-8); with the
    fill's weights left off the tape (their forward unchanged) 2.3 of it."""
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, -9.81, 0.0))
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0, elastic_force="variational")
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), mat, name="block")
    b.add_particle_floor("block", margin=SPACING, ghost=True, slip=True)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    n, nf = model.particle_count, model.ghost_floor.count
    free = np.arange(n) < n - nf
    rng = np.random.default_rng(4)
    x0 = model.particle_x0.copy()
    x0[free] += rng.normal(scale=0.05 * SPACING, size=(free.sum(), 3))
    v = np.zeros_like(x0)
    v[free] = np.array([2.0, 0.0, 0.7]) + rng.normal(scale=0.5, size=(free.sum(), 3))
    w = rng.normal(size=(n, 3)) * ~free[:, None]
    solver = we.Solver(model)
    dt = 3.0e-4

    def loss(x):
        a, c = model.state(requires_grad=False), model.state(requires_grad=False)
        a.x.assign(x)
        a.v.assign(v)
        solver.step(a, c, dt)
        return float((c.ghost_y.numpy() * w).sum()), c

    a, c = model.state(), model.state()
    a.x.assign(x0)
    a.v.assign(v)
    tape = wp.Tape()
    with tape:
        solver.step(a, c, dt)
    tape.backward(grads={c.ghost_y: wp.array(w, dtype=c.ghost_y.dtype, device=c.ghost_y.device)})
    grad = a.x.grad.numpy().ravel()
    fill = loss(x0)[1].ghost_fill.numpy().sum(axis=1)
    assert ((fill > 1e-6) & (fill < 1.0 - 1e-6)).sum() == 24, fill

    def moved(k, d):
        x = x0.copy().ravel()
        x[k] += d
        return loss(x.reshape(-1, 3))[0]

    coords = np.flatnonzero(np.repeat(free, 3))
    fd = central_gradient(moved, coords)
    err = np.abs(grad[coords] - fd).max() / np.abs(fd).max()
    assert err < 1e-6, err


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
    with pytest.raises(ValueError, match=r"slip = True is not allowed without ghost = True"):
        b.add_particle_floor("block", margin=0.0, slip=True)


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


def _first_step_F(floor: str, L: np.ndarray, rs: float | None = None):
    """The S = 0.2 slump scene at 8 across made force-free (no gravity, pressure or
    viscosity, a vanishing modulus), its free particles moved for one step by the velocity
    gradient ``L`` about the wall plane (between the floor and the body's lowest layer), on
    ``floor`` (``validation.FLOORS``; ``rs``: the ghosts' stencil radius in spacings, None: the
    default): ``(F after the step, dt, the free particles more than h inside the rim, those of
    them in the lowest layer)``. At the rim a fit also sees floor particles whose mirror point
    lies outside the body."""
    from benchmarks import validation

    model, free, _, _ = validation.slump_model(0.2, 8, viscosity=0.0, pressure_stiffness=0.0, stiffness=1e-9,
                                               floor_radius=1.5, floor=floor)
    if rs is not None:
        model.ghost_floor.radius = rs * model.spacing
    model.gravity = (0.0, 0.0, 0.0)
    x0 = model.particle_x0.astype(np.float64)
    plane = 0.5 * (x0[free, 1].min() + x0[~free, 1].max())
    v = np.zeros_like(x0)
    v[free] = (x0[free] - [0.0, plane, 0.0]) @ L.T
    model.particle_v0 = v
    solver = we.Solver(model, fused=False)
    a, b = model.state(), model.state()
    dt = 1e-3
    solver.step(a, b, dt)
    inside = free & (np.hypot(x0[:, 0], x0[:, 2]) < 0.05 - model.support_radius)
    lowest = inside & (x0[:, 1] < x0[free, 1].min() + 0.5 * model.spacing)
    return b.F.numpy().astype(np.float64), dt, inside, lowest


#: A shear and stretch that vanish on the wall plane (only d/dy), and a motion that slides
#: along it and compresses against it (normal velocity odd, tangential even about the plane).
NO_SLIP_L = np.outer([2.0, -0.5, 1.0], [0.0, 1.0, 0.0])
SLIP_L = np.diag([0.5, -1.0, 0.5]) + np.outer([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])


def test_ghost_floor_fits_reproduce_an_affine_motion_that_vanishes_on_the_wall():
    """The no-slip ghost floor: every fit next to the floor reproduces an affine motion that
    vanishes on the wall's plane, F = I + dt L (measured: to 1.4e-5 of |dt L| in float32
    with a one-spacing stencil), where the plain particle floor's static particles leave the
    lowest layer's fitted shear at 0.75 of it. Exact with a ghost stencil of one spacing (on the lattice each ghost has
    one partner); the Shepard average of the default 1.2-spacing stencil reproduces
    constants only, and misses the lowest layer's shear by 1.25 % (the partner's neighbour
    above has no mirror below)."""
    L = NO_SLIP_L
    F, dt, inside, lowest = _first_step_F("ghost_particles", L, rs=1.0)
    assert lowest.sum() >= 12
    exact = np.eye(3) + dt * L
    err = np.abs(F[inside] - exact).max() / np.abs(dt * L).max()
    assert err < 1e-3, err
    F_wide, *_ = _first_step_F("ghost_particles", L)
    assert np.abs(F_wide[inside] - exact).max() / np.abs(dt * L).max() < 0.02
    F_plain, *_ = _first_step_F("particles", L)
    shear = F_plain[lowest, 0, 1] / (dt * L[0, 1])
    assert np.all(np.abs(shear - 0.75) < 0.01), shear


def test_slip_ghost_floor_fits_reproduce_a_motion_that_slides_along_the_wall():
    """The slip ghost floor: a motion continued evenly along the plane and oddly across it (a
    compression against the plane, a lateral stretch and shear) is fitted next to the floor
    as in the interior (measured: to 3.6e-5 of |dt L| with a stencil of one spacing, 1.25 %
    with the default), where the no-slip ghosts, which reverse its tangential part, and the
    plain floor's static particles do not (the lowest layer off by 1.75 and 0.875 of it)."""
    L = SLIP_L
    exact = np.eye(3) + 1e-3 * L
    F, dt, inside, lowest = _first_step_F("slip_ghost_particles", L, rs=1.0)
    assert lowest.sum() >= 12
    errs = {}
    errs["slip, rs 1"] = np.abs(F[inside] - exact).max() / np.abs(dt * L).max()
    for floor, rs in (("slip_ghost_particles", None), ("ghost_particles", 1.0), ("particles", None)):
        F, *_ = _first_step_F(floor, L, rs=rs)
        errs[f"{floor}, rs {rs}"] = np.abs(F[lowest] - exact).max() / np.abs(dt * L).max()
    assert errs["slip, rs 1"] < 1e-3, errs
    assert errs["slip_ghost_particles, rs None"] < 0.02, errs
    assert errs["ghost_particles, rs 1.0"] > 0.2 and errs["particles, rs None"] > 0.1, errs


@pytest.mark.parametrize("slip", [True, False])
def test_a_block_sliding_on_the_slip_ghost_floor_stays_undeformed_and_keeps_its_momentum(slip):
    """A block slid along the slip ghost floor (no gravity, pressure or viscosity) moves
    rigidly: every fit, the rim's included, sees a translation, so F stays at I to round-off
    and the block keeps its momentum. The ghosts past the rim, whose stencils hold little or
    no material, make up the part they do not follow with the support-wide average
    (``ghost_floor.stencil_fill``); without it they lagged the slide and the rim was fitted a
    shear (measured: |F - I| up to 0.34 after 20 steps here, the speeds up to 0.2 m/s off;
    with it 1.2e-15 and 6.7e-16 m/s). The no-slip floor holds the same block (|F - I| 1.86,
    its mean speed down to 1.57 m/s): its ghosts move against the slide."""
    b = we.SceneBuilder(spacing=SPACING, gravity=(0.0, 0.0, 0.0))
    mat = we.Material(density=1000.0, mu=1.0e3, lam=1.5e3, pressure_stiffness=0.0, viscosity=0.0)
    b.add_box((0.0, 0.03, 0.0), (0.08, 0.06, 0.08), mat, name="block")
    b.add_particle_floor("block", margin=3 * SPACING, ghost=True, slip=slip)
    model = b.finalize(dtype=wp.float64)
    free = np.arange(model.particle_count) < model.particle_count - model.ghost_floor.count
    v = np.zeros_like(model.particle_x0)
    v[free, 0] = 2.0  # a spacing in 10 steps: the rim's stencils change
    model.particle_v0 = v
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    for _ in range(20):
        solver.step(a, c, DT)
        a, c = c, a
    dF = np.abs(a.F.numpy()[free] - np.eye(3)).max()
    vx = a.v.numpy()[free, 0]
    if slip:
        assert dF < 1e-12, dF
        assert np.abs(vx - 2.0).max() < 1e-10, np.abs(vx - 2.0).max()
    else:
        assert dF > 0.5, dF
        assert vx.mean() < 1.8, vx.mean()


def test_ghost_floor_refuses_a_material_changed_to_the_paper_force_at_the_next_step():
    """``Model.set_material`` after the solver was made: the step refuses by name."""
    model = _model(requires_grad=False)
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    solver.step(a, c, DT)
    model.set_material(0, model.materials[0].replace(elastic_force="paper"))
    with pytest.raises(ValueError, match=r"Material.elastic_force = \['paper'\] is not allowed with a ghost floor"):
        solver.step(c, a, DT)


def _expected_stencils(model, x):
    """Each ghost's stencil rows from the positions ``x`` (numpy): the free particles within
    ``rs`` of its mirror point, or on a slip floor within the fill's ``reach`` where the
    stencil's weight is below ``MIN_TOTAL + SWITCH`` (``stencil_fill`` > 0 exactly there), and
    how many lie within each radius. ``near`` is None where a distance or the weight is
    within round-off of a threshold."""
    from warp_esph.sim import ghost_floor as G

    g = model.ghost_floor
    free = np.flatnonzero(g.slot.numpy() < 0)
    out = []
    for k, off, slip in zip(g.floor.numpy(), g.offset.numpy(), g.slip.numpy()):
        p = np.array([x[k, 0], 2.0 * off - x[k, 1], x[k, 2]])
        d2 = ((x[free] - p) ** 2).sum(axis=1)
        near = d2 < g.radius**2
        wide = d2 < g.reach**2
        total = ((1.0 - d2[near] / g.radius**2) ** 3).sum()
        ties = (np.abs(d2 - g.radius**2).min() < 1e-12 or np.abs(d2 - g.reach**2).min() < 1e-12
                or abs(total - (G.MIN_TOTAL + G.SWITCH)) < 1e-12)
        filled = slip and total < G.MIN_TOTAL + G.SWITCH
        out.append((set(free[wide if filled else near].tolist()), int(near.sum()), int(wide.sum()), bool(filled), ties))
    return out


@pytest.mark.parametrize("width", [None, 8])
def test_slip_ghost_stencil_rows_hold_the_stencil_or_the_fill_and_a_full_row_is_counted(width):
    """The slip ghosts' stencil rows are exactly the free particles within the stencil radius
    ``rs`` of the mirror point, or within the fill's ``reach`` where the stencil is not full,
    as searched from the step's start (one grid query at ``reach``, kept to ``rs`` where the
    stencil is full). With rows narrower than a filled stencil (8, forced: the floor's rows
    are as wide as a neighbour row), a row is counted as cut (``neighbors_cut``) exactly
    where its own set does not fit: a filled stencil past 8 within ``reach``, a full one
    never (it holds about 7 within ``rs``, though more than 8 lie within ``reach``), and a
    full one keeps all its own; the cut warns."""
    model = _model(slide=2.0, slip=True, requires_grad=False)
    if width is not None:
        model.ghost_floor.rows = width
    rows = model.ghost_floor.rows
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    seen = {"filled": 0, "full past the row": 0, "cut": 0}
    with pytest.warns(RuntimeWarning, match="a neighbour row was cut") if width else contextlib.nullcontext():
        for _ in range(STEPS):
            before = solver.guard_counts()["neighbors_cut"]
            x = a.x.numpy()
            solver.step(a, c, DT)
            expected = _expected_stencils(model, x)
            cj, cc = c.ghost_rows.numpy(), c.ghost_count.numpy()
            cut = 0
            for t, (kept, n_near, n_wide, filled, ties) in enumerate(expected):
                assert not ties
                got = cj[t, :cc[t]].tolist()
                assert len(set(got)) == len(got) == min(len(kept), rows) and set(got) <= kept, t
                cut += len(kept) > rows
                seen["filled"] += filled and n_wide > 0
                seen["full past the row"] += (not filled) and n_near <= rows < n_wide
            seen["cut"] += cut
            assert solver.guard_counts()["neighbors_cut"] - before == cut
            a, c = c, a
    assert seen["filled"] > 0, seen
    if width is not None:
        assert seen["cut"] > 0 and seen["full past the row"] > 0, seen


def _mirror_step(rs: float | None):
    """One step of the S = 0.2 slump's cylinder (4 across, float64, no viscosity: the floor's
    pinned particles would drag where the mirror's move) from its lattice, strained (F up to
    4 % from I, so the elastic forces act through the ghosts) and with a non-affine velocity
    field, on the slip ghost floor under its footprint alone (``rs``: the stencil radius in
    spacings, None: the default) and as the upper half of ``validation``'s ``floor="mirror"``
    (its mirror image under gravity towards the plane, ``_Mirror``): ``(x, v, F on the
    floor, the same in the mirror's upper half, F at the start)``."""
    from benchmarks import validation

    kw = {"viscosity": 0.0, "dtype": wp.float64}
    ghost, free, _, _ = validation.slump_model(0.2, 4, floor="slip_ghost_particles", floor_radius=1.0, **kw)
    mirror, upper, _, _ = validation.slump_model(0.2, 4, floor=validation.MIRROR, **kw)
    n = int(upper.sum())
    assert np.array_equal(ghost.particle_x0[free], mirror.particle_x0[upper])
    # Under the footprint the floor's two layers are where the mirror image's lowest two are.
    assert ghost.ghost_floor.count == 2 * n // 4
    if rs is not None:
        ghost.ghost_floor.radius = rs * ghost.spacing
    rng = np.random.default_rng(3)
    v = rng.normal(scale=0.02, size=(n, 3))
    F0 = np.eye(3) + rng.uniform(-0.04, 0.04, size=(n, 3, 3))
    flip = np.array([1.0, -1.0, 1.0])
    vg = np.zeros_like(ghost.particle_x0)
    vg[free] = v
    ghost.particle_v0 = vg
    mirror.particle_v0 = np.concatenate([v, v * flip])
    dt = 2e-4
    out = []
    for model, step_in in ((ghost, None), (mirror, validation._Mirror(mirror, n))):
        solver = we.Solver(model)
        a, b = model.state(), model.state()
        keep = free if model is ghost else upper
        F = a.F.numpy()
        F[keep] = F0
        a.F.assign(F)
        if step_in is not None:
            step_in(a, validation.G, dt)  # the lower half's F := R F R, and gravity
        solver.step(a, b, dt)
        out += [b.x.numpy()[keep], b.v.numpy()[keep], b.F.numpy()[keep]]
    return (*out, F0)


@pytest.mark.parametrize("rs", [1.0, None])
def test_slip_ghost_floor_steps_as_the_mirror_image_from_the_lattice(rs):
    """The slip ghost floor against an exact frictionless wall of the method's own bulk, the
    cylinder's mirror image (``validation.slump(floor="mirror")``): from the lattice, where
    each ghost stands where the mirror places the particle it continues, one step with a
    non-affine velocity field gives every free particle the mirror's x, v and F to
    round-off with a stencil of one spacing (each ghost follows exactly the particle at its
    mirror point, and the hand-over gives each particle the force of its images' energies).
    The default 1.2-spacing stencil's Shepard average mixes in that particle's neighbours:
    the F increments are off by 0.36 % of the largest here (0.97 % from F = I), the order of
    its 1.25 % in an affine motion; in a flowing packing the pinned ghosts also stand off the
    mirror's places, which costs far more (docs/physics.md, "The slip ghost floor")."""
    xg, vg, Fg, xm, vm, Fm, F0 = _mirror_step(rs)
    inc = np.abs(Fm - F0).max()
    assert inc > 1e-4  # the step deforms the lattice
    off = np.abs(Fg - Fm).max() / inc
    if rs == 1.0:
        assert np.abs(xg - xm).max() < 1e-14 and np.abs(vg - vm).max() < 1e-10, (np.abs(xg - xm).max(), np.abs(vg - vm).max())
        assert off < 1e-9, off
    else:
        assert 0.001 < off < 0.03, off
