"""Gradients of whole rollouts through ``wp.Tape`` against float64 central differences.

A small block starts at rest in F (F = I: every singular value repeated) with a
stretching velocity field, yields during the rollout, and the loss is a weighted sum
of final positions, which reaches every material parameter."""

import dataclasses
import functools

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from taped_loss import random_weights, taped_gradients, taped_rollout_loss, untaped_rollout_loss
from warp_esph.sim.guards import COUNT_FADE
from warp_esph.sim.neighbors import MIN_NEIGHBORS
from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS


STEPS = 5
DT = 1.0e-3
ALPHA0 = 0.02

#: A relative step of a parameter large enough that a jump of the loss within it would show
#: in a central difference, and the tolerance there (the loss's curvature: measured 7e-5 and
#: below at 1e-2 on the moving block's paths, 1.3e-4 on the comparison models' under either fit
#: weight), beside the small step of each check.
LARGE_STEP = (1e-2, 1e-3)

#: The fit weight a model gets only by name (poly6, the paper's eq. 7, since the biweight became
#: the default). ``_model`` and ``_images_model`` build poly6 unless told, the weight most bounds
#: here were measured with; the tests that name ``DEFAULT_FIT_WEIGHT`` run the default.
(OTHER_FIT_WEIGHT,) = (w for w in FIT_WEIGHTS if w != DEFAULT_FIT_WEIGHT)


def _model(params=None, velocity_scale=20.0, fit_weight="poly6", field=False, ground=None):
    # pressure_stiffness fixed: its default follows mu and lam, which would make the
    # finite difference in mu also move the pressure.
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "hardening": 200.0, "pressure_stiffness": 1.0,
         "viscosity": 2.0}
    p.update(params or {})
    mat = we.Material(density=1000.0, **p)
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.08, 0.08), mat)
    if field:  # a horizontal squeeze towards a point off the block's centre
        b.add_compression_field((0.01, 0.0, 0.005), 400.0)
    if ground is not None:
        b.add_ground(ground, friction=0.5)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    # A slightly jittered lattice: exact distance ties make the 30-nearest selection (a
    # discrete choice) flip under a finite-difference perturbation.
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    x0 = model.particle_x0
    # Stretch along x, squeeze along y: deviatoric, so the block yields within a few steps.
    model.particle_v0 = velocity_scale * x0 * np.array([1.0, -0.5, 0.0])
    return model


def _rollout_loss(model, weights, grad_of=(), fit="linear", hand_adjoints=True, hourglass=0.0, min_neighbors=6,
                  fused=True):
    solver = we.Solver(model, fit=fit, hourglass=hourglass, min_neighbors=min_neighbors, fused=fused)
    solver.hand_adjoints = hand_adjoints
    untaped = not grad_of and hand_adjoints  # a central difference's run: no tape
    states = [model.state(requires_grad=False)] if untaped else [model.state() for _ in range(STEPS + 1)]
    # A pre-worked material (alpha > 0), so the loss reaches the hardening modulus.
    states[0].alpha.fill_(ALPHA0)
    if untaped:
        return untaped_rollout_loss(solver, states[0], DT, STEPS, weights, forward_only=False), solver
    loss, tape = taped_rollout_loss(solver, states, DT, weights)
    if not grad_of:
        return loss.numpy()[0], solver
    tape.backward(loss)
    grads = {}
    for name in grad_of:
        arr = states[0].v if name == "v0" else states[0].x if name == "x0" else getattr(model, name)
        grads[name] = arr.grad.numpy().copy()
    return loss.numpy()[0], grads


def _reused(model):
    """``at(name, value)``: ``model`` with ``name`` set to ``value`` in each material that holds
    its built value (``Model.set_materials``), so that a test's central differences build their
    model once: a run from a model another run left, its materials set, is a new model's to
    the bit (measured on every case of ``AT_REST`` and of ``test_gradient_coverage.py``)."""
    materials = list(model.materials)

    def at(name, value):
        base = getattr(materials[0], name)
        model.set_materials([mt.replace(**{name: value}) if getattr(mt, name) == base else mt for mt in materials])
        return model

    return at


@pytest.fixture(scope="module")
def weights():
    n = _model().particle_count
    return random_weights(n, 0)


def _v0_central_difference(m, weights, i, comp, eps=1e-6, **kwargs):
    """The rollout loss's central difference in particle ``i``'s initial velocity along
    ``comp`` (step ``eps`` m/s), on one model ``m`` whose initial velocities are set before
    each run and restored after; ``kwargs`` go to ``_rollout_loss``."""
    v0 = m.particle_v0.copy()
    losses = []
    for delta in (eps, -eps):
        m.particle_v0 = v0.copy()
        m.particle_v0[i, comp] += delta
        losses.append(_rollout_loss(m, weights, **kwargs)[0])
    m.particle_v0 = v0
    return (losses[0] - losses[1]) / (2 * eps)


def test_material_gradient_matches_central_differences(weights):
    """The tape's gradient in each material parameter (one taped run's) against its float64
    central difference at a relative step of 1e-5."""
    model = _model()
    names = ("mu", "yield_stress", "lam", "flow_rate", "hardening", "pressure_stiffness", "viscosity")
    _, grads = _rollout_loss(model, weights, grad_of=names)
    at = _reused(_model())
    for name in names:
        base = getattr(model.materials[0], name)
        eps = 1e-5 * abs(base)
        fd = (_rollout_loss(at(name, base + eps), weights)[0] - _rollout_loss(at(name, base - eps), weights)[0]) / (2 * eps)
        # Central-difference noise here is ~1e-13; a loss that did not reach the parameter
        # would give exactly 0 or noise.
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), name


@pytest.mark.parametrize("deformation, fit_weight",
                         [(d, DEFAULT_FIT_WEIGHT) for d in ("rest", "additive", "rest_variational", "rest_variational_corrected")]
                         + [("rest_variational_corrected", OTHER_FIT_WEIGHT)])
def test_comparison_models_gradients_match_central_differences(weights, deformation, fit_weight):
    """The Fig. 8 comparison kernels (``comparison.py``; the additive model's flow its own,
    hardening included) are differentiable too, and so is the
    rest model's variational force (``rest_variational``: its hand-written adjoint), also
    with the curvature-corrected total fit (``..._corrected``): the gradients in ``mu``, the
    yield stress, the flow rate and the hardening (one taped run's) at a relative step of 1e-5
    and at ``LARGE_STEP``, on the moving (yielding) block, with the default fit weight. The
    other weight: here on the plastic rest model's corrected total fit, which no other test
    takes; ``test_gradient_coverage.py``'s ``other_weight_*`` cases on the rest model (either
    force) and the additive one, thrown. Measured (CPU, float64), the largest relative error of
    the biweight's 16 gradients 9.7e-6 at 1e-5 and 1.3e-4 at 1e-2 (poly6's 3.5e-5 and 1.1e-4)."""
    p = {"deformation": deformation}
    if deformation.startswith("rest_variational"):
        p = {"deformation": "rest", "elastic_force": "variational"}
    fit = "curvature_corrected" if deformation.endswith("corrected") else "linear"
    model = _model(p, fit_weight=fit_weight)
    assert model.fit_weight == fit_weight
    names = ("mu", "yield_stress", "flow_rate", "hardening")
    _, grads = _rollout_loss(model, weights, grad_of=names, fit=fit)
    at = _reused(_model(p, fit_weight=fit_weight))
    for name in names:
        base = getattr(model.materials[0], name)
        for rel, tol in ((1e-5, 1e-4), LARGE_STEP):
            eps = rel * abs(base)
            plus = _rollout_loss(at(name, base + eps), weights, fit=fit)[0]
            minus = _rollout_loss(at(name, base - eps), weights, fit=fit)[0]
            fd = (plus - minus) / (2 * eps)
            assert abs(fd) > 1e-11, f"the loss does not reach {name}"
            assert grads[name][0] == pytest.approx(fd, rel=tol, abs=0.0), (name, rel)


#: Relative steps of the central differences below: 1e-5, but larger where the loss reaches
#: a parameter weakly enough that the round-off of a smaller step shows (the spiky pressure's
#: stiffness: 2e-5 of the difference at 1e-5, 7e-6 at 1e-4, 8e-4 at 1e-6).
REL_STEP = {"non_newtonian": 1e-3, "spiky_pressure": 1e-4}

#: The constitutive models, pressure force, schedule and force field the tests above do not
#: take: (material options, ``_model``'s ``field``, ``Solver(fused=)``).
_OTHER_PATHS = {
    "stvk": ({"model": "stvk"}, False, True),
    "hyperelastic": ({"model": "hyperelastic"}, False, True),
    "non_newtonian": ({"model": "non_newtonian", "flow_rate": 500.0}, False, True),
    "spiky_pressure": ({"pressure_force": "spiky"}, False, True),
    "unfused_paper": ({"elastic_force": "paper"}, False, False),
    "unfused_variational": ({}, False, False),
    "compression_field": ({}, True, True),
}


#: The parameters each of ``_OTHER_PATHS`` is checked in (one taped run's gradients).
_OTHER_PATH_NAMES = {"stvk": ("mu", "yield_stress"), "hyperelastic": ("mu", "lam"),
                     "non_newtonian": ("yield_stress", "flow_rate"), "spiky_pressure": ("pressure_stiffness", "viscosity"),
                     "unfused_paper": ("mu",), "unfused_variational": ("mu", "flow_rate", "hardening"),
                     "compression_field": ("mu",)}


@pytest.mark.parametrize("path", list(_OTHER_PATH_NAMES))
def test_other_models_pressure_forces_schedules_and_fields_gradients_match_central_differences(weights, path):
    """The other stress models (St. Venant-Kirchhoff, the hyperelastic one, the
    non-Newtonian flow rule), the spiky pressure force, the non-fused step (its hand-written
    adjoints recorded one kernel at a time) and a force field, on the same yielding rollout
    from F = I: the tape against float64 central differences, at a small step and at
    ``LARGE_STEP``, in each of ``_OTHER_PATH_NAMES``."""
    params, field, fused = _OTHER_PATHS[path]
    names = _OTHER_PATH_NAMES[path]
    model = _model(params, field=field)
    _, grads = _rollout_loss(model, weights, grad_of=names, fused=fused)
    at = _reused(_model(params, field=field))
    for name in names:
        base = getattr(model.materials[0], name)
        for rel, tol in ((REL_STEP.get(path, 1e-5), 1e-4), LARGE_STEP):
            eps = rel * abs(base)
            plus = _rollout_loss(at(name, base + eps), weights, fused=fused)[0]
            minus = _rollout_loss(at(name, base - eps), weights, fused=fused)[0]
            fd = (plus - minus) / (2 * eps)
            assert abs(fd) > 1e-11, f"the loss does not reach {name}"
            assert grads[name][0] == pytest.approx(fd, rel=tol, abs=0.0), (name, rel)


def _contact_model(case, mu=(1.0e3, 2.0e3)):
    """``"bodies"``: a yielding block thrown against an elastic one (two materials; their
    SPH pressure and viscosity act across the gap); ``"mixed_forces"``: the same with the
    elastic block under the paper's force (eqs. 10-13), so one taped step runs both elastic
    forces' adjoints, each for its own particles; ``"elastic_on_ground"``: an elastic
    block landing sideways on the rough ground, which the default solver runs with the
    curvature-corrected fit and the hourglass control."""
    dx = 0.02
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -9.81, 0.0))
    soft = we.Material(density=1000.0, mu=mu[0], lam=1.5e3, yield_stress=10.0, flow_rate=50.0, pressure_stiffness=1.0,
                       viscosity=2.0)
    hard = we.Material(density=1000.0, mu=mu[1], lam=3.0e3, pressure_stiffness=1.0, viscosity=2.0,
                       elastic_force="paper" if case == "mixed_forces" else None)
    if case in ("bodies", "mixed_forces"):
        b.add_box((-0.041, 0.0, 0.0), (3 * dx, 4 * dx, 4 * dx), soft, name="soft", velocity=(1.0, 0.0, 0.1))
        b.add_box((0.041, 0.005, 0.003), (3 * dx, 4 * dx, 4 * dx), hard, name="hard")
    else:
        b.add_box((0.0, 0.045, 0.0), (5 * dx, 4 * dx, 4 * dx), hard, name="hard", velocity=(0.4, -1.0, 0.0))
        b.add_ground(friction=0.6)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * dx, size=model.particle_x0.shape)
    return model


