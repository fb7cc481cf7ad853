"""The formulas that several kernels share, each written once as a ``wp.func``: what each
computes, in both precisions, at the cases its callers meet."""

import functools

import numpy as np
import pytest
import warp as wp

from warp_esph._types import type_set
from warp_esph.sim import curvature, deformation, guards, isotropic, neighbors, plasticity, smoothing

SCALARS = [wp.float32, wp.float64]


@functools.cache
def _uncompensated_update_kernel(scalar):
    T = type_set(scalar)
    update = deformation.funcs(scalar, "poly6").uncompensated_update

    @wp.kernel(module="unique", enable_backward=False)
    def run(F: wp.array(dtype=T.mat33), inc: wp.array(dtype=T.mat33), scale: wp.array(dtype=scalar),
            out: wp.array(dtype=T.mat33), applied: wp.array(dtype=wp.int32)):
        i = wp.tid()
        o, a = update(F[i], inc[i], scale[i])
        out[i] = o
        applied[i] = a

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_uncompensated_update_is_eq8_unless_it_inverts(scalar):
    """``deformation``'s ``uncompensated_update`` (eq. 8 faded, the floor image's own update
    of both fits and what the update adjoint recomputes): ``F + (s inc) F`` and 1 where its
    determinant is positive; ``F`` and 0 where it would invert (paper §4), however the fade
    ``s`` gets there."""
    T = type_set(scalar)
    np_t = np.float32 if scalar == wp.float32 else np.float64
    rng = np.random.default_rng(3)
    F0 = np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    squash = np.diag([0.0, 0.0, -1.6])  # dF = diag(1, 1, -0.6) at s = 1: inverted
    cases = [(F0, 0.05 * rng.normal(size=(3, 3)), 1.0), (F0, squash, 1.0), (F0, squash, 0.5),
             (F0, 0.05 * rng.normal(size=(3, 3)), 0.0)]
    F = np.array([c[0] for c in cases], dtype=np_t)
    inc = np.array([c[1] for c in cases], dtype=np_t)
    s = np.array([c[2] for c in cases], dtype=np_t)
    out = wp.zeros(len(cases), dtype=T.mat33)
    applied = wp.zeros(len(cases), dtype=wp.int32)
    wp.launch(_uncompensated_update_kernel(scalar), len(cases),
              [wp.array(F, dtype=T.mat33), wp.array(inc, dtype=T.mat33), wp.array(s, dtype=scalar)], [out, applied])
    out, applied = out.numpy(), applied.numpy()
    want = F.astype(np.float64) + np.einsum("k,kij,kjl->kil", s.astype(np.float64), inc.astype(np.float64),
                                            F.astype(np.float64))
    assert applied.tolist() == [1, 0, 1, 1]
    tol = 1e-6 if scalar == wp.float32 else 1e-14
    np.testing.assert_allclose(out[[0, 2, 3]], want[[0, 2, 3]], rtol=0, atol=tol)
    assert np.array_equal(out[1], F[1]), "an inverting update keeps F"
    assert np.array_equal(out[3], F[3]), "a fade of 0 leaves F as it was"
    assert np.linalg.det(want[1]) < 0 < np.linalg.det(want[2])


