"""Custom adjoints of the SVD maps (docs/method.md §9) against float64 central differences,
at rest (F = I, every singular value repeated), with two repeated singular values,
at a random F, across the yield point, and for every material parameter."""

import numpy as np
import pytest
import warp as wp

from warp_esph.sim import comparison, deformation, forces, guards, materials, plasticity
from warp_esph._types import type_set

S = wp.float64
T = type_set(S)
_stress = forces.funcs(S, "poly6").stress


@wp.kernel(module="unique")
def _stress_loss(F: wp.array(dtype=T.mat33), W: wp.array(dtype=T.mat33), mu: wp.array(dtype=S), lam: wp.array(dtype=S),
                 model: int, out: wp.array(dtype=S)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.ddot(_stress(F[i], mu[0], lam[0], model), W[i]))


@wp.kernel(module="unique")
def _weighted_sum(a: wp.array(dtype=T.mat33), b: wp.array(dtype=T.mat33), c: wp.array(dtype=S),
                  Wa: wp.array(dtype=T.mat33), Wb: wp.array(dtype=T.mat33), out: wp.array(dtype=S)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.ddot(a[i], Wa[i]) + wp.ddot(b[i], Wb[i]) + S(3.0) * c[i])


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _cases(rng):
    return {
        "identity": np.eye(3),
        "repeated": _rotation(rng) @ np.diag([1.15, 1.15, 0.8]) @ _rotation(rng),
        "random": _rotation(rng) @ np.diag([1.3, 1.0, 0.75]) @ _rotation(rng),
        "rotation": _rotation(rng),
        "volume_change": _rotation(rng) @ np.diag([0.95, 0.75, 0.6]) @ _rotation(rng),
        "inverted": _rotation(rng) @ np.diag([1.2, 0.9, -0.4]) @ _rotation(rng),
        # Repeated singular values in the SVD's own frame (U = V = I), the lower pair repeated,
        # all three (a scaled rotation), and an inverted F whose positive pair is repeated.
        "repeated_unrotated": np.diag([1.15, 1.15, 0.8]),
        "repeated_lower": _rotation(rng) @ np.diag([1.15, 0.8, 0.8]) @ _rotation(rng),
        "scaled_rotation": 1.1 * _rotation(rng),
        "inverted_repeated": _rotation(rng) @ np.diag([1.15, 1.15, -0.8]) @ _rotation(rng),
    }


#: The cases of repeated singular values (``_cases``).
_REPEATED = ("identity", "repeated", "repeated_unrotated", "repeated_lower", "scaled_rotation")


def _central_difference(f, x, eps=1e-6):
    x = np.array(x, dtype=np.float64)
    g = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        xp, xm = x.copy(), x.copy()
        xp[idx] += eps
        xm[idx] -= eps
        g[idx] = (f(xp) - f(xm)) / (2 * eps)
    return g


def _assert_close(tape_grad, fd_grad, rel=1e-6):
    scale = max(np.abs(fd_grad).max(), 1e-3)
    assert np.abs(tape_grad - fd_grad).max() <= rel * scale, (tape_grad, fd_grad)


_STRESS_MODELS = {"linear": 0, "hyperelastic": 2, "stvk": 3, "corotated": forces.COROTATED}
# Only the corotated stress is taken inverted as it is (the polynomial models' is continued,
# comparison.inverted_stress).
_STRESS_CASES = [(m, c) for m in _STRESS_MODELS for c in (*_REPEATED, "random", "rotation")]
_STRESS_CASES += [("corotated", "inverted"), ("corotated", "inverted_repeated")]


@pytest.mark.parametrize("model_name, case", _STRESS_CASES)
def test_stress_adjoint(model_name, case):
    """``forces.stress`` of each model (``COROTATED``: ``corotated_stress``, what a linear
    material that cannot flow takes) against central differences in ``F``, ``mu`` and ``lam``,
    at repeated singular values and, for the corotated stress, through an inverted ``F``."""
    model = _STRESS_MODELS[model_name]
    rng = np.random.default_rng(1)
    F0 = _cases(rng)[case]
    W = wp.array(rng.normal(size=(1, 3, 3)), dtype=T.mat33)

    def loss(F_np, mu_np, lam_np, grad=False):
        F = wp.array(F_np[None], dtype=T.mat33, requires_grad=True)
        mu = wp.array([mu_np], dtype=S, requires_grad=True)
        lam = wp.array([lam_np], dtype=S, requires_grad=True)
        out = wp.zeros(1, dtype=S, requires_grad=True)
        tape = wp.Tape()
        with tape:
            wp.launch(_stress_loss, 1, [F, W, mu, lam, model], [out])
        if not grad:
            return out.numpy()[0]
        tape.backward(out)
        return F.grad.numpy()[0], mu.grad.numpy()[0], lam.grad.numpy()[0]

    gF, gmu, glam = loss(F0, 3.0, 2.0, grad=True)
    _assert_close(gF, _central_difference(lambda F: loss(F, 3.0, 2.0), F0))
    _assert_close(gmu, _central_difference(lambda m: loss(F0, m[()], 2.0), np.array(3.0)))
    _assert_close(glam, _central_difference(lambda lam: loss(F0, 3.0, lam[()]), np.array(2.0)))


_left_stretch = plasticity.funcs(S).left_stretch


@wp.kernel(module="unique")
def _left_stretch_loss(F: wp.array(dtype=T.mat33), W: wp.array(dtype=T.mat33), out: wp.array(dtype=S)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.ddot(_left_stretch(F[i]), W[i]))


