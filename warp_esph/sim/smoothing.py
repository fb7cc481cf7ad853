"""Smoothing kernels: poly6 (eq. 7), the Solenthaler elastic kernel (eqs. 12-13), and
the spiky and viscosity kernels of Müller et al. 2003 used by SPH (SPEC §6).

Each factory returns ``wp.func`` objects specialised to one scalar type.
"""

import functools
import math
import types

import warp as wp

from .._types import type_set


def poly6(r2: float, h: float) -> float:
    """Host-side poly6 value (eq. 7) for tests and rest-state sums."""
    if r2 > h * h:
        return 0.0
    return 315.0 / (64.0 * math.pi * h**9) * (h * h - r2) ** 3


def elastic_kernel(r: float, h: float) -> float:
    """Host-side Solenthaler kernel W(r, h) of eq. 12 with c from eq. 13."""
    if r > h:
        return 0.0
    c = elastic_kernel_constant(h)
    return c * 2.0 * h / math.pi * (math.cos((r + h) * math.pi / (2.0 * h)) + 1.0)


def elastic_kernel_constant(h: float) -> float:
    """c of eq. 13, which makes eq. 12 integrate to 1 over the ball of radius h."""
    return math.pi / (8.0 * h**4 * (math.pi / 3.0 - 8.0 / math.pi + 16.0 / math.pi**2))


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    PI = scalar(math.pi)

    @wp.func
    def w_poly6(r2: scalar, h: scalar) -> scalar:
        # eq. 7, on the squared distance: smooth in r and zero with zero slope at r = h.
        if r2 >= h * h:
            return scalar(0.0)
        d = h * h - r2
        return scalar(315.0) / (scalar(64.0) * PI * wp.pow(h, scalar(9.0))) * d * d * d

    @wp.func
    def grad_w_elastic(r: vec3, h: scalar) -> vec3:
        # Gradient of eq. 12: -c cos(pi |r| / (2h)) r/|r|. It does not vanish as r -> 0,
        # so coincident particles (|r| = 0) get no force instead of a NaN direction.
        r2 = wp.dot(r, r)
        if r2 >= h * h or r2 <= scalar(1.0e-24) * h * h:
            return vec3()
        rl = wp.sqrt(r2)
        c = PI / (scalar(8.0) * h * h * h * h * (PI / scalar(3.0) - scalar(8.0) / PI + scalar(16.0) / (PI * PI)))
        return -c * wp.cos(PI * rl / (scalar(2.0) * h)) / rl * r

    @wp.func
    def grad_w_spiky(r: vec3, h: scalar) -> vec3:
        # -45/(pi h^6) (h - |r|)^2 r/|r| (Müller et al. 2003).
        r2 = wp.dot(r, r)
        if r2 >= h * h or r2 <= scalar(1.0e-24) * h * h:
            return vec3()
        rl = wp.sqrt(r2)
        d = h - rl
        return -scalar(45.0) / (PI * wp.pow(h, scalar(6.0))) * d * d / rl * r

    @wp.func
    def lap_w_viscosity(r2: scalar, h: scalar) -> scalar:
        # 45/(pi h^6) (h - |r|) (Müller et al. 2003).
        if r2 >= h * h:
            return scalar(0.0)
        return scalar(45.0) / (PI * wp.pow(h, scalar(6.0))) * (h - wp.sqrt(r2))

    # The same kernels with their h-dependent constant passed in, so a kernel computes
    # it once per particle instead of once per pair (pow and divisions are a large part
    # of a pair's cost on the CPU). Each ``*_coef`` is the exact expression the function
    # above evaluates, so ``f_c(r, h, f_coef(h))`` rounds exactly like ``f(r, h)``.
    @wp.func
    def poly6_coef(h: scalar) -> scalar:
        return scalar(315.0) / (scalar(64.0) * PI * wp.pow(h, scalar(9.0)))

    @wp.func
    def w_poly6_c(r2: scalar, h: scalar, coef: scalar) -> scalar:
        if r2 >= h * h:
            return scalar(0.0)
        d = h * h - r2
        return coef * d * d * d

    @wp.func
    def elastic_coef(h: scalar) -> scalar:
        return PI / (scalar(8.0) * h * h * h * h * (PI / scalar(3.0) - scalar(8.0) / PI + scalar(16.0) / (PI * PI)))

    @wp.func
    def grad_w_elastic_c(r: vec3, h: scalar, c: scalar) -> vec3:
        r2 = wp.dot(r, r)
        if r2 >= h * h or r2 <= scalar(1.0e-24) * h * h:
            return vec3()
        rl = wp.sqrt(r2)
        return -c * wp.cos(PI * rl / (scalar(2.0) * h)) / rl * r

    @wp.func
    def spiky_coef(h: scalar) -> scalar:
        return -scalar(45.0) / (PI * wp.pow(h, scalar(6.0)))

    @wp.func
    def viscosity_coef(h: scalar) -> scalar:
        return scalar(45.0) / (PI * wp.pow(h, scalar(6.0)))

    @wp.func
    def grad_w_spiky_c(r: vec3, h: scalar, coef: scalar) -> vec3:
        r2 = wp.dot(r, r)
        if r2 >= h * h or r2 <= scalar(1.0e-24) * h * h:
            return vec3()
        rl = wp.sqrt(r2)
        d = h - rl
        return coef * d * d / rl * r

    @wp.func
    def lap_w_viscosity_c(r2: scalar, h: scalar, coef: scalar) -> scalar:
        if r2 >= h * h:
            return scalar(0.0)
        return coef * (h - wp.sqrt(r2))

    return types.SimpleNamespace(
        w_poly6=w_poly6, grad_w_elastic=grad_w_elastic, grad_w_spiky=grad_w_spiky, lap_w_viscosity=lap_w_viscosity,
        poly6_coef=poly6_coef, w_poly6_c=w_poly6_c, elastic_coef=elastic_coef, grad_w_elastic_c=grad_w_elastic_c,
        spiky_coef=spiky_coef, grad_w_spiky_c=grad_w_spiky_c, viscosity_coef=viscosity_coef, lap_w_viscosity_c=lap_w_viscosity_c,
    )