def _contact_loss(model, weights, steps, grad=False):
    solver = we.Solver(model)
    if not grad:  # a central difference's run: no tape
        return untaped_rollout_loss(solver, model.state(requires_grad=False), DT, steps, weights, forward_only=False)
    states = [model.state() for _ in range(steps + 1)]
    loss, tape = taped_rollout_loss(solver, states, DT, weights)
    tape.backward(loss)
    return loss.numpy()[0], model.mu.grad.numpy().copy(), states[-1]


@pytest.mark.parametrize("case", ["bodies", "mixed_forces", "elastic_on_ground"])
def test_gradients_through_contact_between_bodies_and_of_the_default_elastic_solver_match_central_differences(case):
    """Each material's shear modulus through a rollout in which two bodies of different
    materials meet (also of different elastic forces), and through an elastic block's
    landing on the ground under the default solver (the corrected fit and the hourglass
    control, through the contact law): the tape against float64 central differences."""
    steps = 30 if case == "elastic_on_ground" else 20
    model = _contact_model(case)
    w = random_weights(model.particle_count, 1)
    _, g, last = _contact_loss(model, w, steps, grad=True)
    if case != "elastic_on_ground":  # the elastic block was pushed: the bodies met
        hard = model.particle_body.numpy() == 1
        assert last.v.numpy()[hard, 0].mean() > 0.02
    else:  # it landed
        assert np.abs(last.collider_force.numpy()).max() > 0.0
        assert model.solver_choice() == ("curvature_corrected", we.model.AUTO_HOURGLASS)
    for k in range(len(model.materials)):
        mu = [m.mu for m in model.materials]
        vals = []
        for sign in (1, -1):
            moved = list(mu)
            moved[k] *= 1.0 + sign * 1e-5
            vals.append(_contact_loss(_contact_model(case, (1.0e3, moved[0]) if case == "elastic_on_ground" else tuple(moved)),
                                      w, steps))
        fd = (vals[0] - vals[1]) / (2e-5 * mu[k])
        print(case, k, g[k], fd, abs(g[k] / fd - 1))
        assert abs(fd) > 1e-11, k
        assert g[k] == pytest.approx(fd, rel=1e-4, abs=0.0), k


def test_rollout_yields_and_guards_stay_quiet(weights):
    """The gradient setup exercises plastic flow (alpha grows) and no guard fires."""
    model = _model()
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    a.alpha.fill_(ALPHA0)
    for _ in range(STEPS):
        solver.step(a, b, DT)
        a, b = b, a
    assert a.alpha.numpy().max() > ALPHA0
    assert solver.guard_counts()["inverted"] == 0


@pytest.mark.parametrize("elastic_force", ["paper", "variational"])
def test_initial_velocity_gradient(weights, elastic_force):
    model = _model({"elastic_force": elastic_force})
    _, grads = _rollout_loss(model, weights, grad_of=("v0",))
    rng = np.random.default_rng(3)
    for i, c in zip(rng.integers(0, model.particle_count, 3), rng.integers(0, 3, 3)):
        def loss_with(delta):
            m = _model({"elastic_force": elastic_force})
            m.particle_v0[i, c] += delta
            return _rollout_loss(m, weights)[0]

        fd = (loss_with(1e-6) - loss_with(-1e-6)) / 2e-6
        assert grads["v0"][i, c] == pytest.approx(fd, rel=1e-4, abs=1e-9)


@pytest.mark.parametrize("name", ["mu", "lam", "yield_stress", "hardening"])
def test_variational_force_gradients_match_central_differences(weights, name):
    """The variational elastic force (``forces.py``: the fit's moment matrix inverted per
    particle, its weights per pair) is differentiable too, from F = I, with the default fit
    weight (poly6's: ``test_material_gradient...``, in these and more)."""
    def make(params=None):
        return _model({"elastic_force": "variational", **(params or {})}, fit_weight=DEFAULT_FIT_WEIGHT)

    model = make()
    assert model.fit_weight == DEFAULT_FIT_WEIGHT
    _, grads = _rollout_loss(model, weights, grad_of=(name,))
    base = getattr(model.materials[0], name)
    eps = 1e-5 * abs(base)
    plus = _rollout_loss(make({name: base + eps}), weights)[0]
    minus = _rollout_loss(make({name: base - eps}), weights)[0]
    fd = (plus - minus) / (2 * eps)
    assert abs(fd) > 1e-11, f"the loss does not reach {name}"
    assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0)


def _clamped_flows(params) -> tuple[int, int]:
    """(particle-steps whose flow fraction saturated at 1, particle-steps that flowed) in the
    rollout of ``_model(params)``: a saturated flow leaves equal singular values (F_e = c R)."""
    model = _model(params)
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    a.alpha.fill_(ALPHA0)
    clamped = flowed = 0
    for _ in range(STEPS):
        solver.step(a, b, DT)
        s_in = np.linalg.svd(a.F.numpy(), compute_uv=False)
        s_out = np.linalg.svd(b.F_flowed.numpy(), compute_uv=False)
        moved = np.abs(s_out - s_in).max(axis=1) > 1e-12
        flowed += int(moved.sum())
        clamped += int((moved & (np.ptp(s_out, axis=1) < 1e-12 * s_out.max(axis=1))).sum())
        a, b = b, a
    return clamped, flowed


@pytest.mark.parametrize("elastic_force", ["paper", "variational"])
@pytest.mark.parametrize("rate_dt", [0.5, 1.0, 2.0])
def test_gradient_across_the_saturated_flow_step(weights, elastic_force, rate_dt):
    """``gamma = min(flow_rate dt (|s| - Y) / |s|, 1)`` (plasticity.flow_fraction): at
    ``flow_rate * dt = 2`` some particles saturate (gamma = 1, a full return: their flow no
    longer depends on flow_rate or Y) and others do not; at 0.5 and 1.0 none can. The
    taped gradients of flow_rate and yield_stress match central differences in every case,
    and at the kink both one-sided differences agree with it too."""
    params = {"elastic_force": elastic_force, "flow_rate": rate_dt / DT}
    clamped, flowed = _clamped_flows(params)
    assert flowed > 0
    if rate_dt < 1.0 + 1e-12:
        assert clamped == 0
    else:
        assert 0 < clamped < flowed, (clamped, flowed)
    for name in ("flow_rate", "yield_stress"):
        base = params.get(name, 10.0)
        value, grads = _rollout_loss(_model(params), weights, grad_of=(name,))
        eps = 1e-6 * base
        plus = _rollout_loss(_model({**params, name: base + eps}), weights)[0]
        minus = _rollout_loss(_model({**params, name: base - eps}), weights)[0]
        fd = (plus - minus) / (2 * eps)
        assert abs(fd) > 1e-12, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), name
        for one_sided in ((plus - value) / eps, (value - minus) / eps):
            assert grads[name][0] == pytest.approx(one_sided, rel=1e-3), name


@pytest.mark.parametrize("names, elastic_force", [(("mu", "yield_stress", "v0"), "variational"), (("mu",), "paper")],
                         ids=["variational", "paper"])
def test_curvature_corrected_fit_gradients_match_central_differences(weights, names, elastic_force):
    """``Solver(fit="curvature_corrected")`` (``curvature.py``): the hand-written adjoints of
    its deformation update and its elastic force (``variational_forces_adjoint``; eqs. 10-13:
    ``forces.elastic_forces_adjoint``) against central differences, and against Warp's
    generated adjoints, in ``names`` (one taped run's)."""
    params = {"elastic_force": elastic_force}
    model = _model(params)
    _, grads = _rollout_loss(model, weights, grad_of=names, fit="curvature_corrected")
    _, generated = _rollout_loss(_model(params), weights, grad_of=names, fit="curvature_corrected", hand_adjoints=False)
    for name in names:
        np.testing.assert_allclose(grads[name], generated[name], rtol=1e-8, atol=1e-12 * np.abs(generated[name]).max(),
                                   err_msg=name)
        if name == "v0":
            i, c = 7, 1
            fd = _v0_central_difference(_model(params), weights, i, c, fit="curvature_corrected")
            assert grads["v0"][i, c] == pytest.approx(fd, rel=1e-4, abs=1e-9)
            continue
        base = getattr(model.materials[0], name)
        eps = 1e-5 * abs(base)
        at = _reused(_model(params))
        plus = _rollout_loss(at(name, base + eps), weights, fit="curvature_corrected")[0]
        minus = _rollout_loss(at(name, base - eps), weights, fit="curvature_corrected")[0]
        fd = (plus - minus) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4), name


def _hourglass_model(params=None, **kw):
    """The variational block with a random velocity on top of the stretch: non-affine, so
    the hourglass control (which an affine motion does not see) acts (``kw``: ``_model``'s)."""
    m = _model({"elastic_force": "variational", **(params or {})}, **kw)
    m.particle_v0 = m.particle_v0 + np.random.default_rng(11).normal(scale=0.05, size=m.particle_v0.shape)
    return m


@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
def test_hourglass_control_gradients_match_central_differences(weights):
    """``Solver(hourglass=c)`` (``hourglass.py``, Warp's generated adjoint; it reads the
    stored F and mu) against central differences in ``mu`` and an initial velocity (one taped
    run's), with a control strong enough to move the loss."""
    c = 0.5
    loss_on = _rollout_loss(_hourglass_model(), weights, hourglass=c)[0]
    loss_off = _rollout_loss(_hourglass_model(), weights)[0]
    assert abs(loss_on - loss_off) > 1e-6 * abs(loss_off), (loss_on, loss_off)
    _, grads = _rollout_loss(_hourglass_model(), weights, grad_of=("mu", "v0"), hourglass=c)
    i, comp = 7, 1
    fd = _v0_central_difference(_hourglass_model(), weights, i, comp, hourglass=c)
    assert grads["v0"][i, comp] == pytest.approx(fd, rel=1e-4, abs=1e-9)
    base = _model().materials[0].mu
    eps = 1e-5 * base
    plus = _rollout_loss(_hourglass_model({"mu": base + eps}), weights, hourglass=c)[0]
    minus = _rollout_loss(_hourglass_model({"mu": base - eps}), weights, hourglass=c)[0]
    fd = (plus - minus) / (2 * eps)
    assert grads["mu"][0] == pytest.approx(fd, rel=1e-4)


#: A block of 3 x 10 x 3 particles squashed to F = diag(1.7, 0.4, 1.7), positions and F
#: alike, and moving: rows reach h sigma_max(F) = 1.7 h (the paper's force; a comparison
#: model). There, 42 particles have more than ``KEYED_WIDTH`` others (up to the whole block),
#: of which at most 41 are weighed by a kernel of the step (closer than h now, at
#: F^-1 (x_j - x_i), or at rest). The 48 nearest would lack weighed pairs: those one spacing
#: apart along both x and z (0.71 h at rest), 1.2 h apart now.
KEYED_F0 = np.diag([1.7, 0.4, 1.7])
KEYED_WIDTH = 48
#: (material options, parameter differentiated).
KEYED_CASES = {"paper": ({"elastic_force": "paper"}, "mu"), "rest_model": ({"deformation": "rest"}, "lam")}