@pytest.mark.parametrize("case", sorted(_cases(np.random.default_rng(0))))
def test_left_stretch_adjoint(case):
    """``plasticity.left_stretch`` (``U diag(sigma) U^T``, the yield test's with the pressure)
    against central differences in ``F``, at repeated singular values and through an inverted
    ``F``. Its adjoint skipped every pair with ``sigma_i + sigma_j <= 0``, the inverted value's
    own diagonal among them: off by order one at an inverted ``F`` (the flow reads no inverted
    ``F``, so no run reached it)."""
    rng = np.random.default_rng(1)
    F0 = _cases(rng)[case]
    W = wp.array(rng.normal(size=(1, 3, 3)), dtype=T.mat33)

    def loss(F_np, grad=False):
        F = wp.array(F_np[None], dtype=T.mat33, requires_grad=True)
        out = wp.zeros(1, dtype=S, requires_grad=True)
        tape = wp.Tape()
        with tape:
            wp.launch(_left_stretch_loss, 1, [F, W], [out])
        if not grad:
            return out.numpy()[0]
        tape.backward(out)
        return F.grad.numpy()[0]

    _assert_close(loss(F0, grad=True), _central_difference(loss, F0))


PARAMS = ("mu", "yield_stress", "flow_rate", "hardening")


@pytest.mark.parametrize("non_newtonian", [0, 1], ids=["linear", "non_newtonian"])
@pytest.mark.parametrize("case", ["identity", "repeated", "random", "volume_change"])
@pytest.mark.parametrize("yield_stress,flow_rate", [(0.05, 40.0), (0.3, 4.0), (10.0, 4.0)],
                         ids=["gamma_capped", "flowing", "elastic"])
def test_plastic_flow_adjoint(case, yield_stress, flow_rate, non_newtonian):
    """Plastic flow + stress of one particle: gradients wrt F, alpha and every parameter.

    The three regimes: gamma = 1 (the min(., 1) cap), a partial flow, no flow;
    "identity" never flows (zero deviatoric stress); "volume_change" has J outside
    [0.8, 1.25], where the flow does not preserve volume."""
    rng = np.random.default_rng(2)
    F0 = _cases(rng)[case]
    kern = plasticity.kernels(S).constitutive_update
    Wa = wp.array(rng.normal(size=(1, 3, 3)), dtype=T.mat33)
    Wb = wp.array(rng.normal(size=(1, 3, 3)), dtype=T.mat33)
    dt = 0.1
    base = {"mu": 1.0, "yield_stress": yield_stress, "flow_rate": flow_rate, "hardening": 0.5}

    def run(F_np, alpha0, params, grad=False):
        F = wp.array(F_np[None], dtype=T.mat33, requires_grad=True)
        alpha = wp.array([alpha0], dtype=S, requires_grad=True)
        arrays = {k: wp.array([params[k]], dtype=S, requires_grad=True) for k in PARAMS}
        lam = wp.array([1.5], dtype=S, requires_grad=True)
        outs = [wp.zeros(1, dtype=T.mat33, requires_grad=True), wp.zeros(1, dtype=S, requires_grad=True),
                wp.zeros(1, dtype=T.mat33, requires_grad=True), wp.zeros(1, dtype=T.mat33, requires_grad=True)]
        counters = wp.zeros(deformation.COUNT_BODY + 16, dtype=wp.int32)  # every guard and body slot a kernel may write
        out = wp.zeros(1, dtype=S, requires_grad=True)
        tape = wp.Tape()
        with tape:
            mats = materials.make(S, lam=lam, model=wp.array([non_newtonian], dtype=wp.int32), **arrays)
            wp.launch(kern, 1, [F, wp.zeros(1, dtype=T.mat33), alpha, wp.zeros(1, dtype=wp.int32), mats, S(dt)],
                      [outs[0], wp.zeros(1, dtype=T.mat33), *outs[1:], counters])
            wp.launch(_weighted_sum, 1, [outs[0], outs[2], outs[1], Wa, Wb], [out])
        if not grad:
            return out.numpy()[0]
        tape.backward(out)
        return F.grad.numpy()[0], alpha.grad.numpy()[0], {k: arrays[k].grad.numpy()[0] for k in PARAMS}

    alpha0 = 0.2
    gF, galpha, gp = run(F0, alpha0, base, grad=True)
    flows = case != "identity" and yield_stress < 1.0
    capped = yield_stress < 0.1  # gamma = 1: the flow rate no longer matters
    assert (abs(gp["flow_rate"]) > 0) == (flows and not capped), gp
    _assert_close(gF, _central_difference(lambda F: run(F, alpha0, base), F0), rel=2e-6)
    _assert_close(galpha, _central_difference(lambda a: run(F0, a[()], base), np.array(alpha0)), rel=2e-6)
    for k in PARAMS:
        fd = _central_difference(lambda v: run(F0, alpha0, {**base, k: v[()]}), np.array(base[k]))
        _assert_close(gp[k], fd, rel=2e-6)


_inverted_stress = comparison.kernels(S, "poly6").inverted_stress


@wp.kernel(module="unique")
def _inverted_stress_loss(F: wp.array(dtype=T.mat33), W: wp.array(dtype=T.mat33), mu: wp.array(dtype=S),
                          lam: wp.array(dtype=S), model: int, out: wp.array(dtype=S)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.ddot(_inverted_stress(F[i], mu[0], lam[0], model), W[i]))


