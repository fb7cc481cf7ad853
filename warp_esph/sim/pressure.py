"""SPH density, pressure and viscosity (paper §4 "for additional stability"; SPEC §6,
kernels of Müller et al. 2003).

    rho_i = sum_{j in N_i + {i}} m_j W_poly6(|x_i - x_j|, h)
    p_i   = k_p (rho_i - rho0_i)          (clamped at 0 unless the material says not)
    f_i   = -sum_j V_i V_j (p_i + p_j)/2 grad W_spiky(x_i - x_j)
            + sum_j 5 eta_ij V_i V_j ((u_j - u_i) . e_ij) e_ij lap W_visc(|x_i - x_j|)

with ``V = m / rho`` and ``e_ij`` the unit vector between the pair. The viscous force is
Müller's ``eta V_i V_j (u_j - u_i) lap W`` projected onto the line between the particles:
a central force, so it conserves angular momentum and leaves a rigid rotation alone (the
unprojected form stops a spinning body). The factor 5 (``d + 2``) keeps ``eta`` the shear
viscosity: for a divergence-free flow the projection averages to 1/5 of the full sum. ``rho0_i`` is each particle's SPH density in the initial
configuration, so a body starts pressure-free even at its surface, where the SPH sum is
short of neighbours. Lists are capped at 30 and so not symmetric: as for the elastic
force each directed pair applies half its force to both particles, equal and opposite,
which keeps linear momentum exact. Pressure acts between bodies too: it is what keeps
them apart.
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import smoothing


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    sm = smoothing.funcs(scalar)

    @wp.kernel
    def density(
        x: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        rho: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        xi = x[i]
        c6 = sm.poly6_coef(h)
        r = mass[i] * sm.w_poly6_c(scalar(0.0), h, c6)
        for k in range(count[i]):
            j = nbr[i, k]
            d = x[j] - xi
            r += mass[j] * sm.w_poly6_c(wp.dot(d, d), h, c6)
        rho[i] = r

    @wp.func
    def pressure(rho: scalar, rho0: scalar, k_p: scalar, clamp: int) -> scalar:
        p = k_p * (rho - rho0)
        if clamp != 0:
            p = wp.max(p, scalar(0.0))
        return p

    @wp.func
    def viscous_force(eta_VV: scalar, rij: vec3, r2: scalar, lap_w: scalar, vji: vec3) -> vec3:
        """The pair's viscous force on ``i`` (``rij = x_i - x_j``, ``vji = u_j - u_i``)."""
        if r2 <= scalar(1.0e-30):
            return vec3()
        return (scalar(5.0) * eta_VV * lap_w * wp.dot(vji, rij) / r2) * rij

    @wp.kernel
    def pressure_forces(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        pressure_stiffness: wp.array(dtype=scalar),
        viscosity: wp.array(dtype=scalar),
        clamp: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        f: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        mi = material[i]
        xi = x[i]
        vi = v[i]
        Vi = mass[i] / rho[i]
        pi = pressure(rho[i], rest_density[i], pressure_stiffness[mi], clamp[mi])
        c_spiky = sm.spiky_coef(h)
        c_visc = sm.viscosity_coef(h)
        fi = vec3()
        for k in range(count[i]):
            j = nbr[i, k]
            mj = material[j]
            pj = pressure(rho[j], rest_density[j], pressure_stiffness[mj], clamp[mj])
            VV = Vi * mass[j] / rho[j]
            rij = xi - x[j]
            pair = -VV * scalar(0.5) * (pi + pj) * sm.grad_w_spiky_c(rij, h, c_spiky)
            eta = scalar(0.5) * (viscosity[mi] + viscosity[mj])
            r2 = wp.dot(rij, rij)
            pair += viscous_force(eta * VV, rij, r2, sm.lap_w_viscosity_c(r2, h, c_visc), v[j] - vi)
            half = scalar(0.5) * pair
            wp.atomic_add(f, j, -half)
            fi += half
        wp.atomic_add(f, i, fi)

    return types.SimpleNamespace(density=density, pressure_forces=pressure_forces, pressure=pressure,
                                 viscous_force=viscous_force)