def _keyed_rollout(case, max_neighbors=KEYED_WIDTH, params=None, grad=False):
    """The squashed block's 6 taped steps of 1e-5 s: ``(loss, neighbors_cut, rows, grad)``,
    ``rows`` each step's (neighbour rows, counts), ``grad`` the loss's in the case's parameter."""
    options, name = KEYED_CASES[case]
    p = {"mu": 3.8e4, "lam": 5.8e4, "pressure_stiffness": 1.0, **options, **(params or {})}
    b = we.SceneBuilder(spacing=0.02, max_neighbors=max_neighbors)
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.2, 0.06), we.Material(density=1000.0, **p))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    X = model.particle_x0 + np.random.default_rng(3).normal(scale=2e-5, size=model.particle_x0.shape)
    model.particle_x0 = X  # the rest positions the rest model weighs
    solver = we.Solver(model)
    states = [model.state() for _ in range(7)]
    states[0].x.assign(X @ KEYED_F0.T)
    states[0].F.assign(np.tile(KEYED_F0, (model.particle_count, 1, 1)))
    states[0].v.assign(20.0 * (X - X.mean(0)) * np.array([0.5, -0.3, 0.2]))
    loss, tape = taped_rollout_loss(solver, states, 1.0e-5, random_weights(model.particle_count, 4))
    rows = [(s.neighbors.numpy(), s.neighbor_count.numpy()) for s in states[1:]]
    g = None
    if grad:
        tape.backward(loss)
        g = getattr(model, name).grad.numpy()[0]
    return loss.numpy()[0], solver.guard_counts()["neighbors_cut"], rows, g


@pytest.mark.parametrize("case", sorted(KEYED_CASES))
def test_gradients_through_full_keyed_rows_match_central_differences(case):
    """Rows reaching h sigma_max(F) that overflow keep the pairs some kernel weighs first
    (``neighbors.weight_key``) and drop only unweighed ones; the tape records those rows and
    its backward pass replays them. Every taped step has full rows short of particles within
    their reach (the same rollout at the default width holds them, the narrow rows among
    them), none is counted cut, the loss and the tape's gradient are those of the wide rows
    to round-off, and the gradient is that of central differences. Rows of the 48 nearest
    (dropping weighed pairs) moved the loss by 8e-6 and its gradient by 2 %; a backward pass
    that replayed those behind the keyed forward put the gradient 2 % off central differences."""
    name = KEYED_CASES[case][1]
    loss, cut, rows, g = _keyed_rollout(case, grad=True)
    wide_loss, wide_cut, wide_rows, wide_g = _keyed_rollout(case, max_neighbors=None, grad=True)
    for (nbr, cnt), (wide_nbr, wide_cnt) in zip(rows, wide_rows):
        over = wide_cnt > KEYED_WIDTH
        assert over.any() and (cnt[over] == KEYED_WIDTH).all(), "every step has full rows"
        assert (cnt[~over] == wide_cnt[~over]).all()
        for i in range(len(cnt)):
            assert set(nbr[i, :cnt[i]]) <= set(wide_nbr[i, :wide_cnt[i]]), i
    assert cut == 0 and wide_cut == 0
    assert loss == pytest.approx(wide_loss, rel=1e-13, abs=0.0)
    assert g == pytest.approx(wide_g, rel=1e-10, abs=0.0)
    base = 3.8e4 if name == "mu" else 5.8e4
    for rel, tol in ((1e-5, 1e-4), LARGE_STEP):
        eps = rel * base
        fd = (_keyed_rollout(case, params={name: base + eps})[0] - _keyed_rollout(case, params={name: base - eps})[0]) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert g == pytest.approx(fd, rel=tol, abs=0.0), rel


def _energy_spiky_model(case, params=None):
    """The block with the ``energy_spiky`` pressure force (``docs/method.md §6``): ``rest``,
    at rest under gravity with the pressure clamp off (so the pressure answers both ways
    from the rest density); ``merging``, its two middle layers (``y = -/+ dx/2``) moved to 0.2
    spacing of each other and closing at 0.5 m/s, where the spiky density's slope, finite
    at ``r = 0``, carries the push."""
    p = {"pressure_force": "energy_spiky", "clamp_pressure": case != "rest", **(params or {})}
    model = _model(p, velocity_scale=0.0)
    if case == "merging":
        x0 = model.particle_x0
        y = x0[:, 1]
        middle = np.abs(np.abs(y) - 0.01) < 0.002
        x0[middle, 1] -= np.sign(y[middle]) * 0.008
        model.particle_x0 = x0
        v0 = np.zeros_like(x0)
        v0[middle, 1] = -0.5 * np.sign(y[middle])
        model.particle_v0 = v0
    return model


@pytest.mark.parametrize("case", ["rest", "merging"])
def test_energy_spiky_pressure_gradients_match_central_differences(weights, case):
    """``pressure_force = "energy_spiky"``: the hand-written adjoints of the spiky density
    and of its energy pair force (``pressure.density_adjoint``, ``pressure_forces_adjoint``)
    against float64 central differences, at rest and with two particle layers merging, with
    viscosity on: its volumes come from the poly6 SPH density (``State.density``), the
    pressure from the spiky one (``State.pressure_density``), so both densities' adjoints
    carry the gradient. In the pressure stiffness, the viscosity and a particle's initial
    velocity (one taped run's)."""
    model = _energy_spiky_model(case)
    names = ("pressure_stiffness", "viscosity")
    loss, grads = _rollout_loss(model, weights, grad_of=(*names, "v0"))
    i = int(np.flatnonzero(np.abs(np.abs(model.particle_x0[:, 1]) - 0.002) < 0.001)[0]) if case == "merging" else 7
    m = _energy_spiky_model(case)
    for comp in (0, 1):
        fd = _v0_central_difference(m, weights, i, comp)
        assert grads["v0"][i, comp] == pytest.approx(fd, rel=1e-4, abs=1e-9), comp
    for name in names:
        base = getattr(model.materials[0], name)
        # 1e-4, not 1e-5: at rest the loss (0.2) moves by 7e-13 over +-1e-5 of the viscosity,
        # and the round-off of two float64 losses is then 1e-4 of the difference (measured:
        # the quotient moves by 1.6e-4 when F's round-off is carried, State.F_lo, the tape by 2e-12).
        eps = 1e-4 * base
        at = _reused(_energy_spiky_model(case))
        fd = (_rollout_loss(at(name, base + eps), weights)[0] - _rollout_loss(at(name, base - eps), weights)[0]) / (2 * eps)
        assert abs(fd) > 1e-9, "the loss does not reach " + name
        assert grads[name][0] == pytest.approx(fd, rel=1e-4), name


@pytest.mark.parametrize("fused", [True, False])
def test_pair_repulsion_gradients_match_central_differences(weights, fused):
    """``Material.pair_repulsion`` (``pressure.pair_repulsion_force``; its hand-written adjoint
    in ``pressure.pressure_pair_adjoint``, which both the fused step's adjoint pass and
    ``pressure_forces_adjoint`` run): the ``merging`` block of the test above with
    ``pair_repulsion = 2``, its two middle layers 0.2 dx apart, inside the repulsion's range
    ``r0 = h / 4 = 0.5 dx``, and closing. The tape's gradients in ``k_p`` (which scales the
    repulsion), the viscosity and a merging particle's initial velocity against float64
    central differences."""
    params = {"pair_repulsion": 2.0}
    model = _energy_spiky_model("merging", params)
    names = ("pressure_stiffness", "viscosity")
    loss, grads = _rollout_loss(model, weights, grad_of=(*names, "v0"), fused=fused)
    assert loss != _rollout_loss(_energy_spiky_model("merging"), weights, fused=fused)[0], "the repulsion acts"
    i = int(np.flatnonzero(np.abs(np.abs(model.particle_x0[:, 1]) - 0.002) < 0.001)[0])
    m = _energy_spiky_model("merging", params)
    for comp in (0, 1):
        fd = _v0_central_difference(m, weights, i, comp, fused=fused)
        assert grads["v0"][i, comp] == pytest.approx(fd, rel=1e-4, abs=1e-9), comp
    for name in names:
        base = getattr(model.materials[0], name)
        eps = 1e-4 * base
        at = _reused(_energy_spiky_model("merging", params))
        fd = (_rollout_loss(at(name, base + eps), weights, fused=fused)[0]
              - _rollout_loss(at(name, base - eps), weights, fused=fused)[0]) / (2 * eps)
        assert abs(fd) > 1e-9, "the loss does not reach " + name
        assert grads[name][0] == pytest.approx(fd, rel=1e-4), name


#: (parameter at 0, the other SPH parameter's value, pressure force, ``Solver(fused=)``): both at 0,
#: where the step ran no SPH term at all, and the stiffness alone at 0 beside a viscosity,
#: where the clamp of each pressure force held every pressure at 0.
SPH_AT_ZERO = {
    "stiffness-alone": ("pressure_stiffness", 0.0, "energy_spiky", True),
    "viscosity-alone": ("viscosity", 0.0, "energy_spiky", True),
    "stiffness-alone-unfused": ("pressure_stiffness", 0.0, "energy_spiky", False),
    "stiffness-beside-viscosity": ("pressure_stiffness", 2.0, "energy_spiky", True),
    "stiffness-beside-viscosity-energy": ("pressure_stiffness", 2.0, "energy", True),
    "stiffness-beside-viscosity-spiky": ("pressure_stiffness", 2.0, "spiky", False),
}


@pytest.mark.parametrize("case", sorted(SPH_AT_ZERO))
def test_gradients_in_a_pressure_stiffness_or_viscosity_of_zero_are_the_one_sided_slopes(weights, case):
    """A fit may start a pressure stiffness or a viscosity at 0, the lower end of its range
    (``fit._NON_NEGATIVE``): the tape's gradient there is the loss's slope into the range,
    against the second-order one-sided difference ``(-3 L(0) + 4 L(e) - L(2 e)) / (2 e)`` in
    float64 at two steps a hundred times apart (the loss is smooth in either parameter from
    0 on: the tolerance 1e-4 is the difference's round-off at the small step). With both at 0
    the step ran no SPH term and the tape read 0 for both (measured: one-sided -3.7e-7 and
    -4.5e-4); with the stiffness alone at 0, every clamped pressure's adjoint took the tie of
    ``max(k_p (rho - rho0), 0)`` at 0 and read 0 too (-3.9e-7). A taped step's positions stay
    those of an untaped one, bitwise."""
    name, other_value, pressure_force, fused = SPH_AT_ZERO[case]
    other = "viscosity" if name == "pressure_stiffness" else "pressure_stiffness"

    def make(value):
        return _model({name: value, other: other_value, "pressure_force": pressure_force})

    model = make(0.0)
    loss, grads = _rollout_loss(model, weights, grad_of=(name,), fused=fused)
    untaped = we.Solver(make(0.0), fused=fused)
    a, b = untaped.model.state(), untaped.model.state()
    a.alpha.fill_(ALPHA0)
    for _ in range(STEPS):
        untaped.step(a, b, DT)
        a, b = b, a
    taped_model = make(0.0)
    solver = we.Solver(taped_model, fused=fused)
    states = [taped_model.state() for _ in range(STEPS + 1)]
    states[0].alpha.fill_(ALPHA0)
    taped_rollout_loss(solver, states, DT, weights)
    np.testing.assert_array_equal(states[-1].x.numpy(), a.x.numpy())
    for e in (1e-2, 1e-4):
        slope = (-3.0 * loss + 4.0 * _rollout_loss(make(e), weights, fused=fused)[0]
                 - _rollout_loss(make(2.0 * e), weights, fused=fused)[0]) / (2.0 * e)
        assert abs(slope) > 1e-9, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(slope, rel=1e-4), e