def _weighted_stress_gradient(kernel, model, F_np, W, grad):
    F = wp.array(F_np[None], dtype=T.mat33, requires_grad=True)
    mu, lam = wp.array([3.0], dtype=S, requires_grad=True), wp.array([2.0], dtype=S, requires_grad=True)
    out = wp.zeros(1, dtype=S, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(kernel, 1, [F, W, mu, lam, model], [out])
    if not grad:
        return out.numpy()[0]
    tape.backward(out)
    return F.grad.numpy()[0]


@pytest.mark.parametrize("model_name", ["hyperelastic", "stvk"])
@pytest.mark.parametrize("case", ["inverted", "inverted_repeated"])
def test_inverted_rest_fit_stress_adjoint(model_name, case):
    """``comparison.inverted_stress`` (a polynomial model's stress continued through det F = 0,
    what the rest model takes where the fit inverts) against central differences in ``F``, also
    where the positive singular values are repeated."""
    rng = np.random.default_rng(1)
    F0 = _cases(rng)[case]
    W = wp.array(rng.normal(size=(1, 3, 3)), dtype=T.mat33)
    model = _STRESS_MODELS[model_name]
    g = _weighted_stress_gradient(_inverted_stress_loss, model, F0, W, True)
    _assert_close(g, _central_difference(lambda F: _weighted_stress_gradient(_inverted_stress_loss, model, F, W, False),
                                         F0))


def _constitutive_update(F_np, regime, kind, hand):
    """``plasticity.constitutive_update`` of one particle, weighed: ``sum W_a F_e + W_b P + 3
    alpha + W_c F^-1``; with ``hand`` the gradient in ``F`` of it by the hand-written
    ``constitutive_update_adjoint`` (the fused step's under a tape)."""
    yield_stress, flow_rate, elastic_force = regime
    k = plasticity.kernels(S)
    rng = np.random.default_rng(9)
    Wa, Wb, Wc = (rng.normal(size=(3, 3)) for _ in range(3))
    F = wp.array(F_np[None], dtype=T.mat33)
    alpha = wp.array([0.2], dtype=S)
    mats = materials.make(S, mu=wp.array([1.0], dtype=S), lam=wp.array([1.5], dtype=S),
                          yield_stress=wp.array([yield_stress], dtype=S), flow_rate=wp.array([flow_rate], dtype=S),
                          hardening=wp.array([0.5], dtype=S), model=wp.array([kind], dtype=wp.int32),
                          elastic_force=wp.array([elastic_force], dtype=wp.int32))
    material = wp.zeros(1, dtype=wp.int32)
    outs = [wp.zeros(1, dtype=T.mat33), wp.zeros(1, dtype=T.mat33), wp.zeros(1, dtype=S), wp.zeros(1, dtype=T.mat33),
            wp.zeros(1, dtype=T.mat33)]
    wp.launch(k.constitutive_update, 1, [F, wp.zeros(1, dtype=T.mat33), alpha, material, mats, S(0.1)],
              [*outs, wp.zeros(4, dtype=wp.int32)])
    F_e, _, a, P, F_inv = (o.numpy()[0] for o in outs)
    if not hand:
        return (F_e * Wa).sum() + (P * Wb).sum() + 3.0 * a + (F_inv * Wc).sum()
    adj_F = wp.zeros(1, dtype=T.mat33)
    adj_params = [wp.zeros(1, dtype=S) for _ in range(5)]
    wp.launch(k.constitutive_update_adjoint, 1,
              [F, alpha, material, mats, S(0.1), outs[0], outs[4], wp.array(Wa[None], dtype=T.mat33),
               wp.array([3.0], dtype=S), wp.array(Wb[None], dtype=T.mat33), wp.array(Wc[None], dtype=T.mat33),
               adj_F, wp.zeros(1, dtype=S), *adj_params])
    return adj_F.numpy()[0]


_REGIMES = {"gamma_capped": (0.05, 40.0, 0), "flowing": (0.3, 4.0, 0), "elastic": (10.0, 4.0, 0),
            "flowing_variational": (0.3, 4.0, 1), "corotated": (np.inf, 0.0, 1)}


@pytest.mark.parametrize("kind", [0, 1], ids=["linear", "non_newtonian"])
@pytest.mark.parametrize("regime", list(_REGIMES))
@pytest.mark.parametrize("case", [*_REPEATED, "inverted_repeated"])
def test_hand_written_constitutive_adjoint_at_repeated_singular_values(case, regime, kind):
    """The hand-written ``constitutive_update_adjoint`` (one SVD for the flow, eq. 9's or the
    corotated stress and ``F^-1``) against float64 central differences, not only against Warp's
    generated adjoint (``test_hand_written_adjoints_match_the_generated_ones``, which goes
    through the same divided differences): at repeated singular values in and out of the
    SVD's frame, for each flow regime, both elastic forces (the variational one's elastic
    material takes the corotated stress) and an inverted ``F`` with a repeated pair (no
    flow there). Measured: within 1.3e-9 of the largest entry."""
    F0 = _cases(np.random.default_rng(3))[case]
    g = _constitutive_update(F0, _REGIMES[regime], kind, True)
    _assert_close(g, _central_difference(lambda F: _constitutive_update(F, _REGIMES[regime], kind, False), F0),
                  rel=1e-8)


def test_the_stress_of_an_energy_continued_through_inversion_jumps_where_two_singular_values_meet_in_size():
    """Where an inverted ``F`` has two singular values of one size and opposite signs
    (``sigma_i = -sigma_j``, ``diag(a, b, -b)``), the rotation-variant SVD may give either the
    minus sign, and ``psi`` of the signed singular values takes the smaller branch: a crease.
    The corotated stress (its gradient) jumps there, by more than its size, so no derivative,
    hand-written or by central differences, exists; the adjoint's ``sigma_i + sigma_j`` is
    regularised there (``isotropic.skew_coefficient``, docs/method.md). Measured (mu 3, lam 2,
    a = 1.15, b = 0.8): a jump of 19.4 against |P| = 14.5, one-sided slopes of psi 14.5 and
    -4.9."""
    @wp.kernel(module="unique", enable_backward=False)
    def corotated(F: wp.array(dtype=T.mat33), out: wp.array(dtype=T.mat33)):
        out[0] = _stress(F[0], S(3.0), S(2.0), forces.COROTATED)

    def stress(F_np):
        out = wp.zeros(1, dtype=T.mat33)
        wp.launch(corotated, 1, [wp.array(F_np[None], dtype=T.mat33)], [out])
        return out.numpy()[0]

    a, b, e = 1.15, 0.8, 1e-7
    above, below = stress(np.diag([a, b + e, -b])), stress(np.diag([a, b, -(b + e)]))
    assert np.abs(above - below).max() > np.abs(above).max()
    # Away from the crease the stress is continuous: the same two steps of a non-inverted F.
    assert np.abs(stress(np.diag([a, b + e, b])) - stress(np.diag([a, b, b + e]))).max() < 1e-5

@pytest.mark.parametrize("scalar,tol", [(wp.float64, 1e-12), (wp.float32, 2e-2)])
def test_rotation_variant_svd_reconstructs_and_flags_inversion(scalar, tol):
    """U diag(sigma) V^T rebuilds F (float32: up to 1e-2 on badly conditioned input,
    docs/method.md §3), U and V are proper rotations, and an inverted F has one negative sigma."""
    from warp_esph.sim import isotropic

    Ts = type_set(scalar)
    iso = isotropic.funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def k(F: wp.array(dtype=Ts.mat33), s_out: wp.array(dtype=Ts.vec3), G_out: wp.array(dtype=Ts.mat33)):
        i = wp.tid()
        s = iso.singular_values(F[i])
        s_out[i] = s
        G_out[i] = iso.isotropic_map(F[i], s, Ts.vec3(Ts.scalar(1.0), Ts.scalar(1.0), Ts.scalar(1.0)))

    rng = np.random.default_rng(7)
    Fs = [_rotation(rng) @ np.diag(d) @ _rotation(rng) for d in ([1.0, 1.0, 1.0], [2.0, 1.0, 0.5], [1e3, 1.0, 1e-3], [1.2, 0.9, -0.7])]
    Fs += list(rng.normal(size=(20, 3, 3)))
    F = np.array(Fs)
    s = wp.zeros(len(F), dtype=Ts.vec3)
    G = wp.zeros(len(F), dtype=Ts.mat33)
    wp.launch(k, len(F), [wp.array(F, dtype=Ts.mat33)], [s, G])
    s, G = s.numpy(), G.numpy()
    scale = np.abs(F).max(axis=(1, 2))
    assert (np.abs(G - F).max(axis=(1, 2)) <= tol * scale).all()
    assert ((s[:, 2] < 0) == (np.linalg.det(F) < 0)).all()
    assert (s[:, 0] >= s[:, 1]).all() and (s[:, 1] >= np.abs(s[:, 2]) - 1e-6).all()


def _hand_vs_generated_rollout(hand: bool, scalar=S, steps: int = 4, elastic_force: str = "variational",
                               model_name: str = "linear", flow_rate: float = 50.0, pressure_force: str = "spiky",
                               second_pressure_force: str | None = None, ground: float | None = None,
                               fit: str | None = None, pair_repulsion: float = 0.0, friction: float = 0.5,
                               image_jitter: float = 0.0, max_condition: float | None = None):
    """Gradients of a weighted sum of final positions through a yielding, stretching block,
    with the solver's hand-written adjoints (``hand``) or Warp's generated ones; with
    ``second_pressure_force`` a second block of that force touches the first; with ``ground``
    the block stands over the ground at that height with floor images
    (``add_ground(images=True)``, of ``friction``: 0, the images moving with their particles,
    and the block then also sliding along x at 0.3 m/s), squeezed towards it; ``fit``: ``Solver(fit=...)``; with
    ``pair_repulsion`` (``Material``'s) its particle 1 starts 0.3 dx from particle 0, within
    the repulsion's range (0.5 dx); with ``image_jitter`` the images' initial F is moved from
    ``I`` by up to that in each entry (no mirrors of their particles'); with ``max_condition``
    ``Solver(max_condition=...)``."""
    import warp_esph as we  # noqa: PLC0415

    mat = we.Material(density=1000.0, mu=1.0e3, lam=1.5e3, yield_stress=10.0, flow_rate=flow_rate, hardening=200.0,
                      pressure_stiffness=1.0, viscosity=2.0, elastic_force=elastic_force, model=model_name,
                      pressure_force=pressure_force, pair_repulsion=pair_repulsion)
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.08, 0.08), mat)
    if second_pressure_force is not None:
        b.add_box((0.0, 0.08, 0.0), (0.1, 0.08, 0.08), mat.replace(pressure_force=second_pressure_force, viscosity=3.0))
    if ground is not None:
        b.add_ground(ground, friction=friction, images=True)
    model = b.finalize(dtype=scalar, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    if pair_repulsion:
        x0 = model.particle_x0
        d = x0[1] - x0[0]
        x0[1] = x0[0] + 0.3 * 0.02 * d / np.linalg.norm(d)
        model.particle_x0 = x0
    model.particle_v0 = (20.0 if ground is None else -20.0) * model.particle_x0 * np.array([1.0, -0.5, 0.0])
    if friction == 0.0:
        model.particle_v0 = model.particle_v0 + np.array([0.3, 0.0, 0.0])
    solver = we.Solver(model, fit=fit, **({} if max_condition is None else {"max_condition": max_condition}))
    solver.hand_adjoints = hand
    # The fused forward with the hand-written adjoints, or neither (the corrected fit is not fused).
    assert solver.fast_under_tape() == (hand and fit in (None, "linear"))
    states = [model.state() for _ in range(steps + 1)]
    states[0].alpha.fill_(0.02)
    states[0].alpha_image.fill_(0.02)  # the images' hardening as their particles'
    if image_jitter:
        Fg = np.eye(3) + np.random.default_rng(6).uniform(-image_jitter, image_jitter, size=(model.particle_count, 3, 3))
        states[0].F_image.assign(Fg)
    w = wp.array(np.random.default_rng(0).normal(size=(model.particle_count, 3)), dtype=type_set(scalar).vec3)
    tape = wp.Tape()
    with tape:
        for k in range(steps):
            solver.step(states[k], states[k + 1], 1.0e-3)
    states[-1].x.grad.assign(w)
    tape.backward()
    # The images' own F and hardening too, which the variational force's images read (the paper's carry
    # their particle's).
    fields = ("x", "v", "F", "alpha") + (("F_image", "alpha_image") if ground is not None and elastic_force == "variational"
                                         else ())
    out = {name: getattr(states[0], name).grad.numpy().copy() for name in fields}
    for name in ("mu", "lam", "yield_stress", "flow_rate", "hardening", "pressure_stiffness", "viscosity"):
        out[name] = getattr(model, name).grad.numpy().copy()
    return out


@pytest.mark.parametrize("elastic_force", ["paper", "variational"])
@pytest.mark.parametrize("scalar,tol", [(wp.float64, 1e-10), (wp.float32, 2e-4)])
def test_hand_written_adjoints_match_the_generated_ones(scalar, tol, elastic_force):
    """The solver's hand-written adjoints (``deformation.update_deformation_adjoint``,
    ``forces.elastic_forces_adjoint`` or ``forces.variational_forces_adjoint``, the SPH
    ones) give the gradients Warp's generated adjoints give, to round-off, for every initial
    state field and material parameter (the rollout gradients are checked against float64
    central differences in ``tests/test_gradients.py``, which runs the hand-written ones).
    float32 checks the polynomial cosine's derivative."""
    _assert_hand_matches_generated(scalar, tol, elastic_force=elastic_force)


def _assert_hand_matches_generated(scalar, tol, unreached=(), **kw):
    hand = _hand_vs_generated_rollout(True, scalar, **kw)
    gen = _hand_vs_generated_rollout(False, scalar, **kw)
    for name, g in gen.items():
        if name in unreached:  # both zero: a parameter the loss does not reach
            assert not hand[name].any() and not g.any(), name
            continue
        scale = np.abs(g).max()
        assert scale > 0, f"the loss does not reach {name}"
        err = np.abs(hand[name] - g).max() / scale
        assert err <= tol, (name, err)


@pytest.mark.parametrize("model_name,flow_rate", [("non_newtonian", 50.0), ("linear", 2000.0)])
def test_hand_written_constitutive_adjoint_other_branches(model_name, flow_rate):
    """``plasticity.constitutive_update_adjoint`` on the non-Newtonian flow rule and with
    ``flow_rate * dt = 2`` (some flows saturate at gamma = 1, where the gradient must stop
    at the clamp as the generated one does), float64, against Warp's generated adjoints."""
    _assert_hand_matches_generated(wp.float64, 1e-10, model_name=model_name, flow_rate=flow_rate)


@pytest.mark.parametrize("model_name", ["linear", "non_newtonian"])
def test_hand_written_constitutive_adjoint_of_the_corotated_stress(model_name):
    """``plasticity.constitutive_update_adjoint`` where the material cannot flow
    (``flow_rate = 0``) on the variational force: its stress is the corotated one
    (``forces.stress_model``), on the incremental linear fit (``Solver(fit="linear")``; the
    default would run the rest model), float64, against Warp's generated adjoints."""
    _assert_hand_matches_generated(wp.float64, 1e-10, model_name=model_name, flow_rate=0.0, fit="linear",
                                   unreached=("yield_stress", "flow_rate", "hardening", "alpha"))


@pytest.mark.parametrize("pressure_force", ["energy", "energy_spiky"])
@pytest.mark.parametrize("scalar,tol", [(wp.float64, 1e-10), (wp.float32, 2e-4)])
def test_hand_written_energy_pressure_adjoint(scalar, tol, pressure_force):
    """``pressure.pressure_forces_adjoint`` and ``density_adjoint`` on the energy pressure
    forces (``pressure_force = "energy"``, the default, and ``"energy_spiky"``, its energy of
    the spiky-kernel density; the spiky one is in the test above) against Warp's generated
    adjoints."""
    _assert_hand_matches_generated(scalar, tol, pressure_force=pressure_force)


@pytest.mark.parametrize("pressure_force", ["energy", "spiky", "energy_spiky"])
@pytest.mark.parametrize("scalar,tol", [(wp.float64, 1e-10), (wp.float32, 2e-4)])
def test_hand_written_pair_repulsion_adjoint(scalar, tol, pressure_force):
    """``Material.pair_repulsion``'s adjoint in ``pressure.pressure_pair_adjoint`` (the fused
    step's adjoint pass; ``pressure_forces_adjoint`` runs the same function) against Warp's
    generated adjoint of the unfused step, with a pair starting 0.3 dx apart, within the
    repulsion's 0.5 dx: every initial state field and parameter, ``k_p`` (which scales the
    repulsion) among them."""
    _assert_hand_matches_generated(scalar, tol, pressure_force=pressure_force, pair_repulsion=2.0)


@pytest.mark.parametrize("scalar,tol", [(wp.float64, 1e-10), (wp.float32, 2e-4)])
def test_hand_written_pressure_adjoints_between_energy_spiky_and_energy_bodies(scalar, tol):
    """Two touching blocks, ``energy_spiky`` on the energy force: the pressure density is the
    spiky sum in one body and the SPH density in the other, and pairs across the contact read
    both (``State.pressure_density`` beside ``State.density``); hand-written adjoints against
    the generated ones."""
    _assert_hand_matches_generated(scalar, tol, pressure_force="energy_spiky", second_pressure_force="energy")


@pytest.mark.parametrize("ground", [None, -0.045], ids=["free", "images"])
def test_both_densities_adjoints_run_in_one_pass_over_the_pairs(ground):
    """With ``energy_spiky`` the step sums two densities over the same pairs (the SPH one and
    the pressure density); the backward takes both gradients back to the positions in one
    ``density_adjoint`` launch per step (``pressure.launch_state_densities_adjoint``), not one
    launch per density, and its gradients are the two passes' to float64 round-off (their
    sums in another order; ``test_hand_written_energy_pressure_adjoint`` checks them against
    the generated adjoints). With floor images too."""
    import warp_esph as we  # noqa: PLC0415
    from warp_esph.sim import pressure  # noqa: PLC0415

    mat = we.Material(density=1000.0, mu=1.0e3, lam=1.5e3, pressure_stiffness=1.0, pressure_force="energy_spiky")
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.0, 0.0), (0.08, 0.06, 0.06), mat)
    if ground is not None:
        b.add_ground(ground, images=True)
    model = b.finalize(dtype=S, requires_grad=True)
    assert model.separate_pressure_density
    model.particle_x0 += np.random.default_rng(3).normal(scale=0.1 * 0.02, size=model.particle_x0.shape)
    solver = we.Solver(model)
    steps = 2
    states = [model.state() for _ in range(steps + 1)]
    tape = wp.Tape()
    with tape:
        for k in range(steps):
            solver.step(states[k], states[k + 1], 1.0e-3)
    states[-1].x.grad.assign(np.random.default_rng(0).normal(size=(model.particle_count, 3)))
    launched = []
    replayed = model.launches

    def counted(kernel, *args, **kwargs):
        launched.append(kernel.key.rsplit("__locals__", 1)[-1])
        return replayed(kernel, *args, **kwargs)

    model.launches = counted
    try:
        tape.backward()
    finally:
        model.launches = replayed
    assert launched.count("density_adjoint") == steps, launched

    # One pass against the two it replaces, on the last step's densities' gradients.
    out = states[-1]
    rng = np.random.default_rng(1)
    out.density.grad.assign(rng.normal(size=model.particle_count))
    out.pressure_density.grad.assign(rng.normal(size=model.particle_count))
    x = states[-2].x
    x.grad.zero_()
    pressure.launch_state_densities_adjoint(model, x, out)
    both = x.grad.numpy().copy()
    x.grad.zero_()
    pressure.launch_density_adjoint(model, x, out.neighbors, out.neighbor_count, out.density)
    pressure.launch_density_adjoint(model, x, out.neighbors, out.neighbor_count, out.pressure_density, of_pressure=True)
    apart = x.grad.numpy()
    assert np.abs(apart).max() > 0
    assert np.abs(both - apart).max() <= 1e-13 * np.abs(apart).max()


