"""What ``yield_stress`` and ``flow_rate`` mean in a lab's units (Material docstring).

The flow rule compares ``|s| = 2 mu |sigma - mean(sigma)|`` with ``Y``: simple shear ``tau``
has ``|s| = sqrt(2) tau`` and uniaxial ``sigma`` has ``|s| = sqrt(2/3) sigma``. Above yield
the deviatoric log strain relaxes at ``flow_rate (|s| - Y) / |s|``, which in steady simple
shear balances the imposed rate when ``tau = Y / sqrt(2) + (mu / flow_rate) gamma_dot``.
The test drives a material point through the project's own constitutive update (plastic
flow, then eq. 9 stress) in simple shear and reads the steady stress.
"""

import functools
import math
import re

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.material import MODEL_IDS
from warp_esph.sim import forces, plasticity


@functools.cache
def _shear_kernel():
    S = wp.float64
    flow = plasticity.kernels(S).flow
    stress = forces.funcs(S, "poly6").stress
    mat33 = wp.types.matrix(shape=(3, 3), dtype=S)
    vec3 = wp.types.vector(length=3, dtype=S)

    @wp.kernel(module="unique")
    def simple_shear(
        rate: wp.array(dtype=S),
        mu: S,
        lam: S,
        yield_stress: S,
        flow_rate: S,
        dt: S,
        steps: int,
        model: int,
        counters: wp.array(dtype=wp.int32),
        tau_xy: wp.array(dtype=S),
        s_norm: wp.array(dtype=S),
    ):
        # One material point per shear rate: F <- (I + dt L) F, then this step's plastic
        # flow and stress, as a particle in a homogeneous simple shear would see them.
        i = wp.tid()
        L = mat33()
        L[0, 1] = rate[i]
        step = wp.identity(n=3, dtype=S) + dt * L
        F = wp.identity(n=3, dtype=S)
        a = S(0.0)
        P = mat33()
        for _ in range(steps):
            F = step * F
            F, F_lo, a = flow(F, mat33(), a, mu, yield_stress, flow_rate, S(0.0), model, dt, counters)
            P = stress(F, mu, lam, model)
        # The spatial (Kirchhoff) stress P* F^T = U diag(sigma^2 P^) U^T: P* alone carries
        # the elastic rotation the shear's spin has accumulated.
        K = P * wp.transpose(F)
        tau_xy[i] = S(0.5) * (K[0, 1] + K[1, 0])
        U = mat33()
        sig = vec3()
        V = mat33()
        wp.svd3(F, U, sig, V)
        mean = (sig[0] + sig[1] + sig[2]) / S(3.0)
        dev = sig - vec3(mean, mean, mean)
        s_norm[i] = S(2.0) * mu * wp.length(dev)

    return simple_shear


def _steady_shear(material: we.Material, rates, dt=2.0e-5, duration=0.06):
    rates = np.asarray(rates, dtype=np.float64)
    n = len(rates)
    tau = wp.zeros(n, dtype=wp.float64, device="cpu")
    s = wp.zeros(n, dtype=wp.float64, device="cpu")
    counters = wp.zeros(4, dtype=wp.int32, device="cpu")
    wp.launch(
        _shear_kernel(),
        n,
        [wp.array(rates, dtype=wp.float64, device="cpu"), material.mu, material.lam, material.yield_stress,
         material.flow_rate, dt, int(round(duration / dt)), MODEL_IDS[material.model], counters],
        [tau, s],
        device="cpu",
    )
    return tau.numpy(), s.numpy()


def test_rheology_constructor_converts_the_lab_quantities():
    m = we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=100.0, plastic_viscosity=50.0)
    assert m.yield_stress == pytest.approx(100.0 * math.sqrt(2.0))
    assert m.shear_yield_stress == pytest.approx(100.0)
    assert m.uniaxial_yield_stress == pytest.approx(100.0 * math.sqrt(3.0))  # von Mises
    assert m.flow_rate == pytest.approx(m.mu / 50.0)
    assert m.plastic_viscosity == pytest.approx(50.0)
    u = we.Material.from_rheology(1.0e5, 0.3, uniaxial_yield_stress=300.0, plastic_viscosity=50.0)
    assert u.uniaxial_yield_stress == pytest.approx(300.0)
    assert u.yield_stress == pytest.approx(300.0 * math.sqrt(2.0 / 3.0))
    assert we.Material(mu=1.0, lam=1.0).plastic_viscosity == math.inf