def _elastic_model(params=None, **kw):
    """The hourglass block made purely elastic (no yield, no flow): the default solver
    (``fit="auto"``) then runs the curvature-corrected fit with the hourglass control, on the
    rest model (``kw``: ``_model``'s)."""
    return _hourglass_model({"yield_stress": float("inf"), "flow_rate": 0.0, "hardening": 0.0, **(params or {})}, **kw)


def test_default_solver_of_an_elastic_model_gradients_match_central_differences(weights):
    """What the default solver runs for a purely elastic model under a tape (the
    rest model with the corrected total fit, ``Solver.rest_model``: the hand-written adjoints of
    its kernels, ``comparison.adjoint_kernels``, and Warp's generated one of the control)
    against central differences in ``mu``, ``lam`` and an initial velocity (one taped run's)."""
    _, solver = _rollout_loss(_elastic_model(), weights, fit=None, hourglass=None)
    assert solver.fit == "curvature_corrected" and solver.hourglass > 0.0 and solver.rest_model, (solver.fit,
                                                                                                 solver.hourglass)
    _, grads = _rollout_loss(_elastic_model(), weights, grad_of=("mu", "lam", "v0"), fit=None, hourglass=None)
    i, comp = 7, 1
    fd = _v0_central_difference(_elastic_model(), weights, i, comp, fit=None, hourglass=None)
    assert grads["v0"][i, comp] == pytest.approx(fd, rel=1e-4, abs=1e-9)
    for name in ("mu", "lam"):
        base = getattr(_elastic_model().materials[0], name)
        eps = 1e-5 * base
        at = _reused(_elastic_model())
        plus = _rollout_loss(at(name, base + eps), weights, fit=None, hourglass=None)[0]
        minus = _rollout_loss(at(name, base - eps), weights, fit=None, hourglass=None)[0]
        fd = (plus - minus) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4), name


#: The rest model's scenes for its hand-written adjoints (``comparison.adjoint_kernels``):
#: ``rest``, the elastic block from F = I; ``strained``, its positions stretched to
#: ``REST_STRAIN`` of the rest ones (a stored F and stress away from I from the first step);
#: ``contact``, squeezed towards the ground 0.5 mm under its bottom layer, which it reaches
#: in the second step; ``guarded``, ``Solver(min_neighbors=10)``: the block's 8 corners'
#: rest neighbourhoods are guarded (a guarded particle keeps its F, no force; the same 8 under
#: either fit weight, measured); ``inverted``, its
#: positions mirrored through one axis, ``REST_INVERSION`` of the rest ones: every rest fit
#: inverted, taken with its energy continued through det = 0 (``comparison``'s ``inverted_stress``).
REST_CASES = ("rest", "strained", "stretched", "contact", "guarded", "inverted")
REST_STRAIN = np.diag([1.04, 0.97, 1.02])
# Far past small strain, where the corotated stress a linear material that cannot flow takes
# (forces.corotated_stress) and eq. 9's part.
REST_STRETCH = np.array([[1.15, 0.05, 0.0], [0.0, 0.9, 0.04], [0.03, 0.0, 1.1]])
REST_INVERSION = np.diag([1.04, 0.97, -0.6])


def _rest_case_loss(case, weights, params=None, dx=None, dv=None, grad_of=(), hand_adjoints=True, F_loss=False):
    """The loss of ``case`` (``REST_CASES``) on the default solver, which runs the rest model
    (``Solver.rest_model``), with the default fit weight; ``dx``/``dv``: ``(i, c, delta)`` added
    to the first state's ``x``/``v``. With ``grad_of``: ``(loss, grads)`` as ``_rollout_loss``'s,
    the first state's ``x`` as ``"x0"``; ``F_loss``: their gradients with a random weighted sum of
    the last state's ``F`` added to the loss (a guarded particle's F reaches no position)."""
    model = _elastic_model(params, ground=-0.0305 if case == "contact" else None, fit_weight=DEFAULT_FIT_WEIGHT)
    assert model.fit_weight == DEFAULT_FIT_WEIGHT
    if case == "contact":
        model.particle_v0 = -model.particle_v0
    solver = we.Solver(model, min_neighbors=10 if case == "guarded" else MIN_NEIGHBORS)
    solver.hand_adjoints = hand_adjoints
    assert solver.rest_model
    untaped = not grad_of and hand_adjoints  # a central difference's run: no tape
    states = [model.state(requires_grad=False)] if untaped else [model.state() for _ in range(STEPS + 1)]
    x = model.particle_x0 @ {"strained": REST_STRAIN, "stretched": REST_STRETCH,
                             "inverted": REST_INVERSION}.get(case, np.eye(3)).T
    v = model.particle_v0.copy()
    if dx is not None:
        x[dx[0], dx[1]] += dx[2]
    if dv is not None:
        v[dv[0], dv[1]] += dv[2]
    states[0].x.assign(x)
    states[0].v.assign(v)
    if untaped:
        return untaped_rollout_loss(solver, states[0], DT, STEPS, weights, forward_only=False)
    loss, tape = taped_rollout_loss(solver, states, DT, weights)
    if case == "inverted":
        # Inverted all the way, clear of det = 0 (where the continued energy's stress has a kink).
        assert all((np.linalg.det(st.F.numpy()) < -0.1).all() for st in states[1:])
    if not grad_of:
        return loss.numpy()[0]
    if F_loss:
        states[-1].F.grad.assign(np.random.default_rng(1).normal(size=(model.particle_count, 3, 3)))
    tape.backward(loss)
    arrays = {"x0": states[0].x, "v0": states[0].v, "F": states[0].F, "F_p": states[0].F_p}
    return loss.numpy()[0], {n: (arrays[n] if n in arrays else getattr(model, n)).grad.numpy().copy() for n in grad_of}


@pytest.mark.parametrize("case", REST_CASES)
def test_rest_models_hand_written_adjoints_match_central_differences(weights, case):
    """The rest model's hand-written adjoints (its total fit's and its variational force's,
    ``comparison.adjoint_kernels``, with those of the rest of the step) against float64
    central differences in ``mu``, ``lam`` and a particle's initial velocity and position, at
    rest, strained (a few %, and up to 15 %: the block's linear material cannot flow, so it
    takes the corotated stress, ``forces.corotated_stress``), through ground contact, with
    guarded rest neighbourhoods and through inverted rest fits (a bottom corner, 0: guarded in
    ``guarded``, on the ground in ``contact``; an interior particle, 41), all four from one
    taped run; with the default fit weight (the other: ``test_default_solver_of_an_elastic_model...``
    here, ``test_gradient_coverage.py``'s ``default_elastic_other_weight``).
    Measured (CPU, float64): the biweight's largest relative error 4.7e-7 (poly6's 1.0e-6)."""
    loss, grads = _rest_case_loss(case, weights, grad_of=("mu", "lam", "v0", "x0"))
    # The central differences' runs, untaped, difference the taped rollout's loss: to the bit.
    assert _rest_case_loss(case, weights) == loss
    for name in ("v0", "x0"):
        key = "dv" if name == "v0" else "dx"
        eps = 1e-6 if name == "v0" else 1e-7
        for i, c in [(0, 1), (41, 0)]:
            fd = (_rest_case_loss(case, weights, **{key: (i, c, eps)})
                  - _rest_case_loss(case, weights, **{key: (i, c, -eps)})) / (2 * eps)
            assert abs(fd) > 1e-6, (name, i, c)
            assert grads[name][i, c] == pytest.approx(fd, rel=1e-5, abs=1e-9), (name, i, c)
    for name in ("mu", "lam"):
        base = getattr(_elastic_model().materials[0], name)
        eps = 1e-5 * base
        fd = (_rest_case_loss(case, weights, {name: base + eps}) - _rest_case_loss(case, weights, {name: base - eps})) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4), name


#: Rest-configuration materials (``Material(deformation="rest")``) beside the default's rest
#: model, on the yielding block (its flow moves ``F_p``), with the default fit weight:
#: (material options, fit).
REST_MATERIALS = {
    "rest_linear_variational": ({"deformation": "rest", "elastic_force": "variational"}, "linear"),
    "rest_corrected_variational": ({"deformation": "rest", "elastic_force": "variational"}, "curvature_corrected"),
    "rest_linear_paper": ({"deformation": "rest"}, "linear"),
}


@pytest.mark.parametrize("case", REST_CASES + tuple(REST_MATERIALS))
def test_rest_models_hand_written_adjoints_match_the_generated_ones(weights, case):
    """The rest kernels' hand-written adjoints (``comparison.adjoint_kernels``) give Warp's
    generated adjoints' gradients to round-off (float64) in every initial state field and
    material parameter the loss reaches: the default's rest model (``REST_CASES``, the loss
    with the last state's ``F`` in it, which a guarded particle keeps) and the
    rest materials of either fit and elastic force, flowing (``REST_MATERIALS``; eqs. 10-13's
    force has its own adjoint, the total fit's is this one)."""
    if case in REST_MATERIALS:
        options, fit = REST_MATERIALS[case]
        names = ("x0", "v0", "mu", "lam", "yield_stress", "flow_rate", "hardening", "viscosity")
        model = _model(options, fit_weight=DEFAULT_FIT_WEIGHT)
        assert model.fit_weight == DEFAULT_FIT_WEIGHT
        hand, gen = (_rollout_loss(m, weights, grad_of=names, fit=fit, hand_adjoints=h)[1]
                     for m, h in ((model, True), (_model(options, fit_weight=DEFAULT_FIT_WEIGHT), False)))
    else:
        names = ("x0", "v0", "F", "F_p", "mu", "lam", "viscosity")
        hand, gen = (_rest_case_loss(case, weights, grad_of=names, hand_adjoints=h, F_loss=True)[1] for h in (True, False))
    for name in names:
        scale = np.abs(gen[name]).max()
        assert scale > 0, f"the loss does not reach {name}"
        assert np.abs(hand[name] - gen[name]).max() <= 1e-10 * scale, name


def _handover_loss(weights, dF=None, dx=None, grad=False):
    """The elastic block's default solver (the rest model) from a state an incremental step
    wrote (``State.rest_model`` False) whose stored ``F`` is not the rest fit of its positions
    (a flowed body's): its first step hands ``F`` over (``F_p = F^-1 G(x)``,
    ``comparison.rest_handover``), with the default fit weight (``G``'s). ``dF``/``dx``:
    ``(i, a, b, delta)``/``(i, c, delta)`` added to the first state's ``F``/``x``."""
    model = _elastic_model(fit_weight=DEFAULT_FIT_WEIGHT)
    assert model.fit_weight == DEFAULT_FIT_WEIGHT
    solver = we.Solver(model)
    assert solver.rest_model
    # A central difference's run without a tape.
    states = [model.state() for _ in range(STEPS + 1)] if grad else [model.state(requires_grad=False)]
    n = model.particle_count
    shear = np.eye(3)
    shear[0, 1], shear[2, 0] = 0.04, -0.03
    F = np.tile(shear, (n, 1, 1)) + np.random.default_rng(3).normal(scale=0.01, size=(n, 3, 3))
    x = model.particle_x0.copy()
    if dF is not None:
        F[dF[0], dF[1], dF[2]] += dF[3]
    if dx is not None:
        x[dx[0], dx[1]] += dx[2]
    states[0].F.assign(F)
    states[0].x.assign(x)
    states[0].rest_model = False
    if not grad:
        return untaped_rollout_loss(solver, states[0], DT, STEPS, weights, forward_only=False)
    loss, tape = taped_rollout_loss(solver, states, DT, weights)
    # Handed over: the rest shape F_p = F^-1 G(x) carries the stored F's departure from the fit.
    assert np.abs(states[1].F_p.numpy() - np.eye(3)).max() > 0.02
    tape.backward(loss)
    return loss.numpy()[0], states[0].F.grad.numpy().copy(), states[0].x.grad.numpy().copy()