@pytest.mark.parametrize("pressure_force", ["energy", "spiky", "energy_spiky"])
@pytest.mark.parametrize("ground", [None, -0.045], ids=["free", "images"])
def test_pressure_pairs_adjoint_runs_in_the_variational_force_adjoints_pass(ground, pressure_force):
    """The fused step applies the variational force and the SPH pressure and viscosity in one
    loop over the pairs; its backward takes both in one pass too
    (``forces.variational_forces_adjoint`` with ``sph``): no ``pressure_forces_adjoint``
    launch, and the gradients of the two passes it replaces to float64 round-off (their
    scatters in another order; ``test_hand_written_adjoints_match_the_generated_ones`` and
    ``..._carry_the_floor_images`` check them against the generated adjoints)."""
    from warp_esph.sim import forces as forces_, pressure  # noqa: PLC0415

    model, solver, states, tape = _taped_block(pressure_force, ground)
    launched = _backward_launches(model, tape)
    assert "pressure_forces_adjoint" not in launched and launched.count("variational_forces_adjoint") == len(states) - 1

    # One pass against the two it replaces, on a step's gradients.
    s_in, s_out = states[-2], states[-1]
    rng = np.random.default_rng(1)
    s_out.force.grad.assign(rng.normal(size=(model.particle_count, 3)))
    outs = (s_in.x.grad, s_in.v.grad, s_out.stress.grad, s_out.F_flowed.grad, s_out.density.grad,
            pressure.pressure_density(model, s_out).grad, model.pressure_stiffness.grad, model.viscosity.grad)
    args = (model, s_in, s_out, solver.min_neighbors, solver.max_condition)

    def run(one_pass):
        for a in outs:
            a.zero_()
        if one_pass:
            forces_.launch_variational_forces_adjoint(*args, sph=True)
        else:
            pressure.launch_pressure_forces_adjoint(model, s_in, s_out)
            forces_.launch_variational_forces_adjoint(*args)
        return [a.numpy().copy() for a in outs]

    for both, apart in zip(run(True), run(False)):
        assert np.abs(apart).max() > 0
        assert np.abs(both - apart).max() <= 1e-13 * np.abs(apart).max()


