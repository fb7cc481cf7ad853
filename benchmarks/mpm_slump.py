"""An independent reference for the Bingham slump: an explicit 3-D MLS-MPM in NVIDIA Warp.

    python -m benchmarks.mpm_slump --S 0.2 --res 16                # one slump, aspect 1, dx = H0/16
    python -m benchmarks.mpm_slump --S 0.2 0.3 --res 16 24 --json docs/mpm_slump.json
    python -m benchmarks.mpm_slump --column                        # the elastic column check
    python -m benchmarks.mpm_slump --near-yield-column --res 6 9   # the near-yield column, 6 and 9 cells across
    python -m benchmarks.mpm_slump --S 0.2 --res 16 --flow-rate 200   # the particle scene's flow rule
    python -m benchmarks.mpm_slump --S 0.2 --res 8 --flow-rate 200 --floor-shear-cap 1   # a floor gripping up to tau_y
    python -m benchmarks.mpm_slump --quick                         # CI-sized: column + squeeze, a few s
    python -m benchmarks.mpm_slump --table docs/mpm_slump.json     # the markdown table of docs/validation.md

Nothing here is shared with ``warp_esph``'s solver: only the measure ``centre_thickness``, the
1-D height ``slump_theory`` and the constants ``G``, ``RHO`` come from ``benchmarks.validation``.
It exists to answer one question of docs/physics.md ("no independent 3-D solution of this scene
is in the repository"): how deep does a continuum with this material sag in the slump scene?

**Method.** The moving least squares MPM (MLS-MPM, Hu et al. 2018), which is APIC transfer with
quadratic B-spline weights on a uniform grid of spacing ``dx``:

* P2G: each particle scatters mass ``m_p`` and momentum ``m_p v_p + (m_p C_p - dt V0 (4/dx^2)
  tau_p) (x_i - x_p)`` (``tau_p`` the total Kirchhoff stress, ``C_p`` the APIC affine velocity
  matrix, which is the particle's velocity gradient);
* grid: ``v_i = p_i / m_i + dt g``; nodes at ``y <= 0`` are the floor: sticky (all velocity
  set to zero, the slump's default: it glues, holding the material down as well as up, which a
  no-slip reference is by convention), or a contact that only pushes, slip (a downward ``v_y``
  set to zero, the column check) or Coulomb (``--floor-friction``: with it the tangential
  velocity loses at most friction x the normal one taken) or Tresca (``--floor-shear-cap K``:
  it grips up to a shear traction ``K tau_y``, ``tau_y = Y / sqrt(2)`` the material's shear yield
  stress, whatever the normal load: ``tresca_floor``), a node moving up being free in all three
  (before 2026-12-07 slip and Coulomb also took an upward ``v_y``: a floor that pulls); the domain's
  side and top walls are sticky (the material never reaches them: the run stops if it does);
* G2P: ``v_p = sum w v_i``, ``C_p = (4/dx^2) sum w v_i (x_i - x_p)^T``, ``x_p += dt v_p``,
  ``F_p <- (I + dt C_p) F_p``, then the return mapping below.

**Material.** The elastic part is Hencky (log strain): with ``F_e = U diag(s) V^T``,
``eps = log s`` and the Kirchhoff stress ``tau = U diag(2 mu eps + lam tr(eps)) U^T``, whose
small-strain moduli are ``mu``, ``lam``. Plasticity is rate-independent von Mises by return
mapping on the deviatoric Kirchhoff stress: if ``|dev tau|_F = 2 mu |dev eps| > Y`` the
deviatoric log strain is scaled back onto ``|dev tau|_F = Y`` (the volume part is kept, so the
plastic flow is isochoric and ``det F_e = det F``). ``Y`` is ``warp_esph``'s ``yield_stress``:
the Frobenius norm of the deviatoric stress, ``Y = sqrt(2/3) sigma_y``, ``sigma_y = S rho g H0``
the uniaxial yield stress. (The criterion is on Kirchhoff stress ``J sigma``; in the slump
``J`` stays within 0.93-1.01 on the axis, 0.75-1.15 at the floor's rim.) The yield strain is ``Y / (2 mu)``; the accumulated plastic strain
of a particle is the sum of ``|dev eps|`` removed by the return mappings (in those units in the
report). A Newtonian viscous stress ``2 eta D``, ``D = sym(C_p)`` (the APIC velocity gradient),
``eta`` = 2 Pa s as the particle scene's ``viscosity``, is added to the Cauchy stress (``J 2 eta D``
to the Kirchhoff one) so the pile comes to rest. The plastic flow is either rate-independent
(``flow_rate`` = 0, the default: the excess over yield removed in the step) or the particle
scene's own flow rule (``--flow-rate 200``: the excess of ``|dev eps|`` over ``Y / (2 mu)`` decays at
``flow_rate`` per second, integrated implicitly, a Bingham fluid of plastic viscosity
``mu / flow_rate`` = 49 Pa s in the slump; warp_esph's ``Material`` docstring states the rule).
Which one decides where the pile stops (docs/validation.md, "An independent reference: MPM").
``--ramp T`` grows gravity linearly from 0 over ``T`` s instead of switching it on at once.

**Scene.** As ``benchmarks.validation.slump``: a cylinder of height ``H0`` = 0.1 m and radius
``R0 = H0 / (2 aspect)`` standing on the floor ``y = 0``, ``rho`` = 1000, ``mu = 10 rho g H0``,
``lam = 1.5 mu``, gravity ``g`` = 9.81 switched on at ``t = 0`` on a stress-free body. The
particles fill the cylinder on a lattice of spacing ``dx / 2`` (2 per cell per axis, 8 per
cell, not jittered) aligned with the cells, each of volume ``(dx/2)^3`` and mass ``rho (dx/2)^3``.
``res`` is ``H0 / dx`` (cells over the height; at aspect 1 also cells across the diameter,
so particles across are ``2 res``).

**Time step.** ``dt = cfl dx / c`` with ``c = sqrt((lam + 2 mu) / rho)`` the P-wave speed and
``cfl`` = 0.3, and at most half the viscous limit ``rho dx^2 / (6 eta)`` (far above it here).
The particle speed is not checked against the step: in the slump it is bounded by the free-fall
speed sqrt(2 g H0) = 1.4 m/s, 0.07 dx per step at any ``res`` (dt is proportional to dx).

**Measures** (every 0.05 s): the kinetic energy of the particles, the top on the axis (the
highest particle within ``R0 / 2`` of it plus half a particle spacing), the material's thickness
on the axis ``centre_thickness(x, V0, det F, R0 / 2)`` and the largest radius (plus half a
spacing). At rest, as the suite's slump: over the last quarter of the run the top's rate (a
linear fit) below 0.1 % H0/s and the largest kinetic energy below 1e-8 M g H0. A run that is not
at rest at ``duration`` goes on in steps of a quarter of it, up to ``max_duration``.

**Checks** (closed form, ``tests/test_mpm_reference.py``): an elastic column on a slip floor,
laterally free, relaxed under gravity (mass-proportional damping on the grid velocities, which
does not move the equilibrium) shortens by ``rho g L^2 / (2 E)`` (``column``; 1.002 / 0.982 of it at
8 / 16 cells over its height); a block squeezed between two slip plates flows at the uniaxial
yield stress ``sqrt(3/2) Y`` (``squeeze``; volume-mean stress 0.96-0.99 of it at 6-12 cells: the
node rows at each plate hold the layer next to it in, so not all of the block flows); a stiff
block on a slope of gravity on the Tresca floor is held below its cap and slides at
``g sin theta - cap / (rho h)`` above it (1.03 x).

**Cost** (one core, float32): about 41 s per simulated second at ``res`` 16 (26k particles,
dt 3.2e-4 s), 200 s at 24 (87k), 12 s at 12; about 630 s at 32 (estimated). The near-yield
column's 36 periods (3.5 s) and its elastic twin: about 29 / 135 / 670 / 2200 s at 4 / 6 / 9 /
12 cells across (2.6k / 8.6k / 29k / 69k particles; measured with other jobs on the cores).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import sys
import time

import numpy as np
import warp as wp

from benchmarks import _cli
from benchmarks.validation import (G, RHO, bingham_uniaxial_stress, centre_thickness, pile_profile, plug_measures,
                                   slump_theory)

REST_RATE, REST_KINETIC = 0.1, 1.0e-8  # % H0/s, M g H0: the suite's rest bounds
FLOOR_PAD = wp.constant(3)  # grid nodes below y = 0 (node index FLOOR_PAD is at y = 0)


# --------------------------------------------------------------------------- kernels
@wp.func
def bspline_weights(fx: wp.vec3):
    """Quadratic B-spline weights of the three nodes base, base+1, base+2 on each axis: row i
    holds node i's weight per axis (``fx`` the position in cells from ``base``, in [0.5, 1.5))."""
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w0 = 0.5 * wp.cw_mul(a, a)
    w1 = wp.vec3(0.75) - wp.cw_mul(b, b)
    w2 = 0.5 * wp.cw_mul(c, c)
    return wp.matrix_from_rows(w0, w1, w2)