def test_gradient_through_the_rest_models_hand_over_matches_central_differences(weights):
    """The switch back to the rest model after incremental steps (a parameter made the body
    elastic again) hands the stored ``F`` over through ``F_p = F^-1 G(x)``: the gradient of
    the loss in the first state's ``F`` and ``x`` through that hand-over, the rest model's
    steps after it, and its ``F_p``, against central differences (float64). Measured: the
    biweight's largest relative error 5.2e-6 (poly6's 5.4e-6, whose rest fit ``G`` the rest model's
    checks take)."""
    loss, gF, gx = _handover_loss(weights, grad=True)
    assert _handover_loss(weights) == loss  # the untaped runs' loss is the taped one's, to the bit
    for i, a, b in [(7, 0, 1), (20, 2, 0), (33, 1, 1)]:
        eps = 1e-6
        fd = (_handover_loss(weights, dF=(i, a, b, eps)) - _handover_loss(weights, dF=(i, a, b, -eps))) / (2 * eps)
        assert abs(fd) > 1e-9
        assert gF[i, a, b] == pytest.approx(fd, rel=1e-4, abs=1e-10), (i, a, b)
    for i, c in [(7, 0), (20, 1)]:
        eps = 1e-7
        fd = (_handover_loss(weights, dx=(i, c, eps)) - _handover_loss(weights, dx=(i, c, -eps))) / (2 * eps)
        assert gx[i, c] == pytest.approx(fd, rel=1e-4, abs=1e-9), (i, c)


@pytest.mark.parametrize("checkpoint_every", [None, 2])
def test_a_rollout_made_while_its_body_could_flow_hands_f_over_once_elastic(weights, checkpoint_every):
    """A ``Rollout`` makes its taped states once, and a state's ``F_p`` has a gradient only where
    the model could run the rest model then (``Model.auto_runs_rest``). Made while the block
    could flow, a forward from a start an incremental step wrote (``State.rest_model`` False)
    after a parameter made it elastic was refused ('make the states again', which a rollout's
    caller cannot); it now runs, with the gradients of a rollout made on the elastic model."""
    from warp_esph.rollout import Rollout

    model = _model({"elastic_force": "variational"})
    start = model.state()
    shear = np.eye(3)
    shear[0, 1] = 0.04
    start.F.assign(np.tile(shear, (model.particle_count, 1, 1)))
    start.rest_model = False
    elastic = {"yield_stress": [float("inf")], "flow_rate": [0.0]}
    grads = {}
    for made_plastic in (True, False):
        rollout = Rollout(model, STEPS, DT, checkpoint_every=checkpoint_every)
        if made_plastic:
            rollout.forward()
            rollout.backward([weights])  # a checkpointed rollout makes its taped states here
            assert not rollout.solver.rest_model
        rollout.set_parameters(elastic)
        rollout.forward(initial_state=start)
        assert rollout.solver.rest_model
        grads[made_plastic] = rollout.backward([weights])[1]
        model.yield_stress.assign(np.array([10.0]))
        model.flow_rate.assign(np.array([50.0]))
    assert np.abs(grads[False]["F0"]).max() > 0.0
    for name in ("mu", "lam", "F0", "x0"):
        np.testing.assert_array_equal(grads[True][name], grads[False][name])



@pytest.mark.parametrize("checkpoint_every", [None, 2])
def test_a_rollout_whose_solver_runs_the_rest_model_on_another_fits_model_hands_f0_over(weights, checkpoint_every):
    """A ``Rollout`` whose solver asks ``fit="auto"`` of a model built with another fit runs the
    rest model, so a given ``F0`` is handed over to it (``State.rest_model`` False), which needs
    ``F_p``'s gradient. The taped states asked the model's fit (``Model.state``): made without it,
    the forward was refused ('make the states again'); they now follow the solver's, with the
    gradients of the same rollout on a model built with ``fit="auto"``."""
    from warp_esph.rollout import Rollout

    stretch = np.diag([1.04, 0.98, 1.0])
    grads = {}
    for fit in ("linear", None):
        model = _elastic_model()
        if fit is not None:
            model.fit = fit
        solver = we.Solver(model, fit="auto")
        assert solver.rest_model and model.auto_runs_rest() is (fit is None)
        rollout = Rollout(model, STEPS, DT, checkpoint_every=checkpoint_every, solver=solver)
        rollout.forward(F0=stretch)
        grads[fit] = rollout.backward([weights])[1]
    assert np.abs(grads[None]["F0"]).max() > 0.0
    for name in ("mu", "lam", "F0", "x0"):
        np.testing.assert_array_equal(grads["linear"][name], grads[None][name])


def _images_model(params=None, ground=-0.045, v0=None, fit_weight="poly6"):
    """The block over the ground with floor images (``add_ground(images=True)``): by default
    the plane three quarters of a spacing under its bottom layer, so every particle's fit,
    energy and density hold images; squeezed along y towards the plane (its bottom layer sinks 0.07 dx
    in the rollout, staying above half a spacing, where the images are mirrors). ``ground``
    moves the plane, ``v0`` replaces the squeeze by a uniform velocity."""
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "hardening": 200.0, "pressure_stiffness": 1.0,
         "viscosity": 2.0}
    p.update(params or {})
    mat = we.Material(density=1000.0, **p)
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.08, 0.08), mat)
    b.add_ground(ground, friction=0.5, images=True)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    if v0 is None:
        model.particle_v0 = -20.0 * model.particle_x0 * np.array([1.0, -0.5, 0.0])
    else:
        model.particle_v0[:] = v0
    return model


def test_floor_images_gradients_match_central_differences(weights):
    """Through the ground's floor images (fit, variational energy, SPH density, pressure and
    viscosity against the floor; the default pressure force, ``energy_spiky``, whose spiky
    pressure density and poly6 SPH density both hold the images): the taped rollout (the fused forward with the hand-written
    adjoints, which carry the image terms) against float64 central differences, in six
    material parameters and the lowest particle's initial velocity (one taped run's)."""
    model = _images_model()
    names = ("mu", "yield_stress", "flow_rate", "hardening", "pressure_stiffness", "viscosity")
    loss, grads = _rollout_loss(model, weights, grad_of=(*names, "v0"))
    i = int(np.argmin(model.particle_x0[:, 1]))
    m = _images_model()
    for comp in (0, 1):
        fd = _v0_central_difference(m, weights, i, comp)
        assert grads["v0"][i, comp] == pytest.approx(fd, rel=1e-4, abs=1e-9), comp
    for name in names:
        base = getattr(model.materials[0], name)
        eps = 1e-5 * base
        at = _reused(_images_model())
        fd = (_rollout_loss(at(name, base + eps), weights)[0] - _rollout_loss(at(name, base - eps), weights)[0]) / (2 * eps)
        assert abs(fd) > 1e-9, "the loss does not reach " + name
        assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), name


def test_a_rollouts_default_start_after_an_initial_state_has_new_floor_images():
    """``Rollout.forward()`` starts from the model's state, the floor images' ``F`` and hardening
    at I and 0 as a new state's: after a forward from an ``initial_state`` with deformed images
    it started from that state's images (its positions 0.25 mm off a new rollout's in 5 steps)."""
    from warp_esph.rollout import Rollout

    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.04, 0.06), we.Material.preset("clay"), velocity=(0.0, -0.5, 0.0))
    b.add_ground(-0.011, friction=0.5, images=True)
    model = b.finalize(requires_grad=True)
    rollout = Rollout(model, 5, 2e-4)
    first = rollout.forward()
    start = model.state()
    start.F_image.assign(np.tile(np.diag([1.2, 0.8, 1.0]).astype(np.float32), (model.particle_count, 1, 1)))
    start.alpha_image.fill_(0.3)
    assert np.abs(rollout.forward(initial_state=start) - first).max() > 1e-5  # the images matter here
    np.testing.assert_array_equal(rollout.forward(), first)


def _assert_lowest_v0_gradient(make, grads, weights, fit="linear"):
    """``grads["v0"]`` of the lowest particle of ``make()``'s model, along x and y, against
    central differences of the rollout loss at a step of 4e-6 m/s. At 1e-6 the difference is
    the loss's round-off's: through contact on the imaged ground (poly6, the corrected fit) the
    vertical one read 8.5e-5 off the tape, and 1.3e-4 with the tape the same to 16 digits but the
    images' blend written to skip an exact share of 1; at 5e-7 and 2.5e-7 +1.7e-4 and -1.8e-4, at
    4e-6 2.6e-5 both ways, the horizontal one 1.4e-9 (no truncation to speak of)."""
    m = make()
    i = int(np.argmin(m.particle_x0[:, 1]))
    for comp in (0, 1):
        fd = _v0_central_difference(m, weights, i, comp, eps=4e-6, fit=fit)
        assert grads["v0"][i, comp] == pytest.approx(fd, rel=1e-4, abs=0.0)


#: The block's bottom layer is at y = -0.03 (spacing 0.02). "rest": at rest (F = I, v = 0)
#: 0.3 dx over the plane, below half a spacing (the images stay put: d g / d x is the
#: tangential projector), under gravity; "contact": falling at 5 cm/s from 0.01 dx over it,
#: so the bottom layer reaches the plane within the rollout.
IMAGE_SCENES = {"rest": {"ground": -0.036, "v0": (0.0, 0.0, 0.0)},
                "contact": {"ground": -0.0302, "v0": (0.0, -0.05, 0.0)}}


def _lowest_height(scene: str) -> float:
    """The bottom layer's least height over the plane at the end of the untaped rollout."""
    model = _images_model(**IMAGE_SCENES[scene])
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    for _ in range(STEPS):
        solver.step(a, b, DT)
        a, b = b, a
    return float(a.x.numpy()[:, 1].min() - IMAGE_SCENES[scene]["ground"])


@pytest.mark.parametrize("scene", sorted(IMAGE_SCENES))
def test_floor_images_gradients_at_rest_and_through_contact(weights, scene):
    """The hand-written adjoints with the floor images (the fused forward under the tape,
    ``Solver.fast_under_tape``) against float64 central differences: a block at rest on
    the imaged ground (F = I, every singular value repeated), and one landing on it (the
    collider's contact within the rollout); in ``mu``, the pressure stiffness, the viscosity
    and the lowest particle's initial velocity (one taped run's)."""
    kw = IMAGE_SCENES[scene]
    model = _images_model(**kw)
    assert we.Solver(model).fast_under_tape()
    low = _lowest_height(scene)  # the scene does what its name says
    assert (low <= 1e-9) if scene == "contact" else (0.0 < low < 0.5 * 0.02)
    names = ("mu", "pressure_stiffness", "viscosity")
    _, grads = _rollout_loss(model, weights, grad_of=(*names, "v0"))
    _assert_lowest_v0_gradient(lambda: _images_model(**kw), grads, weights)
    for name in names:
        base = getattr(model.materials[0], name)
        eps = 1e-5 * base
        at = _reused(_images_model(**kw))
        fd = (_rollout_loss(at(name, base + eps), weights)[0] - _rollout_loss(at(name, base - eps), weights)[0]) / (2 * eps)
        assert abs(fd) > 1e-9, "the loss does not reach " + name
        assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), name


#: The floor images' scenes of the paper's force and of the corrected fit, each with the default
#: fit weight, and the other weight through contact (no other test takes either over the images).
IMAGE_WEIGHT_SCENES = [(s, DEFAULT_FIT_WEIGHT) for s in sorted(IMAGE_SCENES) + ["squeezed"]] + [("contact", OTHER_FIT_WEIGHT)]