@functools.cache
def _pair_viscosity_kernel(scalar):
    from warp_esph.sim import pressure

    pair_viscosity = pressure.funcs(scalar).pair_viscosity

    @wp.kernel(module="unique", enable_backward=False)
    def run(eta: wp.array(dtype=scalar), out: wp.array(dtype=scalar)):
        i = wp.tid()
        out[i] = pair_viscosity(eta[2 * i], eta[2 * i + 1])

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_pair_viscosity_is_the_mean_and_symmetric(scalar):
    """``pressure``'s ``pair_viscosity``, the ``eta_ij`` of the viscous force on both the
    fused and the differentiable path (and its adjoint): the mean of the two viscosities,
    the same for ``(i, j)`` and ``(j, i)`` so that a pair's forces are equal and opposite
    across materials."""
    np_t = np.float32 if scalar == wp.float32 else np.float64
    eta = np.array([0.0, 3.0, 3.0, 0.0, 1.5, 1.5, 0.25, 40.0], dtype=np_t)
    out = wp.zeros(len(eta) // 2, dtype=scalar)
    wp.launch(_pair_viscosity_kernel(scalar), len(out), [wp.array(eta, dtype=scalar)], [out])
    got = out.numpy()
    np.testing.assert_allclose(got, 0.5 * (eta[0::2] + eta[1::2]), rtol=1e-7, atol=0)
    assert got[0] == got[1], "the pair's coefficient does not depend on its order"


@functools.cache
def _flow_kernel(scalar):
    from warp_esph.sim import plasticity

    T = type_set(scalar)
    fl = plasticity.funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def run(s: wp.array(dtype=T.vec3), gamma: wp.array(dtype=scalar), mu: scalar, dev: wp.array(dtype=T.vec3),
            norm2: wp.array(dtype=scalar), g: wp.array(dtype=T.vec3), cp: wp.array(dtype=T.vec3)):
        i = wp.tid()
        d = fl.deviatoric(s[i])
        dev[i] = d
        norm2[i] = fl.deviatoric_stress_norm2(mu, wp.dot(d, d))
        gi, c, p = fl.flowed_values(s[i], gamma[i])
        g[i] = gi
        cp[i] = T.vec3(c, p, fl.flow_rate_fraction(wp.sqrt(norm2[i]), fl.yield_surface(scalar(10.0), scalar(-4.0),
                                                                                             gamma[i]),
                                                  scalar(50.0), scalar(0.01), i % 2))

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_flow_formulas_keep_volume_and_rate(scalar):
    """``plasticity``'s flow formulas, shared by ``flow_step``, its hand-written adjoint and
    the additive model: the deviatoric part has no mean; ``|s|^2 = |2 mu dev|^2``; the flowed
    singular values ``g = c s^p`` keep the volume ``J`` inside the volume-preserving range and
    relax only the part beyond it outside, and ``gamma = 0`` leaves ``s``; the flow fraction
    before its clamp is ``nu dt (|s| - y) / |s|`` (non-Newtonian: over ``|s|`` again) with
    the yield surface ``max(Y + K alpha, 0)``."""
    from warp_esph.sim import plasticity

    T = type_set(scalar)
    np_t = np.float32 if scalar == wp.float32 else np.float64
    mu = 30.0
    s = np.array([[1.2, 1.0, 0.9], [1.1, 0.95, 1.0], [1.4, 1.3, 1.2], [0.7, 0.8, 0.75], [1.3, 0.9, 1.05]], dtype=np_t)
    gamma = np.array([0.3, 0.0, 0.5, 0.2, 4.0], dtype=np_t)
    n = len(s)
    dev, norm2 = wp.zeros(n, dtype=T.vec3), wp.zeros(n, dtype=scalar)
    g, cp = wp.zeros(n, dtype=T.vec3), wp.zeros(n, dtype=T.vec3)
    wp.launch(_flow_kernel(scalar), n, [wp.array(s, dtype=T.vec3), wp.array(gamma, dtype=scalar), scalar(mu)],
              [dev, norm2, g, cp])
    dev, norm2, g, cp = (a.numpy().astype(np.float64) for a in (dev, norm2, g, cp))
    s64, g64 = s.astype(np.float64), gamma.astype(np.float64)
    rtol = 1e-5 if scalar == wp.float32 else 1e-12
    want_dev = s64 - s64.mean(axis=1, keepdims=True)
    np.testing.assert_allclose(dev, want_dev, rtol=0, atol=rtol)
    np.testing.assert_allclose(norm2, ((2.0 * mu * want_dev) ** 2).sum(axis=1), rtol=rtol)
    J = s64.prod(axis=1)
    lo, hi = plasticity.VOLUME_PRESERVING_RANGE
    Jc = np.clip(J, lo, hi)
    assert lo < J[0] < hi and J[2] > hi and J[3] < lo
    np.testing.assert_allclose(g.prod(axis=1), Jc ** g64 * J ** (1.0 - g64), rtol=10 * rtol)
    np.testing.assert_allclose(g[0].prod(), J[0], rtol=10 * rtol)  # volume kept inside the range
    assert np.array_equal(g[1], s64[1]), "no flow leaves the singular values"
    np.testing.assert_allclose(cp[:, 1], 1.0 - g64, rtol=rtol)
    y = np.maximum(10.0 - 4.0 * g64, 0.0)
    assert y[4] == 0.0
    sn = np.sqrt(norm2)
    rate = 50.0 * 0.01 * (sn - y) / sn
    rate[1::2] /= sn[1::2]
    np.testing.assert_allclose(cp[:, 2], rate, rtol=10 * rtol)


@functools.cache
def _rest_elastic_kernel(scalar):
    from warp_esph.sim import comparison

    T = type_set(scalar)
    part = comparison.kernels(scalar, "poly6").rest_elastic_part

    @wp.kernel(module="unique", enable_backward=False)
    def run(G: wp.array(dtype=T.mat33), Fp: wp.array(dtype=T.mat33), Fe: wp.array(dtype=T.mat33)):
        i = wp.tid()
        Fe[i] = part(G[i], Fp[i])

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_rest_elastic_part_is_the_multiplicative_split(scalar):
    """``comparison``'s ``rest_elastic_part``, the rest model's ``F_e`` in its update, its start
    fit and its adjoint: ``F_e F_p = G``; a total fit that is all plastic (``G = F_p``) holds
    no elastic strain."""
    T = type_set(scalar)
    np_t = np.float32 if scalar == wp.float32 else np.float64
    rng = np.random.default_rng(5)
    Fp = np.eye(3) + 0.2 * rng.normal(size=(2, 3, 3))
    G = np.stack([np.eye(3) + 0.2 * rng.normal(size=(3, 3)), Fp[1]]).astype(np_t)
    Fp = Fp.astype(np_t)
    Fe = wp.zeros(2, dtype=T.mat33)
    wp.launch(_rest_elastic_kernel(scalar), 2, [wp.array(G, dtype=T.mat33), wp.array(Fp, dtype=T.mat33)], [Fe])
    Fe = Fe.numpy().astype(np.float64)
    tol = 1e-5 if scalar == wp.float32 else 1e-13
    np.testing.assert_allclose(Fe @ Fp.astype(np.float64), G.astype(np.float64), rtol=0, atol=tol)
    np.testing.assert_allclose(Fe[1], np.eye(3), rtol=0, atol=tol)


@functools.cache
def _image_chain_kernel():
    S = wp.float64
    T = type_set(S)
    fn = deformation.funcs(S, "poly6")

    @wp.kernel(module="unique", enable_backward=False)
    def run(x: wp.array(dtype=T.vec3), g: T.vec3, gg: T.vec3, gn: T.vec3, goff: S, gmin: S, image: int,
            adj_x: wp.array(dtype=T.vec3), adj_own: wp.array(dtype=T.vec3), img: wp.array(dtype=T.vec3)):
        i = wp.tid()
        fn.scatter_partner_adjoint(adj_x, i, x[i], g, gn, goff, gmin, image)
        fn.scatter_own_adjoint(adj_own, i, x[i], g, gg, gn, goff, gmin)
        img[i] = fn.floor_image(x[i], gn, goff, gmin)

    return run


def _image_chain(x, g, gg, n, goff, gmin, image, held):
    """``scatter_partner_adjoint`` and ``scatter_own_adjoint`` at the points ``x`` onto
    ``held``, and the points' floor images."""
    T = type_set(wp.float64)
    adj, own = wp.array(held, dtype=T.vec3), wp.array(held, dtype=T.vec3)
    img = wp.zeros(len(x), dtype=T.vec3)
    wp.launch(_image_chain_kernel(), len(x),
              [wp.array(x, dtype=T.vec3), T.vec3(*g), T.vec3(*gg), T.vec3(*n), goff, gmin, image], [adj, own, img])
    return adj.numpy(), own.numpy(), img.numpy()


def _image_jacobians(x, n, goff, gmin, eps=1e-7):
    """``d g / d x`` of each point's floor image by central differences: ``[k, a, c] = d g_a /
    d x_c``."""
    zero, held = np.zeros(3), np.zeros((len(x), 3))
    jac = np.empty((len(x), 3, 3))
    for c in range(3):
        e = np.zeros(3)
        e[c] = eps
        plus = _image_chain(x + e, zero, zero, n, goff, gmin, 0, held)[2]
        minus = _image_chain(x - e, zero, zero, n, goff, gmin, 0, held)[2]
        jac[:, :, c] = (plus - minus) / (2 * eps)
    return jac


@pytest.mark.parametrize("image", [0, 1])
def test_partner_adjoint_is_the_chain_rule_through_the_image(image):
    """``deformation``'s ``scatter_partner_adjoint``, the scatter of a pair's far end in the
    variational force adjoints (both fits), the paper force's and the density's: the adjoint
    ``g`` of ``x_j`` itself, or of ``j``'s floor image, ``(d g_j / d x_j)^T g``, against central
    differences of ``floor_image`` (above the plane, in the cubic blend and below it), added
    to what ``adj x_j`` held."""
    n = np.array([0.2, 0.95, 0.1])
    n /= np.linalg.norm(n)
    goff, gmin = 0.1, 0.01
    heights = np.array([0.03, 0.008, 0.006, -0.004])
    x = (goff + heights)[:, None] * n + 0.3 * np.cross(n, [1.0, 0.0, 0.0])
    g = np.array([0.4, -1.1, 0.7])
    held = np.full((len(x), 3), 0.25)
    adj = _image_chain(x, g, np.zeros(3), n, goff, gmin, image, held)[0]
    want = np.tile(g, (len(x), 1))
    if image:
        want = np.einsum("kac,a->kc", _image_jacobians(x, n, goff, gmin), g)
    np.testing.assert_allclose(adj - held, want, rtol=0, atol=1e-6)


def test_own_adjoint_is_the_particle_and_its_image():
    """``deformation``'s ``scatter_own_adjoint``, the closing add of the adjoints whose loops
    reach a particle's own floor image (variational and paper forces, both fits, the image's
    own update): ``adj x_i += gx + (d g_i / d x_i)^T gg``, against central differences of
    ``floor_image`` above the plane, in the blend and below it."""
    n = np.array([0.0, 1.0, 0.0])
    goff, gmin = 0.0, 0.01
    x = np.array([[0.1, 0.03, 0.2], [0.0, 0.007, 0.0], [0.3, -0.002, 0.1]])
    gx, gg = np.array([0.5, 0.1, -0.3]), np.array([-0.2, 0.9, 0.4])
    held = np.full((len(x), 3), -0.5)
    own = _image_chain(x, gx, gg, n, goff, gmin, 0, held)[1]
    want = held + gx + np.einsum("kac,a->kc", _image_jacobians(x, n, goff, gmin), gg)
    np.testing.assert_allclose(own, want, rtol=0, atol=1e-6)


@functools.cache
def _p_hat_kernel(scalar):
    from warp_esph.sim import forces

    T = type_set(scalar)
    fo = forces.funcs(scalar, "poly6")

    @wp.kernel(module="unique", enable_backward=False)
    def run(s: wp.array(dtype=T.vec3), mu: scalar, lam: scalar, eq9: wp.array(dtype=T.vec3),
            p_hat: wp.array(dtype=T.vec3)):
        i = wp.tid()
        eq9[i] = fo.principal_stress(s[i], mu, lam)
        p_hat[i] = fo.corotated_principal_stress(s[i], mu, lam)

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_eq9_is_the_corotated_principal_stress_scaled_by_sigma(scalar):
    """Eq. 9's principal values ``sigma o P^`` (``principal_stress``) scale the corotated
    stress's ``P^ = 2 mu (sigma - 1) + lam sum(sigma - 1)`` (``corotated_principal_stress``,
    also the hand-written constitutive adjoint's): to the bit, one formula; and ``P^`` is 0 at
    rest and the small-strain linear stress."""
    T = type_set(scalar)
    np_t = np.float32 if scalar == wp.float32 else np.float64
    s = np.array([[1.0, 1.0, 1.0], [1.2, 0.9, 0.7], [1.001, 1.0, 0.999], [-0.4, 0.8, 1.3]], dtype=np_t)
    mu, lam = 3.0e4, 2.0e4
    eq9, p_hat = wp.zeros(len(s), dtype=T.vec3), wp.zeros(len(s), dtype=T.vec3)
    wp.launch(_p_hat_kernel(scalar), len(s), [wp.array(s, dtype=T.vec3), scalar(mu), scalar(lam)], [eq9, p_hat])
    eq9, p_hat = eq9.numpy(), p_hat.numpy()
    assert np.array_equal(eq9, s * p_hat), "eq. 9 is sigma o P^ to the bit"
    assert np.all(p_hat[0] == 0.0)
    e = s.astype(np.float64) - 1.0
    want = 2.0 * mu * e + lam * e.sum(axis=1, keepdims=True)
    rtol = 1e-5 if scalar == wp.float32 else 1e-12
    np.testing.assert_allclose(p_hat, want, rtol=rtol, atol=rtol * mu)


@functools.cache
def _energy_weight_kernel(scalar):
    from warp_esph.sim import pressure

    weight = pressure.funcs(scalar).energy_pair_weight

    @wp.kernel(module="unique", enable_backward=False)
    def run(m: wp.array(dtype=scalar), p: wp.array(dtype=scalar), rho: wp.array(dtype=scalar),
            out: wp.array(dtype=scalar)):
        k = wp.tid()
        i = 2 * k
        j = i + 1
        VV = m[i] * m[j] / (rho[i] * rho[j])
        out[i] = weight(VV, p[i], p[j], rho[i], rho[j])
        out[j] = weight(VV, p[j], p[i], rho[j], rho[i])

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_energy_pair_weight_is_the_pressure_energys_factor(scalar):
    """``pressure``'s ``energy_pair_weight``, the factor of both energy forms' pair force
    (poly6 ``energy``, ``energy_spiky``): ``m_i m_j (p_i / rho_i^2 + p_j / rho_j^2)`` from
    ``VV = m_i m_j / (rho_i rho_j)``, the same from either end of the pair (so the pair's
    forces are equal and opposite)."""
    np_t = np.float32 if scalar == wp.float32 else np.float64
    m = np.array([1.0e-3, 2.0e-3, 5.0e-4, 5.0e-4], dtype=np_t)
    p = np.array([120.0, -30.0, 0.0, 800.0], dtype=np_t)
    rho = np.array([1010.0, 990.0, 1200.0, 1000.0], dtype=np_t)
    out = wp.zeros(len(m), dtype=scalar)
    wp.launch(_energy_weight_kernel(scalar), len(m) // 2,
              [wp.array(m, dtype=scalar), wp.array(p, dtype=scalar), wp.array(rho, dtype=scalar)], [out])
    got = out.numpy().astype(np.float64)
    m64, p64, r64 = (a.astype(np.float64) for a in (m, p, rho))
    want = np.repeat(m64[0::2] * m64[1::2] * (p64[0::2] / r64[0::2] ** 2 + p64[1::2] / r64[1::2] ** 2), 2)
    rtol = 1e-5 if scalar == wp.float32 else 1e-13
    np.testing.assert_allclose(got, want, rtol=rtol, atol=0)


@functools.cache
def _eos_kernel():
    from warp_esph.sim import pressure

    S = wp.float64
    eos = pressure.funcs(S).pressure
    eos_adjoint = pressure.kernels(S).pressure_adjoint

    @wp.kernel(module="unique", enable_backward=False)
    def run(rho: wp.array(dtype=S), k: wp.array(dtype=S), clamp: wp.array(dtype=wp.int32), rho0: S, adj_p: S,
            p: wp.array(dtype=S), adj: wp.array(dtype=S)):
        i = wp.tid()
        p[i] = eos(rho[i], rho0, k[i], clamp[i])
        a_rho, a_k = eos_adjoint(adj_p, rho[i], rho0, k[i], clamp[i])
        adj[2 * i] = a_rho
        adj[2 * i + 1] = a_k

    return run


def test_pressure_adjoint_is_the_equation_of_states_derivative():
    """``pressure``'s ``pressure_adjoint``, the hand-written SPH adjoint's for every particle
    and pair: ``adj p`` times the derivative of ``p = k_p (rho - rho0)`` (clamped at 0) in
    ``rho`` and ``k_p``, against central differences, compressed and stretched, clamped or not,
    and at ``k_p = 0``, where a compressed particle keeps its slope in ``k_p``."""
    rho0, adj_p, eps = 1000.0, 0.7, 1e-4
    rho = np.array([1010.0, 990.0, 990.0, 1005.0])
    k = np.array([50.0, 50.0, 50.0, 0.0])
    clamp = np.array([1, 1, 0, 1], dtype=np.int32)

    def run(r, kk):
        p, adj = wp.zeros(len(r), dtype=wp.float64), wp.zeros(2 * len(r), dtype=wp.float64)
        wp.launch(_eos_kernel(), len(r), [wp.array(r, dtype=wp.float64), wp.array(kk, dtype=wp.float64),
                                          wp.array(clamp, dtype=wp.int32), rho0, adj_p], [p, adj])
        return p.numpy(), adj.numpy().reshape(-1, 2)

    _, adj = run(rho, k)
    d_rho = (run(rho + eps, k)[0] - run(rho - eps, k)[0]) / (2 * eps)
    d_k = (run(rho, k + eps)[0] - run(rho, k - eps)[0]) / (2 * eps)
    np.testing.assert_allclose(adj[:, 0], adj_p * d_rho, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(adj[:, 1], adj_p * d_k, rtol=1e-8, atol=1e-10)
    assert adj[1, 0] == 0.0 and adj[1, 1] == 0.0, "the clamp holds a stretched particle's pressure at 0"
    assert adj[3, 1] == adj_p * 5.0, "at k_p = 0 the compressed particle's slope in k_p stays"


@functools.cache
def _spiky_kernel():
    from warp_esph.sim import smoothing

    S = wp.float64
    T = type_set(S)
    sm = smoothing.funcs(S)

    @wp.kernel(module="unique", enable_backward=False)
    def run(rl: wp.array(dtype=S), h: S, out: wp.array(dtype=T.vec3)):
        i = wp.tid()
        c = sm.spiky_coef(h)
        r = T.vec3(rl[i], S(0.0), S(0.0))
        psi = sm.spiky_gradient_factor(rl[i], h, c)
        out[i] = T.vec3(psi, sm.spiky_gradient_factor_slope(rl[i], h, c, rl[i] * rl[i]),
                        sm.grad_w_spiky_at(r, rl[i], h, c)[0] - psi * rl[i])

    return run


def test_spiky_gradient_factor_and_its_slope():
    """``smoothing``'s ``spiky_gradient_factor`` ``psi`` (``grad W_spiky(r) = psi(|r|) r``,
    the forward's and the SPH adjoint's) and ``spiky_gradient_factor_slope``, its derivative in
    ``|r|`` the adjoint takes: ``psi r`` is ``grad_w_spiky_at`` to the bit, ``psi`` is Müller et
    al.'s ``-45/(pi h^6) (h - |r|)^2 / |r|``, and the slope matches central differences."""
    h, eps = 0.1, 1e-7
    rl = np.array([0.01, 0.04, 0.07, 0.099])

    def run(r):
        out = wp.zeros(len(r), dtype=type_set(wp.float64).vec3)
        wp.launch(_spiky_kernel(), len(r), [wp.array(r, dtype=wp.float64), h], [out])
        return out.numpy()

    out = run(rl)
    np.testing.assert_allclose(out[:, 0], -45.0 / (np.pi * h ** 6) * (h - rl) ** 2 / rl, rtol=1e-13)
    assert np.all(out[:, 2] == 0.0), "grad_w_spiky_at is psi r"
    fd = (run(rl + eps)[:, 0] - run(rl - eps)[:, 0]) / (2 * eps)
    np.testing.assert_allclose(out[:, 1], fd, rtol=1e-6)


@functools.cache
def _viscosity_kernel():
    S = wp.float64
    sm = smoothing.funcs(S)

    @wp.kernel(module="unique", enable_backward=False)
    def run(rl: wp.array(dtype=S), h: S, out: wp.array2d(dtype=S)):
        i = wp.tid()
        c = sm.viscosity_coef(h)
        out[i, 0] = sm.lap_w_viscosity_at(rl[i], h, c)
        out[i, 1] = sm.lap_w_viscosity_slope_at(rl[i], h, c)

    return run


def test_the_viscosity_laplacian_meets_zero_with_zero_slope():
    """``lap_w_viscosity_at`` is Müller et al.'s ``45/(pi h^6) (h - |r|)`` to the bit up to the
    last ``VISCOSITY_EDGE`` of ``h``, then a cubic that meets the line with its value and slope
    and reaches 0 at ``h`` with slope 0 (the line's slope there was ``-coef``: a kink of the
    step wherever a pair crossed the support); ``lap_w_viscosity_slope_at``, the slope the
    SPH adjoint takes, matches central differences on the line and in the band."""
    h, eps = 0.1, 1e-9
    a = smoothing.VISCOSITY_EDGE * h
    coef = 45.0 / (np.pi * h ** 6)
    line = np.array([0.01, 0.05, 0.09, h - a])
    band = h - a * np.array([0.9, 0.5, 0.1, 1e-3])

    def run(r):
        out = wp.zeros((len(r), 2), dtype=wp.float64)
        wp.launch(_viscosity_kernel(), len(r), [wp.array(r, dtype=wp.float64), h], [out])
        return out.numpy()

    on, inside = run(line), run(band)
    np.testing.assert_array_equal(on[:, 0], coef * (h - line))
    assert np.all(on[:, 1] == -coef)
    u = h - band
    np.testing.assert_allclose(inside[:, 0], coef * u * u * (2 * a - u) / a ** 2, rtol=1e-12)
    assert np.all((0.0 < inside[:, 0]) & (inside[:, 0] < coef * u)), "below the line, above 0"
    for r, out in ((line[:-1], on[:-1]), (band, inside)):
        fd = (run(r + eps)[:, 0] - run(r - eps)[:, 0]) / (2 * eps)
        np.testing.assert_allclose(out[:, 1], fd, rtol=1e-5)
    edge = run(np.array([h - a - eps, h - a + eps, h - eps]))
    assert edge[0, 1] == pytest.approx(edge[1, 1], rel=1e-5), "the slope is continuous where the cubic meets the line"
    assert abs(edge[2, 1]) < 1e-5 * coef, "and reaches 0 at h"


@functools.cache
def _moments_kernel(scalar, fit):
    T = type_set(scalar)
    df = deformation.funcs(scalar, "poly6")
    cf = curvature.funcs(scalar, "poly6")

    @wp.kernel(module="unique", enable_backward=False)
    def run(x: wp.array(dtype=T.vec3), body: wp.array(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32),
            count: wp.array(dtype=wp.int32), h: scalar, gn: T.vec3, goff: scalar, gmin: scalar, images: int,
            fit_sums: wp.array2d(dtype=T.mat33), same_fit: wp.array(dtype=scalar), pos_sums: wp.array2d(dtype=T.mat33),
            same_pos: wp.array(dtype=scalar)):
        i = wp.tid()
        if wp.static(fit == "linear"):
            A, B, same = df.fit_sums(i, x, x, x, x, body, nbr, count[i], h, gn, goff, gmin, images)
            fit_sums[i, 0] = A
            same_fit[i] = same
            A2, same2 = df.position_moments(i, x, body, nbr, count[i], h, gn, goff, gmin, images)
            pos_sums[i, 0] = A2
            same_pos[i] = same2
        else:
            A, B, C, D, E, same = cf.fit_sums(i, x, x, x, x, body, nbr, count[i], h, gn, goff, gmin, images)
            fit_sums[i, 0] = A
            fit_sums[i, 1] = C
            fit_sums[i, 2] = D
            same_fit[i] = same
            A2, C2, D2, same2 = cf.position_moments(i, x, body, nbr, count[i], h, gn, goff, gmin, images)
            pos_sums[i, 0] = A2
            pos_sums[i, 1] = C2
            pos_sums[i, 2] = D2
            same_pos[i] = same2

    return run


def _moments(scalar, x, body, nbr, counts, h, images, fit):
    """``fit_sums``' position moments (``A``; the corrected fit's ``A``, ``C``, ``D``) and count
    on ``x`` alone, then ``position_moments``'."""
    T = type_set(scalar)
    n = len(x)
    outs = [wp.zeros((n, 3), dtype=T.mat33), wp.zeros(n, dtype=scalar), wp.zeros((n, 3), dtype=T.mat33),
            wp.zeros(n, dtype=scalar)]
    wp.launch(_moments_kernel(scalar, fit), n,
              [wp.array(x, dtype=T.vec3), wp.array(body, dtype=wp.int32), wp.array(nbr, dtype=wp.int32),
               wp.array(counts, dtype=wp.int32), scalar(h), T.vec3(0.0, 1.0, 0.0), scalar(0.0), scalar(0.005), images],
              outs)
    return [o.numpy() for o in outs]


@pytest.mark.parametrize("scalar", SCALARS)
@pytest.mark.parametrize("images", [0, 1])
@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
def test_position_moments_are_the_fits_moments_bit_for_bit(scalar, images, fit):
    """``position_moments``, which the variational force sums its moments with (the fused step's
    ``A``, the corrected fit's ``A``, ``C``, ``D``, without the displacement moments), gives
    ``fit_sums``' on ``x`` alone and its smooth count to the bit: rows with partners of another
    body and beyond ``h``, near a floor whose images count."""
    np_t = np.float32 if scalar == wp.float32 else np.float64
    rng = np.random.default_rng(5)
    g = np.arange(4) * 0.01
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + 0.004
    x = (x + rng.normal(scale=1e-3, size=x.shape)).astype(np_t)
    n = len(x)
    body = (np.arange(n) % 5 == 0).astype(np.int32)  # every fifth particle another body
    h = 0.02
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    rows = [[j for j in np.argsort(d[i], kind="stable") if j != i and d[i, j] < 1.3 * h] for i in range(n)]
    nbr = np.zeros((n, max(len(r) for r in rows)), dtype=np.int32)
    for i, r in enumerate(rows):
        nbr[i, :len(r)] = r
    counts = np.array([len(r) for r in rows], dtype=np.int32)
    sums_fit, same_fit, sums_pos, same_pos = _moments(scalar, x, body, nbr, counts, h, images, fit)
    used = 1 if fit == "linear" else 3
    assert all(np.abs(sums_fit[:, k]).max() > 0 for k in range(used)) and same_fit.max() > 0
    if images:
        assert not np.array_equal(sums_fit, _moments(scalar, x, body, nbr, counts, h, 0, fit)[0]), \
            "the floor's images must count in this case"
    assert np.array_equal(sums_pos, sums_fit)
    assert np.array_equal(same_pos, same_fit)


@functools.cache
def _pair_terms_kernel(scalar, weight):
    T = type_set(scalar)
    df = deformation.funcs(scalar, weight)
    cf = curvature.funcs(scalar, weight)
    fw = smoothing.fit_weight_funcs(scalar, weight)

    @wp.kernel(module="unique", enable_backward=False)
    def run(xb: wp.array(dtype=T.vec3), yb: wp.array(dtype=T.vec3), h: scalar, lin: wp.array2d(dtype=T.mat33),
            cor: wp.array2d(dtype=T.mat33), scal: wp.array2d(dtype=scalar)):
        i = wp.tid()
        c6 = fw.coef(h)
        w, dA, c = df.moment_pair_terms(xb[i], h, c6, h * h)
        r2, w2, dA2 = df.moment_term(xb[i], h, c6)
        lin[i, 0] = dA
        lin[i, 1] = dA2
        scal[i, 0] = w
        scal[i, 1] = c
        scal[i, 2] = w2
        scal[i, 3] = r2
        cA, cB, cC, cD, cE, cc = cf.moment_pair_terms(xb[i], yb[i], h, c6, h * h)
        cor[i, 0] = cA
        cor[i, 1] = cB
        cor[i, 2] = cC
        cor[i, 3] = cD
        cor[i, 4] = cE
        scal[i, 4] = cc

    return run


@pytest.mark.parametrize("scalar", SCALARS)
@pytest.mark.parametrize("weight", ["poly6", "biweight"])
def test_moment_pair_terms_are_eq5s_term_and_the_guards_count(scalar, weight):
    """``deformation.moment_pair_terms`` (the one pair term every linear fit's moment sum adds:
    ``fit_pair_sums``, ``position_moments``, the variational force's adjoint) and
    ``curvature.moment_pair_terms`` (the corrected fit's): the fit's weight ``w(|xb|^2)`` of eq.
    7 (poly6 ``315/(64 pi h^9) (h^2 - r^2)^3`` or the biweight ``(h^2 - r^2)^2 / h^4``), eq. 5's
    ``w xb xb^T`` (with the corrected fit's ``w yb xb^T``, ``w xb q^T``, ``w q q^T``, ``w yb q^T``,
    ``q = (x y, x z, y z) / h``) and the few-neighbours guard's smooth count: 1 up to 0.95 h, 0
    from h, ``1 - smoothstep`` in ``r^2`` between; nothing at all beyond h."""
    np_t = np.float32 if scalar == wp.float32 else np.float64
    h = 0.02
    dirs = np.array([[1.0, 2.0, 2.0], [0.0, 3.0, -4.0], [-2.0, 1.0, 2.0], [6.0, -2.0, 3.0], [1.0, 0.0, 0.0]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = np.array([0.3, 0.93, 0.97, 0.995, 1.2]) * h  # inside the fade, in it, beyond h
    xb = (dirs * radii[:, None]).astype(np_t)
    yb = (np.random.default_rng(2).normal(scale=h, size=xb.shape)).astype(np_t)
    n = len(xb)
    T = type_set(scalar)
    lin = wp.zeros((n, 2), dtype=T.mat33)
    cor = wp.zeros((n, 5), dtype=T.mat33)
    scal = wp.zeros((n, 5), dtype=scalar)
    wp.launch(_pair_terms_kernel(scalar, weight), n, [wp.array(xb, dtype=T.vec3), wp.array(yb, dtype=T.vec3),
                                                      scalar(h)], [lin, cor, scal])
    lin, cor, scal = lin.numpy(), cor.numpy(), scal.numpy()
    x64, y64 = xb.astype(np.float64), yb.astype(np.float64)
    r2 = (x64 * x64).sum(1)
    d = np.maximum(h * h - r2, 0.0)
    w = 315.0 / (64.0 * np.pi * h ** 9) * d ** 3 if weight == "poly6" else d ** 2 / h ** 4
    t = np.clip((r2 - (0.95 * h) ** 2) / (h * h - (0.95 * h) ** 2), 0.0, 1.0)
    count = 1.0 - t * t * (3.0 - 2.0 * t)
    q = np.stack([x64[:, 0] * x64[:, 1], x64[:, 0] * x64[:, 2], x64[:, 1] * x64[:, 2]], 1) / h
    outer = lambda a, b: w[:, None, None] * a[:, :, None] * b[:, None, :]  # noqa: E731
    rtol = 2e-5 if scalar == wp.float32 else 1e-11
    for got, want in [(scal[:, 0], w), (scal[:, 2], w), (lin[:, 0], outer(x64, x64)), (cor[:, 0], outer(x64, x64)),
                      (cor[:, 1], outer(y64, x64)), (cor[:, 2], outer(x64, q)), (cor[:, 3], outer(q, q)),
                      (cor[:, 4], outer(y64, q))]:
        scale = np.abs(want).max()
        np.testing.assert_allclose(got, want, rtol=rtol, atol=rtol * scale)
    np.testing.assert_allclose(scal[:, 1], count, rtol=0, atol=1e-5 if scalar == wp.float32 else 1e-11)
    np.testing.assert_allclose(scal[:, 3], r2, rtol=rtol)
    assert np.array_equal(scal[:, 4], scal[:, 1]), "both fits' guards count a pair alike"
    assert np.array_equal(lin[:, 1], lin[:, 0]), "moment_term is moment_pair_terms' A term"
    assert scal[0, 1] == 1.0 and 0.0 < scal[2, 1] < 1.0 and scal[4, 1] == 0.0
    assert w[-1] == 0.0 and not lin[-1].any() and not cor[-1].any(), "beyond h a pair adds nothing"


@functools.cache
def _python_constant_kernel():
    T = type_set(wp.float64)
    gf = guards.guard_funcs(wp.float64)
    cf = curvature.funcs(wp.float64, "poly6")
    nk = neighbors.kernels(wp.float64, "poly6")

    @wp.kernel(module="unique", enable_backward=False)
    def run(r2: wp.array(dtype=wp.float64), hh: wp.float64, A: T.mat33, F: T.mat33, det: wp.float64,
            count: wp.array2d(dtype=wp.float64), mats: wp.array(dtype=T.mat33)):
        i = wp.tid()
        c, dc = gf.count_weight(r2[i], hh)
        count[i, 0] = c
        count[i, 1] = dc
        if i == 0:
            mats[0] = cf.ridge_inverse(A, T.mat33())
            mats[1] = nk.flow_inverse_bound(F, det)

    return run


def test_float64_kernels_take_constants_of_python_arithmetic_in_float64():
    """A float64 model's constants that are Python arithmetic (the few-neighbours count's fade
    edge ``COUNT_FADE^2 h^2``, the curvature fit's ridge ``1e-4 tr(A) / 3``, the flow bound's
    ``J^(1/3)``) are float64 in its kernels: Warp evaluates such arithmetic inside a kernel in
    float32 whatever it is cast to, which put the fade edge 2.6e-8 h^2 low. Checked against
    numpy float64 where each constant decides the result: the count is exactly 1 with slope 0
    at the fade edge and the smoothstep's to round-off in the band; ``(0 + eps I)^-1 = I /
    eps``; ``G = I / clamp(J)^(1/3)`` for ``F = 0.5 I``."""
    h = 0.02
    hh = h * h
    q0 = guards.COUNT_FADE**2 * hh
    f = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    r2 = np.concatenate([[0.5 * q0], q0 + f * (hh - q0)])
    A = np.diag([2.0, 3.0, 4.0]) * 1e-3
    det = 1.2
    count = wp.zeros((len(r2), 2), dtype=wp.float64)
    mats = wp.zeros(2, dtype=wp.mat33d)
    wp.launch(_python_constant_kernel(), len(r2), [wp.array(r2, dtype=wp.float64), hh, wp.mat33d(*A.ravel()),
                                                   wp.mat33d(*(0.5 * np.eye(3)).ravel()), det], [count, mats])
    count, mats = count.numpy(), mats.numpy()
    band = hh - q0
    t = np.clip((r2 - q0) / band, 0.0, 1.0)
    want_c = np.where(r2 < hh, 1.0 - t * t * (3.0 - 2.0 * t), 0.0)
    want_dc = np.where((r2 > q0) & (r2 < hh), -6.0 * t * (1.0 - t) / band, 0.0)
    assert count[1, 0] == 1.0 and count[1, 1] == 0.0, f"the fade edge q0 counts {count[1, 0]!r}, slope {count[1, 1]!r}"
    np.testing.assert_allclose(count[:, 0], want_c, rtol=1e-13, atol=0)
    np.testing.assert_allclose(count[:, 1], want_dc, rtol=1e-12, atol=0)
    eps = curvature.CURVATURE_RIDGE * np.trace(A) / 3.0
    np.testing.assert_allclose(mats[0], np.eye(3) / eps, rtol=1e-14, atol=0)
    # (the SVD leaves round-off off the diagonal)
    np.testing.assert_allclose(mats[1], np.eye(3) / det ** (1.0 / 3.0), rtol=1e-13, atol=1e-15)


@functools.cache
def _fade_and_gradient_kernel(scalar):
    T = type_set(scalar)
    sm = smoothing.funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def run(t: wp.array(dtype=scalar), r: wp.array(dtype=T.vec3), h: scalar, fade: wp.array2d(dtype=scalar),
            w: wp.array(dtype=scalar), grad: wp.array(dtype=T.vec3)):
        i = wp.tid()
        s, ds = sm.smoothstep(t[i])
        fade[i, 0] = s
        fade[i, 1] = ds
        c6 = sm.poly6_coef(h)
        r2 = wp.dot(r[i], r[i])
        w[i] = sm.w_poly6_c(r2, h, c6)
        grad[i] = sm.grad_w_poly6_at(r[i], r2, h * h, c6)

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_the_smoothstep_and_poly6s_gradient(scalar):
    """``smoothing.smoothstep``, the shape of every fade (the guards, the floor image's share,
    the isotropic pressure's regularisation, the touchdown share): ``t^2 (3 - 2 t)`` and its
    slope, 0 and 1 with zero slope at the ends, the slope the central difference of the value.
    ``grad_w_poly6_at`` (the ``energy`` pressure force, the densities' adjoints): the central
    difference of eq. 7 (``w_poly6_c``) in each coordinate, inside the support."""
    T = type_set(scalar)
    np_t = np.float32 if scalar == wp.float32 else np.float64
    h = 0.02
    dt = 1e-3 if scalar == wp.float32 else 1e-6
    t0 = np.array([0.0, 0.1, 0.37, 0.5, 0.81, 1.0])
    t = np.concatenate([t0, t0 - dt, t0 + dt])
    rng = np.random.default_rng(5)
    r0 = rng.normal(size=(6, 3))
    r0 *= (np.array([0.05, 0.3, 0.6, 0.8, 0.95, 0.99]) * h / np.linalg.norm(r0, axis=1))[:, None]
    e = (dt if scalar == wp.float64 else 1e-3) * h
    r = np.concatenate([r0] + [r0 + sg * e * np.eye(3)[k] for k in range(3) for sg in (-1.0, 1.0)])
    n = max(len(t), len(r))
    tt = np.resize(t, n)
    fade = wp.zeros((n, 2), dtype=scalar)
    w = wp.zeros(n, dtype=scalar)
    grad = wp.zeros(n, dtype=T.vec3)
    wp.launch(_fade_and_gradient_kernel(scalar), n, [wp.array(tt.astype(np_t), dtype=scalar),
                                                    wp.array(r.astype(np_t), dtype=T.vec3), scalar(h)], [fade, w, grad])
    fade, w, grad = fade.numpy().astype(np.float64), w.numpy().astype(np.float64), grad.numpy().astype(np.float64)
    k = len(t0)
    tol = 1e-6 if scalar == wp.float32 else 1e-13
    np.testing.assert_allclose(fade[:k, 0], t0 * t0 * (3.0 - 2.0 * t0), rtol=0, atol=tol)
    assert fade[0, 0] == 0.0 and fade[k - 1, 0] == 1.0 and fade[0, 1] == 0.0 and fade[k - 1, 1] == 0.0
    central = (fade[2 * k:3 * k, 0] - fade[k:2 * k, 0]) / (2.0 * dt)
    np.testing.assert_allclose(fade[1:k - 1, 1], central[1:k - 1], rtol=2e-3 if scalar == wp.float32 else 1e-8)
    fd = np.stack([(w[k * (2 + 2 * c):k * (3 + 2 * c)] - w[k * (1 + 2 * c):k * (2 + 2 * c)]) / (2.0 * e)
                   for c in range(3)], axis=1)
    scale = np.abs(grad[:k]).max()
    np.testing.assert_allclose(grad[:k], fd, rtol=0, atol=(2e-3 if scalar == wp.float32 else 1e-7) * scale)


@functools.cache
def _flow_bound_kernel(scalar):
    T = type_set(scalar)
    bound = neighbors.kernels(scalar, "poly6").flow_inverse_bound
    iso = isotropic.funcs(scalar)
    flowed_values = plasticity.funcs(scalar).flowed_values

    @wp.kernel(module="unique", enable_backward=False)
    def run(F: wp.array(dtype=T.mat33), gamma: wp.array(dtype=scalar), G: wp.array(dtype=T.mat33),
            flowed: wp.array2d(dtype=T.mat33)):
        i, k = wp.tid()
        Fi = F[i]
        if k == 0:
            G[i] = bound(Fi, wp.determinant(Fi))
        # The flow's F' as plasticity.flow_under makes it: F plus isotropic_change's U diag(g - s) V^T.
        U, s, V = iso.svd(Fi)
        g, c, p = flowed_values(s, gamma[k])
        flowed[i, k] = Fi + iso.from_principal(U, g - s, V)

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_the_flow_inverse_bound_bounds_every_flowed_inverse_and_is_tight(scalar):
    """``neighbors.flow_inverse_bound`` (the key of a full stretched row of a material that
    flows) is ``G`` with ``|G d| <= |F'^-1 d|`` for every ``F'`` this step's flow may make of
    ``F``: ``sigma_max(G F') <= 1`` for every flow fraction ``gamma``, ``F'`` made as the flow
    makes it (``isotropic.svd``, ``plasticity.flowed_values``), with ``J`` inside and outside
    the volume range; and tight, ``sigma_max(G F) = 1`` at ``gamma = 0`` (``F' = F``) where
    some singular value reaches the flow's target ``t``. To round-off, the same whether ``G``
    reads ``isotropic.svd``'s singular values or ``wp.svd3``'s: in float32 2e-5 where every
    singular value is within 0.4 of 1 (``isotropic.svd`` takes them from the strain there),
    0.3 % farther (``wp.svd3``'s own error), in float64 1e-13; far below the slack of at least
    5 % the key divides by. ``max(sigma_k, t)`` as ``min``, or ``t`` of ``J`` unclamped,
    breaks it."""
    T = type_set(scalar)
    np_t = np.float32 if scalar == wp.float32 else np.float64
    rng = np.random.default_rng(11)

    def rotations(n):
        q = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
        return q * np.sign(np.linalg.det(q))[:, None, None]

    n = 60
    near = np.concatenate([1 + rng.normal(scale=1e-6, size=(n, 3)), 1 + rng.normal(scale=0.05, size=(n, 3))])
    far = np.concatenate([np.exp(rng.normal(scale=0.4, size=(n, 3))), np.tile([1.6, 1.2, 0.4], (n, 1)),
                          np.tile([0.9, 0.8, 0.7], (n, 1))])  # J = 0.77, 0.504: below the range
    sig = np.concatenate([near, far])
    F = rotations(len(sig)) @ (sig[:, :, None] * np.eye(3)) @ np.transpose(rotations(len(sig)), (0, 2, 1))
    F[0] = np.eye(3)
    F = F.astype(np_t)
    gamma = np.array([0.0, 1e-4, 0.02, 0.3, 1.0])
    G = wp.zeros(len(F), dtype=T.mat33)
    flowed = wp.zeros((len(F), len(gamma)), dtype=T.mat33)
    wp.launch(_flow_bound_kernel(scalar), (len(F), len(gamma)),
              [wp.array(F, dtype=T.mat33), wp.array(gamma.astype(np_t), dtype=scalar)], [G, flowed])
    GF = np.einsum("nij,nkjl->nkil", G.numpy().astype(np.float64), flowed.numpy().astype(np.float64))
    largest = np.linalg.svd(GF, compute_uv=False)[..., 0] - 1.0
    near_i = np.abs(sig - 1.0).max(axis=1) < 0.4
    assert near_i[:2 * n].all() and (~near_i).sum() >= n
    tol = np.where(near_i, 2e-5, 3e-3)[:, None] if scalar == wp.float32 else 1e-13
    over = largest - tol
    assert (over <= 0).all(), f"|G d| > |F'^-1 d| by {largest.max():.3g} (F {np.unravel_index(np.argmax(over), over.shape)})"
    # Tight where the flow's target t = clamp(J)^(1/3) is not above every singular value.
    tight = sig.max(axis=1) >= np.clip(sig.prod(axis=1), 0.8, 1.25) ** (1.0 / 3.0)
    assert tight.sum() > len(sig) - 2 * n
    assert (np.abs(largest[tight, 0]) <= (tol[tight, 0] if np.ndim(tol) else tol)).all(), "not tight at gamma = 0"
    assert (largest[:, -1] < -0.05).any(), "a full flow moves F' off the bound somewhere"


@functools.cache
def _pair_repulsion_kernel():
    from warp_esph.sim import pressure

    fn = pressure.funcs(wp.float64)

    @wp.kernel(module="unique", enable_backward=False)
    def run(r: wp.array(dtype=wp.float64), s: wp.float64, h: wp.float64, out: wp.array(dtype=wp.vec3d)):
        i = wp.tid()
        # Along a direction off the axes: the force is along rij whatever it is.
        d = wp.normalize(wp.vec3d(wp.float64(0.6), wp.float64(-0.48), wp.float64(0.64)))
        out[i] = fn.pair_repulsion_force(s, r[i] * d, r[i], h)

    return run


def test_the_pair_repulsion_is_minus_the_gradient_of_its_potential_and_meets_zero_with_zero_slope():
    """``pressure``'s ``pair_repulsion_force`` (``Material.pair_repulsion``) is ``-dU/dr`` of
    ``U = s (1 - r/r0)^3``, ``r0 = PAIR_REPULSION_RANGE h``, along the pair (central differences
    of ``U``), pushing the pair apart; 0 at and beyond ``r0``, where it meets 0 with zero slope
    (``3 s d^2 / r0^3`` at ``d`` inside it: no kink of the step where a pair crosses ``r0``)."""
    from warp_esph.sim import pressure

    h, s = 0.04, 0.016
    r0 = pressure.PAIR_REPULSION_RANGE * h
    d = np.array([0.6, -0.48, 0.64]) / np.linalg.norm([0.6, -0.48, 0.64])

    def run(r):
        out = wp.zeros(len(r), dtype=wp.vec3d)
        wp.launch(_pair_repulsion_kernel(), len(r), [wp.array(r, dtype=wp.float64), s, h], [out])
        return out.numpy()

    r = r0 * np.array([1e-3, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99])
    f = run(r)
    np.testing.assert_allclose(f, np.outer(np.linalg.norm(f, axis=1), d), rtol=1e-12)
    eps = 1e-9 * r0

    def U(q):
        return s * np.clip(1.0 - q / r0, 0.0, None) ** 3

    np.testing.assert_allclose(f @ d, -(U(r + eps) - U(r - eps)) / (2 * eps), rtol=1e-6)
    assert np.all(f @ d > 0.0), "a push"
    assert not run(r0 * np.array([1.0, 1.0 + 1e-12, 2.0, 4.0])).any()
    gap = r0 * np.array([1e-2, 1e-4, 1e-6])
    np.testing.assert_allclose(run(r0 - gap) @ d, 3.0 * s * gap ** 2 / r0 ** 3, rtol=1e-9)