@wp.func
def hencky_kirchhoff(U: wp.mat33, eps: wp.vec3, mu: float, lam: float):
    """Kirchhoff stress of the Hencky model, U diag(2 mu eps + lam tr eps) U^T."""
    tr = eps[0] + eps[1] + eps[2]
    t = 2.0 * mu * eps + wp.vec3(lam * tr)
    return U * wp.diag(t) * wp.transpose(U)


@wp.func
def von_mises_return(eps: wp.vec3, mu: float, Y: float, relax: float):
    """Return mapping of the principal log strain onto |dev tau|_F <= Y, tau = 2 mu dev eps + ...:
    (eps after, |dev eps| removed). ``relax`` = dt flow_rate: 0 is rate-independent (the excess
    over yield removed at once); else the excess of |dev eps| over Y / (2 mu) decays at the rate
    flow_rate (implicit Euler), a Bingham (Perzyna) flow of plastic viscosity mu / flow_rate."""
    tr = eps[0] + eps[1] + eps[2]
    dev = eps - wp.vec3(tr / 3.0)
    n = wp.length(dev)
    if 2.0 * mu * n > Y:
        keep = Y / (2.0 * mu)
        if relax > 0.0:
            keep = (n + relax * keep) / (1.0 + relax)
        return dev * (keep / n) + wp.vec3(tr / 3.0), n - keep
    return eps, 0.0


@wp.func
def stencil_base(xp: wp.vec3, lo: wp.vec3, inv_dx: float):
    """The lowest node of a particle's 3x3x3 stencil and its position from that node, in cells."""
    X = (xp - lo) * inv_dx
    base = wp.vec3i(int(X[0] - 0.5), int(X[1] - 0.5), int(X[2] - 0.5))
    return base, X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))


@wp.kernel(module="unique")
def p2g(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
        tau: wp.array(dtype=wp.mat33), J: wp.array(dtype=float), mp: float, vp0: float, eta: float,
        dt: float, dx: float, lo: wp.vec3, gm: wp.array3d(dtype=float), gmv: wp.array3d(dtype=wp.vec3)):
    p = wp.tid()
    inv_dx = 1.0 / dx
    base, fx = stencil_base(x[p], lo, inv_dx)
    bi = base[0]
    bj = base[1]
    bk = base[2]
    W = bspline_weights(fx)
    Cp = C[p]
    viscous = (eta * J[p]) * (Cp + wp.transpose(Cp))  # Kirchhoff form of 2 eta D
    affine = (-dt * vp0 * 4.0 * inv_dx * inv_dx) * (tau[p] + viscous) + mp * Cp
    mv = mp * v[p]
    for i in range(3):
        for j in range(3):
            for k in range(3):
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                w = W[i, 0] * W[j, 1] * W[k, 2]
                wp.atomic_add(gmv, bi + i, bj + j, bk + k, w * (mv + affine * dpos))
                wp.atomic_add(gm, bi + i, bj + j, bk + k, w * mp)


@wp.func
def tangential_slowed(vel: wp.vec3, loss: float):
    """The tangential (x, z) part of ``vel`` with its speed less ``loss``, down to 0 and never
    reversed: a floor's friction impulse on a node, per unit of its mass."""
    tangential = wp.vec3(vel[0], 0.0, vel[2])
    speed = wp.length(tangential)
    if speed > 0.0:
        tangential = tangential * (wp.max(0.0, speed - loss) / speed)
    return tangential


@wp.func
def tresca_speed_loss(shear_cap: float, dx: float, dt: float, column_mass: float, full_mass: float):
    """The tangential speed a Tresca floor takes from each contact node of a node column in one
    step: the impulse shear_cap x (the floor area the column's material covers) x dt, shared
    as one speed loss by the column's contact nodes of total mass ``column_mass``. The covered
    area is dx^2 x min(1, column_mass / full_mass) (``full_mass`` the floor nodes' mass of a
    column the material fills), so the loss is shear_cap dx^2 dt / max(column_mass, full_mass)."""
    return shear_cap * dx * dx * dt / wp.max(column_mass, full_mass)