@pytest.mark.parametrize("scene, fit_weight", IMAGE_WEIGHT_SCENES)
def test_floor_images_gradients_of_the_paper_force_match_central_differences(weights, scene, fit_weight):
    """The paper's force (eqs. 10-13) over the floor images (``forces.paper_image_forces``,
    its hand-written adjoint ``forces.elastic_forces_adjoint``): the taped rollout against
    float64 central differences in ``mu`` and ``lam`` (one taped run's) at rest, through
    contact and squeezed. Measured (CPU, float64): the biweight's largest relative error 6.7e-6
    (poly6's 8.9e-6)."""
    kw = {**IMAGE_SCENES.get(scene, {}), "fit_weight": fit_weight}
    paper = {"elastic_force": "paper"}
    model = _images_model(paper, **kw)
    assert model.fit_weight == fit_weight
    assert we.Solver(model).fast_under_tape()
    _, grads = _rollout_loss(model, weights, grad_of=("mu", "lam"))
    for name in ("mu", "lam"):
        base = getattr(model.materials[0], name)
        eps = 1e-5 * base
        at = _reused(_images_model(paper, **kw))
        fd = (_rollout_loss(at(name, base + eps), weights)[0] - _rollout_loss(at(name, base - eps), weights)[0]) / (2 * eps)
        assert abs(fd) > 1e-11, "the loss does not reach " + name  # at rest lam: 6.6e-10
        assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), name


@pytest.mark.parametrize("scene, fit_weight", IMAGE_WEIGHT_SCENES)
@pytest.mark.parametrize("names, elastic_force", [(("mu", "v0"), "variational"), (("lam",), "paper")],
                         ids=["variational", "paper"])
def test_floor_images_gradients_of_the_corrected_fit_match_central_differences(weights, scene, fit_weight, names,
                                                                               elastic_force):
    """``fit="curvature_corrected"`` over the floor images (``curvature.moment_pair_sums``,
    ``floor_image_moment``, ``floor_image_forces``; the paper's force's image pairs): its
    hand-written adjoints against Warp's generated ones and against float64 central
    differences, at rest, through contact and squeezed: with the variational force in ``mu``
    and the lowest particle's initial velocity (one taped run's), with the paper's in ``lam``.
    Measured (CPU, float64): the biweight's largest relative error 8.6e-5, the lowest
    particle's vertical velocity through contact (poly6's 8.5e-5 there)."""
    kw = {**IMAGE_SCENES.get(scene, {}), "fit_weight": fit_weight}
    params = {"elastic_force": elastic_force}
    fit = "curvature_corrected"
    model = _images_model(params, **kw)
    assert model.fit_weight == fit_weight
    _, grads = _rollout_loss(model, weights, grad_of=names, fit=fit)
    _, generated = _rollout_loss(_images_model(params, **kw), weights, grad_of=names, fit=fit, hand_adjoints=False)
    for name in names:
        np.testing.assert_allclose(grads[name], generated[name], rtol=1e-8, atol=1e-12 * np.abs(generated[name]).max(),
                                   err_msg=name)
        if name == "v0":
            _assert_lowest_v0_gradient(lambda: _images_model(params, **kw), grads, weights, fit)
            continue
        base = getattr(model.materials[0], name)
        eps = 1e-5 * base
        at = _reused(_images_model(params, **kw))
        fd = (_rollout_loss(at(name, base + eps), weights, fit=fit)[0]
              - _rollout_loss(at(name, base - eps), weights, fit=fit)[0]) / (2 * eps)
        assert abs(fd) > 1e-11, "the loss does not reach " + name
        assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), name


@pytest.mark.parametrize("name", ["pressure_stiffness", "viscosity"])
def test_floor_images_gradients_of_the_energy_pressure_force_match_central_differences(weights, name):
    """The ``energy`` pressure force over the floor images (the images in its poly6 density,
    which sets both the pressure and the viscous volumes); the default ``energy_spiky`` is the
    test above. The taped rollout against float64 central differences."""
    energy = {"pressure_force": "energy"}
    model = _images_model(energy)
    _, grads = _rollout_loss(model, weights, grad_of=(name,))
    base = getattr(model.materials[0], name)
    eps = 1e-5 * base
    fd = (_rollout_loss(_images_model({**energy, name: base + eps}), weights)[0]
          - _rollout_loss(_images_model({**energy, name: base - eps}), weights)[0]) / (2 * eps)
    assert abs(fd) > 1e-9, "the loss does not reach " + name
    assert grads[name][0] == pytest.approx(fd, rel=1e-4)


#: The biweight fit (``SceneBuilder(fit_weight="biweight")``) on each path its weight enters:
#: the fused linear fit with the variational force or the paper's (eqs. 10-13), the
#: curvature-corrected fit, and the floor images at rest (F = I, 0.3 dx over the plane) and
#: through contact.
BIWEIGHT_CASES = {
    "linear": ("block", "variational", "linear", ("mu", "yield_stress", "flow_rate", "v0")),
    "paper": ("block", "paper", "linear", ("lam",)),
    "corrected": ("block", "variational", "curvature_corrected", ("mu",)),
    "images-rest": ("rest", "variational", "linear", ("mu",)),
    "images-contact": ("contact", "variational", "linear", ("v0",)),
}


def _biweight_model(scene, elastic_force, params=None):
    p = {"elastic_force": elastic_force, **(params or {})}
    if scene == "block":
        return _model(p, fit_weight="biweight")
    return _images_model(p, fit_weight="biweight", **IMAGE_SCENES[scene])


@pytest.mark.parametrize("case", sorted(BIWEIGHT_CASES))
def test_biweight_fit_gradients_match_central_differences(weights, case):
    """The biweight's hand-written adjoints (its weight and slope in the fit's, the
    variational force's and the corrected fit's pair adjoints) against float64 central
    differences at a relative step of 1e-5, and against Warp's generated adjoints, in the
    case's parameters (one taped run's)."""
    scene, elastic_force, fit, names = BIWEIGHT_CASES[case]
    model = _biweight_model(scene, elastic_force)
    assert model.fit_weight == "biweight"
    _, grads = _rollout_loss(model, weights, grad_of=names, fit=fit)
    _, generated = _rollout_loss(_biweight_model(scene, elastic_force), weights, grad_of=names, fit=fit,
                                 hand_adjoints=False)
    for name in names:
        np.testing.assert_allclose(grads[name], generated[name], rtol=1e-8, atol=1e-12 * np.abs(generated[name]).max(),
                                   err_msg=name)
        if name == "v0":
            _assert_lowest_v0_gradient(lambda: _biweight_model(scene, elastic_force), grads, weights, fit)
            continue
        base = getattr(model.materials[0], name)
        eps = 1e-5 * abs(base)
        at = _reused(_biweight_model(scene, elastic_force))
        plus = _rollout_loss(at(name, base + eps), weights, fit=fit)[0]
        minus = _rollout_loss(at(name, base - eps), weights, fit=fit)[0]
        fd = (plus - minus) / (2 * eps)
        assert abs(fd) > 1e-11, f"the loss does not reach {name}"
        assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), name


# A single layer 6 x 6 of particles, every other one raised 0.08 dx (a checkerboard): its
# 16 inner fits have cond(A) = 31.4, in the band where the fit's increment and the
# variational force fade out (guards.py); the rim's have too few neighbours.
def _sheet_model(params=None, standing=False):
    """``standing``: the sheet upright on the imaged ground (``add_ground(images=True)``), its
    bottom row half a spacing over the plane and its heights 0.09 dx: the fits of the two
    rows nearest the ground take the images in, at ``cond(A)`` 25-34 (numpy, images mirrored)."""
    dx = 0.02
    if standing:
        pts = np.array([((i - 2.5) * dx, (j + 0.5) * dx, 0.09 * dx * (1 - 2 * ((i + j) % 2)))
                        for i in range(6) for j in range(6)])
    else:
        pts = np.array([((i - 2.5) * dx, 0.08 * dx * (1 - 2 * ((i + j) % 2)), (j - 2.5) * dx)
                        for i in range(6) for j in range(6)])
    return _few_particles(pts, params, standing)


def _few_particles(pts, params=None, standing=False):
    """A body of the points ``pts`` (spacing 0.02, no gravity), on the imaged ground with
    ``standing``, moving with a stretching velocity field plus noise."""
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "pressure_stiffness": 1.0, "viscosity": 2.0}
    p.update(params or {})
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_particles(pts, we.Material(density=1000.0, **p), name="body")
    if standing:
        b.add_ground(0.0, images=True)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_v0 = 5.0 * model.particle_x0 * np.array([1.0, 0.0, -0.5]) + np.random.default_rng(3).normal(
        scale=0.02, size=model.particle_x0.shape)
    return model


def _fit_conditions(model) -> np.ndarray:
    """cond(A) of each particle's fit at rest with 6 or more neighbours (poly6, h = 2 dx)."""
    x = model.particle_x0
    h = model.support_radius
    out = []
    for xi in x:
        d = x - xi
        r2 = (d * d).sum(axis=1)
        m = (r2 < h * h) & (r2 > 0.0)
        if m.sum() >= 6:
            A = ((h * h - r2[m])[:, None, None] ** 3 * d[m][:, :, None] * d[m][:, None, :]).sum(axis=0)
            lam = np.linalg.eigvalsh(A)
            out.append(lam[-1] / lam[0])
    return np.array(out)


@pytest.mark.parametrize("standing", [False, True], ids=["flat", "standing_on_images"])
@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
@pytest.mark.parametrize("name", ["mu", "v0"])
def test_faded_ill_conditioned_fits_have_the_gradients_of_central_differences(fit, name, standing):
    """Fits in the fade of the ill-conditioned guard (``guards.guard_scale``: whole up to
    ``cond(A) = 20``, zero from 40): the hand-written adjoints of the deformation update and
    the variational force (the fade's slope through the eigenvalues of ``A``; standing on
    the imaged ground, the images' terms too) against Warp's generated ones, and both against
    central differences in float64."""
    model = _sheet_model(standing=standing)
    if not standing:
        cond = _fit_conditions(model)
        assert ((cond > 25.0) & (cond < 35.0)).sum() == 16, np.round(cond, 1)
    sheet = functools.partial(_sheet_model, standing=standing)
    w = random_weights(model.particle_count, 1)
    _, grads = _rollout_loss(model, w, grad_of=(name,), fit=fit)
    _, generated = _rollout_loss(sheet(), w, grad_of=(name,), fit=fit, hand_adjoints=False)
    np.testing.assert_allclose(grads[name], generated[name], rtol=1e-7, atol=1e-10 * np.abs(generated[name]).max())
    if name == "v0":
        i, c, eps = 14, 1, 1e-6  # an inner particle, across the sheet

        def loss_with(delta):
            m = sheet()
            m.particle_v0[i, c] += delta
            return _rollout_loss(m, w, fit=fit)[0]

        fd = (loss_with(eps) - loss_with(-eps)) / (2 * eps)
        assert abs(fd) > 1e-9
        assert grads["v0"][i, c] == pytest.approx(fd, rel=1e-4, abs=1e-9)
        return
    eps = 1e-5 * model.materials[0].mu
    fd = (_rollout_loss(sheet({"mu": model.materials[0].mu + eps}), w, fit=fit)[0]
          - _rollout_loss(sheet({"mu": model.materials[0].mu - eps}), w, fit=fit)[0]) / (2 * eps)
    assert abs(fd) > 1e-11
    assert grads["mu"][0] == pytest.approx(fd, rel=1e-4)