def _taped_block(pressure_force, ground=None, steps=2, flow_rate=50.0):
    """A yielding float64 block of the variational force (the fused step under a tape), over
    the ground with floor images at ``ground``, taped over ``steps`` steps from a stretching
    start; the last state's position gradient seeded."""
    import warp_esph as we  # noqa: PLC0415

    mat = we.Material(density=1000.0, mu=1.0e3, lam=1.5e3, yield_stress=10.0, flow_rate=flow_rate, pressure_stiffness=1.0,
                      viscosity=2.0, pressure_force=pressure_force)
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.0, 0.0), (0.08, 0.06, 0.06), mat)
    if ground is not None:
        b.add_ground(ground, images=True)
    model = b.finalize(dtype=S, requires_grad=True)
    model.particle_x0 += np.random.default_rng(3).normal(scale=0.1 * 0.02, size=model.particle_x0.shape)
    model.particle_v0 = 20.0 * model.particle_x0 * np.array([1.0, -0.5, 0.0])
    solver = we.Solver(model)
    states = [model.state() for _ in range(steps + 1)]
    tape = wp.Tape()
    with tape:
        for k in range(steps):
            solver.step(states[k], states[k + 1], 1.0e-3)
    assert solver.fast_under_tape()
    states[-1].x.grad.assign(np.random.default_rng(0).normal(size=(model.particle_count, 3)))
    return model, solver, states, tape