@wp.kernel(module="unique")
def tresca_floor(gm: wp.array3d(dtype=float), gmv: wp.array3d(dtype=wp.vec3), shear_cap: float, dx: float,
                 dt: float, full_mass: float):
    """A floor that grips up to a shear traction ``shear_cap`` whatever the normal load (Tresca
    friction), on the node columns (i, k) after ``grid_update``'s slip floor: its contact nodes
    (y <= 0, with mass, not moving up) lose the same tangential speed (``tresca_speed_loss``).

    The node's floor area. The grid is 3-D (not axisymmetric): the floor y = 0 is tiled by one
    dx x dx square per node column, and the floor nodes of a column with mass are two rows,
    y = 0 and y = -dx (a particle's quadratic stencil reaches 1.5 dx, so the rows below carry
    the lowest half cell's particles), which share that square. A column at a body's edge holds
    material over only part of it: reading dx^2 there gives a block of 4 x 4 cells the grip of
    the 7 x 7 columns its stencils reach (3 x its base). So a column's area is dx^2 x its contact
    mass over ``full_floor_mass`` (at most dx^2; the horizontal B-spline weights sum to 1, so a
    body's columns add up to its base area), and a node's is that share of it by mass: dx^2
    m_node / max(column mass, full mass), an impulse cap of shear_cap x it x dt."""
    i, k = wp.tid()
    column_mass = float(0.0)
    for j in range(FLOOR_PAD + 1):
        if gm[i, j, k] > 0.0 and gmv[i, j, k][1] <= 0.0:
            column_mass += gm[i, j, k]
    if column_mass <= 0.0:
        return
    loss = tresca_speed_loss(shear_cap, dx, dt, column_mass, full_mass)
    for j in range(FLOOR_PAD + 1):
        vel = gmv[i, j, k]
        if gm[i, j, k] > 0.0 and vel[1] <= 0.0:
            gmv[i, j, k] = tangential_slowed(vel, loss)


@wp.kernel(module="unique")
def grid_update(gm: wp.array3d(dtype=float), gmv: wp.array3d(dtype=wp.vec3), gravity: wp.vec3, dt: float,
                damping: float, floor_friction: float, wall: int):
    i, j, k = wp.tid()
    m = gm[i, j, k]
    if m <= 0.0:
        return
    vel = gmv[i, j, k] / m + dt * gravity
    vel = vel * damping
    ni = gm.shape[0]
    nj = gm.shape[1]
    nk = gm.shape[2]
    if j <= FLOOR_PAD:
        if floor_friction < 0.0:
            vel = wp.vec3(0.0)
        elif vel[1] < 0.0:
            # Slip / Coulomb is a contact: it only pushes. It takes an inward normal velocity and,
            # with it, at most friction x that much of the tangential one (the impulse ratio is
            # the force ratio); a node moving away is left free. Taking the outward velocity too
            # lets the floor pull: at rest the node row at y = 0 then pushes 1.25 x the pile's
            # weight and the row below pulls 0.25 x it (docs/physics.md).
            vel = tangential_slowed(vel, -floor_friction * vel[1])
    if i < wall or i >= ni - wall or k < wall or k >= nk - wall or j >= nj - wall:
        vel = wp.vec3(0.0)
    gmv[i, j, k] = vel


@wp.kernel(module="unique")
def plate_update(gm: wp.array3d(dtype=float), gmv: wp.array3d(dtype=wp.vec3), j_plate: int, v_plate: float,
                 force: wp.array(dtype=float), dt: float):
    """A slip plate: nodes at or above j_plate move down at v_plate (x, z free); the y-momentum
    it adds per step over dt is the plate's force on the material."""
    i, j, k = wp.tid()
    m = gm[i, j, k]
    if m <= 0.0 or j < j_plate:
        return
    vel = gmv[i, j, k]
    wp.atomic_add(force, 0, m * (-v_plate - vel[1]) / dt)
    gmv[i, j, k] = wp.vec3(vel[0], -v_plate, vel[2])


@wp.kernel(module="unique")
def g2p(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
        F: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33), J: wp.array(dtype=float),
        plastic: wp.array(dtype=float), ratio: wp.array(dtype=float), gmv: wp.array3d(dtype=wp.vec3),
        mu: float, lam: float, Y: float, relax: float, dt: float, dx: float, lo: wp.vec3):
    p = wp.tid()
    inv_dx = 1.0 / dx
    base, fx = stencil_base(x[p], lo, inv_dx)
    bi = base[0]
    bj = base[1]
    bk = base[2]
    W = bspline_weights(fx)
    nv = wp.vec3(0.0)
    nC = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                w = W[i, 0] * W[j, 1] * W[k, 2]
                gv = gmv[bi + i, bj + j, bk + k]
                nv += w * gv
                nC += (4.0 * inv_dx * inv_dx * w) * wp.outer(gv, dpos)
    v[p] = nv
    C[p] = nC
    x[p] = x[p] + dt * nv
    Ft = (wp.identity(n=3, dtype=float) + dt * nC) * F[p]
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(Ft, U, s, V)
    eps = wp.vec3(wp.log(wp.max(s[0], 1.0e-6)), wp.log(wp.max(s[1], 1.0e-6)), wp.log(wp.max(s[2], 1.0e-6)))
    e, dg = von_mises_return(eps, mu, Y, relax)
    plastic[p] = plastic[p] + dg
    if dg > 0.0:
        Ft = U * wp.diag(wp.vec3(wp.exp(e[0]), wp.exp(e[1]), wp.exp(e[2]))) * wp.transpose(V)
    F[p] = Ft
    tr = e[0] + e[1] + e[2]
    J[p] = wp.exp(tr)
    tau[p] = hencky_kirchhoff(U, e, mu, lam)
    ratio[p] = 2.0 * mu * wp.length(e - wp.vec3(tr / 3.0)) / Y