@pytest.mark.parametrize("call, message", [
    (lambda: we.Material.preset("dough", shear_yield_stress=50.0),
     r"'shear_yield_stress' is not allowed in Material\.preset: must be one of mu, .*; shear_yield_stress is a lab's value, "
     r"not a field: yield_stress = sqrt\(2\) shear_yield_stress \(give the fields, or make the material with "
     r"Material\.from_rheology\)"),
    (lambda: we.Material.preset("dough").replace(plastic_viscosity=10.0),
     r"'plastic_viscosity' is not allowed in Material\.replace: .*; plastic_viscosity is a lab's value, not a field: "
     r"flow_rate = mu / plastic_viscosity"),
    (lambda: we.Material.from_young(1e4, 0.3, uniaxial_yield_stress=80.0),
     r"uniaxial_yield_stress is a lab's value, not a field: yield_stress = sqrt\(2/3\) uniaxial_yield_stress"),
])
def test_a_lab_quantity_given_as_a_field_is_refused_saying_which_field_it_sets(call, message):
    """A preset set to a rheometer's values (``Material.preset("dough", shear_yield_stress=50)``)
    is what a lab's user tries first: the refusal listed the fields alone, not that the value
    is yield_stress / sqrt(2), nor where a lab's values are taken."""
    with pytest.raises(ValueError, match=message):
        call()


def test_a_lab_quantity_fitted_or_swept_is_refused_saying_which_parameter_it_sets():
    """``warp-esph fit --params shear_yield_stress`` and ``sweep --param
    dough.plastic_viscosity=...``: a rheometer's user names the values measured; the refusals
    listed the parameters alone."""
    from warp_esph.fit import check_options
    from warp_esph.sweep import parse_param

    with pytest.raises(ValueError, match=r"entry 'shear_yield_stress' is not allowed: must be one of mu, .*; "
                                         r"shear_yield_stress is a lab's value, not a parameter: yield_stress = sqrt\(2\) "
                                         r"shear_yield_stress \(fit yield_stress: the fitted material's "
                                         r"shear_yield_stress is yield_stress / sqrt\(2\)\)"):
        check_options(params="shear_yield_stress", iterations=1)
    with pytest.raises(ValueError, match=r"params entry 'dough.plastic_viscosity' is not allowed: unknown parameter; .*; "
                                         r"plastic_viscosity is a lab's value, not a parameter: flow_rate = mu / "
                                         r"plastic_viscosity \(sweep flow_rate\)"):
        parse_param("dough.plastic_viscosity=5:50:log:3")


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(plastic_viscosity=1.0), "shear_yield_stress"),
        (dict(shear_yield_stress=1.0, uniaxial_yield_stress=1.0, plastic_viscosity=1.0), "shear_yield_stress"),
        (dict(shear_yield_stress=-1.0, plastic_viscosity=1.0), "shear_yield_stress"),
        (dict(shear_yield_stress=1.0, plastic_viscosity=0.0), "plastic_viscosity"),
        (dict(shear_yield_stress=1.0, plastic_viscosity=1.0, flow_rate=3.0), "flow_rate"),
    ],
)
def test_rheology_constructor_names_the_bad_parameter(kwargs, name):
    with pytest.raises(ValueError, match=name):
        we.Material.from_rheology(1.0e5, 0.3, **kwargs)