def test_the_loss_has_no_jump_where_fits_enter_and_leave_the_fade():
    """The sheet's checkerboard height ``a`` (in dx) sets its 16 inner fits' ``cond(A)``: 40.9
    at 0.07, 31.4 at 0.08, 24.9 at 0.09, below 20 past 0.10. Scanned over 0.065-0.105 (all 16
    cross both ends of the fade at once), the loss's increment over each interval is the mean
    of the tape's slopes at its ends within 2 %. With the old switch at ``cond(A) = 20`` the
    16 fits went off together: a jump. Measured: within 0.46 %; with the fade narrowed to
    20-20.4 (``guards.FADE = 1.02``, nearly the switch) two intervals read 2.0 and 2.4 times
    the trapezoid."""
    w = random_weights(_sheet_model().particle_count, 1)
    pattern = np.zeros_like(_sheet_model().particle_x0)
    pattern[:, 1] = np.sign(_sheet_model().particle_x0[:, 1]) * 0.02  # the checkerboard per unit of a (dx = 0.02)
    heights = np.linspace(0.065, 0.105, 17)
    losses, slopes = [], []
    for a in heights:
        model = _sheet_model()
        model.particle_x0 = model.particle_x0 + (a - 0.08) * pattern
        loss, grads = _rollout_loss(model, w, grad_of=("x0",))
        losses.append(loss)
        slopes.append(float((grads["x0"] * pattern).sum()))
    losses, slopes = np.array(losses), np.array(slopes)
    increments = np.diff(losses) / np.diff(heights)
    trapezoid = 0.5 * (slopes[1:] + slopes[:-1])
    assert np.abs(increments / trapezoid - 1.0).max() < 0.02, np.round(increments / trapezoid, 4)


# A cluster of 2 x 2 x 2 particles, spaced dx along x and y and 1.34 dx along z, its body
# diagonal at 0.975 h: each particle's seven neighbours are six inside 0.84 h and the
# diagonal one in the band where a neighbour's count for the few-neighbours guard fades
# (guards.count_weight, 0.95-1.0 h), so its smooth count is 6.51. With min_neighbors = 7
# every fit sits in the count's fade (guards.count_scale: 0.52).
CLUSTER_DIAGONAL = 0.975


def _cluster_model(params=None, standing=False, dz_shift=0.0):
    """``standing``: the cluster on the imaged ground (``add_ground(images=True)``), its
    bottom layer 0.72 dx over the plane: the bottom particles' smooth counts, images
    included, are 8.75 (some images in the band), the top ones' 6.51. ``dz_shift`` moves the
    layers along z apart (the diagonal through the band)."""
    dx = 0.02
    h = 2.0 * dx
    dz = np.sqrt((CLUSTER_DIAGONAL * h) ** 2 - 2.0 * dx * dx)
    lift = 0.72 if standing else -0.5
    pts = np.array([((i - 0.5) * dx, (j + lift) * dx, (k - 0.5) * dz) for i in range(2) for j in range(2) for k in range(2)])
    model = _few_particles(pts, params, standing)
    model.particle_x0 = model.particle_x0 + dz_shift * _cluster_pattern(model)
    return model


def _cluster_pattern(model) -> np.ndarray:
    """The layers' motion along z per unit of ``dz_shift``."""
    pattern = np.zeros_like(model.particle_x0)
    pattern[:, 2] = np.sign(model.particle_x0[:, 2]) * 0.5
    return pattern


def _smooth_counts(x, h, ground=None) -> np.ndarray:
    """Each particle's count for the few-neighbours guard (guards.count_weight), numpy, with
    the images mirrored in the plane ``y = ground``."""
    q0 = COUNT_FADE**2

    def weight(r2):
        q = np.clip((r2 / (h * h) - q0) / (1.0 - q0), 0.0, 1.0)
        return np.where(r2 < h * h, 1.0 - q * q * (3.0 - 2.0 * q), 0.0)
    out = []
    for i, xi in enumerate(x):
        r2 = ((x - xi) ** 2).sum(axis=1)
        n = weight(np.delete(r2, i)).sum()
        if ground is not None:
            g = x * np.array([1.0, -1.0, 1.0]) + np.array([0.0, 2.0 * ground, 0.0])
            n += weight(((g - xi) ** 2).sum(axis=1)).sum()
        out.append(n)
    return np.array(out)


@pytest.mark.parametrize("standing", [False, True], ids=["free", "standing_on_images"])
@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
@pytest.mark.parametrize("name", ["mu", "v0"])
def test_fits_in_the_few_neighbours_fade_have_the_gradients_of_central_differences(fit, name, standing):
    """Fits in the fade of the few-neighbours guard (``guards.count_scale`` on the smooth
    count of ``guards.count_weight``): the hand-written adjoints of the deformation update
    and the variational force (the count's slope through each pair's distance; standing on
    the imaged ground, the images' too) against Warp's generated ones, and both against
    central differences in float64. Dropping the count's term from any of the four
    adjoints fails the generated comparison (rtol 1e-7) by 1e-4 or more."""
    model = _cluster_model(standing=standing)
    min_neighbors = 9 if standing else 7
    counts = _smooth_counts(model.particle_x0, model.support_radius, 0.0 if standing else None)
    inside = (counts > min_neighbors - 1) & (counts < min_neighbors)
    assert inside.sum() == (4 if standing else 8), np.round(counts, 3)
    cluster = functools.partial(_cluster_model, standing=standing)
    roll = functools.partial(_rollout_loss, fit=fit, min_neighbors=min_neighbors)
    w = random_weights(model.particle_count, 1)
    _, grads = roll(model, w, grad_of=(name,))
    _, generated = roll(cluster(), w, grad_of=(name,), hand_adjoints=False)
    np.testing.assert_allclose(grads[name], generated[name], rtol=1e-7, atol=1e-10 * np.abs(generated[name]).max())
    if name == "v0":
        i, c, eps = 3, 2, 1e-6

        def loss_with(delta):
            m = cluster()
            m.particle_v0[i, c] += delta
            return roll(m, w)[0]

        fd = (loss_with(eps) - loss_with(-eps)) / (2 * eps)
        assert abs(fd) > 1e-9
        assert grads["v0"][i, c] == pytest.approx(fd, rel=1e-4, abs=1e-9)
        return
    mu = model.materials[0].mu
    eps = 1e-5 * mu
    fd = (roll(cluster({"mu": mu + eps}), w)[0] - roll(cluster({"mu": mu - eps}), w)[0]) / (2 * eps)
    assert abs(fd) > 1e-11
    assert grads["mu"][0] == pytest.approx(fd, rel=1e-4, abs=0.0)


def test_the_loss_has_no_jump_where_a_neighbour_leaves_the_count():
    """The cluster's layers drawn apart along z take each particle's diagonal neighbour from
    0.88 h through the count's band (0.95-1.0 h) to 1.02 h: the smooth counts go from 7 to 6
    together, and with ``min_neighbors = 7`` all eight fits fade out. The loss's increment
    over each interval of the scan is the mean of the tape's slopes at its ends within 2 %.
    With the count a switch (a neighbour counting whole up to ``h``), the eight fits went
    off together where the diagonal crossed ``h``: a jump. Measured: within 0.68 %; with the
    band narrowed to 0.999-1.0 h (``guards.COUNT_FADE = 0.999``, nearly the switch) the
    interval across ``h`` reads 1.21 times the trapezoid."""
    dx, h = 0.02, 0.04
    dz0 = np.sqrt((CLUSTER_DIAGONAL * h) ** 2 - 2.0 * dx * dx)
    shifts = np.linspace(np.sqrt((0.88 * h) ** 2 - 2 * dx * dx), np.sqrt((1.02 * h) ** 2 - 2 * dx * dx), 17) - dz0
    w = random_weights(8, 1)
    losses, slopes, counts = [], [], []
    for a in shifts:
        model = _cluster_model({"mu": 8.0e3, "lam": 1.2e4}, dz_shift=a)  # stiff: the fit's share of the loss shows
        counts.append(_smooth_counts(model.particle_x0, h).mean())
        loss, grads = _rollout_loss(model, w, grad_of=("x0",), min_neighbors=7)
        losses.append(loss)
        slopes.append(float((grads["x0"] * _cluster_pattern(model)).sum()))
    assert counts[0] == 7.0 and counts[-1] == 6.0, counts
    losses, slopes = np.array(losses), np.array(slopes)
    increments = np.diff(losses) / np.diff(shifts)
    trapezoid = 0.5 * (slopes[1:] + slopes[:-1])
    assert np.abs(increments / trapezoid - 1.0).max() < 0.02, np.round(increments / trapezoid, 4)


#: Step-path options whose float64 checks above run only in motion or off the ground, checked
#: here at rest on a floor: (material options, ``Solver`` options, parameters).
AT_REST = {
    "stvk": ({"model": "stvk"}, {}, ("lam",)),
    "hyperelastic": ({"model": "hyperelastic"}, {}, ("lam",)),
    "non_newtonian": ({"model": "non_newtonian", "flow_rate": 500.0}, {}, ("lam",)),
    "spiky_pressure": ({"pressure_force": "spiky"}, {}, ("pressure_stiffness",)),
    "energy_pressure": ({"pressure_force": "energy"}, {}, ("pressure_stiffness",)),
    "unfused": ({}, {"fused": False}, ("lam", "viscosity")),
    "hourglass": ({}, {"hourglass": 0.5}, ("lam",)),
    "corrected": ({}, {"fit": "curvature_corrected"}, ("lam",)),
    "rest_model": ({"deformation": "rest"}, {}, ("lam",)),
    "additive_model": ({"deformation": "additive"}, {}, ("lam",)),
    "ghost_floor": ({"elastic_force": "variational"}, {}, ("lam",)),
    "paper": ({"elastic_force": "paper"}, {}, ("lam",)),
    "unfused_paper": ({"elastic_force": "paper"}, {"fused": False}, ("lam",)),
    "rest_variational": ({"deformation": "rest", "elastic_force": "variational"}, {}, ("lam",)),
    "ghost_floor_slip": ({"elastic_force": "variational"}, {}, ("lam",)),
    "images": ({}, {}, ("lam", "viscosity")),
    "unfused_images": ({}, {"fused": False}, ("lam",)),
    "sphere_collider": ({}, {}, ("lam",)),
    "box_collider": ({}, {}, ("lam",)),
    "held_tools": ({}, {}, ("lam",)),
    "particle_floor": ({}, {}, ("lam",)),
}

#: What each case of ``AT_REST`` rests on, where not the rough ground: a ghost floor (no-slip
#: or slip), the ground with floor images, a static sphere or box collider whose top is the
#: ground's height, three held tools (a box under the block's first column of particles along x, a
#: wide sphere under the middle two, a plane tilted by 20 degrees under the last: the floor of
#: each, friction holding it), or a particle floor (a pinned set) under it.
REST_FLOOR = {"ghost_floor": "ghost", "ghost_floor_slip": "slip", "images": "images", "unfused_images": "images",
              "sphere_collider": "sphere", "box_collider": "box", "held_tools": "tools", "particle_floor": "pinned"}


def _resting_model(case, params=None):
    """A 4 x 3 x 3 block from rest (F = I, v = 0) on the rough ground under gravity, its
    bottom layer on the plane (jittered by 1e-3 dx: some particles touch down within the
    rollout, the others are pressed into it); or on the floor ``REST_FLOOR`` gives the case."""
    dx = 0.02
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "hardening": 200.0, "pressure_stiffness": 1.0,
         "viscosity": 2.0, **AT_REST[case][0], **(params or {})}
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.03, 0.0), (4 * dx, 3 * dx, 3 * dx), we.Material(density=1000.0, **p), name="block")
    floor = REST_FLOOR.get(case, "ground")
    if floor in ("ghost", "slip"):
        b.add_particle_floor("block", margin=dx, ghost=True, slip=floor == "slip")
    elif floor == "pinned":
        b.add_particle_floor("block", margin=dx)  # of the block's material: one parameter moves both
    elif floor == "sphere":
        b.add_sphere_collider((0.0, 0.01 - 0.3, 0.0), 0.3, friction=0.5)
    elif floor == "box":
        b.add_box_collider((0.0, 0.01 - 0.05, 0.0), (0.1, 0.05, 0.1), friction=0.5)
    elif floor == "tools":
        # Their tops at the bottom layer's height, each under its own columns.
        b.add_tool("box", half_extents=(0.04, 0.05, 0.1), position=(-0.06, 0.01 - 0.05, 0.0), friction=0.5, name="box")
        b.add_tool("sphere", radius=10.0, position=(0.0, 0.01 - 10.0, 0.0), friction=0.5, name="ball")
        tilt = np.radians(20.0)
        b.add_tool("plane", normal=(-np.sin(tilt), np.cos(tilt), 0.0), position=(0.03, 0.01, 0.0), friction=0.5,
                   name="ramp")
    else:
        b.add_ground(0.01, friction=0.5, images=floor == "images")
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * dx, size=model.particle_x0.shape)
    return model


