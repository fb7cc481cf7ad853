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

    @wp.kernel
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


def test_steady_simple_shear_is_bingham_with_the_documented_constants():
    tau_y, eta = 100.0, 50.0
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
    assert intercept == pytest.approx(tau_y, rel=0.02)


def test_below_yield_simple_shear_is_elastic():
    m = we.Material.from_rheology(1.0e5, 0.3, shear_yield_stress=1.0e4, plastic_viscosity=50.0)
    rate, dt, duration = 1.0, 2.0e-5, 0.02
    tau, _ = _steady_shear(m, [rate], dt=dt, duration=duration)
    # No flow: tau = mu gamma (small strain), far below tau_y.
    assert tau[0] == pytest.approx(m.mu * rate * duration, rel=2e-3)