@pytest.mark.parametrize("call, message", [
    # sqrt(2) x 1.5e308 overflowed to inf: an elastic material, the yield stress given without effect.
    (lambda: we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=1.5e308, plastic_viscosity=50.0),
     r"^shear_yield_stress = 1\.5e\+308 is not allowed: yield_stress = sqrt\(2\) shear_yield_stress must be a finite"),
    # mu / 1e-320 was refused as 'Material.flow_rate = inf', a value nobody gave.
    (lambda: we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=100.0, plastic_viscosity=1e-320),
     r"^plastic_viscosity = 1e-320 is not allowed with E = 100000\.0, nu = 0\.3: flow_rate = mu / plastic_viscosity "
     r"= 38461\.5 / 9\.99989e-321 = inf must be a finite number above 0"),
    # mu / 1e100 underflowed to a flow rate of 0: an elastic material, without a word.
    (lambda: we.Material.from_rheology(1e-300, 0.3, shear_yield_stress=0.0, plastic_viscosity=1e100),
     r"^plastic_viscosity = 1e\+100 is not allowed with E = 1e-300, nu = 0\.3: .* = 0 must be a finite number above 0"),
    # mu or lam past the floats were refused as 'Material.mu = inf', 'Material.lam = inf'.
    (lambda: we.Material.from_young(1e308, -0.9), r"^E = 1e\+308 and nu = -0\.9 are not allowed together: the Lame "
                                                   r"parameters they give, mu = E / \(2 \(1 \+ nu\)\) = inf"),
    (lambda: we.Material.from_rheology(1e300, 0.4999999999999999, shear_yield_stress=1.0, plastic_viscosity=1.0),
     r"^E = 1e\+300 and nu = 0\.4999999999999999 are not allowed together: .* lam = .* = inf, must be finite"),
    # A subnormal or tiny E (or nu) was accepted and refused only at the model's build, naming
    # Material.mu (or lam) = 3.84383e-321, in either dtype; E = 5e-324 as 'Material.mu = 0.0'.
    (lambda: we.Material.from_young(1e-320, 0.3), r"^E = 1e-320 and nu = 0\.3 are not allowed together: .* mu = E / "
                                                  r"\(2 \(1 \+ nu\)\) = 3\.84383e-321 .* must be at least 2\.23e-308 \(mu\).*"
                                                  r"give a larger E$"),
    (lambda: we.Material.from_young(5e-324, 0.3), r"^E = 5e-324 and nu = 0\.3 are not allowed together: .* mu = .* = 0 "),
    (lambda: we.Material.from_young(3e-308, 0.49), r"^E = 3e-308 and nu = 0\.49 are not allowed together: .* = 1\.00671e-308"),
    (lambda: we.Material.from_young(1.0, 1e-310), r"^E = 1\.0 and nu = 1e-310 are not allowed together: .* lam = .* "
                                                  r"= 1e-310, must be .*; give nu = 0 or a nu further from 0$"),
    (lambda: we.Material.from_rheology(1e-320, 0.3, shear_yield_stress=1.0, plastic_viscosity=1.0),
     r"^E = 1e-320 and nu = 0\.3 are not allowed together"),
])
def test_the_constructors_name_the_lab_quantity_whose_derived_value_leaves_the_floats(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_a_modulus_from_e_and_nu_that_a_precision_cannot_hold_is_refused_naming_e_and_nu():
    """E = 1e-39 holds in float64 but its mu = 3.8e-40 not in float32: the build refused it as
    'Material.mu = 3.84615e-40', a value never given. It names E and nu now, as the constructor
    does for what no precision holds; a copy with other moduli names its own."""
    import warp as wp

    def build(material, dtype):
        b = we.SceneBuilder(spacing=0.05)
        b.add_box((0.0, 0.2, 0.0), (0.1, 0.1, 0.1), material)
        return b.finalize(dtype=dtype)

    for soft in (we.Material.from_young(1e-39, 0.3),
                 we.Material.from_rheology(1e-39, 0.3, shear_yield_stress=0.0, plastic_viscosity=1e-40)):
        with pytest.raises(ValueError, match=r"^E = 1e-39 \(material 0\) is not allowed in float32: with nu = 0\.3 it "
                                             r"gives mu = E / \(2 \(1 \+ nu\)\) = 3\.84615e-40: must be 0 or at least "
                                             r"1\.18e-38 in size; use dtype=float64 or a larger value$"):
            build(soft, wp.float32)
        assert build(soft, wp.float64).particle_count > 0
    with pytest.raises(ValueError, match=r"^Material\.mu = 1e-40 \(material 0\) is not allowed in float32"):
        build(we.Material.from_young(1e-39, 0.3).replace(mu=1e-40), wp.float32)


def test_rheology_constructor_needs_the_plastic_viscosity():
    """Left out, the plastic viscosity was infinite: a flow rate of 0, an elastic material on
    which the shear yield stress given had no effect. An explicit ``inf`` still says so. The
    signature said so too: ``plastic_viscosity: float | None = None`` showed a default that
    every call without it was refused for; it is a required keyword."""
    import inspect  # noqa: PLC0415

    param = inspect.signature(we.Material.from_rheology).parameters["plastic_viscosity"]
    assert (param.kind, param.default, param.annotation) == (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.empty, "float")
    with pytest.raises(TypeError, match=r"missing 1 required keyword-only argument: 'plastic_viscosity'"):
        we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=100.0)
    with pytest.raises(ValueError, match=r"^plastic_viscosity = None is not allowed in Material.from_rheology: give the "
                                         r"Bingham plastic viscosity"):
        we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=100.0, plastic_viscosity=None)
    rigid = we.Material.from_rheology(1.0e5, 0.3, uniaxial_yield_stress=100.0, plastic_viscosity=math.inf)
    assert rigid.flow_rate == 0.0 and not rigid.plastic