# --------------------------------------------------------------------------- simulator
class MPM:
    """A minimal MLS-MPM of one material on a box grid [lo, lo + n dx] with the floor at y = 0."""

    def __init__(self, points, spacing, dx, mu, lam, Y, eta, half_width, height, floor_friction=-1.0,
                 cfl=0.3, damping=0.0, flow_rate=0.0, floor_shear_cap=None, device="cpu"):
        # floor_friction < 0: sticky (no-slip) floor nodes; 0: slip; > 0: Coulomb friction.
        # floor_shear_cap (Pa, >= 0; with the slip floor only): the Tresca floor, ``tresca_floor``.
        if floor_shear_cap is not None:
            if not floor_shear_cap >= 0.0 or not math.isfinite(floor_shear_cap):
                raise ValueError(f"floor_shear_cap = {floor_shear_cap!r} is not allowed: a shear traction in Pa, "
                                 "finite and >= 0")
            if floor_friction != 0.0:
                raise ValueError(f"floor_shear_cap = {floor_shear_cap!r} is not allowed with floor_friction = "
                                 f"{floor_friction!r}: the Tresca floor is the slip floor (0) that grips up to the cap")
        self.device = device
        self.dx, self.mu, self.lam, self.Y, self.eta = float(dx), float(mu), float(lam), float(Y), float(eta)
        self.vp0 = float(spacing) ** 3
        self.mp = RHO * self.vp0
        n_side = int(math.ceil(half_width / dx)) + 4
        n_up = int(math.ceil(height / dx)) + 4
        self.lo = wp.vec3(-n_side * dx, -FLOOR_PAD * dx, -n_side * dx)
        self.shape = (2 * n_side, n_up + FLOOR_PAD, 2 * n_side)
        self.half_width_grid = (n_side - 3) * dx  # beyond this the wall nodes act
        self.top_grid = (n_up - 3) * dx
        c = math.sqrt((lam + 2.0 * mu) / RHO)
        dt = cfl * dx / c
        dt_visc = RHO * dx * dx / (6.0 * eta) if eta > 0 else float("inf")
        self.dt = min(dt, 0.5 * dt_visc)
        self.relax = float(flow_rate) * self.dt  # 0: rate-independent plasticity
        self.damping_rate = float(damping)
        self.damping = math.exp(-damping * self.dt)
        self.floor_friction = float(floor_friction)
        self.floor_shear_cap = None if floor_shear_cap is None else float(floor_shear_cap)
        self.full_floor_mass = full_floor_mass(spacing, dx)
        n = len(points)
        self.n = n
        z3 = np.zeros((n, 3), np.float32)
        eye = np.tile(np.eye(3, dtype=np.float32), (n, 1, 1))
        self.x0 = np.asarray(points, np.float64)
        self.x = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
        self.v = wp.array(z3, dtype=wp.vec3, device=device)
        self.C = wp.zeros(n, dtype=wp.mat33, device=device)
        self.F = wp.array(eye, dtype=wp.mat33, device=device)
        self.tau = wp.zeros(n, dtype=wp.mat33, device=device)
        self.J = wp.array(np.ones(n, np.float32), dtype=float, device=device)
        self.plastic = wp.zeros(n, dtype=float, device=device)
        self.ratio = wp.zeros(n, dtype=float, device=device)
        self.gm = wp.zeros(self.shape, dtype=float, device=device)
        self.gmv = wp.zeros(self.shape, dtype=wp.vec3, device=device)
        self.gravity = wp.vec3(0.0, -G, 0.0)
        self.ramp = 0.0  # > 0: gravity grows linearly from 0 to g over this time (s)
        self.plate = None  # (j_plate, v_plate) of a squeezing plate
        self.plate_force = wp.zeros(1, dtype=float, device=device)
        self.t = 0.0

    def step(self):
        d = self.device
        self.gm.zero_()
        self.gmv.zero_()
        wp.launch(p2g, self.n, inputs=[self.x, self.v, self.C, self.tau, self.J, self.mp, self.vp0, self.eta, self.dt,
                                       self.dx, self.lo, self.gm, self.gmv], device=d)
        g = self.gravity
        if self.ramp > 0.0:
            g = g * min(1.0, (self.t + self.dt) / self.ramp)
        wp.launch(grid_update, self.shape, inputs=[self.gm, self.gmv, g, self.dt, self.damping,
                                                   self.floor_friction, 3], device=d)
        if self.floor_shear_cap is not None:
            wp.launch(tresca_floor, (self.shape[0], self.shape[2]), inputs=[self.gm, self.gmv, self.floor_shear_cap,
                                                                          self.dx, self.dt, self.full_floor_mass], device=d)
        if self.plate is not None:
            self.plate_force.zero_()
            wp.launch(plate_update, self.shape, inputs=[self.gm, self.gmv, self.plate[0], self.plate[1],
                                                        self.plate_force, self.dt], device=d)
        wp.launch(g2p, self.n, inputs=[self.x, self.v, self.C, self.F, self.tau, self.J, self.plastic, self.ratio,
                                       self.gmv, self.mu, self.lam, self.Y, self.relax, self.dt, self.dx, self.lo], device=d)
        self.t += self.dt

    def kinetic(self):
        v = self.v.numpy().astype(np.float64)
        return 0.5 * self.mp * float((v * v).sum())


def full_floor_mass(spacing, dx):
    """The mass on the floor nodes (y <= 0) of one node column under material at rest density
    filling y > 0 on this MPM's lattice (particles of side ``spacing`` from spacing / 2 up):
    rho dx^2 spacing sum_n [N(y_n / dx) + N(y_n / dx + 1)], y_n = (n + 1/2) spacing, N the
    quadratic B-spline (the horizontal weights sum to 1 over a column's share of the floor,
    dx^2 / spacing^2 particles). At spacing dx / 2: rho dx^3 (33 / 64), rows y = dx/4, 3dx/4
    and 5dx/4 weighing 0.6875 + 0.03125, 0.28125 and 0.03125. The Tresca floor reads a column's
    covered area as dx^2 x its floor mass over this, at most dx^2."""
    def bspline(u):
        u = abs(u)
        return 0.75 - u * u if u < 0.5 else (0.5 * (1.5 - u) ** 2 if u < 1.5 else 0.0)

    total, n = 0.0, 0
    while (n + 0.5) * spacing < 1.5 * dx:
        u = (n + 0.5) * spacing / dx
        total += bspline(u) + bspline(u + 1.0)
        n += 1
    return RHO * dx * dx * spacing * total


def shear_cap_pa(floor_shear_cap, Y):
    """The Tresca floor's cap in Pa from ``floor_shear_cap`` in units of the shear yield stress
    ``Y / sqrt(2)`` (None: no Tresca floor); ``ValueError`` naming it unless finite and >= 0."""
    if floor_shear_cap is None:
        return None
    if not (isinstance(floor_shear_cap, (int, float)) and math.isfinite(floor_shear_cap) and floor_shear_cap >= 0.0):
        raise ValueError(f"floor_shear_cap = {floor_shear_cap!r} is not allowed: a multiple of the shear yield stress, "
                         "finite and >= 0 (or None: no Tresca floor)")
    return float(floor_shear_cap) * Y / math.sqrt(2.0)


def _lattice(nx, ny, nz, s, origin):
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    p = np.stack([i.ravel(), j.ravel(), k.ravel()], 1).astype(np.float64)
    return (p + 0.5) * s + np.asarray(origin, np.float64)


def material(S, H0=0.1, stiffness=10.0):
    """(mu, lam, Y) of the slump: mu = stiffness rho g H0, lam = 1.5 mu, Y = sqrt(2/3) S rho g H0."""
    mu = stiffness * RHO * G * H0
    return mu, 1.5 * mu, math.sqrt(2.0 / 3.0) * S * RHO * G * H0


