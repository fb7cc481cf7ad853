"""Smoothing kernels: poly6 (eq. 7), the Solenthaler elastic kernel (eqs. 12-13), and
the spiky and viscosity kernels of Müller et al. 2003 used by SPH (docs/method.md §6).

Each factory returns ``wp.func`` objects specialised to one scalar type.
"""

import functools
import math
import types

import warp as wp

from .. import checks
from .._types import type_set
from .fit_weights import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS  # noqa: F401 (the package's names for them)


def elastic_kernel(r: float, h: float) -> float:
    """Host-side Solenthaler kernel W(r, h) of eq. 12 with c from eq. 13 (the step needs only
    its gradient, ``grad_w_elastic_c``; tests check that against this)."""
    if r > h:
        return 0.0
    c = elastic_kernel_constant(h)
    return c * 2.0 * h / math.pi * (math.cos((r + h) * math.pi / (2.0 * h)) + 1.0)


def elastic_kernel_constant(h: float) -> float:
    """c of eq. 13, which makes eq. 12 integrate to 1 over the ball of radius h."""
    return math.pi / (8.0 * h**4 * (math.pi / 3.0 - 8.0 / math.pi + 16.0 / math.pi**2))


# Taylor coefficients of cos(pi s / 2) in t = s^2 up to t^7: on s in [0, 1] the
# truncation error is below 1e-8, under float32 rounding (max error measured against
# float64: 1.4e-7, libm cosf: 1.1e-7).
_COS_COEFFS = [(-1) ** k * (math.pi / 2) ** (2 * k) / math.factorial(2 * k) for k in range(8)]