@pytest.mark.parametrize("model", ["hyperelastic", "non_newtonian"])
def test_models_that_are_no_bingham_fluid_get_no_rheometer_quantities(model):
    """The simple-shear test of the next test on the same constants with the other flow
    models: neither is the Bingham fluid ``from_rheology`` promises (hyperelastic: its
    stresses twice the linear ones; non_newtonian: the rate divided by ``|s|`` once more).
    ``from_rheology`` built them anyway and the properties reported the values asked for;
    both now refuse, naming the model."""
    base = we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=100.0, plastic_viscosity=50.0)
    other = base.replace(model=model)
    rates = [0.5, 1.0, 2.0, 4.0]
    tau, _ = _steady_shear(other, rates)
    slope, intercept = np.polyfit(rates, tau, 1)
    assert abs(slope / 50.0 - 1.0) > 0.5 or abs(intercept / 100.0 - 1.0) > 0.5, (slope, intercept)
    with pytest.raises(ValueError, match=f"model = '{model}' is not allowed in Material.from_rheology"):
        we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=100.0, plastic_viscosity=50.0, model=model)
    for name in ("shear_yield_stress", "uniaxial_yield_stress", "plastic_viscosity"):
        with pytest.raises(ValueError, match=f"Material.{name} is not allowed for model = '{model}'"):
            getattr(other, name)
    with pytest.raises(ValueError, match="deformation = 'rest' is not allowed in Material.from_rheology"):
        we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=100.0, plastic_viscosity=50.0, deformation="rest")


@pytest.mark.parametrize("tau_y", [100.0, 0.0])
def test_steady_simple_shear_is_bingham_with_the_documented_constants(tau_y):
    """With ``shear_yield_stress = 0`` (``yield_stress = 0``, ``flow_rate > 0``) the line goes
    through 0: a Newtonian fluid of viscosity ``mu / flow_rate`` (Material's docstring)."""
    eta = 50.0
    m = we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=tau_y, plastic_viscosity=eta)
    rates = [0.5, 1.0, 2.0, 4.0]
    tau, s = _steady_shear(m, rates)
    expected = tau_y + eta * np.asarray(rates)
    # Simple shear: the deviatoric norm is sqrt(2) times the shear stress.
    np.testing.assert_allclose(s, math.sqrt(2.0) * tau, rtol=2e-3)
    np.testing.assert_allclose(tau, expected, rtol=0.02)
    # The Bingham line through the points: intercept tau_y, slope eta_p.
    slope, intercept = np.polyfit(rates, tau, 1)
    assert slope == pytest.approx(eta, rel=0.02)
    assert intercept == pytest.approx(tau_y, rel=0.02, abs=0.01)


def test_below_yield_simple_shear_is_elastic():
    m = we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=1.0e4, plastic_viscosity=50.0)
    rate, dt, duration = 1.0, 2.0e-5, 0.02
    tau, _ = _steady_shear(m, [rate], dt=dt, duration=duration)
    # No flow: tau = mu gamma (small strain), far below tau_y.
    assert tau[0] == pytest.approx(m.mu * rate * duration, rel=2e-3)


@functools.cache
def _held_strain_kernel():
    S = wp.float64
    flow = plasticity.kernels(S).flow
    mat33 = wp.types.matrix(shape=(3, 3), dtype=S)
    vec3 = wp.types.vector(length=3, dtype=S)

    @wp.kernel(module="unique")
    def held_strain(
        hardening: wp.array(dtype=S),
        strain: S,
        mu: S,
        yield_stress: S,
        flow_rate: S,
        dt: S,
        steps: int,
        counters: wp.array(dtype=wp.int32),
        s_norm: wp.array(dtype=S),
        alpha: wp.array(dtype=S),
    ):
        # One material point per hardening modulus, stretched once and then held: only the
        # flow moves its elastic F, so it stops where the stress meets the (softened) yield stress.
        i = wp.tid()
        F = wp.diag(vec3(wp.exp(strain), wp.exp(S(-0.5) * strain), wp.exp(S(-0.5) * strain)))
        a = S(0.0)
        for _ in range(steps):
            F, F_lo, a = flow(F, mat33(), a, mu, yield_stress, flow_rate, hardening[i], 0, dt, counters)
        U = mat33()
        sig = vec3()
        V = mat33()
        wp.svd3(F, U, sig, V)
        mean = (sig[0] + sig[1] + sig[2]) / S(3.0)
        s_norm[i] = S(2.0) * mu * wp.length(sig - vec3(mean, mean, mean))
        alpha[i] = a

    return held_strain