# --------------------------------------------------------------------------- the slump
def slump(S, res=16, aspect=1.0, H0=0.1, duration=8.0, max_duration=16.0, eta=2.0, flow_rate=0.0, ramp=0.0, cfl=0.3, sample_dt=0.05,
          half_width=None, save=None, log=None, floor_friction=-1.0, floor_shear_cap=None):
    """The slump of ``benchmarks.validation.slump``'s cylinder in the MPM: a dict of measures.
    ``floor_shear_cap``: a Tresca floor gripping up to this multiple of the material's shear
    yield stress ``tau_y = Y / sqrt(2)`` (with ``floor_friction`` 0)."""
    R0 = H0 / (2.0 * aspect)
    dx = H0 / res
    s = 0.5 * dx
    nr = int(round(2 * R0 / s))
    ny = int(round(H0 / s))
    pts = _lattice(nr, ny, nr, s, (-R0, 0.0, -R0))
    pts = pts[np.hypot(pts[:, 0], pts[:, 2]) <= R0]
    mu, lam, Y = material(S, H0)
    if half_width is None:
        half_width = max(3.2 * R0, 0.16)
    cap_pa = shear_cap_pa(floor_shear_cap, Y)
    sim = MPM(pts, s, dx, mu, lam, Y, eta, half_width, H0 + 2 * dx, floor_friction=floor_friction, cfl=cfl,
              flow_rate=flow_rate, floor_shear_cap=cap_pa)
    sim.ramp = float(ramp)
    vol0 = np.full(len(pts), sim.vp0)
    mass = sim.mp * len(pts)
    every = max(1, int(round(sample_dt / sim.dt)))
    T, TOP, TH, KE, RAD = [], [], [], [], []

    def sample():
        x = sim.x.numpy().astype(np.float64)
        r = np.hypot(x[:, 0], x[:, 2])
        near = r < 0.5 * R0
        T.append(sim.t)
        TOP.append(float(x[near, 1].max() + 0.5 * s))
        TH.append(centre_thickness(x, vol0, sim.J.numpy().astype(np.float64), 0.5 * R0))
        KE.append(sim.kinetic())
        RAD.append(float(r.max() + 0.5 * s))
        if not np.isfinite(x).all():
            raise FloatingPointError("MPM blew up at t = %.3f" % sim.t)
        if RAD[-1] > sim.half_width_grid or x[:, 1].max() > sim.top_grid:
            raise RuntimeError("the material reached the grid's walls: widen half_width")

    def verdict():
        t, h, ke, th = map(np.asarray, (T, TOP, KE, TH))
        last = t >= t[-1] - 0.25 * t[-1]
        rate = -np.polyfit(t[last], h[last], 1)[0]
        rate_th = -np.polyfit(t[last], th[last], 1)[0]
        ke_last = float(ke[last].max()) / (mass * G * H0)
        return 100.0 * rate / H0, 100.0 * rate_th / H0, ke_last

    t0 = time.perf_counter()
    sample()
    target = duration
    while True:
        while sim.t < target - 0.5 * sim.dt:
            for _ in range(every):
                sim.step()
            sample()
            if log and len(T) % 20 == 0:
                print(f"  t={sim.t:.2f} top/H0={TOP[-1] / H0:.4f} th/H0={TH[-1] / H0:.4f} "
                      f"KE/MgH0={KE[-1] / (mass * G * H0):.2e} R/R0={RAD[-1] / R0:.3f} "
                      f"wall={time.perf_counter() - t0:.0f}s", file=log, flush=True)
        rate, rate_th, ke_last = verdict()
        at_rest = abs(rate) < REST_RATE and ke_last < REST_KINETIC
        if at_rest or target >= max_duration - 1e-9:
            break
        target = min(max_duration, target + 0.25 * duration)
    wall = time.perf_counter() - t0

    x = sim.x.numpy().astype(np.float64)
    J = sim.J.numpy().astype(np.float64)
    plastic = sim.plastic.numpy().astype(np.float64) / (Y / (2.0 * mu))  # in yield strains
    ratio = sim.ratio.numpy().astype(np.float64)
    x0 = sim.x0
    depth0 = H0 - x0[:, 1]
    bands, layers = pile_profile(x0, x, depth0, plastic, ratio, R0, s, H0)
    # The unyielded plug on the axis: the top run of layers where most particles never yielded.
    plug = 0.0
    for L in layers:
        if L["never_yielded_fraction"] >= 0.5:
            plug = L["depth0_over_H0"] + 0.5 * s / H0
        else:
            break
    rate, rate_th, ke_last = verdict()
    th = TH[-1] / H0
    theory = slump_theory(S)
    out = {
        "method": "MLS-MPM", "S": S, "aspect": aspect, "res_cells_per_H0": res, "dx": dx,
        "particles_across": int(round(2 * R0 / s)), "particles": int(len(pts)), "particles_per_cell": 8,
        "dt": sim.dt, "duration": sim.t, "steps": int(round(sim.t / sim.dt)), "eta": eta, "cfl": cfl,
        "flow_rate": flow_rate, "gravity_ramp_s": ramp,
        "floor": ("Tresca %g tau_y" % floor_shear_cap if floor_shear_cap is not None else
                  "sticky" if floor_friction < 0 else ("slip" if floor_friction == 0 else "Coulomb %g" % floor_friction)),
        **({"floor_shear_cap_Pa": cap_pa} if cap_pa is not None else {}),
        "plasticity": "Bingham (Perzyna)" if flow_rate > 0 else "rate-independent",
        "thickness_over_H0": th, "theory_h_over_H0": theory, "thickness_vs_theory_pct": 100.0 * (th / theory - 1.0),
        "top_on_axis_over_H0": TOP[-1] / H0, "top_vs_theory_pct": 100.0 * (TOP[-1] / H0 / theory - 1.0),
        "top_per_quarter_R0_band_over_H0": bands,
        "radius_over_R0": RAD[-1] / R0,
        "top_rate_pct_H0_per_s": rate, "thickness_rate_pct_H0_per_s": rate_th,
        "kinetic_last_quarter_over_MgH0": ke_last, "at_rest": bool(abs(rate) < REST_RATE and ke_last < REST_KINETIC),
        "J_range": [float(J.min()), float(J.max())],
        "plug_depth_over_H0": plug, "plug_1d_depth_over_H0": S,
        # The particle suite's own plug criterion on the same region (docs/validation.md, the
        # plug), so the continuum is read as the particle piles are; the region is
        # S H0 / 2 = S res / 2 cells thick (the particle suite reads it only from one support
        # radius up, the MPM at any grid).
        **plug_measures(depth0, np.hypot(x0[:, 0], x0[:, 2]), ratio, plastic, S, H0, R0),
        "plug_region_cells": 0.5 * S * res,
        "fraction_at_yield": float((ratio >= 0.99).mean()),
        "axis_layers": layers,
        "history": {"t": [round(v, 4) for v in T], "thickness_over_H0": [round(v / H0, 5) for v in TH],
                    "top_over_H0": [round(v / H0, 5) for v in TOP],
                    "ke_over_MgH0": [float("%.3e" % (v / (mass * G * H0))) for v in KE]},
        "wall_s": wall, "threads": 1, "device": "cpu",
    }
    if save:
        np.savez_compressed(save, x0=x0, x=x, J=J, plastic=plastic, ratio=ratio)
    return out