def _resting_loss(model, case, w, grad_of=None, steps=8):
    solver = we.Solver(model, **AT_REST[case][1])
    if grad_of is None:  # a central difference's run: no tape
        return untaped_rollout_loss(solver, model.state(requires_grad=False), DT, steps, w, forward_only=False)
    states = [model.state() for _ in range(steps + 1)]
    loss, tape = taped_rollout_loss(solver, states, DT, w)
    grads = taped_gradients(model, states, loss, tape, grad_of)
    return loss.numpy()[0], grads, states


@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
@pytest.mark.parametrize("case", sorted(AT_REST))
def test_gradients_at_rest_on_the_ground_match_central_differences(case):
    """Each option from rest on a floor (F = I with its singular values nearly repeated all
    along; through the contact law of a static collider or of held tools, or the fits of a
    ghost or pinned floor): the tape's gradient in a material parameter and in the initial
    velocity of a bottom particle (along the floor) and of a top one (down) against float64
    central differences at two steps a hundred times apart, the larger one large enough that
    a jump in the loss would show. (At rest the stress is nearly zero, so these see the
    constitutive adjoints and the contact's; a term proportional to the stress, such as
    the pair forces' slope in the positions, is the moving scenes' above to check.)"""
    names = AT_REST[case][2]
    model = _resting_model(case)
    w = random_weights(model.particle_count, 2)
    _, grads, states = _resting_loss(model, case, w, (*names, "v0"))
    last = states[-1]
    sv = np.linalg.svd(last.F.numpy(), compute_uv=False)
    assert np.abs(sv - 1.0).max() < 0.05, "F stays near I"
    floor = REST_FLOOR.get(case, "ground")
    if floor in ("tools", "pinned"):
        # (A particle resting on a swept tool meets it every other step: its entry puts it
        # a thousandth of a spacing outside, which gravity takes two steps to drift back.)
        rows = np.array([st.reaction_force.numpy() for st in states[-2:]])
        assert (np.abs(rows).max(axis=(0, 2)) > 0.0).all(), "every tool (the pinned floor) holds the block"
    elif floor not in ("ghost", "slip"):
        assert np.abs(last.collider_force.numpy()).max() > 0.0, "the block rests on the collider"
    # One model for the central differences' runs (a run from a model another run left, its
    # materials or initial velocities set, is a new one's to the bit): the parameter set in each
    # material made with it (a particle floor's is the block's), then put back.
    m = _resting_model(case)
    materials = list(m.materials)
    for name in names:
        base = getattr(model.materials[0], name)

        def loss_at(value):
            m.set_materials([mt.replace(**{name: value}) if getattr(mt, name) == base else mt for mt in materials])
            return _resting_loss(m, case, w)

        for rel in (1e-3, 1e-5):
            eps = rel * base
            fd = (loss_at(base + eps) - loss_at(base - eps)) / (2 * eps)
            assert abs(fd) > 1e-11, f"the loss does not reach {name}"
            assert grads[name][0] == pytest.approx(fd, rel=1e-4, abs=0.0), (name, rel)
        m.set_materials(materials)
    # The block's own particles (a ghost floor's follow them).
    x0 = model.particle_x0[:36]
    v0 = m.particle_v0.copy()
    for i, c in ((int(np.argmin(x0[:, 1])), 0), (int(np.argmax(x0[:, 1])), 1)):
        for eps in (1e-4, 1e-6):
            def loss_with(delta):
                m.particle_v0 = v0.copy()
                m.particle_v0[i, c] += delta
                return _resting_loss(m, case, w)

            fd = (loss_with(eps) - loss_with(-eps)) / (2 * eps)
            assert abs(fd) > 1e-9, (i, c)
            assert grads["v0"][i, c] == pytest.approx(fd, rel=1e-4, abs=1e-9), (i, c, eps)


def test_a_taped_step_refuses_a_state_the_tape_wrote_and_says_when_no_gradient_can_flow():
    """Two states swapped under one tape: the second step overwrote what the backward pass
    of the first reads (the shear modulus's gradient came out 4.5 x the true one, without a
    word). A state made without gradients under a tape: the gradient stopped there (0 or a
    part of the rollout's), without a word."""
    model = _model()
    solver = we.Solver(model)
    a, b = model.state(requires_grad=True), model.state(requires_grad=True)
    with wp.Tape():
        solver.step(a, b, DT)
        solver.step(b, a, DT)
        with pytest.raises(ValueError, match="state_out is not allowed under this wp.Tape: an earlier step of the same "
                                             "tape wrote it"):
            solver.step(a, b, DT)
    with wp.Tape():  # a new tape: the same states may be written again
        solver.step(a, b, DT)
    plain = model.state(requires_grad=False)
    with pytest.warns(RuntimeWarning, match="state_out made without requires_grad: no gradient flows back"):
        with wp.Tape():
            solver.step(a, plain, DT)


def _two_taped_steps():
    """The block of ``_model`` stepped twice on a ``wp.Tape``, and a seed for the last state's
    gradient: ``(model, states, tape, seed)``."""
    model = _model()
    solver = we.Solver(model)
    states = [model.state(requires_grad=True) for _ in range(3)]
    tape = wp.Tape()
    with tape:
        for k in range(2):
            solver.step(states[k], states[k + 1], DT)
    return model, states, tape, np.random.default_rng(3).normal(size=(model.particle_count, 3))


def test_a_parameter_written_in_place_after_the_taped_steps_is_named_before_the_backward_pass():
    """The adjoints read the parameter arrays as they are at ``tape.backward()``: a shear
    modulus written in place after the taped steps gave the gradient of neither value without
    a word (-1: 4 % off; NaN: every gradient NaN). The first thing the backward pass runs
    names the parameter, the material and both values; nothing has flowed back yet."""
    model, states, tape, seed = _two_taped_steps()
    mu = float(model.mu.numpy()[0])
    for bad, why in ((-1.0, r" \(Material\.mu = -1\.0 is not allowed: must be > 0\)"),
                     (float("nan"), r" \(Material\.mu = nan is not allowed: must be a finite number\)"),
                     (3.0 * mu, "")):
        model.mu.assign([bad])
        tape.zero()
        states[2].x.grad.assign(seed)
        with pytest.raises(RuntimeError, match=rf"^tape\.backward\(\) is not allowed: the model's mu \(material 0\) = "
                                               rf"{bad:g} now{why}, {mu:g} when Solver\.step ran under this wp\.Tape; "
                                               "the backward pass reads the parameter arrays again"):
            tape.backward()
        assert not states[1].x.grad.numpy().any() and not model.mu.grad.numpy().any()
    model.mu.assign([mu])  # the value the steps ran with: the backward pass runs
    tape.zero()
    states[2].x.grad.assign(seed)
    tape.backward()
    assert np.isfinite(model.mu.grad.numpy()).all() and model.mu.grad.numpy()[0] != 0.0


def test_a_material_set_or_a_parameter_nudged_after_the_taped_steps_is_named_before_the_backward_pass():
    """The adjoints read the materials as they are at ``tape.backward()`` too: a
    ``set_material`` to another ``elastic_force`` after the taped steps gave mu's gradient 63 %
    off without a word. It is named (field, both values) before anything flows back; the same
    material set again is no change. A parameter written from 1000 to 1000.0001 is named with
    every digit: ':g' had said '1000 now, 1000 when Solver.step ran'."""
    model, states, tape, seed = _two_taped_steps()
    mat = model.materials[0]
    model.set_material(0, mat.replace(elastic_force="paper"))
    states[2].x.grad.assign(seed)
    with pytest.raises(RuntimeError, match=r"^tape\.backward\(\) is not allowed: material 0 was replaced \(set_material\) "
                                           rf"since Solver\.step ran under this wp\.Tape: elastic_force = 'paper' now, "
                                           rf"{mat.elastic_force!r} then; the backward pass reads the materials again"):
        tape.backward()
    assert not states[1].x.grad.numpy().any() and not model.mu.grad.numpy().any()
    model.mu.assign([1000.0001])
    with pytest.raises(RuntimeError, match=r"the model's mu \(material 0\) = 1000\.0001 now, 1000\.0 when Solver\.step ran"):
        tape.backward()
    model.set_material(0, dataclasses.replace(mat))  # an equal material, another object: no change
    tape.zero()
    states[2].x.grad.assign(seed)
    tape.backward()
    assert np.isfinite(model.mu.grad.numpy()).all() and model.mu.grad.numpy()[0] != 0.0


def test_a_material_changed_in_one_world_after_the_taped_steps_is_named_as_set_material_takes_it():
    """With worlds, the refusal names the material as ``set_material`` takes it (its index
    within its world, and the world): ``set_material(1, ..., world=1)`` on two worlds of two
    materials read 'material 3', an index the user never gave."""
    soft = we.Material(density=1000.0, mu=1e3, lam=1.5e3)
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), soft)
    b.add_box((0.2, 0.0, 0.0), (0.06, 0.06, 0.06), soft.replace(mu=2e3))
    model = b.finalize(dtype=wp.float64, requires_grad=True, worlds=2)
    solver = we.Solver(model)
    states = [model.state(requires_grad=True) for _ in range(2)]
    tape = wp.Tape()
    with tape:
        solver.step(states[0], states[1], DT)
    model.set_material(1, soft.replace(mu=2e3, elastic_force="paper"), world=1)
    states[1].x.grad.fill_(1.0)
    with pytest.raises(RuntimeError, match=r"^tape\.backward\(\) is not allowed: material 1 of world 1 \(model material 3\) "
                                           r"was replaced \(set_material\)"):
        tape.backward()
    model.set_material(1, soft.replace(mu=2e3), world=1)
    model.mu.assign(np.where(np.arange(4) == 2, 5e3, model.mu.numpy()))
    with pytest.raises(RuntimeError, match=r"the model's mu \(material 0 of world 1 \(model material 2\)\) = 5000 now, 1000 when"):
        tape.backward()


@pytest.mark.parametrize("adjoint", ["launch_integrate.<locals>.backward",
                                     "launch_constitutive_forces.<locals>.backward"])
def test_a_recorded_adjoint_run_after_its_tape_was_freed_says_so(adjoint):
    """The adjoints a taped step records hold their tape weakly (the tape holds them; a strong
    reference back made every dropped tape a reference cycle). One run after its tape was
    freed (a caller who kept only ``tape.launches``) met ``None`` where the tape had been: the
    integration's ended in ``'NoneType' object has no attribute 'get_adjoint'``, the fused
    step's ran on without the tape its gradients register on for ``zero()``. Either now
    refuses, naming the freed tape, before it launches anything."""
    import gc

    model, states, tape, seed = _two_taped_steps()
    launches = list(tape.launches)
    del tape
    gc.collect()
    found = [f for f in launches if getattr(f, "__qualname__", "").endswith(adjoint)]
    assert len(found) == 2, [getattr(f, "__qualname__", f) for f in launches if callable(f)]
    states[2].x.grad.assign(seed)
    before = states[1].x.grad.numpy().copy()
    with pytest.raises(RuntimeError, match=r"recorded on a wp\.Tape .* after that tape was freed"):
        found[-1]()
    np.testing.assert_array_equal(states[1].x.grad.numpy(), before)