#: The viscosity Laplacian's ``h - |r|`` meets 0 at ``h`` with a slope, so every pair crossing the
#: support made the step, and a loss, kinked there (docs/physics.md, "The landing loss's kinks are
#: pairs leaving the viscosity's support"). Over the last ``VISCOSITY_EDGE h`` a cubic joins it to 0
#: with zero slope; the band is narrower than the gap from ``h`` to the nearest lattice distance
#: below it at ``h`` = 2 dx and 2.5 dx (0.134 h, 0.020 h), so on a lattice only pairs a rounding
#: error inside ``h`` fall in it.
VISCOSITY_EDGE = 0.01


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    """Each kernel's formula once, with its ``h``-dependent constant passed in (``*_coef``),
    so a kernel computes the constant once per particle instead of once per pair (pow and
    divisions are a large part of a pair's cost on the CPU); the two-argument forms
    (``w_poly6(r2, h)``, ...) compute the constant themselves."""
    T = type_set(scalar)
    vec3 = T.vec3
    PI = scalar(math.pi)
    c0, c1, c2, c3, c4, c5, c6, c7 = (scalar(c) for c in _COS_COEFFS)
    exact_cos = scalar is wp.float64

    @wp.func
    def smoothstep(t: scalar):
        """``t^2 (3 - 2 t)`` and its slope ``6 t (1 - t)``, for ``t`` in [0, 1] (the caller
        clamps): 0 to 1 with zero slope at both ends, so a quantity faded by it is C1 where the
        fade starts and ends (the guards, the floor image's share, the isotropic pressure's
        regularisation, the touchdown share)."""
        return t * t * (scalar(3.0) - scalar(2.0) * t), scalar(6.0) * t * (scalar(1.0) - t)

    @wp.func
    def poly6_coef(h: scalar) -> scalar:
        return scalar(315.0) / (scalar(64.0) * PI * wp.pow(h, scalar(9.0)))

    @wp.func
    def w_poly6_c(r2: scalar, h: scalar, coef: scalar) -> scalar:
        """Eq. 7, on the squared distance: smooth in r and zero with zero slope at r = h."""
        if r2 >= h * h:
            return scalar(0.0)
        d = h * h - r2
        return coef * d * d * d

    @wp.func
    def w_poly6_inside(r2: scalar, hh: scalar, coef: scalar):
        """Eq. 7 and its slope on the squared distance, ``w = coef e^3`` and
        ``d w / d r2 = -3 coef e^2`` with ``e = h^2 - r2``, for ``r2 < hh = h^2`` (the
        hand-written adjoints' pairs; the caller tests the support)."""
        e = hh - r2
        return coef * e * e * e, scalar(-3.0) * coef * e * e

    @wp.func
    def w_poly6(r2: scalar, h: scalar) -> scalar:
        return w_poly6_c(r2, h, poly6_coef(h))

    @wp.func
    def grad_w_poly6_at(r: vec3, r2: scalar, hh: scalar, coef: scalar) -> vec3:
        """The gradient of eq. 7 at ``r``, ``-6 coef (h^2 - |r|^2)^2 r``: ``w_poly6_inside``'s
        slope on ``r2 = |r|^2 < hh = h^2``, times ``2 r`` (the caller tests the support)."""
        w, dw = w_poly6_inside(r2, hh, coef)
        return (scalar(2.0) * dw) * r

    @wp.func
    def elastic_coef(h: scalar) -> scalar:
        """c of eq. 13."""
        return PI / (scalar(8.0) * h * h * h * h * (PI / scalar(3.0) - scalar(8.0) / PI + scalar(16.0) / (PI * PI)))

    @wp.func
    def elastic_cos(r2: scalar, rl: scalar, h: scalar) -> scalar:
        """cos(pi |r| / (2h)) of eq. 12's gradient, for ``r2 = |r|^2``, ``rl = |r|`` in [0, h]:
        the library cosine in float64; in float32 a polynomial in ``|r|^2 / h^2`` (a third
        of a pair's elastic-force cost was the libm call and its wait for the square root)."""
        if wp.static(exact_cos):
            return wp.cos(PI * rl / (scalar(2.0) * h))
        t = r2 * (scalar(1.0) / (h * h))
        return c0 + t * (c1 + t * (c2 + t * (c3 + t * (c4 + t * (c5 + t * (c6 + t * c7))))))

    @wp.func
    def elastic_cos_dr2(r2: scalar, rl: scalar, h: scalar) -> scalar:
        """``d elastic_cos / d r2``: of the library cosine in float64, of the polynomial in
        float32 (the function the forward evaluates, so hand-written adjoints are exact)."""
        if wp.static(exact_cos):
            k = PI / (scalar(2.0) * h)
            return -wp.sin(k * rl) * k / (scalar(2.0) * rl)
        ih2 = scalar(1.0) / (h * h)
        t = r2 * ih2
        d = c1 + t * (scalar(2.0) * c2 + t * (scalar(3.0) * c3 + t * (scalar(4.0) * c4 + t * (
            scalar(5.0) * c5 + t * (scalar(6.0) * c6 + t * scalar(7.0) * c7)))))
        return d * ih2

    @wp.func
    def grad_w_elastic_adjoint(r: vec3, h: scalar, c: scalar, adj: vec3):
        """``grad_w_elastic_c(r)`` and its adjoint ``J^T adj`` (``J = d gradW / d r``), sharing
        one square root and cosine. With ``gradW = phi(r2) r``, ``phi = -c cos / |r|``:
        ``J = phi I + 2 phi' r r^T``."""
        r2 = wp.dot(r, r)
        if r2 >= h * h or r2 <= scalar(1.0e-24) * h * h:
            return vec3(), vec3()
        rl = wp.sqrt(r2)
        cs = elastic_cos(r2, rl, h)
        phi = -c * cs / rl
        # d phi / d r2 = -c (cos' / rl - cos / (2 rl^3))
        dphi = -c * (elastic_cos_dr2(r2, rl, h) / rl - cs / (scalar(2.0) * rl * r2))
        return phi * r, phi * adj + scalar(2.0) * dphi * wp.dot(r, adj) * r

    @wp.func
    def grad_w_elastic_c(r: vec3, h: scalar, c: scalar) -> vec3:
        """Gradient of eq. 12: -c cos(pi |r| / (2h)) r/|r|. It does not vanish as r -> 0,
        so coincident particles (|r| = 0) get no force instead of a NaN direction."""
        r2 = wp.dot(r, r)
        if r2 >= h * h or r2 <= scalar(1.0e-24) * h * h:
            return vec3()
        rl = wp.sqrt(r2)
        return -c * elastic_cos(r2, rl, h) / rl * r

    @wp.func
    def grad_w_elastic(r: vec3, h: scalar) -> vec3:
        return grad_w_elastic_c(r, h, elastic_coef(h))

    @wp.func
    def spiky_coef(h: scalar) -> scalar:
        return -scalar(45.0) / (PI * wp.pow(h, scalar(6.0)))

    @wp.func
    def spiky_gradient_factor(rl: scalar, h: scalar, coef: scalar) -> scalar:
        """``psi(|r|) = coef (h - |r|)^2 / |r|``, ``grad_w_spiky_at``'s ``psi r`` (``rl = |r|`` in
        (0, h), ``coef = spiky_coef``)."""
        d = h - rl
        return coef * d * d / rl

    @wp.func
    def spiky_gradient_factor_slope(rl: scalar, h: scalar, coef: scalar, r2: scalar) -> scalar:
        """``d psi / d |r| = -coef (h - |r|) (h + |r|) / |r|^2`` of ``spiky_gradient_factor``
        (``r2 = |r|^2``), for the adjoints of the spiky forces."""
        d = h - rl
        return -coef * d * (scalar(2.0) * rl + d) / r2

    @wp.func
    def grad_w_spiky_at(r: vec3, rl: scalar, h: scalar, coef: scalar) -> vec3:
        """-45/(pi h^6) (h - |r|)^2 r/|r| (Müller et al. 2003) given ``rl = |r|`` in (0, h):
        ``spiky_gradient_factor(|r|) r``."""
        return spiky_gradient_factor(rl, h, coef) * r

    @wp.func
    def grad_w_spiky_c(r: vec3, h: scalar, coef: scalar) -> vec3:
        r2 = wp.dot(r, r)
        if r2 >= h * h or r2 <= scalar(1.0e-24) * h * h:
            return vec3()
        return grad_w_spiky_at(r, wp.sqrt(r2), h, coef)

    @wp.func
    def grad_w_spiky(r: vec3, h: scalar) -> vec3:
        return grad_w_spiky_c(r, h, spiky_coef(h))

    @wp.func
    def w_spiky_coef(h: scalar) -> scalar:
        return scalar(15.0) / (PI * wp.pow(h, scalar(6.0)))

    @wp.func
    def w_spiky_c(r2: scalar, h: scalar, coef: scalar) -> scalar:
        """The spiky kernel 15/(pi h^6) (h - |r|)^3 (Müller et al. 2003) on the squared
        distance: its slope ``-3 coef (h - |r|)^2`` does not vanish at ``r = 0``, so a density
        summed with it keeps growing as two particles meet (the ``energy_spiky`` pressure)."""
        if r2 >= h * h:
            return scalar(0.0)
        d = h - wp.sqrt(r2)
        return coef * d * d * d

    @wp.func
    def viscosity_coef(h: scalar) -> scalar:
        return scalar(45.0) / (PI * wp.pow(h, scalar(6.0)))

    edge = scalar(VISCOSITY_EDGE)

    @wp.func
    def lap_w_viscosity_at(rl: scalar, h: scalar, coef: scalar) -> scalar:
        """45/(pi h^6) (h - |r|) (Müller et al. 2003) given ``rl = |r| < h``, joined to 0 at
        ``h`` with zero slope by ``coef u^2 (2a - u) / a^2`` (``u = h - |r| < a = VISCOSITY_EDGE h``),
        which meets the line with its value and slope at ``u = a``."""
        u = h - rl
        a = edge * h
        if u < a:
            return coef * u * u * (scalar(2.0) * a - u) / (a * a)
        return coef * u

    @wp.func
    def lap_w_viscosity_slope_at(rl: scalar, h: scalar, coef: scalar) -> scalar:
        """``d lap_w_viscosity_at / d |r|``: ``-coef`` on the line, ``-coef u (4a - 3u) / a^2`` in the
        edge band (0 at ``h``)."""
        u = h - rl
        a = edge * h
        if u < a:
            return -coef * u * (scalar(4.0) * a - scalar(3.0) * u) / (a * a)
        return -coef

    @wp.func
    def lap_w_viscosity_c(r2: scalar, h: scalar, coef: scalar) -> scalar:
        if r2 >= h * h:
            return scalar(0.0)
        return lap_w_viscosity_at(wp.sqrt(r2), h, coef)

    @wp.func
    def lap_w_viscosity(r2: scalar, h: scalar) -> scalar:
        return lap_w_viscosity_c(r2, h, viscosity_coef(h))

    return types.SimpleNamespace(
        smoothstep=smoothstep, w_poly6=w_poly6, grad_w_poly6_at=grad_w_poly6_at, grad_w_elastic=grad_w_elastic, grad_w_spiky=grad_w_spiky, lap_w_viscosity=lap_w_viscosity,
        poly6_coef=poly6_coef, w_poly6_c=w_poly6_c, w_poly6_inside=w_poly6_inside, elastic_coef=elastic_coef,
        grad_w_elastic_c=grad_w_elastic_c,
        grad_w_elastic_adjoint=grad_w_elastic_adjoint, elastic_cos_dr2=elastic_cos_dr2,
        elastic_cos=elastic_cos, spiky_coef=spiky_coef, w_spiky_coef=w_spiky_coef, w_spiky_c=w_spiky_c,
        grad_w_spiky_c=grad_w_spiky_c, grad_w_spiky_at=grad_w_spiky_at, spiky_gradient_factor=spiky_gradient_factor,
        spiky_gradient_factor_slope=spiky_gradient_factor_slope,
        viscosity_coef=viscosity_coef, lap_w_viscosity_c=lap_w_viscosity_c, lap_w_viscosity_at=lap_w_viscosity_at,
        lap_w_viscosity_slope_at=lap_w_viscosity_slope_at,
    )