# --------------------------------------------------------------------------- closed-form checks
def column(res=16, L=0.1, width=0.04, stiffness=10.0, duration=0.6, damping=60.0, cfl=0.3):
    """An elastic column (square section ``width``, height ``L``) on a slip floor, laterally free,
    relaxed under gravity with mass-proportional grid damping: its top's drop against the
    closed form ``rho g L^2 / (2 E)`` of uniaxial stress (each particle's drop against
    ``u(y0) = rho g (L y0 - y0^2 / 2) / E``). No yield (Y huge), no viscosity."""
    dx = L / res
    s = 0.5 * dx
    nw = int(round(width / s))
    ny = int(round(L / s))
    pts = _lattice(nw, ny, nw, s, (-0.5 * width, 0.0, -0.5 * width))
    mu = stiffness * RHO * G * L
    lam = 1.5 * mu
    E = mu * (3 * lam + 2 * mu) / (lam + mu)
    sim = MPM(pts, s, dx, mu, lam, 1e30, 0.0, width, L + 2 * dx, floor_friction=0.0, cfl=cfl, damping=damping)
    t0 = time.perf_counter()
    while sim.t < duration:
        sim.step()
    wall = time.perf_counter() - t0
    x = sim.x.numpy().astype(np.float64)
    y0 = sim.x0[:, 1]
    u = y0 - x[:, 1]
    u_th = RHO * G * (L * y0 - 0.5 * y0 * y0) / E
    top = y0 > y0.max() - 1e-9
    drop_top, drop_top_th = float(u[top].mean()), float(u_th[top].mean())
    return {"case": "column", "res_cells_per_L": res, "particles": len(pts), "E": E,
            "top_drop": drop_top, "top_drop_theory": drop_top_th,
            "top_drop_over_theory": drop_top / drop_top_th,
            "shortening_theory_rhogL2_2E": RHO * G * L * L / (2 * E),
            "mean_drop_over_theory": float(u.mean() / u_th.mean()),
            "kinetic": sim.kinetic(), "duration": sim.t, "wall_s": wall}


def near_yield_column(res=6, width=0.06, aspect=5, E=1.5e5, nu=0.3, yield_depth=0.8, flow_rate=200.0, periods=36.0,
                      ramp=4.0, elastic_periods=8.0, cfl=0.3, floor_shear_cap=None):
    """The particle suite's near-yield column (``benchmarks.validation.near_yield_column``) in
    the continuum: a square column ``width`` across (``res`` cells, ``2 res`` particles) and
    ``aspect`` times as tall on a slip floor, laterally free, ``E``, ``nu``, its uniaxial yield
    stress the weight above ``yield_depth`` L (``Y = sqrt(2/3) rho g yield_depth L``), the
    particle scene's flow rule (``flow_rate``), gravity ramped over ``ramp`` axial periods and
    the same dynamic relaxation (grid damping 1.4 omega, omega the fixed-free axial mode's),
    run ``periods`` axial periods. The plastic shortening (the top's drop less that of the
    same column with the yield off, run ``elastic_periods``) against the 1-D analysis
    ``benchmarks.validation.near_yield_column_theory``, whose layers spread freely; the
    depth of the highest yielded particle (the front); the top's rate over the last tenth and
    its lateral offset (a tilt: the column on its yielded base is unstable to leaning, which
    grows from round-off some time after the base has come to rest, docs/validation.md).
    ``floor_shear_cap``: the Tresca floor instead, gripping up to this multiple of the shear yield
    stress ``Y / sqrt(2)`` (the same cap in Pa under the elastic twin)."""
    L = aspect * width
    dx = width / res
    s = 0.5 * dx
    nw, ny = int(round(width / s)), int(round(L / s))
    pts = _lattice(nw, ny, nw, s, (-0.5 * width, 0.0, -0.5 * width))
    mu, lam = E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    omega = 0.5 * math.pi * math.sqrt(E / RHO) / L
    y0 = pts[:, 1]
    top = y0 > y0.max() - 1e-9
    t0 = time.perf_counter()

    Y_column = math.sqrt(2.0 / 3.0) * RHO * G * yield_depth * L
    cap_pa = shear_cap_pa(floor_shear_cap, Y_column)

    def relax(Y, n_periods):
        sim = MPM(pts, s, dx, mu, lam, Y, 0.0, 1.6 * width, L + 2.0 * dx, floor_friction=0.0, cfl=cfl,
                  damping=1.4 * omega, flow_rate=flow_rate, floor_shear_cap=cap_pa)
        sim.ramp = ramp * 2.0 * math.pi / omega
        end = n_periods * 2.0 * math.pi / omega
        hist = []
        while sim.t < end:
            sim.step()
            if len(hist) == 0 or sim.t >= hist[-1][0] + 0.01 * end:
                x = sim.x.numpy()
                hist.append((sim.t, float(y0[top].mean() - x[top, 1].mean())))
        return sim, np.array(hist)

    elastic, _ = relax(1.0e30, elastic_periods)
    x_el = elastic.x.numpy().astype(np.float64)
    drop_elastic = float(y0[top].mean() - x_el[top, 1].mean())
    sim, hist = relax(Y_column, periods)
    x = sim.x.numpy().astype(np.float64)
    drop = float(y0[top].mean() - x[top, 1].mean())
    last = hist[hist[:, 0] > 0.9 * hist[-1, 0]]
    plastic_theory = ((1.0 - yield_depth) + yield_depth * math.log(yield_depth)) * L
    yielded = (L - y0[sim.plastic.numpy() > 1e-6]) / L
    return {"case": "near_yield_column", "res_cells_across": res, "width": width, "particles": len(pts), "E": E, "nu": nu,
            "yield_depth": yield_depth, "flow_rate": flow_rate, "periods": periods, "duration": sim.t,
            "floor": "slip" if cap_pa is None else "Tresca %g tau_y" % floor_shear_cap,
            "elastic_drop": drop_elastic, "elastic_over_theory": drop_elastic / (RHO * G * L * L / (2.0 * E)),
            "plastic_over_theory": (drop - drop_elastic) / plastic_theory,
            "top_rate_pct_of_plastic_per_s": 100.0 * float(np.polyfit(last[:, 0], last[:, 1], 1)[0]) / plastic_theory,
            "front_depth": float(yielded.min()) if len(yielded) else 1.0,
            "top_offset_over_width": float(np.hypot(x[top, 0].mean(), x[top, 2].mean())) / width,
            "kinetic_over_MgL": sim.kinetic() / (sim.mp * len(pts) * G * L), "wall_s": time.perf_counter() - t0}