def _held_strain(hardening, strain, mu=1.0e3, yield_stress=100.0, flow_rate=50.0, dt=1.0e-3, steps=3000):
    n = len(hardening)
    s, a = wp.zeros(n, dtype=wp.float64, device="cpu"), wp.zeros(n, dtype=wp.float64, device="cpu")
    wp.launch(_held_strain_kernel(), n,
              [wp.array(hardening, dtype=wp.float64, device="cpu"), strain, mu, yield_stress, flow_rate, dt, steps,
               wp.zeros(4, dtype=wp.int32, device="cpu")], [s, a], device="cpu")
    return s.numpy(), a.numpy()


def test_softening_stops_at_a_softened_yield_stress_above_minus_two_mu_and_is_refused_beyond():
    """``hardening < 0`` softens: the flow stress ``Y + K alpha`` falls by ``|K|`` per unit of
    plastic strain while the flow relaxes ``|s|`` by ``2 mu`` per unit, so a point stretched to
    1.1 Y and held stops at ``Y + K (|s0| - Y) / (2 mu + K)`` for ``K > -2 mu`` and, at or below
    it, flows on until no yield stress is left, however small the overstress. ``Material``
    took any hardening (-1e30 ran, its yield stress gone at the first flow); it now refuses
    ``hardening <= -2 mu``, naming it, as the rheometer constructor and a preset's override do."""
    mu, Y = 1.0e3, 100.0
    strain = 0.0444  # |s0| = 110 Pa, 1.1 Y
    s0, _ = _held_strain([0.0], strain, steps=0)
    assert s0[0] == pytest.approx(1.1 * Y, rel=0.01)
    softening = np.array([-500.0, -1000.0, -1500.0])
    s, alpha = _held_strain(softening, strain)
    # The small-strain balance (|s| = 2 mu |dev ln sigma|), within the finite strain's 3 %.
    np.testing.assert_allclose(s, Y + softening * (s0[0] - Y) / (2.0 * mu + softening), rtol=0.05)
    np.testing.assert_allclose(s, Y + softening * alpha, rtol=1e-3)  # at rest on the softened yield surface
    beyond = np.array([-2.0 * mu, -2.1 * mu, -3.0 * mu, -1e30])
    s, alpha = _held_strain(beyond, strain)
    assert (s < 1e-6 * Y).all() and (Y + beyond * alpha <= 0.0).all(), (s, alpha)

    for K in (-2.0 * mu, -1e30):
        message = rf"^Material\.hardening = {re.escape(repr(K))} is not allowed: must be > -2 mu = -2000: a softening"
        with pytest.raises(ValueError, match=message):
            we.Material(mu=mu, lam=mu, yield_stress=Y, flow_rate=50.0, hardening=K)
    rheology = we.Material.from_rheology(2.0e4, 0.3, shear_yield_stress=Y, plastic_viscosity=10.0)
    for K in (-2.0 * rheology.mu, -1e30):
        with pytest.raises(ValueError, match=r"^Material\.hardening = .* must be > -2 mu = -15384\.6"):
            we.Material.from_rheology(2.0e4, 0.3, shear_yield_stress=Y, plastic_viscosity=10.0, hardening=K)
    for K in (-2.0 * we.PRESETS["dough"].mu, -1e30):
        with pytest.raises(ValueError, match=r"^Material\.hardening = .* must be > -2 mu = -15384\.6"):
            we.Material.preset("dough", hardening=K)
    assert we.Material.preset("dough", hardening=-0.99 * 2.0 * we.PRESETS["dough"].mu).hardening < -15000.0
    # A change of mu moves the bound: the softening it leaves beyond it is refused by name.
    with pytest.raises(ValueError, match=r"^Material\.hardening = -1500\.0 is not allowed: must be > -2 mu = -1000"):
        we.Material(mu=mu, lam=mu, hardening=-1500.0).replace(mu=500.0)


def test_a_lab_value_past_the_models_precision_is_refused_by_the_value_given():
    """``Material.from_rheology``'s yield stress and flow rate derive from the lab's values: one
    past float32's range was refused as ``Material.yield_stress = 1.41421e+39``, a value the
    caller never gave; it is named as given, with the conversion."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1),
              we.Material.from_rheology(1e5, 0.3, uniaxial_yield_stress=1e39, plastic_viscosity=10.0))
    with pytest.raises(ValueError, match=r"^uniaxial_yield_stress = 1e\+39 \(material 0\) is not allowed in float32: it "
                                         r"gives yield_stress = sqrt\(2/3\) uniaxial_yield_stress = 8\.16497e\+38: must be "
                                         r"at most 3\.4e\+38; use dtype=float64 or a smaller value$"):
        b.finalize(dtype=wp.float32)
    assert b.finalize(dtype=wp.float64).materials[0].uniaxial_yield_stress == pytest.approx(1e39)