#: ``FIT_WEIGHTS``, ``DEFAULT_FIT_WEIGHT``: ``fit_weights``' (no Warp there, for the validation suite).


@functools.cache
def fit_weight_funcs(scalar, weight: str) -> types.SimpleNamespace:
    """``coef(h)``, ``w_c(r2, h, coef)`` and ``w_inside(r2, hh, coef)`` (the weight and its
    slope on ``r2`` inside the support) of the fit's ``weight`` (``FIT_WEIGHTS``). Their constant
    cancels wherever they enter (``A^-1 B``, and ``w A^-1`` in the forces), so the biweight's
    is ``1 / h^4``, a weight of order 1."""
    if weight not in FIT_WEIGHTS:
        raise ValueError(f"fit_weight = {checks.shorten(weight)!r} is not allowed: must be one of {', '.join(map(repr, FIT_WEIGHTS))}")
    sm = funcs(scalar)
    if weight == "poly6":
        return types.SimpleNamespace(coef=sm.poly6_coef, w_c=sm.w_poly6_c, w_inside=sm.w_poly6_inside)

    @wp.func
    def biweight_coef(h: scalar) -> scalar:
        hh = h * h
        return scalar(1.0) / (hh * hh)

    @wp.func
    def w_biweight_c(r2: scalar, h: scalar, coef: scalar) -> scalar:
        """``coef (h^2 - r^2)^2``: zero with zero slope at r = h."""
        if r2 >= h * h:
            return scalar(0.0)
        d = h * h - r2
        return coef * d * d

    @wp.func
    def w_biweight_inside(r2: scalar, hh: scalar, coef: scalar):
        """The biweight and its slope on ``r2``, ``coef e^2`` and ``-2 coef e``, ``e = h^2 - r2``,
        for ``r2 < hh``."""
        e = hh - r2
        return coef * e * e, scalar(-2.0) * coef * e

    return types.SimpleNamespace(coef=biweight_coef, w_c=w_biweight_c, w_inside=w_biweight_inside)