def squeeze(res=8, L=0.05, S=0.2, H0=0.1, strain=0.06, rate=0.25, cfl=0.3, flow_rate=0.0, eta=0.0, samples=0):
    """A cube of side ``L`` of the slump's material (``S``), no gravity, on a slip floor, squeezed by
    a slip plate (grid nodes at or above it move down at ``rate L`` /s) by ``strain``: the plate's
    force over the current area (the cube's, volume kept by the isochoric flow) against the
    uniaxial yield stress ``sqrt(3/2) Y`` = sigma_y. The median over the second half of the squeeze
    (the force jumps for a step when the plate moves onto the next row of nodes).

    ``flow_rate`` and ``eta``: the slump's Bingham flow rule and viscous stress (0: rate-independent,
    inviscid). ``samples`` > 0 adds ``history``: that many rows of the log strain of the cube's
    height, the volume-mean vertical stress over the steps since the last row and the Bingham
    stress at the current strain rate (``benchmarks.validation.bingham_uniaxial_stress``), both
    in sigma_y: the reference for ``benchmarks.validation.uniaxial_flow`` (docs/physics.md, "The
    flow stress in sustained uniaxial flow")."""
    dx = L / res
    s = 0.5 * dx
    n = int(round(L / s))
    pts = _lattice(n, n, n, s, (-0.5 * L, 0.0, -0.5 * L))
    mu, lam, Y = material(S, H0)
    sim = MPM(pts, s, dx, mu, lam, Y, eta, 1.5 * L, L + 2 * dx, floor_friction=0.0, cfl=cfl, flow_rate=flow_rate)
    sim.gravity = wp.vec3(0.0, 0.0, 0.0)
    # The plate: its nodes are those at or above the cube's top node row; it moves with them.
    v_plate = rate * L
    T = strain / rate
    forces, hs = [], []  # the plate's force, the mean vertical compressive stress
    sigma_y = math.sqrt(1.5) * Y
    history, last = [], 0
    every = max(1, int(round(T / sim.dt / samples))) if samples > 0 else 0
    t0 = time.perf_counter()
    y_plate = L
    while sim.t < T:
        jp = int(math.floor(y_plate / dx + 1e-9)) + FLOOR_PAD + 1  # first node row strictly above the plate's row
        sim.plate = (jp, v_plate)
        sim.step()
        y_plate -= v_plate * sim.dt
        forces.append(float(sim.plate_force.numpy()[0]))
        hs.append(float(-(sim.tau.numpy()[:, 1, 1].sum()) / sim.J.numpy().sum()))
        if every and len(hs) % every == 0:
            h = float(sim.x.numpy()[:, 1].max()) + 0.5 * s
            history.append({"log_strain": -math.log(h / L), "stress_over_sigma_y": float(np.mean(hs[last:])) / sigma_y,
                            "bingham_over_sigma_y": bingham_uniaxial_stress(S, v_plate / h, H0, flow_rate=flow_rate)
                            / sigma_y if flow_rate > 0 else 1.0})
            last = len(hs)
    wall = time.perf_counter() - t0
    x = sim.x.numpy().astype(np.float64)
    h = x[:, 1].max() + 0.5 * s  # the cube's current height
    k = len(forces) // 2
    f = -float(np.median(forces[-k:]))
    area = L ** 3 / h
    # The vertical stress averaged over the current volume, sum V0 tau_yy / sum V0 J: by
    # equilibrium (the mean stress theorem) the load over the area, whatever its distribution.
    out = {"case": "squeeze", "res_cells_per_L": res, "particles": len(pts), "strain": 1.0 - h / L,
           "mean_stress_over_sigma_y": float(np.mean(hs[-k:])) / sigma_y,
           "plate_stress_over_sigma_y": f / area / sigma_y, "fraction_at_yield": float((sim.ratio.numpy() >= 0.99).mean()),
           "flow_rate": flow_rate, "eta": eta, "wall_s": wall}
    if samples > 0:
        out["history"] = history
    return out


#: The particle solver's slump (docs/validation.md, variational force, particle floor, 8 s; by
#: thickness against the 1-D height, %) at 12 and 16 particles across the diameter.
PARTICLE_SOLVER_PCT = {0.1: (1.0, -0.3), 0.2: (-15.6, -14.5), 0.3: (-4.0, -10.1), 0.5: (3.9, 0.3)}


def table(rows):
    """The markdown table of docs/validation.md's "An independent reference: MPM" from slump rows."""
    head = ("| S | aspect | plasticity | dx | particles | t (s) | MPM thickness/H0 | vs 1-D | top on axis/H0 | "
            "R/R0 | top rate (% H0/s) | KE (M g H0) | at rest | 1-D h/H0 | particle solver 12 / 16 across | wall (s) |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in sorted(rows, key=lambda r: (r["aspect"], r["S"], r["flow_rate"] == 0, r.get("gravity_ramp_s", 0),
                                         r.get("floor", "sticky") != "sticky", r.get("floor", "sticky"),
                                         r["res_cells_per_H0"])):
        ps = PARTICLE_SOLVER_PCT.get(r["S"]) if r["aspect"] == 1.0 else None
        plast = "Bingham, flow rate %g /s" % r["flow_rate"] if r["flow_rate"] > 0 else "rate-independent"
        if r.get("gravity_ramp_s", 0) > 0:
            plast += ", g ramped over %g s" % r["gravity_ramp_s"]
        if r.get("floor", "sticky") != "sticky":
            plast += ", %s floor" % r["floor"]
        lines.append(
            f"| {r['S']} | {r['aspect']:g} | {plast} | H0/{r['res_cells_per_H0']} | {r['particles']} | "
            f"{r['duration']:.1f} | {r['thickness_over_H0']:.4f} | {r['thickness_vs_theory_pct']:+.1f} % | "
            f"{r['top_on_axis_over_H0']:.4f} | {r['radius_over_R0']:.2f} | {r['top_rate_pct_H0_per_s']:.3f} | "
            f"{r['kinetic_last_quarter_over_MgH0']:.1e} | {'yes' if r['at_rest'] else 'no'} | "
            f"{r['theory_h_over_H0']:.4f} | {'%+.1f / %+.1f %%' % ps if ps else '–'} | {r['wall_s']:.0f} |")
    return "\n".join(lines)


#: The fields of a slump row that ``table`` reads.
TABLE_FIELDS = ("S", "aspect", "flow_rate", "res_cells_per_H0", "particles", "duration", "thickness_over_H0",
                "thickness_vs_theory_pct", "top_on_axis_over_H0", "radius_over_R0", "top_rate_pct_H0_per_s",
                "kinetic_last_quarter_over_MgH0", "at_rest", "theory_h_over_H0", "wall_s")

PROG = "python -m benchmarks.mpm_slump"


def table_rows(data, name: str = "--table", path: str = "?") -> list:
    """The rows of a results JSON (a list, or an object with ``slumps``) that ``table`` can read:
    ``ValueError`` naming the file and the row otherwise."""
    where = f"{name} = {path!r} is not allowed"
    if isinstance(data, dict):
        if not isinstance(data.get("slumps"), list):
            raise ValueError(f"{where}: a JSON object must have 'slumps', a list of rows")
        data = data["slumps"]
    for i, r in enumerate(data):
        if not isinstance(r, dict):
            raise ValueError(f"{where}: row {i} is {type(r).__name__}, not an object")
        if r.get("method") == "MLS-MPM":
            missing = [k for k in TABLE_FIELDS if k not in r]
            if missing:
                raise ValueError(f"{where}: row {i} (an MLS-MPM row) has no {', '.join(repr(k) for k in missing)}")
            bad = [k for k in TABLE_FIELDS if k != "at_rest" and (isinstance(r[k], bool) or not isinstance(r[k], (int, float)))]
            if bad:
                raise ValueError(f"{where}: row {i} (an MLS-MPM row) has {bad[0]} = {r[bad[0]]!r}, not a number")
    if not any(r.get("method") == "MLS-MPM" for r in data):
        raise ValueError(f"{where}: it holds no slump row (one with \"method\": \"MLS-MPM\"), so no table")
    return data


