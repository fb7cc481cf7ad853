"""Multiplicative plasticity (Bargteil et al. 2007; paper §3, docs/method.md §4) applied to the
stored elastic deformation gradient, and the per-particle constitutive update.

In the SVD frame ``F = U diag(sigma) V^T`` the deviatoric stress is
``s = 2 mu (sigma - mean(sigma))``. Where ``|s| > Y + K alpha``:

    gamma   = min(nu_f dt (|s| - Y - K alpha) / |s|, 1)       (non-Newtonian: / |s|^2)
    sigma_k <- sigma_k^(1 - gamma) J^(gamma/3),  J = sigma_1 sigma_2 sigma_3
    alpha   <- alpha + gamma |ln sigma - mean(ln sigma)|

which is ``F_e = F F_p^-1`` with ``F_p <- V (J^(-1/3) F^)^gamma V^T F_p`` without storing
``F_p``. ``nu_f`` is a rate (1/s): ``nu_f dt`` is the paper's per-step fraction, so a result
does not depend on the time step. Where ``J`` leaves [0.8, 1.25] the flow uses
``J_c^(1/3) J^(-1/3) F^`` with ``J_c`` the nearer end of the range, relaxing the volume
change beyond it (paper §4: relaxing volume preservation under large volume change improves
stability; the paper's ``F^`` alone would make the flow jump where ``J`` crosses an end), and
where ``min sigma < 0.01`` the flow is skipped.
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import forces, isotropic, materials
from .roundoff import compensated_sum

#: Index into the solver's guard counters: plastic flow skipped because min sigma < 0.01.
COUNT_PLASTICITY_SKIPPED = 3
MIN_SINGULAR_VALUE = 0.01
VOLUME_PRESERVING_RANGE = (0.8, 1.25)


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    iso = isotropic.funcs(scalar)
    # Below this relative gap the divided difference of sigma^(1-gamma) is replaced by
    # its derivative at the midpoint (error ~ gap^2).
    close = scalar(1.0e-3 if scalar is wp.float32 else 1.0e-5)
    j_lo = scalar(VOLUME_PRESERVING_RANGE[0])
    j_hi = scalar(VOLUME_PRESERVING_RANGE[1])
    min_sigma = scalar(MIN_SINGULAR_VALUE)

    @wp.func
    def power_difference(a: scalar, b: scalar, p: scalar, c: scalar) -> scalar:
        # c (a^p - b^p) / (a - b) and its limit c p a^(p-1) as a -> b.
        if wp.abs(a - b) < close * (a + b):
            m = scalar(0.5) * (a + b)
            return c * p * wp.pow(m, p - scalar(1.0))
        return c * (wp.pow(a, p) - wp.pow(b, p)) / (a - b)

    @wp.func
    def deviatoric(v: vec3) -> vec3:
        """``v`` less its mean: the deviatoric part of principal values (the flow's
        ``dev sigma``, the hardening's log strain). A symmetric projection: also its own adjoint."""
        mean = (v[0] + v[1] + v[2]) / scalar(3.0)
        return v - vec3(mean, mean, mean)

    @wp.func
    def deviatoric_stress_norm2(mu: scalar, dev_norm2: scalar) -> scalar:
        """``|s|^2`` of the deviatoric stress ``s = 2 mu dev`` the flow rule compares with the
        yield surface (paper §4), from ``|dev|^2``."""
        return scalar(4.0) * mu * mu * dev_norm2

    @wp.func
    def yield_surface(yield_stress: scalar, hardening: scalar, alpha: scalar) -> scalar:
        """The yield surface ``Y + K alpha`` with hardening, not below 0 (a negative ``K``
        softens to no strength, not to a negative one)."""
        return wp.max(yield_stress + hardening * alpha, scalar(0.0))

    @wp.func
    def flow_rate_fraction(s_norm: scalar, y: scalar, flow_rate: scalar, dt: scalar, non_newtonian: int) -> scalar:
        """The flow fraction before its clamp at 1: ``nu_f dt (|s| - y) / |s|`` (non-Newtonian:
        ``/ |s|^2``) of a deviatoric stress ``|s|`` above the yield surface ``y``."""
        rate = flow_rate * dt * (s_norm - y) / s_norm
        if non_newtonian != 0:
            rate = rate / s_norm
        return rate

    @wp.func
    def may_flow(s: vec3) -> bool:
        """Whether ``F``'s singular values ``s`` let it flow: not where the smallest is below
        ``MIN_SINGULAR_VALUE`` (paper §4)."""
        return wp.min(wp.min(s[0], s[1]), s[2]) >= min_sigma

    @wp.func
    def flowed_values(s: vec3, gamma: scalar):
        """The singular values after a flow of fraction ``gamma``, ``g = c s^p`` with ``p = 1 -
        gamma`` and ``c = J_c^(gamma / 3)``: volume is kept inside ``[j_lo, j_hi]``; outside,
        only the volume change beyond the range is relaxed (paper §4), so ``c`` is continuous
        in ``J = s_0 s_1 s_2`` (``J_c`` it clamped to the range; docs/method.md §4). Returns
        ``(g, c, p)``."""
        J = s[0] * s[1] * s[2]
        c = wp.pow(wp.min(wp.max(J, j_lo), j_hi), gamma / scalar(3.0))
        p = scalar(1.0) - gamma
        g = c * vec3(wp.pow(s[0], p), wp.pow(s[1], p), wp.pow(s[2], p))
        return g, c, p

    @wp.func
    def flow_fraction(
        s_norm2: scalar,
        yield_stress: scalar,
        hardening: scalar,
        alpha: scalar,
        flow_rate: scalar,
        dt: scalar,
        non_newtonian: int,
    ):
        """Returns (flowed, gamma): whether the deviatoric stress ``|s|`` (given squared)
        exceeds the yield surface ``Y + K alpha``, and the flow fraction
        ``gamma = min(nu_f dt (|s| - Y - K alpha) / |s|, 1)`` (non-Newtonian: ``/ |s|^2``)."""
        y = yield_surface(yield_stress, hardening, alpha)
        flowed = int(0)
        gamma = scalar(0.0)
        # Compare squares: |s| = 0 at rest, where sqrt has an infinite derivative.
        if s_norm2 > y * y:
            gamma = wp.min(flow_rate_fraction(wp.sqrt(s_norm2), y, flow_rate, dt, non_newtonian), scalar(1.0))
            flowed = 1
        return flowed, gamma

    @wp.func
    def left_stretch(F: mat33) -> mat33:
        """``U diag(sigma) U^T`` of ``F = U diag(sigma) V^T`` (``isotropic.from_principal`` with
        ``U`` on both sides): the principal values the flow rule reads, in space (the frame of a
        Cauchy stress), so a stress given in space can be added to the elastic one
        (``pressure_yield_norm2``)."""
        U, s, V = iso.svd(F)
        return iso.from_principal(U, s, U)

    @wp.func_grad(left_stretch)
    def adj_left_stretch(F: mat33, adj_ret: mat33):
        # d(V_L^2) = dF F^T + F dF^T in U's frame gives (U^T dV_L U)_ij (s_i + s_j) = R_ij s_j +
        # s_i R_ji with R = U^T dF V: finite where singular values repeat (F = I), where
        # wp.svd3's own adjoint is not (isotropic.py).
        U, s, V = iso.svd(F)
        G = wp.transpose(U) * adj_ret * U
        A = mat33()
        for i in range(3):
            for j in range(3):
                d = s[i] + s[j]
                # Signed: an inverted value's own diagonal and its pairs have d < 0 (at d = 0,
                # sigma_j = -sigma_i, no derivative exists).
                if d != scalar(0.0):
                    A[i, j] = s[j] * (G[i, j] + G[j, i]) / d
        wp.adjoint[F] += U * A * wp.transpose(V)

    @wp.func
    def deviatoric_tensor(S: mat33) -> mat33:
        """``S`` less its mean normal stress: the part a yield surface on the deviator reads."""
        m = (S[0, 0] + S[1, 1] + S[2, 2]) / scalar(3.0)
        return S - m * wp.identity(n=3, dtype=scalar)

    @wp.func
    def pressure_yield_norm2(mu: scalar, dev_norm2: scalar, VL: mat33, D: mat33) -> scalar:
        """``|2 mu dev(V_L) + D|^2``: the yield test's deviatoric stress with the SPH pressure's
        deviator ``D`` (traceless, in space) added to the elastic one (``V_L = left_stretch(F)``,
        ``|dev(V_L)|^2 = dev_norm2``); ``D = 0`` gives ``deviatoric_stress_norm2``."""
        return (deviatoric_stress_norm2(mu, dev_norm2) + scalar(4.0) * mu * wp.trace(VL * D)
                + wp.ddot(D, D))

    @wp.func
    def yield_test_norm2(s: vec3, mu: scalar, F: mat33, D: mat33, with_pressure: int) -> scalar:
        """The deviatoric stress ``|s|^2`` the yield test compares with the yield surface: the
        elastic one of ``F``'s singular values ``s`` (paper §4), or, ``with_pressure != 0``,
        that plus the SPH pressure's deviator ``D`` (``pressure_yield_norm2``)."""
        dev = deviatoric(s)
        n2 = deviatoric_stress_norm2(mu, wp.dot(dev, dev))
        # A runtime switch, not a second function: the paper's path and the option's share
        # every other formula, and with 0 passed through inlined calls it costs no SVD.
        if with_pressure != 0:
            n2 = pressure_yield_norm2(mu, wp.dot(dev, dev), left_stretch(F), D)
        return n2

    @wp.func
    def flow_step(
        s: vec3,
        s_norm2: scalar,
        yield_stress: scalar,
        flow_rate: scalar,
        hardening: scalar,
        alpha: scalar,
        dt: scalar,
        non_newtonian: int,
    ):
        """The flow of the singular values ``s`` under the tested deviatoric stress ``|s|^2``
        (``yield_test_norm2``): it relaxes them at the rate that stress's excess over the yield
        surface sets; returns (flowed, new singular values g = c s^p, c, p, new alpha)."""
        flowed, gamma = flow_fraction(s_norm2, yield_stress, hardening, alpha, flow_rate, dt, non_newtonian)
        g = s
        c = scalar(1.0)
        p = scalar(1.0)
        alpha_new = alpha
        if flowed != 0:
            g, c, p = flowed_values(s, gamma)
            ld = deviatoric(vec3(wp.log(s[0]), wp.log(s[1]), wp.log(s[2])))
            alpha_new = alpha + gamma * wp.sqrt(wp.dot(ld, ld))
        return flowed, g, c, p, alpha_new

    @wp.func
    def guarded_flow_step_under(
        s: vec3,
        F: mat33,
        D: mat33,
        with_pressure: int,
        mu: scalar,
        yield_stress: scalar,
        flow_rate: scalar,
        hardening: scalar,
        alpha: scalar,
        dt: scalar,
        kind: int,
        counters: wp.array(dtype=wp.int32),
    ):
        """``flow_step`` of ``F``'s singular values ``s`` under ``yield_test_norm2(s, mu, F, D,
        with_pressure)``, unless the smallest is below ``MIN_SINGULAR_VALUE`` (paper §4): then
        no flow, counted. ``kind``: the material model (1: non-Newtonian)."""
        flowed = int(0)
        g = s
        c = scalar(1.0)
        p = scalar(1.0)
        alpha_new = alpha
        if may_flow(s):
            flowed, g, c, p, alpha_new = flow_step(
                s, yield_test_norm2(s, mu, F, D, with_pressure), yield_stress, flow_rate, hardening, alpha, dt,
                wp.where(kind == 1, 1, 0)
            )
        else:
            wp.atomic_add(counters, COUNT_PLASTICITY_SKIPPED, 1)
        return flowed, g, c, p, alpha_new

    @wp.func
    def guarded_flow_step(s: vec3, mu: scalar, yield_stress: scalar, flow_rate: scalar, hardening: scalar,
                          alpha: scalar, dt: scalar, kind: int, counters: wp.array(dtype=wp.int32)):
        """``guarded_flow_step_under`` with the paper's yield test, on ``F``'s singular values
        alone (the fused kernels, which have ``s`` from their own SVD)."""
        flowed, g, c, p, alpha_new = guarded_flow_step_under(s, mat33(), mat33(), 0, mu, yield_stress, flow_rate,
                                                             hardening, alpha, dt, kind, counters)
        return flowed, g, c, p, alpha_new

    @wp.func
    def flow_under(
        F: mat33,
        F_lo: mat33,
        a: scalar,
        mu: scalar,
        yield_stress: scalar,
        flow_rate: scalar,
        hardening: scalar,
        kind: int,
        dt: scalar,
        D: mat33,
        with_pressure: int,
        counters: wp.array(dtype=wp.int32),
    ):
        """``(F_e, F_e_lo, alpha)`` after this step's plastic flow of ``F + F_lo`` (``F_lo``:
        ``F``'s round-off, ``State.F_lo``) under ``yield_test_norm2``: ``with_pressure != 0``
        adds the SPH pressure's deviatoric stress ``D`` (in space) to the elastic one in the
        yield test (``Solver(yield_with_pressure=True)``); the flow still relaxes the elastic
        part only, so it stops where the sum sits on the yield surface. Differentiable: the
        new singular values through ``isotropic_change`` with the divided differences of
        ``g = c s^p`` its adjoint needs. The decomposition is ``F``'s: ``F_lo`` is below its
        round-off."""
        Fe = F
        Fe_lo = F_lo
        a_new = a
        if flow_rate > scalar(0.0):
            s = iso.singular_values(F)
            flowed, g, c, p, a_flow = guarded_flow_step_under(s, F, D, with_pressure, mu, yield_stress, flow_rate,
                                                              hardening, a, dt, kind, counters)
            if flowed != 0:
                d1 = vec3(
                    power_difference(s[0], s[1], p, c),
                    power_difference(s[0], s[2], p, c),
                    power_difference(s[1], s[2], p, c),
                )
                # F + F_lo plus the flow's change, compensated (State.F_lo).
                Fe, Fe_lo = compensated_sum(F, F_lo + iso.isotropic_change(F, g, d1))
                a_new = a_flow
        return Fe, Fe_lo, a_new

    @wp.func
    def flow(F: mat33, F_lo: mat33, a: scalar, mu: scalar, yield_stress: scalar, flow_rate: scalar,
             hardening: scalar, kind: int, dt: scalar, counters: wp.array(dtype=wp.int32)):
        """``flow_under`` with the paper's yield test, on ``F`` alone."""
        Fe, Fe_lo, a_new = flow_under(F, F_lo, a, mu, yield_stress, flow_rate, hardening, kind, dt, mat33(), 0,
                                      counters)
        return Fe, Fe_lo, a_new

    return types.SimpleNamespace(
        flow=flow, flow_under=flow_under, left_stretch=left_stretch, yield_test_norm2=yield_test_norm2,
        deviatoric_tensor=deviatoric_tensor, pressure_yield_norm2=pressure_yield_norm2,
        flow_step=flow_step, guarded_flow_step=guarded_flow_step, guarded_flow_step_under=guarded_flow_step_under,
        flow_fraction=flow_fraction, may_flow=may_flow,
        power_difference=power_difference, deviatoric=deviatoric, deviatoric_stress_norm2=deviatoric_stress_norm2,
        yield_surface=yield_surface, flow_rate_fraction=flow_rate_fraction, flowed_values=flowed_values,
    )


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    mat33 = T.mat33
    flow = funcs(scalar).flow
    stress = forces.funcs(scalar, "poly6").stress
    stress_model = forces.funcs(scalar, "poly6").stress_model
    Materials = materials.struct(scalar)

    flow_under = funcs(scalar).flow_under
    deviatoric_tensor = funcs(scalar).deviatoric_tensor

    @wp.func
    def constitutive_point(
        i: int,
        F_in: wp.array(dtype=mat33),
        F_lo_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        dt: scalar,
        D: mat33,
        with_pressure: int,
        F_out: wp.array(dtype=mat33),
        F_lo_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        stress_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """Particle ``i``'s plastic flow (``flow_under``), then the stress P* and ``F_e^-1`` the
        pair forces read. It stores them itself: in this order, Warp's generated adjoint sums
        ``F_e``'s contributions as it did when this was the kernel's own body."""
        m = material[i]
        kind = mat.model[m]
        mu = mat.mu[m]
        Fe, Fe_lo, a_new = flow_under(F_in[i], F_lo_in[i], alpha_in[i], mu, mat.yield_stress[m], mat.flow_rate[m],
                                      mat.hardening[m], kind, dt, D, with_pressure, counters)
        F_out[i] = Fe
        F_lo_out[i] = Fe_lo
        alpha_out[i] = a_new
        stress_out[i] = stress(Fe, mu, mat.lam[m], stress_model(mat, m))
        F_inv_out[i] = wp.inverse(Fe)

    @wp.kernel(module="unique")
    def constitutive_update(
        F_in: wp.array(dtype=mat33),
        F_lo_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        dt: scalar,
        F_out: wp.array(dtype=mat33),
        F_lo_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        stress_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """Plastic flow of the stored F, then the stress P* and F^-1 for the pair forces."""
        constitutive_point(wp.tid(), F_in, F_lo_in, alpha_in, material, mat, dt, mat33(), 0, F_out, F_lo_out,
                           alpha_out, stress_out, F_inv_out, counters)

    @wp.kernel(module="unique")
    def constitutive_update_with_pressure(
        F_in: wp.array(dtype=mat33),
        F_lo_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        dt: scalar,
        pressure_stress: wp.array(dtype=mat33),
        F_out: wp.array(dtype=mat33),
        F_lo_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        stress_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """``constitutive_update`` whose yield test adds each particle's SPH pressure stress
        (``pressure.launch_pressure_stress``) to the elastic one (``flow_under``)."""
        i = wp.tid()
        constitutive_point(i, F_in, F_lo_in, alpha_in, material, mat, dt, deviatoric_tensor(pressure_stress[i]), 1,
                           F_out, F_lo_out, alpha_out, stress_out, F_inv_out, counters)

    @wp.kernel(module="unique")
    def image_constitutive_update(
        x: wp.array(dtype=T.vec3),
        F_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        dt: scalar,
        gn: T.vec3,
        goff: scalar,
        h: scalar,
        F_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        stress_out: wp.array(dtype=mat33),
        counters: wp.array(dtype=wp.int32),
    ):
        """``constitutive_update`` of each floor image's own F and hardening
        (``State.F_image``, ``State.alpha_image``) where the image can reach a particle (its
        particle within ``h`` of the plane ``dot(gn, x) = goff``); elsewhere nothing reads them
        (the fit's update and ``image_hardening_update`` give such an image its particle's):
        kept, and no stress."""
        i = wp.tid()
        Fg = F_in[i]
        a = alpha_in[i]
        P = mat33()
        if wp.dot(gn, x[i]) - goff < h:
            m = material[i]
            kind = mat.model[m]
            mu = mat.mu[m]
            Fe, Fe_lo, a = flow(Fg, mat33(), a, mu, mat.yield_stress[m], mat.flow_rate[m], mat.hardening[m], kind, dt,
                                counters)
            Fg = Fe + Fe_lo
            P = stress(Fg, mu, mat.lam[m], stress_model(mat, m))
        F_out[i] = Fg
        alpha_out[i] = a
        stress_out[i] = P

    @wp.kernel(module="unique")
    def image_hardening_update(
        alpha: wp.array(dtype=scalar),
        alpha_image_flowed: wp.array(dtype=scalar),
        share: wp.array(dtype=scalar),
        alpha_image_out: wp.array(dtype=scalar),
    ):
        """Each floor image's hardening after the step: its own flowed one where the image is
        its own (``State.image_share`` 1: every image at rest), its particle's where it has no
        particle within ``h`` of the plane (0, a moving image), as the fit's update picks its F
        (``deformation.floor_image_share``)."""
        i = wp.tid()
        a = alpha_image_flowed[i]
        if share[i] < scalar(1.0):
            a = alpha[i] + share[i] * (a - alpha[i])
        alpha_image_out[i] = a

    vec3 = T.vec3
    fl = funcs(scalar)
    fo = forces.funcs(scalar, "poly6")  # the stress only: no fit weight in it
    j_lo = scalar(VOLUME_PRESERVING_RANGE[0])
    j_hi = scalar(VOLUME_PRESERVING_RANGE[1])

    # The isotropic map's adjoint in the SVD frame: its formulas, used step by step here.
    COROTATED = forces.COROTATED
    off_diagonal = isotropic.funcs(scalar).off_diagonal
    pair_d2 = isotropic.funcs(scalar).pair_skew_coefficients
    svd = isotropic.funcs(scalar).svd

    @wp.kernel(enable_backward=False, module="unique")
    def constitutive_update_adjoint(
        F_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        dt: scalar,
        F_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        adj_F_out: wp.array(dtype=mat33),
        adj_alpha_out: wp.array(dtype=scalar),
        adj_stress: wp.array(dtype=mat33),
        adj_F_inv: wp.array(dtype=mat33),
        adj_F_in: wp.array(dtype=mat33),
        adj_alpha_in: wp.array(dtype=scalar),
        adj_mu: wp.array(dtype=scalar),
        adj_lam: wp.array(dtype=scalar),
        adj_yield: wp.array(dtype=scalar),
        adj_rate: wp.array(dtype=scalar),
        adj_hardening: wp.array(dtype=scalar),
    ):
        """Hand-written adjoint of ``constitutive_update`` for the SVD-based models (linear,
        non-Newtonian): one SVD of ``F`` where Warp's generated adjoint replays and
        differentiates four (``flow``'s and ``stress``'s ``singular_values`` and
        ``isotropic_map``), as the fused forward reuses one.

        ``F = U diag(s) V^T``; plastic flow ``F_e = U diag(g) V^T`` (``g = c s^p``,
        ``flow_step``); ``P = U diag(f(g)) V^T`` (eq. 9, ``principal_stress``, or
        ``corotated_principal_stress`` where ``forces.stress_model`` says so); ``F^-1``.
        Backward: ``adj F_e = adj F_out - F^-T adj F^-1 F^-T + U (diag(J_f^T diag(C_P)) + M_P) V^T``
        with ``C_P = U^T adj P V`` and ``M_P`` the off-diagonal part with the divided
        differences of ``f`` (isotropic.py); then ``C = U^T adj F_e V``, ``adj g = diag(C)``
        through ``flow_step`` by the chain rule below to ``adj s`` and the parameters, and
        ``adj F = U (diag(adj s) + M) V^T`` with ``M`` from ``g``'s divided differences."""
        i = wp.tid()
        m = material[i]
        kind = mat.model[m]
        mu = mat.mu[m]
        lam = mat.lam[m]
        Y = mat.yield_stress[m]
        nu = mat.flow_rate[m]
        K = mat.hardening[m]
        F = F_in[i]
        a0 = alpha_in[i]
        U, s, V = svd(F)
        Ut = wp.transpose(U)

        # Forward, as flow_step (only where it flows do g, c, p differ from s, 1, 1).
        flowed = int(0)
        g = s
        c = scalar(1.0)
        p = scalar(1.0)
        gamma = scalar(0.0)
        in_range = int(0)
        s_norm = scalar(0.0)
        y = scalar(0.0)
        nn = wp.where(kind == 1, 1, 0)
        dev = fl.deviatoric(s)
        if nu > scalar(0.0) and fl.may_flow(s):
            y = fl.yield_surface(Y, K, a0)
            s_norm2 = fl.deviatoric_stress_norm2(mu, wp.dot(dev, dev))
            flowed, gamma = fl.flow_fraction(s_norm2, Y, K, a0, nu, dt, nn)
            if flowed != 0:
                s_norm = wp.sqrt(s_norm2)
                g, c, p = fl.flowed_values(s, gamma)
                # c = J_c^(gamma/3) (flowed_values): where J is inside the range, c follows s.
                J = s[0] * s[1] * s[2]
                if J >= j_lo and J <= j_hi:
                    in_range = 1

        # Stress P = U diag(f(g)) V^T and F^-1 into adj F_e (in the frame: C = U^T adj V).
        Finv = F_inv_out[i]
        FinvT = wp.transpose(Finv)
        G = adj_F_out[i] - FinvT * adj_F_inv[i] * FinvT
        C = Ut * G * V
        CP = Ut * adj_stress[i] * V
        af = vec3(CP[0, 0], CP[1, 1], CP[2, 2])
        tr = fo.principal_strain_trace(g)
        one = vec3(scalar(1.0), scalar(1.0), scalar(1.0))
        base = fo.corotated_principal_stress(g, mu, lam)
        f = base
        d_f = vec3(scalar(2.0) * mu, scalar(2.0) * mu, scalar(2.0) * mu)
        ag_P = vec3()
        a_mu = scalar(0.0)
        a_lam = scalar(0.0)
        if fo.stress_model(mat, m) == COROTATED:
            # f = P^ (forces.corotated_stress)
            saf = af[0] + af[1] + af[2]
            ag_P = scalar(2.0) * mu * af + lam * saf * one
            a_mu = scalar(2.0) * wp.dot(af, g - one)
            a_lam = saf * tr
        else:
            # f = g o P^ (eq. 9)
            f = fo.principal_stress(g, mu, lam)
            d_f = fo.principal_stress_differences(g, mu, lam)
            afg = wp.dot(af, g)
            ag_P = wp.cw_mul(af, base) + scalar(2.0) * mu * wp.cw_mul(af, g) + lam * afg * one
            a_mu = scalar(2.0) * wp.dot(af, wp.cw_mul(g, g - one))
            a_lam = afg * tr
        C = C + wp.diag(ag_P) + off_diagonal(CP, d_f, pair_d2(f, g))

        a_alpha = adj_alpha_out[i]
        ag = vec3(C[0, 0], C[1, 1], C[2, 2])
        a_s = ag
        M = mat33()
        a_Y = scalar(0.0)
        a_nu = scalar(0.0)
        a_K = scalar(0.0)
        if flowed != 0:
            d1 = vec3(fl.power_difference(s[0], s[1], p, c), fl.power_difference(s[0], s[2], p, c),
                      fl.power_difference(s[1], s[2], p, c))
            M = off_diagonal(C, d1, pair_d2(g, s))
            # g_k = c s_k^p
            a_c = wp.dot(ag, g) / c
            ls = vec3(wp.log(s[0]), wp.log(s[1]), wp.log(s[2]))
            a_p = wp.dot(wp.cw_mul(ag, g), ls)
            a_s = p * wp.cw_div(wp.cw_mul(ag, g), s)
            a_gamma = -a_p
            if in_range != 0:
                # c = J^(gamma / 3): ln c = gamma / 3 (ln s_0 + ln s_1 + ln s_2)
                a_gamma += a_c * c * (ls[0] + ls[1] + ls[2]) / scalar(3.0)
                a_s += (a_c * c * gamma / scalar(3.0)) * wp.cw_div(one, s)
            else:
                # c = J_c^(gamma / 3) with J_c the end of the range: no dependence on s.
                a_gamma += a_c * c * wp.log(wp.min(wp.max(s[0] * s[1] * s[2], j_lo), j_hi)) / scalar(3.0)
            # alpha_new = alpha + gamma |ld|, ld = ls - mean(ls)
            ld = fl.deviatoric(ls)
            nld = wp.sqrt(wp.dot(ld, ld))
            a_gamma += a_alpha * nld
            if nld > scalar(0.0):
                a_s += wp.cw_div(fl.deviatoric((a_alpha * gamma / nld) * ld), s)
            # gamma = min(rate, 1) (the gradient goes to rate only below the clamp, as Warp's min)
            if fl.flow_rate_fraction(s_norm, y, nu, dt, nn) < scalar(1.0):
                a_rate = a_gamma
                a_sn = scalar(0.0)
                a_y = scalar(0.0)
                if nn != 0:
                    a_nu = a_rate * dt * (s_norm - y) / (s_norm * s_norm)
                    a_y = -a_rate * nu * dt / (s_norm * s_norm)
                    a_sn = a_rate * nu * dt * (scalar(2.0) * y - s_norm) / (s_norm * s_norm * s_norm)
                else:
                    a_nu = a_rate * dt * (s_norm - y) / s_norm
                    a_y = -a_rate * nu * dt / s_norm
                    a_sn = a_rate * nu * dt * y / (s_norm * s_norm)
                # y = max(Y + K alpha, 0)
                if Y + K * a0 > scalar(0.0):
                    a_Y = a_y
                    a_K = a_y * a0
                    a_alpha += a_y * K
                # s_norm = sqrt(4 mu^2 |dev|^2)
                a_n2 = a_sn / (scalar(2.0) * s_norm)
                a_mu += a_n2 * scalar(8.0) * mu * wp.dot(dev, dev)
                a_s += fl.deviatoric((a_n2 * scalar(8.0) * mu * mu) * dev)
            adj_F_in[i] = adj_F_in[i] + U * (wp.diag(a_s) + M) * wp.transpose(V)
        else:
            # F_e = F: adj F = adj F_e = U C V^T.
            adj_F_in[i] = adj_F_in[i] + U * C * wp.transpose(V)
        adj_alpha_in[i] = adj_alpha_in[i] + a_alpha
        wp.atomic_add(adj_mu, m, a_mu)
        wp.atomic_add(adj_lam, m, a_lam)
        wp.atomic_add(adj_yield, m, a_Y)
        wp.atomic_add(adj_rate, m, a_nu)
        wp.atomic_add(adj_hardening, m, a_K)

    return types.SimpleNamespace(constitutive_update=constitutive_update, image_constitutive_update=image_constitutive_update,
                                 constitutive_update_with_pressure=constitutive_update_with_pressure,
                                 image_hardening_update=image_hardening_update,
                                 flow=flow,
                                 constitutive_update_adjoint=constitutive_update_adjoint)


def launch_constitutive_update(model, state_in, state_out, dt, counters, pressure_stress=None):
    """Plastic flow of ``state_in.F`` (paper §3), stress and ``F^-1`` into ``state_out``.
    ``pressure_stress``: each particle's SPH pressure stress (``pressure.launch_pressure_stress``),
    added to the elastic stress in the yield test (``constitutive_update_with_pressure``);
    None: the paper's test on ``F`` alone."""
    k = kernels(model.scalar)
    inputs = [state_in.F, state_in.F_lo, state_in.alpha, model.particle_material, model.material_arrays(),
              model.scalar(dt)]
    kernel = k.constitutive_update
    if pressure_stress is not None:
        kernel = k.constitutive_update_with_pressure
        inputs.append(pressure_stress)
    model.launches(
        kernel,
        model.particle_count,
        inputs,
        [state_out.F_flowed, state_out.F_flowed_lo, state_out.alpha, state_out.stress, state_out.F_inv, counters],
        device=model.device,
    )


def launch_image_constitutive_update(model, state_in, state_out, dt, counters):
    """``image_constitutive_update``: the plastic flow and stress of each floor image's own
    ``F`` and hardening (``State.F_image``, ``alpha_image``; ``add_ground(images=True)``) into
    ``state_out.F_image_flowed``, ``alpha_image_flowed`` and ``image_stress``; recorded on a
    tape as any launch (Warp's generated adjoint)."""
    gn, goff, _gmin, _images = model.image_args()
    model.launches(
        kernels(model.scalar).image_constitutive_update,
        model.particle_count,
        [state_in.x, state_in.F_image, state_in.alpha_image, model.particle_material, model.material_arrays(),
         model.scalar(dt), gn, goff, model.scalar(model.support_radius)],
        [state_out.F_image_flowed, state_out.alpha_image_flowed, state_out.image_stress, counters],
        device=model.device,
    )


def launch_image_hardening_update(model, state_out):
    """``image_hardening_update``: ``state_out.alpha_image`` from the particles' and the
    images' flowed hardening and the share the fit's update wrote (``state_out.image_share``);
    after that update. Warp's generated adjoint."""
    model.launches(
        kernels(model.scalar).image_hardening_update,
        model.particle_count,
        [state_out.alpha, state_out.alpha_image_flowed, state_out.image_share],
        [state_out.alpha_image],
        device=model.device,
    )


def launch_constitutive_update_adjoint(model, state_in, state_out, dt, counters, tape, hand: bool = True):
    """The adjoint of ``constitutive_update`` (for the fused step under a tape, which writes
    the same outputs in its own kernel): the gradients of ``state_out.F_flowed, alpha,
    stress, F_inv`` into those of ``state_in.F, alpha`` and the material parameters. The
    hand-written ``constitutive_update_adjoint`` when every material is linear or
    non-Newtonian (and ``hand``), else Warp's generated adjoint, launched by hand."""
    if hand and model.material_model.numpy().max() <= 1:
        S = model.scalar
        model.launches(
            kernels(S).constitutive_update_adjoint, model.particle_count,
            [state_in.F, state_in.alpha, model.particle_material, model.material_arrays(), S(dt), state_out.F_flowed,
             state_out.F_inv, state_out.F_flowed.grad, state_out.alpha.grad, state_out.stress.grad, state_out.F_inv.grad,
             state_in.F.grad, state_in.alpha.grad, model.mu.grad, model.lam.grad, model.yield_stress.grad,
             model.flow_rate.grad, model.hardening.grad],
            device=model.device, record_tape=False,
        )
        return
    mats = model.material_arrays()
    inputs = [state_in.F, state_in.F_lo, state_in.alpha, model.particle_material, mats, model.scalar(dt)]
    outputs = [state_out.F_flowed, state_out.F_flowed_lo, state_out.alpha, state_out.stress, state_out.F_inv, counters]
    model.launches(
        kernels(model.scalar).constitutive_update, model.particle_count, inputs, outputs,
        adj_inputs=[tape.get_adjoint(a) for a in inputs], adj_outputs=[tape.get_adjoint(a) for a in outputs],
        device=model.device, adjoint=True, record_tape=False,
    )