def _backward_launches(model, tape):
    """The names of the kernels ``tape.backward()`` launches through the model's launches."""
    launched = []
    replayed = model.launches

    def counted(kernel, *args, **kwargs):
        launched.append(kernel.key.rsplit("__locals__", 1)[-1])
        return replayed(kernel, *args, **kwargs)

    model.launches = counted
    try:
        tape.backward()
    finally:
        model.launches = replayed
    return launched


@pytest.mark.parametrize("pressure_force,ground,elastic_force", [
    ("energy", -0.045, "variational"), ("energy_spiky", -0.045, "variational"), ("spiky", -0.045, "variational"),
    ("energy", -0.031, "variational"), ("energy", -0.045, "paper"), ("energy", -0.031, "paper")],
    ids=["energy", "energy_spiky", "spiky", "energy-contact", "paper", "paper-contact"])
@pytest.mark.parametrize("scalar,tol", [(wp.float64, 1e-10), (wp.float32, 2e-4)])
def test_hand_written_adjoints_carry_the_floor_images(scalar, tol, pressure_force, ground, elastic_force):
    """With ``add_ground(images=True)`` the hand-written adjoints carry the image terms (the
    fit's image pairs, the images' energy through their own moment matrices, the image
    densities; the images' pressure forces through the generated adjoint of
    ``pressure.image_pressure_forces`` alone) and give the generated adjoints' gradients:
    the plane 0.75 dx under the bottom layer (the images mirrors), or 0.05 dx under it
    (below half a spacing, the images held, and the collider's contact within the rollout).
    Leaving any one of the four image parts out moves some gradient by 1e-3 to 0.6 of its
    scale (measured). With the paper's force (eqs. 10-13) its image pairs
    (``forces.elastic_forces_adjoint``); through its contact in float32 the two schedules'
    forwards (one SVD against two) part by round-off that moves the viscosity gradient by
    1.0e-3 of its scale, yield_stress 1.2e-4 (measured; 1e-10 in float64)."""
    if scalar == wp.float32 and elastic_force == "paper" and ground > -0.04:
        tol = 2e-3
    _assert_hand_matches_generated(scalar, tol, pressure_force=pressure_force, ground=ground,
                                   elastic_force=elastic_force)