def _save_prefix(text, name):
    """A path prefix of the .npz files: its folder exists and is writable."""
    folder = pathlib.Path(str(text) + "_").parent
    if not str(text).strip() or not folder.is_dir():
        raise _cli.refuse(name, text, f"must be a path prefix in a folder that exists ('{folder}' is not one)")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise _cli.refuse(name, text, f"its folder '{folder}' is not writable")
    return text


def main(argv=None):
    ap = _cli.Parser(prog=PROG, description=__doc__.split("\n")[0])
    ap.add_argument("--S", type=_cli.positive_float, nargs="*", default=None)
    ap.add_argument("--res", type=_cli.positive_int, nargs="*", default=None)
    ap.add_argument("--aspect", type=_cli.positive_float, default=None)
    ap.add_argument("--duration", type=_cli.positive_float, default=None)
    ap.add_argument("--max-duration", type=_cli.positive_float, default=None)
    ap.add_argument("--flow-rate", type=_cli.nonnegative_float, default=None,
                    help="0: rate-independent plasticity; else the Bingham relaxation rate (1/s)")
    ap.add_argument("--ramp", type=_cli.nonnegative_float, default=None, help="gravity ramped from 0 over this time (s); 0: at once")
    ap.add_argument("--floor-friction", type=_cli.finite_float, default=None,
                    help="the slump's floor: < 0 sticky (no-slip, the default), 0 slip, > 0 Coulomb friction "
                         "(slip and Coulomb only push)")
    ap.add_argument("--floor-shear-cap", type=_cli.nonnegative_float, default=None,
                    help="the slump's floor: Tresca, gripping up to this multiple of the material's shear yield "
                         "stress tau_y = S rho g H0 / sqrt(3) whatever the normal load, and only pushing")
    ap.add_argument("--column", action="store_true")
    ap.add_argument("--squeeze", action="store_true")
    ap.add_argument("--near-yield-column", action="store_true",
                    help="the suite's near-yield column in the continuum, --res cells across (default 6)")
    ap.add_argument("--quick", action="store_true", help="the closed-form checks at CI size")
    ap.add_argument("--json", type=_cli.output_file, help="append the results to this JSON list")
    ap.add_argument("--save", type=_cli.Check(_save_prefix), help="save the final particles of each slump (npz) to this prefix")
    ap.add_argument("--table", type=_cli.json_file, help="print the markdown table of the slump rows in this JSON and exit")
    args = ap.parse_args(argv)
    # The slump's options without --S values ran nothing, said nothing and exited 0.
    given = [f"--{k.replace('_', '-')}" for k in ("res", "aspect", "duration", "max_duration", "flow_rate", "ramp",
                                                  "floor_friction", "floor_shear_cap", "save")
             if getattr(args, k) not in (None, -1.0)]
    if args.near_yield_column and not args.S:
        given = [g for g in given if g not in ("--res", "--floor-shear-cap")]
    if given and not args.S:
        also = (" (--res and --floor-shear-cap also set the --near-yield-column runs)"
                if given[0] in ("--res", "--floor-shear-cap") else "")
        ap.error(f"{given[0]} is not allowed without --S: it sets the slump runs, and --S gives their yield stresses{also}")
    for k in ("S", "res"):
        if getattr(args, k) == []:
            ap.error(f"--{k} is not allowed without values")
    args.S = args.S or []
    if not (args.S or args.quick or args.column or args.squeeze or args.near_yield_column or args.table):
        ap.error("nothing to run: give --S values, --quick, --column, --squeeze, --near-yield-column or --table")
    column_res = args.res or [6]  # the near-yield column's cells across (the slump's default is 16 over H0)
    # Any --floor-friction given is refused beside the cap, the sticky -1 too (its default once
    # let an explicit -1 pass and run the Tresca floor instead).
    if args.floor_shear_cap is not None and args.floor_friction is not None:
        ap.error(f"--floor-friction = {args.floor_friction:g} is not allowed with --floor-shear-cap: the Tresca floor's "
                 "grip is its shear cap alone")
    defaults = {"res": [16], "aspect": 1.0, "duration": 8.0, "max_duration": 16.0, "flow_rate": 0.0, "ramp": 0.0,
                "floor_friction": -1.0}
    for k, v in defaults.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    if args.max_duration < args.duration:
        ap.error(f"--max-duration = {args.max_duration:g} is not allowed: below --duration = {args.duration:g}")
    if args.table:
        rows = table_rows(_cli.load_json(args.table, "--table"), "--table", args.table)
        print(table([r for r in rows if r.get("method") == "MLS-MPM"]))
        return rows
    for res in args.res if args.S else ():
        if round(2 * res / args.aspect) < 1:
            ap.error(f"--aspect = {args.aspect:g} is not allowed with --res {res}: the cylinder would have no particle "
                     "across (2 res / aspect must be above 0.5)")
    if args.json and pathlib.Path(args.json).exists():
        old = _cli.load_json(args.json, "--json")
        if not isinstance(old, list):
            ap.error(f"--json = {args.json!r} is not allowed: the results are appended to a JSON list, and it holds an object")
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    rows = []
    if args.quick or args.column:
        r = column(res=8 if args.quick else 16)
        print(json.dumps(r), flush=True)
        rows.append(r)
    if args.quick or args.squeeze:
        r = squeeze(res=6 if args.quick else 8)
        print(json.dumps(r), flush=True)
        rows.append(r)
    for res in column_res if args.near_yield_column else ():
        r = near_yield_column(res=res, floor_shear_cap=args.floor_shear_cap)
        print(json.dumps(r), flush=True)
        rows.append(r)
    if rows and args.json:  # the checks' rows were printed, never written
        p = pathlib.Path(args.json)
        old = json.loads(p.read_text()) if p.exists() else []
        p.write_text(json.dumps(old + rows, indent=1) + "\n")
    for S in args.S:
        for res in args.res:
            tresca = args.floor_shear_cap is not None
            floor = f"t{args.floor_shear_cap:g}" if tresca else f"m{args.floor_friction:g}"
            save = f"{args.save}_S{S}_a{args.aspect}_r{res}_f{args.flow_rate:g}_g{args.ramp:g}_{floor}.npz" if args.save else None
            r = slump(S, res, aspect=args.aspect, duration=args.duration, max_duration=args.max_duration,
                      flow_rate=args.flow_rate, ramp=args.ramp, save=save, log=sys.stdout,
                      floor_friction=0.0 if tresca else args.floor_friction, floor_shear_cap=args.floor_shear_cap)
            print(json.dumps({k: v for k, v in r.items() if k not in ("history", "axis_layers")}), flush=True)
            rows.append(r)
            if args.json:
                p = pathlib.Path(args.json)
                old = json.loads(p.read_text()) if p.exists() else []
                p.write_text(json.dumps(old + [r], indent=1) + "\n")
    return rows


if __name__ == "__main__":
    _cli.run(main, PROG)