@pytest.mark.parametrize("ground,fit,image_jitter", [
    (-0.045, None, 0.0), (-0.037, None, 0.0), (-0.031, None, 0.0), (-0.045, "curvature_corrected", 0.0),
    (-0.037, "curvature_corrected", 0.0), (-0.045, None, 0.01), (-0.045, "curvature_corrected", 0.01)],
    ids=["linear", "linear-ramp", "linear-contact", "corrected", "corrected-ramp", "linear-fade", "corrected-fade"])
@pytest.mark.parametrize("scalar,tol", [(wp.float64, 1e-10), (wp.float32, 2e-4)])
def test_hand_written_adjoints_carry_the_moving_floor_images(scalar, tol, ground, fit, image_jitter):
    """On the frictionless imaged ground (``friction = 0``) the images move with their
    particles over the step (``deformation.partner_displacement``: ``J(x_j) u_j`` in both fits'
    image pairs and in each image's own fit, ``J(x_j) v_j`` in the SPH viscosity), and the
    block slides along it: the hand-written adjoints of the linear and the corrected fit give
    the generated adjoints' gradients (to 1e-10 in float64, 2e-4 in float32, as the rough
    images'), with the bottom layer 0.75 dx over the plane (mirrors), 0.35 dx (on the images'
    depth ramp, ``deformation.image_depth``, where the Jacobian's own slope enters:
    ``mirrored_motion_adjoint``) and 0.05 dx (held at half a spacing deep, and the collider's
    contact). The elastic force sends every image's reaction to its particle through ``J``
    (``forces.moving_image_forces``), so its adjoint carries ``J``'s slope too: without it the
    ramp's case read 1.3e-4 off (measured). The image's share of the energy fades over the last
    half spacing under ``h`` (``forces.image_energy_share``), where the second layer stands,
    1.75 dx over the plane in the mirrors' case: with the images' F no mirrors (``image_jitter``)
    its slope's force and the maps' dependence on it (``forces.image_share_adjoint``) enter; without the share's second slope
    the fade cases read 6.0e-6 off, without the maps' slope 1.1e-3 / 1.6e-3 (linear / corrected;
    measured)."""
    _assert_hand_matches_generated(scalar, tol, pressure_force="energy", ground=ground, friction=0.0, fit=fit,
                                   image_jitter=image_jitter)


@pytest.mark.parametrize("fit", [None, "curvature_corrected"], ids=["linear", "corrected"])
def test_hand_written_adjoints_carry_the_image_share_force_through_the_guards_fade(fit):
    """The image's share's force (``forces.image_share_force``, ``-s V c' (psi_g - psi) n``)
    carries the guards' fade ``s`` of its particle's fit, and its adjoint a term in ``adj s``
    (``forces.image_share_adjoint``), read through ``ds/dA`` only where the fade is neither 0
    nor 1. The fade case above with ``max_condition`` 1.3, so that the condition guard fades
    many fits (none from 3 up to the default 20: there that term read nothing, removed or
    not): within 1e-10 (measured 2.0e-14 / 4.7e-15, linear / corrected); without the term
    2.6e-5 / 2.0e-5 off (measured)."""
    _assert_hand_matches_generated(wp.float64, 1e-10, pressure_force="energy", ground=-0.045, friction=0.0, fit=fit,
                                   image_jitter=0.01, max_condition=1.3)


_gf = guards.guard_funcs(S)


@wp.kernel(module="unique", enable_backward=False)
def _guard_parts(A: wp.array(dtype=T.mat33), same: wp.array(dtype=S), r2: wp.array(dtype=S), hh: S, min_neighbors: int,
                 max_condition: S, code: wp.array(dtype=wp.int32), code_alone: wp.array(dtype=wp.int32),
                 scale: wp.array(dtype=S), scale_alone: wp.array(dtype=S), dA: wp.array(dtype=T.mat33),
                 dn: wp.array(dtype=S), c: wp.array(dtype=S), dc: wp.array(dtype=S)):
    i = wp.tid()
    k, s, G, d = _gf.guard(A[i], same[i], min_neighbors, max_condition)
    code[i] = k
    scale[i] = s
    dA[i] = G
    dn[i] = d
    code_alone[i] = _gf.guard_code(A[i], same[i], min_neighbors, max_condition)
    scale_alone[i] = _gf.guard_scale(A[i], same[i], min_neighbors, max_condition)
    w, dw = _gf.count_weight(r2[i], hh)
    c[i] = w
    dc[i] = dw


def _guard_parts_of(A, same, r2, hh=1.0, min_neighbors=6, max_condition=20.0):
    n = len(A)
    outs = dict(code=wp.zeros(n, dtype=wp.int32), code_alone=wp.zeros(n, dtype=wp.int32), scale=wp.zeros(n, dtype=S),
                scale_alone=wp.zeros(n, dtype=S), dA=wp.zeros(n, dtype=T.mat33), dn=wp.zeros(n, dtype=S),
                c=wp.zeros(n, dtype=S), dc=wp.zeros(n, dtype=S))
    wp.launch(_guard_parts, n, [wp.array(A, dtype=T.mat33), wp.array(same, dtype=S), wp.array(r2, dtype=S), hh,
                                min_neighbors, max_condition], list(outs.values()))
    return {k: v.numpy() for k, v in outs.items()}


def test_the_guards_fade_with_their_slopes_and_switch_only_where_the_fade_is_zero():
    """``guards.guard`` (the switch, the fade and its slopes at once) against its parts and
    central differences: the fade's slopes in the moment matrix (through the eigenvalues) and
    in the smooth neighbour count, the count weight's slope in ``r^2``, both continuous with
    their slopes at the ends of their bands (``count_weight``: 1 up to 0.95 h, 0 from h), and
    the switch set only where the fade is zero."""
    rng = np.random.default_rng(11)
    conds = np.concatenate([rng.uniform(1.0, 60.0, 40), [19.0, 21.0, 39.0, 41.0]])
    # Positive definite, as every moment matrix (a weighted sum of outer products) is.
    Q = [_rotation(rng) for _ in conds]
    A = np.array([q @ np.diag([1.0, rng.uniform(1.0, c), c]) @ q.T * 0.3 for q, c in zip(Q, conds)])
    same = rng.uniform(4.0, 8.0, len(A))
    same[:4] = [5.0, 6.0, 5.5, 4.9]
    q0 = guards.COUNT_FADE**2
    r2 = np.concatenate([rng.uniform(0.8, 1.05, len(A) - 4), [q0, 1.0, 0.5 * (q0 + 1.0), 1.2]])
    out = _guard_parts_of(A, same, r2)
    np.testing.assert_array_equal(out["code"], out["code_alone"])
    np.testing.assert_array_equal(out["scale"], out["scale_alone"])
    assert (out["scale"][out["code"] != 0] == 0.0).all()
    assert set(out["code"]) == {0, 1, 2}, out["code"]
    faded = (out["scale"] > 0.0) & (out["scale"] < 1.0)
    assert faded.sum() > 5
    eps = 1e-6
    for i in np.flatnonzero(out["code"] == 0):
        # d s / d A along a random symmetric direction, and d s / d same.
        E = rng.normal(size=(3, 3))
        E = 0.5 * (E + E.T)
        up = _guard_parts_of(np.array([A[i] + eps * E, A[i] - eps * E]), np.full(2, same[i]), np.ones(2))["scale"]
        assert (up[0] - up[1]) / (2 * eps) == pytest.approx(np.sum(out["dA"][i] * E), rel=1e-5, abs=1e-8), i
        up = _guard_parts_of(np.array([A[i], A[i]]), same[i] + np.array([eps, -eps]), np.ones(2))["scale"]
        assert (up[0] - up[1]) / (2 * eps) == pytest.approx(out["dn"][i], rel=1e-5, abs=1e-5), i
    # The count weight: 1 inside the band, 0 from h, its slope the central difference's, and
    # the fade's value and slope continuous at the ends of both bands.
    w = _guard_parts_of(np.tile(np.eye(3), (5, 1, 1)), np.full(5, 6.0),
                        np.array([q0 - eps, q0 + eps, 1.0 - eps, 1.0 + eps, 0.9]))
    np.testing.assert_allclose(w["c"][:4], [1.0, 1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(w["dc"][:4], 0.0, atol=1e-3)  # the largest slope is 15
    mid = 0.5 * (q0 + 1.0)
    side = _guard_parts_of(np.tile(np.eye(3), (2, 1, 1)), np.full(2, 6.0), np.array([mid + eps, mid - eps]))["c"]
    assert (side[0] - side[1]) / (2 * eps) == pytest.approx(out["dc"][-2], rel=1e-6)
    ends = _guard_parts_of(np.tile(np.eye(3), (4, 1, 1)), np.array([5.0 - eps, 5.0 + eps, 6.0 - eps, 6.0 + eps]),
                           np.ones(4))
    np.testing.assert_allclose(ends["scale"], [0.0, 0.0, 1.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(ends["dn"], 0.0, atol=1e-4)


@pytest.mark.parametrize("case", ["generated", "corrected", "rest", "paper_images", "ghost"])
def test_backward_leaves_the_recorded_forces_as_the_forward_wrote_them(case):
    """Warp's generated adjoint of the elastic forces replays each ``wp.func``'s forward, and
    the funcs scatter the pair forces: ``tape.backward()`` added the step's elastic forces to
    ``State.force`` once more (2.5-93 % off, measured by an audit; the gradients were right).
    ``replay.kept_through_backward`` restores them: every state the tape recorded reads after
    the backward what it read before, on each path that records a generated adjoint (the
    non-fused linear and corrected fits, a rest-configuration material (whose hand-written
    adjoint, ``comparison.adjoint_kernels``, the solver records by default), the paper's force
    on the imaged ground, a ghost floor; each failed without it)."""
    import warp_esph as we  # noqa: PLC0415

    elastic = "paper" if case == "paper_images" else "variational"
    mat = we.Material(density=1000.0, mu=1.0e3, lam=1.5e3, yield_stress=10.0, flow_rate=50.0, viscosity=2.0,
                      elastic_force=elastic, deformation="rest" if case == "rest" else "incremental")
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    body = b.add_box((0.0, 0.0, 0.0), (0.1, 0.08, 0.08), mat)
    if case == "paper_images":
        b.add_ground(-0.045, friction=0.5, images=True)
    if case == "ghost":
        b.add_particle_floor(body, margin=0.02, ghost=True)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_v0 = -20.0 * model.particle_x0 * np.array([1.0, -0.5, 0.0])
    solver = we.Solver(model, fit="curvature_corrected" if case == "corrected" else None, fused=case != "generated")
    if case in ("generated", "corrected", "paper_images", "rest"):
        solver.hand_adjoints = False
    states = [model.state() for _ in range(4)]
    tape = wp.Tape()
    with tape:
        for k in range(3):
            solver.step(states[k], states[k + 1], 1.0e-3)
    before = [s.force.numpy().copy() for s in states[1:]]
    assert all(np.abs(f).max() > 0.0 for f in before)
    # (Weights that differ by particle: the internal forces move the centre of mass nowhere.)
    states[-1].x.grad.assign(np.random.default_rng(0).normal(size=(model.particle_count, 3)))
    tape.backward()
    assert np.abs(model.mu.grad.numpy()).max() > 0.0
    for k, f in enumerate(before):
        np.testing.assert_array_equal(states[k + 1].force.numpy(), f, err_msg=f"step {k}")
