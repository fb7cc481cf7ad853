"""SPH density, pressure and viscosity (paper §4 "for additional stability"; docs/method.md §6,
kernels of Müller et al. 2003).

    rho_i = sum_{j in N_i + {i}} m_j W_poly6(|x_i - x_j|, h)
    p_i   = k_p (rho_i - rho0_i)          (clamped at 0 unless the material says not)
    f_i   = -sum_j V_i V_j (p_i + p_j)/2 grad W_spiky(x_i - x_j)
            + sum_j 5 eta_ij V_i V_j ((u_j - u_i) . e_ij) e_ij lap W_visc(|x_i - x_j|)

with ``V = m / rho`` and ``e_ij`` the unit vector between the pair. That ``f_i`` is the
paper's pressure (``pressure_force = "spiky"``); the ``energy`` force is minus the gradient
of ``sum_k m_k e_k(rho_k)``, ``de/drho = p / rho^2``, and ``energy_spiky`` the same of a
density summed with the spiky kernel instead of poly6 (``density_weight``; docs/method.md §6),
which only its pressure reads (``State.pressure_density``): ``rho`` and the volumes ``V``
stay the poly6 ones for every material. ``isotropic`` reads ``energy_spiky``'s pressure but
applies it as each particle's stress ``-p_i I`` through its neighbourhood's moment matrix
(``isotropic_pressure_forces``), not along the pairs. The viscous force is
Müller's ``eta V_i V_j (u_j - u_i) lap W`` projected onto the line between the particles:
a central force, so it conserves angular momentum and leaves a rigid rotation alone (the
unprojected form stops a spinning body). The factor 5 (``d + 2``) keeps ``eta`` the shear
viscosity: for a divergence-free flow the projection averages to 1/5 of the full sum. ``rho0_i`` is each particle's pressure density in the initial
configuration, so a body starts pressure-free even at its surface, where the SPH sum is
short of neighbours. Rows may reach ``h sigma_max(F_i)`` and may be capped, and so are not symmetric: as for the elastic
force each directed pair applies half its force to both particles, equal and opposite,
which keeps linear momentum exact. Pressure acts between bodies too: it is what keeps
them apart. ``Material.pair_repulsion`` adds a short-range pair potential below ``h / 4``
(``pair_repulsion_force``), off by default.
"""

import functools
import types

import warp as wp

from .._types import type_set
from . import deformation, guards, materials, smoothing
from .replay import outside_recording_tape, recording_tape


#: The conditioning ``q = det A / (tr A / 3)^3`` of the isotropic pressure's moments from
#: which its map is ``A^-1`` itself (``isotropic_pressure_map``). Lattices, their surfaces
#: and lattices jittered by 0.2 dx have ``q`` >= 0.47 (0.08 at 0.3 dx); neighbours near a
#: plane (``lmin / lmax`` ~ 3.4 q) or a line lower it towards 0.
ISOTROPIC_Q_FULL = 0.2
#: The share of ``tr A / 3`` added to the diagonal of the isotropic pressure's moments at
#: ``q = 0``: a compressed one-layer sheet keeps 0.94 of ``p V`` in its plane, and a particle
#: of it moved off the plane is pushed with at most 5 ``p V / dx`` (at 0.2 dx, where the map
#: is ``A^-1``; ``A^-1`` alone gave ``p V / d``, 1000 ``p V / dx`` at 0.001 dx, and no
#: pressure at all on the plane: ``tests/test_isotropic_pressure.py``).
ISOTROPIC_REGULARISATION = 0.1
#: Index into the solver's guard counters (``Solver.guard_counts()["pressure_regularised"]``):
#: particle-steps whose isotropic pressure map was regularised (``q < ISOTROPIC_Q_FULL``), where
#: the virial of the particle's own forces is short of ``p V I`` (a flat layer, a line, a pair).
COUNT_PRESSURE_REGULARISED = 5
#: The range ``r0 / h`` of the pair repulsion (``Material.pair_repulsion``,
#: ``pair_repulsion_force``): a quarter of the support, half a spacing at ``h = 2 dx``, well
#: inside a lattice's nearest neighbour (``dx``), so a body at rest does not feel it.
PAIR_REPULSION_RANGE = 0.25


@functools.cache
def funcs(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    sm = smoothing.funcs(scalar)
    Materials = materials.struct(scalar)

    @wp.func
    def pressure(rho: scalar, rho0: scalar, k_p: scalar, clamp: int) -> scalar:
        """The equation of state ``p = k_p (rho - rho0)``, clamped at 0 when ``clamp``.
        The clamp holds the density's excess, not the product: the same value for
        ``k_p >= 0``, and at ``k_p = 0`` (where a fit may start it) the adjoint keeps the
        slope ``dp/dk_p = rho - rho0`` of a compressed particle, where ``max(k_p (rho - rho0),
        0)`` tied at 0 and gave none."""
        d = rho - rho0
        if clamp != 0:
            d = wp.max(d, scalar(0.0))
        return k_p * d

    @wp.func
    def pressure_pair_force(VV: scalar, p_i: scalar, p_j: scalar, rij: vec3, rl: scalar, h: scalar, c_spiky: scalar) -> vec3:
        """``-V_i V_j (p_i + p_j)/2 grad W_spiky(x_i - x_j)`` on ``i`` (``VV = V_i V_j``,
        ``rij = x_i - x_j``, ``rl = |rij|`` in (0, h)): Müller et al.'s force
        (``pressure_force = "spiky"``, docs/method.md §6)."""
        return -VV * scalar(0.5) * (p_i + p_j) * sm.grad_w_spiky_at(rij, rl, h, c_spiky)

    @wp.func
    def energy_pair_weight(VV: scalar, p_i: scalar, p_j: scalar, rho_i: scalar, rho_j: scalar) -> scalar:
        """``m_i m_j (p_i / rho_i^2 + p_j / rho_j^2)``, the pair's factor of the energy forms'
        pressure force (``energy_pressure_pair_force``, ``energy_spiky_pair_force``: the
        gradient of ``sum_k m_k e_k(rho_k)`` with ``de/drho = p / rho^2``), from ``VV = m_i m_j /
        (rho_i rho_j)``: ``p_i rho_j / rho_i + p_j rho_i / rho_j`` over one division (one per
        pair, not two)."""
        return VV * (p_i * rho_j * rho_j + p_j * rho_i * rho_i) / (rho_i * rho_j)

    @wp.func
    def energy_pressure_pair_force(
        VV: scalar, p_i: scalar, p_j: scalar, rho_i: scalar, rho_j: scalar, rij: vec3, r2: scalar, h: scalar, c6: scalar
    ) -> vec3:
        """``-m_i m_j (p_i / rho_i^2 + p_j / rho_j^2) grad W_poly6(x_i - x_j)`` on ``i``, the
        pair's share of ``-grad sum_k m_k e_k(rho_k)`` with ``de/drho = p / rho^2`` and ``rho``
        the poly6 sum (``pressure_force = "energy"``, docs/method.md §6). ``VV = V_i V_j =
        m_i m_j / (rho_i rho_j)``, ``rij = x_i - x_j``, ``r2 = |rij|^2 < h^2``; ``grad W_poly6(r)
        = -6 c6 (h^2 - |r|^2)^2 r`` (``smoothing.grad_w_poly6_at``)."""
        return -energy_pair_weight(VV, p_i, p_j, rho_i, rho_j) * sm.grad_w_poly6_at(rij, r2, h * h, c6)

    @wp.func
    def density_weight(r2: scalar, h: scalar, c6: scalar, c_ws: scalar, form: int) -> scalar:
        """The kernel a particle's pressure density sums (docs/method.md §6): poly6 (eq. 7) for
        the ``energy`` and ``spiky`` forces (and for the SPH density of every material), the
        spiky kernel for ``energy_spiky`` and ``isotropic`` (``form`` 2, 3), whose slope does
        not vanish as two particles meet."""
        if form >= 2:
            return sm.w_spiky_c(r2, h, c_ws)
        return sm.w_poly6_c(r2, h, c6)

    @wp.func
    def density_weight_gradient(d: vec3, r2: scalar, h: scalar, c6: scalar, c_spiky: scalar, form: int) -> vec3:
        """``d W / d d`` of ``density_weight`` at ``d`` (``r2 = |d|^2 < h^2``): poly6's
        ``grad_w_poly6_at``; for ``form`` 2 and 3 the spiky kernel's ``grad_w_spiky_at`` (0 at
        ``d = 0``, where the direction is undefined)."""
        g = vec3()
        if form >= 2:
            if r2 > scalar(1.0e-24) * h * h:
                g = sm.grad_w_spiky_at(d, wp.sqrt(r2), h, c_spiky)
        else:
            g = sm.grad_w_poly6_at(d, r2, h * h, c6)
        return g

    @wp.func
    def energy_spiky_pair_force(
        VV: scalar, p_i: scalar, p_j: scalar, rho_i: scalar, rho_j: scalar, rij: vec3, rl: scalar, h: scalar,
        c_spiky: scalar
    ) -> vec3:
        """``-m_i m_j (p_i / rho_i^2 + p_j / rho_j^2) grad W_spiky(x_i - x_j)`` on ``i``, the
        pair's share of ``-grad sum_k m_k e_k(rho_k)`` with ``de/drho = p / rho^2`` and ``rho``
        the spiky-kernel density (``pressure_force = "energy_spiky"``, docs/method.md §6):
        the ``energy`` force's pressure energy on a density whose kernel slope ``-45/(pi h^6)
        (h - |r|)^2`` stays finite at ``r = 0``, so the push between two particles grows until
        they meet. ``VV = m_i m_j / (rho_i rho_j)``, ``rij = x_i - x_j``, ``rl = |rij|`` in
        (0, h)."""
        return -energy_pair_weight(VV, p_i, p_j, rho_i, rho_j) * sm.grad_w_spiky_at(rij, rl, h, c_spiky)

    @wp.func
    def viscous_pair_force(eta_VV: scalar, rij: vec3, r2: scalar, lap_w: scalar, vji: vec3) -> vec3:
        """``5 eta V_i V_j ((u_j - u_i) . e_ij) e_ij lap W`` on ``i`` (``eta_VV = eta_ij V_i V_j``,
        ``rij = x_i - x_j``, ``r2 = |rij|^2``, ``vji = u_j - u_i``)."""
        if r2 <= scalar(1.0e-30):
            return vec3()
        return (scalar(5.0) * eta_VV * lap_w * wp.dot(vji, rij) / r2) * rij

    @wp.func
    def pair_repulsion_force(s: scalar, rij: vec3, rl: scalar, h: scalar) -> vec3:
        """``-dU/d x_i = 3 s / r0 (1 - r/r0)^2 e_ij`` on ``i`` of the pair potential ``U = s (1 -
        r/r0)^3`` below ``r0 = PAIR_REPULSION_RANGE h`` (0 beyond), ``s =
        pair_repulsion_strength``, ``rij = x_i - x_j``, ``rl = |rij|``: the pressure forces'
        push between two particles stays finite as they meet (``energy_spiky``'s) or fades
        (``energy``'s), so a landing's impact can drive a pair together; this one's work
        ``s`` at contact, with ``s`` a pressure energy, keeps such a pair apart. Zero with
        zero slope at ``r0``, so it is continuous and differentiable in the positions; zero
        at ``r = 0``, where its direction is undefined."""
        r0 = scalar(PAIR_REPULSION_RANGE) * h
        f = vec3()
        if rl < r0 and rl > scalar(1.0e-12) * h:
            e = scalar(1.0) - rl / r0
            f = (scalar(3.0) * s * e * e / (r0 * rl)) * rij
        return f

    @wp.func
    def pair_repulsion_strength(k_i: scalar, c_i: scalar, k_j: scalar, c_j: scalar, m_i: scalar, m_j: scalar) -> scalar:
        """The pair potential's energy scale ``s = (c_i k_p,i + c_j k_p,j)/2 sqrt(m_i m_j)``
        (``pair_repulsion_force``; ``c = Material.pair_repulsion``): ``k_p m`` is a pressure
        energy (``p / rho`` times a mass), so ``c`` is a number, the same at every spacing and
        stiffness; the mean keeps a pair of materials' forces equal and opposite. 0 (the
        force off) unless a material of the pair has ``c > 0``."""
        s = scalar(0.0)
        if c_i > scalar(0.0) or c_j > scalar(0.0):
            s = scalar(0.5) * (c_i * k_i + c_j * k_j) * wp.sqrt(m_i * m_j)
        return s

    @wp.func
    def pair_repulsion_of(i: int, j: int, mass: wp.array(dtype=scalar), material: wp.array(dtype=wp.int32),
                          mat: Materials) -> scalar:
        """``pair_repulsion_strength`` of the particles ``i, j``."""
        mi = material[i]
        mj = material[j]
        return pair_repulsion_strength(mat.pressure_stiffness[mi], mat.pair_repulsion[mi], mat.pressure_stiffness[mj],
                                       mat.pair_repulsion[mj], mass[i], mass[j])

    @wp.func
    def sph_pair_force(
        VV: scalar, VVp: scalar, p_i: scalar, p_j: scalar, rho_i: scalar, rho_j: scalar, form: int, eta: scalar,
        rij: vec3, vji: vec3, h: scalar, c6: scalar, c_spiky: scalar, c_visc: scalar, s_rep: scalar
    ) -> vec3:
        """Pressure (``form``: 0 ``energy_pressure_pair_force``, 1 ``pressure_pair_force``, 2
        ``energy_spiky_pair_force``; 3, ``isotropic``, none: its pressure is
        ``isotropic_pressure_forces``') plus viscous force of the pair on ``i``, the kernels
        sharing one ``|rij|``. ``VV = V_i V_j`` with the SPH (poly6) density's volumes ``m /
        rho`` (viscosity, the spiky force); ``rho_i, rho_j`` are the pressure densities and
        ``VVp = m_i m_j / (rho_i rho_j)`` (the energy forces): the same as the SPH density but
        for an ``energy_spiky`` particle (``State.pressure_density``). ``s_rep > 0`` adds the pair
        repulsion (``pair_repulsion_force``; 0: the option off, not evaluated)."""
        r2 = wp.dot(rij, rij)
        f = vec3()
        if r2 < h * h:
            rl = wp.sqrt(r2)
            if form == 0:
                f = energy_pressure_pair_force(VVp, p_i, p_j, rho_i, rho_j, rij, r2, h, c6)
            elif r2 > scalar(1.0e-24) * h * h:
                if form == 1:
                    f = pressure_pair_force(VV, p_i, p_j, rij, rl, h, c_spiky)
                elif form == 2:
                    f = energy_spiky_pair_force(VVp, p_i, p_j, rho_i, rho_j, rij, rl, h, c_spiky)
            f += viscous_pair_force(eta * VV, rij, r2, sm.lap_w_viscosity_at(rl, h, c_visc), vji)
            if s_rep > scalar(0.0):
                f += pair_repulsion_force(s_rep, rij, rl, h)
        return f

    @wp.func
    def pair_virial_share(f: vec3, rij: vec3) -> T.mat33:
        """One end's share of a pair force's virial, ``-f (x) rij / 2`` (``f`` the force on ``i``,
        ``rij = x_i - x_j``): summed over a particle's pairs and divided by its volume, the
        Cauchy stress the pair forces carry through it (tension positive; a push between the
        two is compressive along their line)."""
        return scalar(-0.5) * wp.outer(f, rij)

    @wp.func
    def pair_viscosity(eta_i: scalar, eta_j: scalar) -> scalar:
        """The viscous force's ``eta_ij`` of a pair (docs/method.md §6): the mean of the two
        particles' viscosities, so that a pair of materials acts on each as one coefficient and
        the pair's forces stay equal and opposite."""
        return scalar(0.5) * (eta_i + eta_j)

    @wp.func
    def particle_terms(i: int, mass: wp.array(dtype=scalar), rho: wp.array(dtype=scalar), rho_p: wp.array(dtype=scalar),
                       rest_density: wp.array(dtype=scalar), material: wp.array(dtype=wp.int32), mat: Materials):
        """Particle ``i``'s terms of its SPH pairs: its volume ``V_i = m_i / rho_i`` of the SPH
        density, ``Vp_i = m_i / rho_p_i`` of the pressure density and its ``pressure`` (of the
        pressure density)."""
        mi = material[i]
        return (mass[i] / rho[i], mass[i] / rho_p[i],
                pressure(rho_p[i], rest_density[i], mat.pressure_stiffness[mi], mat.clamp_pressure[mi]))

    @wp.func
    def partner_terms(j: int, Vi: scalar, Vpi: scalar, visc_i: scalar, mass: wp.array(dtype=scalar),
                      rho: wp.array(dtype=scalar), rho_p: wp.array(dtype=scalar), rest_density: wp.array(dtype=scalar),
                      material: wp.array(dtype=wp.int32), mat: Materials):
        """A pair's terms from its partner ``j`` (``sph_pair_force``'s arguments): ``j``'s
        ``pressure`` ``p_j``, ``VV = V_i V_j`` of the SPH density, ``VVp = m_i m_j / (rho_p_i
        rho_p_j)`` of the pressure density (``Vi``, ``Vpi``: ``i``'s, ``particle_terms``) and
        the pair's viscosity ``eta = (eta_i + eta_j) / 2``."""
        mj = material[j]
        pj = pressure(rho_p[j], rest_density[j], mat.pressure_stiffness[mj], mat.clamp_pressure[mj])
        VV = Vi * mass[j] / rho[j]
        VVp = Vpi * mass[j] / rho_p[j]
        eta = pair_viscosity(visc_i, mat.viscosity[mj])
        return pj, VV, VVp, eta

    # The images' geometry only (no fit weight in it): any weight's namespace serves.
    floor_image = deformation.funcs(scalar, "poly6").floor_image
    floor_image_jacobian = deformation.funcs(scalar, "poly6").floor_image_jacobian
    mirrored_motion = deformation.funcs(scalar, "poly6").mirrored_motion
    image_row_length = deformation.funcs(scalar, "poly6").image_row_length
    image_row_particle = deformation.image_row_particle

    @wp.func
    def image_density(i: int, x: wp.array(dtype=vec3), mass: wp.array(dtype=scalar), nbr: wp.array2d(dtype=wp.int32),
                      n: int, h: scalar, c6: scalar, c_ws: scalar, form: int, gn: vec3, goff: scalar, gmin: scalar) -> scalar:
        """The rough floor's part of particle ``i``'s density: ``sum_k m_k W(|x_i - g_k|)``,
        ``W`` the kernel of ``form`` (``density_weight``: poly6 for the SPH density, the
        pressure density's for ``energy_spiky``), over the mirror images ``g_k`` of ``i`` and of its row (``deformation.floor_image``;
        an image is at least as far as its particle, so the row holds every one within
        ``h``). A particle near the floor then has an interior density, as on a floor of
        particles (docs/physics.md, "The ground collider's thin-layer strength")."""
        xi = x[i]
        r = scalar(0.0)
        for k in range(image_row_length(xi, n, h, gn, goff)):
            j = image_row_particle(i, k, n, nbr)
            d = xi - floor_image(x[j], gn, goff, gmin)
            r += mass[j] * density_weight(wp.dot(d, d), h, c6, c_ws, form)
        return r

    @wp.func
    def image_pressure_forces(i: int, x: wp.array(dtype=vec3), v: wp.array(dtype=vec3), nbr: wp.array2d(dtype=wp.int32),
                              n: int, Vi: scalar, Vpi: scalar, pi: scalar, rho_pi: scalar, vi: vec3,
                              mass: wp.array(dtype=scalar), rho: wp.array(dtype=scalar), rho_p: wp.array(dtype=scalar),
                              rest_density: wp.array(dtype=scalar), material: wp.array(dtype=wp.int32), mat: Materials,
                              h: scalar, c6: scalar, c_spiky: scalar, c_visc: scalar, gn: vec3, goff: scalar,
                              gmin: scalar, images: int) -> vec3:
        """The SPH force on ``i`` (velocity ``vi``, volume ``Vi = m_i / rho_i`` of the SPH
        density, ``Vpi = m_i / rho_pi`` of the pressure density ``rho_pi``, pressure ``pi``)
        of the floor images in the densities (``image_density``), the floor taking the
        reaction: for each neighbour ``k`` (and ``i`` itself), the pair ``(i, g_k)`` in
        ``rho_i`` and the pair ``(k, g_i)`` in ``rho_k``, the second through ``d g_i / d x_i``
        (``floor_image_jacobian``: the mirror ``R = I - 2 n n^T`` while ``i`` is above
        ``min_depth``, the tangential projector ``I - n n^T`` where its image stays put); and
        the viscous force of the images on ``i``: at rest (``images`` 1, relative velocity
        ``-v_i``) or moving with their particles (``images`` 2, ``J(x_k) v_k - v_i``,
        ``deformation.mirrored_motion``, which a body sliding on a frictionless imaged ground
        does not feel). As for the particle pairs (``sph_pair_force``) the pressure and the
        energy forms read the pressure density ``rho_p`` and the volumes the SPH density
        ``rho``. For the energy forms it is minus the gradient of the pressure energy."""
        xi = x[i]
        mi = material[i]
        form = mat.pressure_force[mi]
        gi = floor_image(xi, gn, goff, gmin)
        J = floor_image_jacobian(xi, gn, goff, gmin)
        fi = vec3()
        zero = scalar(0.0)
        for k in range(image_row_length(xi, n, h, gn, goff)):
            j = image_row_particle(i, k, n, nbr)
            pj, VV, VVp, eta = partner_terms(j, Vi, Vpi, mat.viscosity[mi], mass, rho, rho_p, rest_density, material,
                                             mat)
            # No pair repulsion with the images (s_rep 0): they are no particles a landing drives
            # together, and a particle's own image, 2 y below it, would push it off the floor.
            vg = vec3()
            if images == 2:
                vg = mirrored_motion(x[j], v[j], gn, goff, gmin)
            fi += sph_pair_force(VV, VVp, pi, zero, rho_pi, rho_p[j], form, eta, xi - floor_image(x[j], gn, goff, gmin),
                                 vg - vi, h, c6, c_spiky, c_visc, zero)
            fi += J * sph_pair_force(VV, VVp, zero, pj, rho_pi, rho_p[j], form, zero, gi - x[j], vec3(), h, c6, c_spiky,
                                     c_visc, zero)
        return fi

    @wp.func
    def isotropic_weight(r2: scalar, h: scalar) -> scalar:
        """The weight ``(1 - |r|/h)^2 h / |r|`` of the isotropic pressure's moments and pairs
        (``isotropic_pressure_forces``): the spiky kernel's gradient over ``|r|`` without its
        constant, which cancels in ``w A^-1``; ``w r`` stays finite as two particles meet, so
        the push between them does not vanish there (a poly6 weight's ``w r`` does)."""
        w = scalar(0.0)
        if r2 < h * h and r2 > scalar(1.0e-24) * h * h:
            rl = wp.sqrt(r2)
            e = scalar(1.0) - rl / h
            w = e * e * h / rl
        return w

    @wp.func
    def isotropic_moments(i: int, x: wp.array(dtype=vec3), nbr: wp.array2d(dtype=wp.int32), n: int,
                          h: scalar) -> mat33:
        """``A_i = sum_j w_ij x_ij x_ij^T`` over every neighbour (any body: the pressure acts
        between bodies), ``x_ij = x_j - x_i``, ``w = isotropic_weight``; in a function of its own
        so that its inverse does not see a loop accumulator (docs/method.md, Warp pitfall 1)."""
        xi = x[i]
        A = mat33()
        for k in range(n):
            d = x[nbr[i, k]] - xi
            A += isotropic_weight(wp.dot(d, d), h) * wp.outer(d, d)
        return A

    # The isotropic pressure's moments' conditioning (no neighbour: no map, nothing regularised).
    isotropic_conditioning = guards.guard_funcs(scalar).isotropic_conditioning

    @wp.func
    def isotropic_regularised(A: mat33) -> int:
        """1 where the isotropic pressure map of the moments ``A`` is regularised
        (``isotropic_conditioning`` below ``ISOTROPIC_Q_FULL``, ``isotropic_regularisation``
        above 0), else 0: what ``COUNT_PRESSURE_REGULARISED`` counts."""
        r = int(0)
        if isotropic_conditioning(A) < scalar(ISOTROPIC_Q_FULL):
            r = 1
        return r

    @wp.func
    def isotropic_regularisation(q: scalar) -> scalar:
        """The share ``e`` of ``tr A / 3`` added to the moments' diagonal
        (``isotropic_pressure_map``) at the conditioning ``q = det A / (tr A / 3)^3`` (1 for an
        isotropic ``A``, 0 for neighbours on a plane or a line): 0 from ``ISOTROPIC_Q_FULL``
        (the map is ``A^-1`` itself there), ``ISOTROPIC_REGULARISATION`` at 0, a smoothstep
        between, so that the force stays continuous and differentiable in the positions."""
        t = wp.clamp(q / scalar(ISOTROPIC_Q_FULL), scalar(0.0), scalar(1.0))
        st, dst = sm.smoothstep(t)
        return scalar(ISOTROPIC_REGULARISATION) * (scalar(1.0) - st)

    @wp.func
    def isotropic_pressure_map(p: scalar, V: scalar, A: mat33) -> mat33:
        """``M = -p V (A + e (tr A / 3) I)^-1``, ``e = isotropic_regularisation``: where ``A``
        is well conditioned (``e = 0``) the variational force's map ``V P F^T A^-1``
        (``forces.py``) of the stress ``-p I`` on the current volume ``V``, so that ``sum_j
        x_ij (x) (-w M x_ij) = p V I`` exactly. Where the neighbours lie near a plane or a
        line, ``A^-1`` would push a particle a distance ``d`` off the plane with ``p V / d``
        (the virial's normal part kept at ``p V`` by ever shorter arms); the added diagonal
        bounds that and keeps the pressure within the plane or along the line (a lone pair
        repels), and ``A M^T`` stays symmetric (no torque). 0 for a particle alone. Also at
        ``p = 0``: the adjoint keeps the slope in ``p`` there (``k_p = 0``, where a fit may
        start it, and a body at rest), which a branch on ``p`` cut."""
        M = mat33()
        tr = A[0, 0] + A[1, 1] + A[2, 2]
        if tr > scalar(0.0):
            a = tr / scalar(3.0)
            e = isotropic_regularisation(isotropic_conditioning(A))
            M = (-p * V) * wp.inverse(A + (e * a) * wp.identity(n=3, dtype=scalar))
        return M

    @wp.func
    def isotropic_pair_force(M: mat33, d: vec3, h: scalar) -> vec3:
        """``g = w M d`` of particle ``i``'s pressure on the pair at ``d = x_j - x_i``: taken
        from ``j``, added to ``i`` (equal and opposite)."""
        return isotropic_weight(wp.dot(d, d), h) * (M * d)

    return types.SimpleNamespace(
        image_density=image_density, image_pressure_forces=image_pressure_forces, floor_image=floor_image,
        particle_terms=particle_terms, partner_terms=partner_terms,
        floor_image_jacobian=floor_image_jacobian,
        pressure=pressure, pressure_pair_force=pressure_pair_force,
        energy_pressure_pair_force=energy_pressure_pair_force, viscous_pair_force=viscous_pair_force,
        density_weight=density_weight, energy_spiky_pair_force=energy_spiky_pair_force,
        density_weight_gradient=density_weight_gradient,
        sph_pair_force=sph_pair_force, pair_repulsion_force=pair_repulsion_force,
        pair_repulsion_strength=pair_repulsion_strength, pair_repulsion_of=pair_repulsion_of,
        pair_viscosity=pair_viscosity, energy_pair_weight=energy_pair_weight,
        pair_virial_share=pair_virial_share,
        isotropic_weight=isotropic_weight, isotropic_moments=isotropic_moments,
        isotropic_pressure_map=isotropic_pressure_map, isotropic_pair_force=isotropic_pair_force,
        isotropic_regularisation=isotropic_regularisation, isotropic_conditioning=isotropic_conditioning,
        isotropic_regularised=isotropic_regularised,
    )


@functools.cache
def kernels(scalar) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3 = T.vec3
    sm = smoothing.funcs(scalar)
    fn = funcs(scalar)
    image_slots = deformation.funcs(scalar, "poly6").image_slots
    image_row_particle = deformation.image_row_particle
    scatter_partner_adjoint = deformation.funcs(scalar, "poly6").scatter_partner_adjoint
    Materials = materials.struct(scalar)

    @wp.kernel(module="unique")
    def density(
        x: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        of_pressure: int,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        rho: wp.array(dtype=scalar),
    ):
        """The SPH density (poly6, every material), or with ``of_pressure`` each material's
        pressure density (``density_weight``: the spiky sum for ``energy_spiky``); with
        ``images`` the floor images' part (``image_density``) in the same kernel."""
        i = wp.tid()
        xi = x[i]
        c6 = sm.poly6_coef(h)
        c_ws = sm.w_spiky_coef(h)
        form = int(0)
        if of_pressure != 0:
            form = mat.pressure_force[material[i]]
        r = mass[i] * fn.density_weight(scalar(0.0), h, c6, c_ws, form)
        for k in range(count[i]):
            j = nbr[i, k]
            d = x[j] - xi
            r += mass[j] * fn.density_weight(wp.dot(d, d), h, c6, c_ws, form)
        if images != 0:
            r += fn.image_density(i, x, mass, nbr, count[i], h, c6, c_ws, form, gn, goff, gmin)
        rho[i] = r

    @wp.kernel(module="unique")
    def pressure_forces(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        pairs: int,
        f: wp.array(dtype=vec3),
    ):
        """``rho``: the SPH density (the volumes ``m / rho``); ``rho_p``: the pressure density
        (``rest_density`` its initial value), the same array unless a material is
        ``energy_spiky``. ``pairs`` 0: the floor images' part alone (``image_pressure_forces``),
        launched only for its generated adjoint, the image part of ``pressure_forces_adjoint``."""
        i = wp.tid()
        mi = material[i]
        xi = x[i]
        vi = v[i]
        Vi, Vpi, pi = fn.particle_terms(i, mass, rho, rho_p, rest_density, material, mat)
        visc_i = mat.viscosity[mi]
        form = mat.pressure_force[mi]
        c6 = sm.poly6_coef(h)
        c_spiky = sm.spiky_coef(h)
        c_visc = sm.viscosity_coef(h)
        fi = vec3()
        n = count[i]
        if pairs == 0:
            n = 0
        for k in range(n):
            j = nbr[i, k]
            pj, VV, VVp, eta = fn.partner_terms(j, Vi, Vpi, visc_i, mass, rho, rho_p, rest_density, material, mat)
            half = scalar(0.5) * fn.sph_pair_force(VV, VVp, pi, pj, rho_p[i], rho_p[j], form, eta, xi - x[j], v[j] - vi,
                                                   h, c6, c_spiky, c_visc, fn.pair_repulsion_of(i, j, mass, material, mat))
            wp.atomic_add(f, j, -half)
            fi += half
        if images != 0:
            fi += fn.image_pressure_forces(i, x, v, nbr, count[i], Vi, Vpi, pi, rho_p[i], vi, mass, rho, rho_p, rest_density,
                                           material, mat, h, c6, c_spiky, c_visc, gn, goff, gmin, images)
        wp.atomic_add(f, i, fi)

    @wp.kernel(module="unique")
    def pressure_stress(
        x: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        sigma: wp.array(dtype=T.mat33),
    ):
        """Each particle's share of its pressure pairs' virial over its volume ``m / rho``
        (``pair_virial_share``; the pair forces of ``pressure_forces`` without the viscous
        part): the Cauchy stress the SPH pressure carries through it, accumulated into
        ``sigma`` (zeroed by the caller). Each directed pair of ``pressure_forces`` applies half
        its force to both ends, and its virial goes half to each end likewise."""
        i = wp.tid()
        mi = material[i]
        xi = x[i]
        Vi, Vpi, pi = fn.particle_terms(i, mass, rho, rho_p, rest_density, material, mat)
        form = mat.pressure_force[mi]
        c6 = sm.poly6_coef(h)
        c_spiky = sm.spiky_coef(h)
        c_visc = sm.viscosity_coef(h)
        zero = scalar(0.0)
        for k in range(count[i]):
            j = nbr[i, k]
            pj, VV, VVp, eta = fn.partner_terms(j, Vi, Vpi, zero, mass, rho, rho_p, rest_density, material, mat)
            rij = xi - x[j]
            half = scalar(0.5) * fn.sph_pair_force(VV, VVp, pi, pj, rho_p[i], rho_p[j], form, zero, rij, vec3(), h, c6,
                                                   c_spiky, c_visc, fn.pair_repulsion_of(i, j, mass, material, mat))
            w = fn.pair_virial_share(half, rij)
            wp.atomic_add(sigma, i, w / Vi)
            wp.atomic_add(sigma, j, w * (rho[j] / mass[j]))

    @wp.func
    def density_pair_adjoint(a: scalar, a_p: scalar, mj: scalar, d: vec3, r2: scalar, h: scalar, c6: scalar,
                             c_spiky: scalar, form: int, both: int) -> vec3:
        """A pair's ``adj d`` through the density ``m_j W(d)`` of gradient ``a`` (``form`` its
        kernel, ``density_weight_gradient``); with ``both`` also through the pressure density
        ``m_j W_form(d)`` of gradient ``a_p`` (``a`` then the SPH density's, poly6)."""
        g = vec3()
        if both != 0:
            g = (a * mj) * fn.density_weight_gradient(d, r2, h, c6, c_spiky, 0) + (a_p * mj) * fn.density_weight_gradient(
                d, r2, h, c6, c_spiky, form)
        else:
            g = (a * mj) * fn.density_weight_gradient(d, r2, h, c6, c_spiky, form)
        return g

    @wp.kernel(enable_backward=False, module="unique")
    def density_adjoint(
        x: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        of_pressure: int,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        adj_rho: wp.array(dtype=scalar),
        adj_rho_p: wp.array(dtype=scalar),
        adj_x: wp.array(dtype=vec3),
    ):
        """Hand-written adjoint of ``density``: ``d rho_i / d x_j = m_j grad W(d)``,
        ``d = x_j - x_i`` (``density_weight_gradient``); with ``images`` the same for each
        image ``g_j`` of ``image_density`` in place of ``x_j``, scattered to ``x_j`` through
        ``deformation.floor_image_jacobian``. ``of_pressure`` 1: ``adj_rho`` is the pressure
        density's; 2: both densities' at once, ``adj_rho`` the SPH density's and ``adj_rho_p``
        the pressure density's, in one pass over the pairs (one scatter per pair instead of
        two launches' one each)."""
        i = wp.tid()
        a = adj_rho[i]
        a_p = scalar(0.0)
        both = wp.where(of_pressure == 2, 1, 0)
        if both != 0:
            a_p = adj_rho_p[i]
        xi = x[i]
        c6 = sm.poly6_coef(h)
        c_spiky = sm.spiky_coef(h)
        form = int(0)
        if of_pressure != 0:
            form = mat.pressure_force[material[i]]
        hh = h * h
        n = count[i]
        gx_i = vec3()
        for k in range(n):
            j = nbr[i, k]
            d = x[j] - xi
            r2 = wp.dot(d, d)
            if r2 < hh:
                g = density_pair_adjoint(a, a_p, mass[j], d, r2, h, c6, c_spiky, form, both)
                wp.atomic_add(adj_x, j, g)
                gx_i -= g
        n_img = image_slots(xi, n, h, gn, goff, images)
        for k in range(n_img):
            j = image_row_particle(i, k, n, nbr)
            xj = x[j]
            d = fn.floor_image(xj, gn, goff, gmin) - xi
            r2 = wp.dot(d, d)
            if r2 < hh:
                g = density_pair_adjoint(a, a_p, mass[j], d, r2, h, c6, c_spiky, form, both)
                scatter_partner_adjoint(adj_x, j, xj, g, gn, goff, gmin, 1)
                gx_i -= g
        wp.atomic_add(adj_x, i, gx_i)

    @wp.func
    def pressure_slope(rho: scalar, rho0: scalar, k_p: scalar, clamp: int) -> scalar:
        """1 where ``pressure`` follows ``k_p (rho - rho0)``, 0 where the clamp holds the
        density's excess at 0 (as Warp's adjoint of ``max``: a tie goes to the clamp),
        whatever ``k_p``: at ``k_p = 0`` a compressed particle's pressure still has the slope
        ``rho - rho0`` in ``k_p``."""
        out = scalar(1.0)
        if clamp != 0:
            if not (rho - rho0 > scalar(0.0)):
                out = scalar(0.0)
        return out

    @wp.func
    def pressure_adjoint(adj_p: scalar, rho: scalar, rho0: scalar, k_p: scalar, clamp: int):
        """Adjoint of ``pressure`` (the equation of state) in the density and the stiffness:
        ``(adj rho, adj k_p) = adj p s (k_p, rho - rho0)``, ``s`` its ``pressure_slope``."""
        a = adj_p * pressure_slope(rho, rho0, k_p, clamp)
        return a * k_p, a * (rho - rho0)

    @wp.func
    def pressure_pair_adjoint(
        i: int,
        j: int,
        r: vec3,
        r2: scalar,
        h: scalar,
        hh: scalar,
        c6: scalar,
        c_spiky: scalar,
        c_visc: scalar,
        afi: vec3,
        vi: vec3,
        Vi: scalar,
        rho_i: scalar,
        pi: scalar,
        rp_i: scalar,
        visc_i: scalar,
        form: int,
        v: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        adj_f: wp.array(dtype=vec3),
        adj_x: wp.array(dtype=vec3),
        adj_v: wp.array(dtype=vec3),
        adj_rho: wp.array(dtype=scalar),
        adj_rho_p: wp.array(dtype=scalar),
        adj_k: wp.array(dtype=scalar),
        adj_visc: wp.array(dtype=scalar),
        adj_pi: scalar,
        adj_Ai: scalar,
        adj_rho_i: scalar,
        adj_visc_i: scalar,
        gx_i: vec3,
        gv_i: vec3,
    ):
        """One pair's part of ``pressure_forces_adjoint`` (its docstring has the formulas), the
        pair ``i, j`` at ``r = x_i - x_j`` within ``h``: scatters ``j``'s gradients and returns
        ``i``'s sums ``(adj p_i, adj A_i, adj rho_i, adj visc_i, adj x_i, adj v_i)`` with the
        pair's terms added. A function of its own so that another pass over the same pairs
        (``forces.variational_forces_adjoint``'s) can take them too."""
        mj = material[j]
        rho_j = rho[j]
        rp_j = rho_p[j]
        k_j = mat.pressure_stiffness[mj]
        pj = fn.pressure(rp_j, rest_density[j], k_j, mat.clamp_pressure[mj])
        VV = Vi * mass[j] / rho_j
        eta = fn.pair_viscosity(visc_i, mat.viscosity[mj])
        a = scalar(0.5) * (afi - adj_f[j])
        rl = wp.sqrt(r2)
        adj_r = vec3()
        adj_VV = scalar(0.0)
        adj_rl = scalar(0.0)
        energy_like = int(0)
        adj_A = scalar(0.0)
        if form == 0:
            # energy_pressure_pair_force: G = C w e^2 r, w = m_i m_j (A_i + A_j).
            e = hh - r2
            ar = wp.dot(a, r)
            mm = mass[i] * mass[j]
            w = mm * (pi / (rp_i * rp_i) + pj / (rp_j * rp_j))
            adj_A = scalar(6.0) * c6 * mm * e * e * ar
            energy_like = 1
            adj_r += (scalar(6.0) * c6 * w * e) * (e * a - scalar(4.0) * ar * r)
        elif form == 2 and r2 > scalar(1.0e-24) * hh:
            # energy_spiky_pair_force: G = -w psi(|r|) r, w = m_i m_j (A_i + A_j).
            psi = sm.spiky_gradient_factor(rl, h, c_spiky)
            mm = mass[i] * mass[j]
            w = mm * (pi / (rp_i * rp_i) + pj / (rp_j * rp_j))
            adj_A = -psi * mm * wp.dot(a, r)
            energy_like = 1
            b = -w * a
            adj_r += psi * b
            adj_rl += sm.spiky_gradient_factor_slope(rl, h, c_spiky, r2) * wp.dot(r, b)
        elif form == 1 and r2 > scalar(1.0e-24) * hh:
            psi = sm.spiky_gradient_factor(rl, h, c_spiky)
            q = psi * wp.dot(a, r)
            adj_VV -= scalar(0.5) * (pi + pj) * q
            adj_p = scalar(-0.5) * VV * q
            adj_pi += adj_p
            adj_rp_j, adj_k_j = pressure_adjoint(adj_p, rp_j, rest_density[j], k_j, mat.clamp_pressure[mj])
            wp.atomic_add(adj_rho_p, j, adj_rp_j)
            wp.atomic_add(adj_k, mj, adj_k_j)
            b = scalar(-0.5) * VV * (pi + pj) * a
            adj_r += psi * b
            adj_rl += sm.spiky_gradient_factor_slope(rl, h, c_spiky, r2) * wp.dot(r, b)
        if energy_like != 0:
            # A = p / rho_p^2 of both particles (i's summed over the pairs, below).
            adj_Ai += adj_A
            adj_rp_j, adj_k_j = pressure_adjoint(adj_A / (rp_j * rp_j), rp_j, rest_density[j], k_j,
                                                 mat.clamp_pressure[mj])
            wp.atomic_add(adj_rho_p, j, scalar(-2.0) * adj_A * pj / (rp_j * rp_j * rp_j) + adj_rp_j)
            wp.atomic_add(adj_k, mj, adj_k_j)
        if r2 > scalar(1.0e-30):
            vji = v[j] - vi
            lap = sm.lap_w_viscosity_at(rl, h, c_visc)
            s5 = scalar(5.0) * eta * VV * lap / r2
            u = wp.dot(vji, r)
            ar = wp.dot(a, r)
            adj_s = u * ar
            adj_u = s5 * ar
            adj_r += s5 * u * a + adj_u * vji
            adj_vji = adj_u * r
            wp.atomic_add(adj_v, j, adj_vji)
            gv_i -= adj_vji
            base = scalar(5.0) * lap / r2
            adj_eta = adj_s * base * VV
            # pair_viscosity's adjoint: half to each particle's viscosity.
            adj_visc_i += scalar(0.5) * adj_eta
            wp.atomic_add(adj_visc, mj, scalar(0.5) * adj_eta)
            adj_VV += adj_s * base * eta
            adj_rl += sm.lap_w_viscosity_slope_at(rl, h, c_visc) * adj_s * scalar(5.0) * eta * VV / r2
            adj_r -= scalar(2.0) * adj_s * s5 / r2 * r
        s_rep = fn.pair_repulsion_of(i, j, mass, material, mat)
        r0 = scalar(PAIR_REPULSION_RANGE) * h
        if s_rep > scalar(0.0) and rl < r0 and rl > scalar(1.0e-12) * h:
            # pair_repulsion_force: G = g(|r|) r, g = 3 s e^2 / (r0 |r|), e = 1 - |r| / r0;
            # s = (c_i k_i + c_j k_j) sqrt(m_i m_j) / 2 (pair_repulsion_strength) to each k_p.
            e = scalar(1.0) - rl / r0
            ar = wp.dot(a, r)
            adj_s = ar * scalar(3.0) * e * e / (r0 * rl)
            adj_r += (s_rep * scalar(3.0) * e * e / (r0 * rl)) * a
            adj_rl -= ar * scalar(3.0) * s_rep * e * (scalar(2.0) * rl / r0 + e) / (r0 * rl * rl)
            half_mm = scalar(0.5) * wp.sqrt(mass[i] * mass[j])
            mi = material[i]
            wp.atomic_add(adj_k, mi, adj_s * half_mm * mat.pair_repulsion[mi])
            wp.atomic_add(adj_k, mj, adj_s * half_mm * mat.pair_repulsion[mj])
        if rl > scalar(0.0):
            adj_r += (adj_rl / rl) * r
        adj_rho_i -= adj_VV * VV / rho_i
        wp.atomic_add(adj_rho, j, -adj_VV * VV / rho_j)
        gx_i += adj_r
        wp.atomic_add(adj_x, j, -adj_r)
        return adj_pi, adj_Ai, adj_rho_i, adj_visc_i, gx_i, gv_i

    @wp.func
    def pressure_particle_terms(i: int, v: wp.array(dtype=vec3), mass: wp.array(dtype=scalar),
                                rho: wp.array(dtype=scalar), rho_p: wp.array(dtype=scalar),
                                rest_density: wp.array(dtype=scalar), material: wp.array(dtype=wp.int32), mat: Materials):
        """What ``pressure_pair_adjoint`` reads of particle ``i``: ``(material, v_i, rho_i, V_i = m_i
        / rho_i, rho_p_i, k_p, p_i, viscosity, pressure force)``."""
        mi = material[i]
        vi = v[i]
        rho_i = rho[i]
        Vi = mass[i] / rho_i
        rp_i = rho_p[i]
        k_i = mat.pressure_stiffness[mi]
        pi = fn.pressure(rp_i, rest_density[i], k_i, mat.clamp_pressure[mi])
        visc_i = mat.viscosity[mi]
        form = mat.pressure_force[mi]
        return mi, vi, rho_i, Vi, rp_i, k_i, pi, visc_i, form

    @wp.func
    def pressure_particle_adjoint(i: int, mi: int, rp_i: scalar, k_i: scalar, pi: scalar,
                                  rest_density: wp.array(dtype=scalar), mat: Materials, adj_pi: scalar, adj_Ai: scalar,
                                  adj_rho_i: scalar, adj_visc_i: scalar, gv_i: vec3, adj_v: wp.array(dtype=vec3),
                                  adj_rho: wp.array(dtype=scalar), adj_rho_p: wp.array(dtype=scalar),
                                  adj_k: wp.array(dtype=scalar), adj_visc: wp.array(dtype=scalar)):
        """After ``i``'s pairs (``pressure_pair_adjoint``): its sums through ``A_i = p_i /
        rho_p_i^2`` and ``p_i`` to its densities, ``k_p`` and viscosity, and its ``adj v``."""
        adj_rp_i = scalar(0.0)
        wp.atomic_add(adj_v, i, gv_i)
        adj_pi += adj_Ai / (rp_i * rp_i)
        adj_rp_i -= scalar(2.0) * adj_Ai * pi / (rp_i * rp_i * rp_i)
        adj_rp_p, adj_k_i = pressure_adjoint(adj_pi, rp_i, rest_density[i], k_i, mat.clamp_pressure[mi])
        wp.atomic_add(adj_rho, i, adj_rho_i)
        wp.atomic_add(adj_rho_p, i, adj_rp_i + adj_rp_p)
        wp.atomic_add(adj_k, mi, adj_k_i)
        wp.atomic_add(adj_visc, mi, adj_visc_i)

    @wp.kernel(enable_backward=False, module="unique")
    def pressure_forces_adjoint(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        adj_f: wp.array(dtype=vec3),
        adj_x: wp.array(dtype=vec3),
        adj_v: wp.array(dtype=vec3),
        adj_rho: wp.array(dtype=scalar),
        adj_rho_p: wp.array(dtype=scalar),
        adj_k: wp.array(dtype=scalar),
        adj_visc: wp.array(dtype=scalar),
    ):
        """Hand-written adjoint of ``pressure_forces``: per pair, with ``a = (adj f_i -
        adj f_j) / 2`` against the pair's force on ``i`` (pressure, ``energy``: ``6 c6 m_i m_j
        (A_i + A_j) (h^2 - |r|^2)^2 r`` with ``A = p / rho_p^2``; ``spiky``: ``-VV (p_i + p_j)/2
        psi(|r|) r``, ``psi = c_s (h - |r|)^2 / |r|``; viscosity ``s (v_ji . r) r``,
        ``s = 5 eta VV lap(|r|) / |r|^2``, ``lap`` the Laplacian ``lap_w_viscosity_at`` with
        its slope ``lap_w_viscosity_slope_at``), the chain rule to ``r = x_i - x_j``,
        ``v_ji``, ``VV = m_i m_j / (rho_i rho_j)`` (then the SPH density ``rho``), ``A`` and
        ``p`` (then the pressure density ``rho_p`` and ``k_p``) and
        ``eta``; the pair repulsion (``pair_repulsion_force``, ``3 s (1 - |r|/r0)^2 / (r0 |r|) r``)
        to ``r`` and, through ``s``, both particles' ``k_p``. ``adj_rho`` and ``adj_rho_p`` may be
        one array (``rho_p`` is ``rho``)."""
        i = wp.tid()
        xi = x[i]
        mi, vi, rho_i, Vi, rp_i, k_i, pi, visc_i, form = pressure_particle_terms(i, v, mass, rho, rho_p, rest_density,
                                                                                  material, mat)
        c6 = sm.poly6_coef(h)
        c_spiky = sm.spiky_coef(h)
        c_visc = sm.viscosity_coef(h)
        hh = h * h
        afi = adj_f[i]
        adj_pi = scalar(0.0)
        adj_Ai = scalar(0.0)
        adj_rho_i = scalar(0.0)
        adj_visc_i = scalar(0.0)
        gx_i = vec3()
        gv_i = vec3()
        for k in range(count[i]):
            j = nbr[i, k]
            r = xi - x[j]
            r2 = wp.dot(r, r)
            if r2 < hh:
                adj_pi, adj_Ai, adj_rho_i, adj_visc_i, gx_i, gv_i = pressure_pair_adjoint(
                    i, j, r, r2, h, hh, c6, c_spiky, c_visc, afi, vi, Vi, rho_i, pi, rp_i, visc_i, form, v, mass, rho, rho_p,
                    rest_density, material, mat, adj_f, adj_x, adj_v, adj_rho, adj_rho_p, adj_k, adj_visc, adj_pi, adj_Ai,
                    adj_rho_i, adj_visc_i, gx_i, gv_i)
        wp.atomic_add(adj_x, i, gx_i)
        pressure_particle_adjoint(i, mi, rp_i, k_i, pi, rest_density, mat, adj_pi, adj_Ai, adj_rho_i, adj_visc_i, gv_i, adj_v,
                                  adj_rho, adj_rho_p, adj_k, adj_visc)

    return types.SimpleNamespace(density=density, pressure_forces=pressure_forces, pressure_stress=pressure_stress,
                                 pressure_forces_adjoint=pressure_forces_adjoint, density_adjoint=density_adjoint,
                                 pressure_pair_adjoint=pressure_pair_adjoint, pressure_particle_terms=pressure_particle_terms,
                                 pressure_particle_adjoint=pressure_particle_adjoint,
                                 pressure_slope=pressure_slope, pressure_adjoint=pressure_adjoint)


def launch_density(model, x, neighbors, neighbor_count, rho, hand_adjoint: bool = True, of_pressure: bool = False):
    """SPH density at ``x`` over the given neighbour lists into ``rho`` (``of_pressure``: each
    material's pressure density, ``density_weight``); under a ``wp.Tape`` the backward runs
    ``density_adjoint`` (``hand_adjoint=False``: Warp's generated adjoint)."""
    k = kernels(model.scalar)
    inputs = [x, model.particle_mass, model.particle_material, model.material_arrays(), neighbors, neighbor_count,
              model.scalar(model.support_radius), int(of_pressure), *model.image_args()]
    tape = recording_tape()
    if tape is None or not hand_adjoint or x.grad is None or rho.grad is None:
        model.launches(k.density, model.particle_count, inputs, [rho], device=model.device)
        return
    model.launches(k.density, model.particle_count, inputs, [rho], device=model.device, record_tape=False)

    tape.record_func(lambda: launch_density_adjoint(model, x, neighbors, neighbor_count, rho, of_pressure), [x, rho])


def launch_density_adjoint(model, x, neighbors, neighbor_count, rho, of_pressure: bool = False, rho_p=None):
    """``density_adjoint``: ``rho.grad`` into ``x.grad``; with ``rho_p`` (the pressure density
    beside the SPH density ``rho``) ``rho_p.grad`` too, in the same pass."""
    mode = 2 if rho_p is not None else int(of_pressure)
    model.launches(
        kernels(model.scalar).density_adjoint, model.particle_count,
        [x, model.particle_mass, model.particle_material, model.material_arrays(), neighbors, neighbor_count,
         model.scalar(model.support_radius), mode, *model.image_args(), rho.grad,
         (rho if rho_p is None else rho_p).grad, x.grad],
        device=model.device, record_tape=False,
    )


def pressure_density(model, state):
    """The array the pressure reads as its density in ``state``: ``state.pressure_density``
    where a material is ``energy_spiky`` (``Model.separate_pressure_density``; allocated here
    for a state made before ``Model.set_material`` made one so), else ``state.density``."""
    if not model.separate_pressure_density:
        return state.density
    if state.pressure_density is None:
        d = state.density
        state.pressure_density = wp.zeros(d.shape[0], dtype=d.dtype, device=d.device, requires_grad=d.requires_grad)
    return state.pressure_density


def launch_state_densities(model, x, state_out, hand_adjoint: bool = True):
    """The SPH density into ``state_out.density`` and, where a material is ``energy_spiky``
    (``Model.separate_pressure_density``), the pressure density into
    ``state_out.pressure_density``. Under a ``wp.Tape`` with both, the backward takes both
    densities' gradients in one ``density_adjoint`` pass (``launch_state_densities_adjoint``)."""
    rho = state_out.density
    rho_p = pressure_density(model, state_out) if model.separate_pressure_density else None
    tape = recording_tape()
    if (rho_p is None or tape is None or not hand_adjoint or x.grad is None or rho.grad is None
            or rho_p.grad is None):
        launch_density(model, x, state_out.neighbors, state_out.neighbor_count, rho, hand_adjoint)
        if rho_p is not None:
            launch_density(model, x, state_out.neighbors, state_out.neighbor_count, rho_p, hand_adjoint, of_pressure=True)
        return
    with outside_recording_tape():
        launch_density(model, x, state_out.neighbors, state_out.neighbor_count, rho)
        launch_density(model, x, state_out.neighbors, state_out.neighbor_count, rho_p, of_pressure=True)
    tape.record_func(lambda: launch_state_densities_adjoint(model, x, state_out), [x, rho, rho_p])


def launch_state_densities_adjoint(model, x, state_out):
    """The hand-written adjoints of ``launch_state_densities``: both densities' in one launch
    where there are two (their pairs are the same)."""
    launch_density_adjoint(model, x, state_out.neighbors, state_out.neighbor_count, state_out.density,
                           rho_p=pressure_density(model, state_out) if model.separate_pressure_density else None)


def launch_pressure_forces(model, state_in, state_out, hand_adjoint: bool = True):
    """SPH pressure and viscosity forces into ``state_out.force`` (the SPH density in
    ``state_out.density``, the pressure density in ``state_out.pressure_density``).
    Under a ``wp.Tape`` the backward runs ``pressure_forces_adjoint`` (``hand_adjoint=False``:
    Warp's generated adjoint)."""
    k = kernels(model.scalar)
    rho_p = pressure_density(model, state_out)
    inputs = [
        state_in.x, state_in.v, model.particle_mass, state_out.density, rho_p,
        model.particle_rest_density, model.particle_material, model.material_arrays(), state_out.neighbors,
        state_out.neighbor_count, model.scalar(model.support_radius), *model.image_args(), 1,
    ]
    tape = recording_tape()
    grads = (state_in.x, state_in.v, state_out.density, rho_p, model.pressure_stiffness,
             model.viscosity, state_out.force)
    if tape is None or not hand_adjoint or any(a.grad is None for a in grads):
        model.launches(k.pressure_forces, model.particle_count, inputs, [state_out.force], device=model.device)
        return
    model.launches(k.pressure_forces, model.particle_count, inputs, [state_out.force], device=model.device, record_tape=False)

    tape.record_func(lambda: launch_pressure_forces_adjoint(model, state_in, state_out), list(grads))


def launch_pressure_stress(model, state_in, state_out, sigma):
    """Each particle's SPH pressure stress (``pressure_stress``: its pressure pairs' virial over
    its volume, Cauchy, tension positive) at ``state_in.x`` with the densities in ``state_out``,
    into ``sigma`` (zeroed here). The floor images' pressure (``Model.image_plane``) is not in
    it (``Solver`` refuses the option beside them). Recorded on a tape as any launch (Warp's
    generated adjoint)."""
    sigma.zero_()
    model.launches(
        kernels(model.scalar).pressure_stress, model.particle_count,
        [state_in.x, model.particle_mass, state_out.density, pressure_density(model, state_out),
         model.particle_rest_density, model.particle_material, model.material_arrays(), state_out.neighbors,
         state_out.neighbor_count, model.scalar(model.support_radius)],
        [sigma], device=model.device,
    )


def launch_pressure_forces_adjoint(model, state_in, state_out):
    """``pressure_forces_adjoint``: ``state_out.force.grad`` into the gradients of ``state_in.x,
    v``, ``state_out.density``, ``state_out.pressure_density`` and the model's
    ``pressure_stiffness`` and ``viscosity``."""
    rho_p = pressure_density(model, state_out)
    model.launches(
        kernels(model.scalar).pressure_forces_adjoint, model.particle_count,
        [
            state_in.x, state_in.v, model.particle_mass, state_out.density, rho_p,
            model.particle_rest_density, model.particle_material, model.material_arrays(), state_out.neighbors,
            state_out.neighbor_count, model.scalar(model.support_radius), state_out.force.grad, state_in.x.grad,
            state_in.v.grad, state_out.density.grad, rho_p.grad, model.pressure_stiffness.grad,
            model.viscosity.grad,
        ],
        device=model.device, record_tape=False,
    )
    launch_pressure_image_forces_adjoint(model, state_in, state_out)


def launch_pressure_image_forces_adjoint(model, state_in, state_out):
    """The floor images' part of ``launch_pressure_forces_adjoint`` (with an image plane; else
    nothing), for a pass that took the pairs' (``forces.launch_variational_forces_adjoint``)."""
    rho_p = pressure_density(model, state_out)
    if model.image_plane is not None:
        # The images' part: the generated adjoint of pressure_forces without its pairs
        # (pairs = 0: image_pressure_forces alone, which the forward adds to the pairs'
        # force). Its replayed forward writes a scratch array, not the force; as the pairs'
        # hand-written adjoint, none to the masses and rest densities.
        inputs = [
            state_in.x, state_in.v, model.particle_mass, state_out.density, rho_p, model.particle_rest_density,
            model.particle_material, model.material_arrays(), state_out.neighbors, state_out.neighbor_count,
            model.scalar(model.support_radius), *model.image_args(), 0,
        ]
        adjoint = wp.Tape().get_adjoint
        scratch = wp.zeros_like(state_out.force, requires_grad=False)
        model.launches(kernels(model.scalar).pressure_forces, model.particle_count, inputs, [scratch],
                  adj_inputs=[None if a is model.particle_mass or a is model.particle_rest_density else adjoint(a)
                              for a in inputs], adj_outputs=[state_out.force.grad],
                  adjoint=True, device=model.device, record_tape=False)


@functools.cache
def isotropic_kernels(scalar) -> types.SimpleNamespace:
    """The isotropic pressure force (``launch_isotropic_pressure_forces``); Warp's generated
    adjoint differentiates it (the moments are summed in ``isotropic_moments``, a function of
    their own, before their inverse: docs/method.md, Warp pitfall 1)."""
    T = type_set(scalar)
    vec3 = T.vec3
    fn = funcs(scalar)
    Materials = materials.struct(scalar)

    @wp.kernel(module="unique")
    def isotropic_pressure_forces(
        x: wp.array(dtype=vec3),
        mass: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        f: wp.array(dtype=vec3),
        counters: wp.array(dtype=wp.int32),
    ):
        """Particle ``i``'s pressure ``p_i`` (of its pressure density, as the pair forces read
        it) applied as the stress ``-p_i I`` on its volume ``V_i = m_i / rho_i``: ``g_ij = w_ij
        M_i x_ij`` with ``M_i = isotropic_pressure_map``, taken from each neighbour ``j`` and
        added to ``i``. Only an ``isotropic`` material's particles (``pressure_force`` 3) apply
        it; each whose map is regularised is counted in ``counters`` (an int32 diagnostic
        without gradient: the replayed forward of the adjoint does not count again)."""
        i = wp.tid()
        mi = material[i]
        if mat.pressure_force[mi] != 3:
            return
        n = count[i]
        p = fn.pressure(rho_p[i], rest_density[i], mat.pressure_stiffness[mi], mat.clamp_pressure[mi])
        A = fn.isotropic_moments(i, x, nbr, n, h)
        M = fn.isotropic_pressure_map(p, mass[i] / rho[i], A)
        if fn.isotropic_regularised(A) != 0:
            wp.atomic_add(counters, COUNT_PRESSURE_REGULARISED, 1)
        xi = x[i]
        fi = vec3()
        for k in range(n):
            j = nbr[i, k]
            g = fn.isotropic_pair_force(M, x[j] - xi, h)
            wp.atomic_sub(f, j, g)
            fi += g
        wp.atomic_add(f, i, fi)

    return types.SimpleNamespace(isotropic_pressure_forces=isotropic_pressure_forces)


def launch_isotropic_pressure_forces(model, state_in, state_out, hand_adjoint: bool = True, counters=None):
    """``launch_pressure_forces`` with each particle's pressure applied as the isotropic
    stress ``-p_i I`` through its neighbourhood's moment matrix (``isotropic_pressure_map``)
    instead of the pair forces: the virial of a particle's own pressure forces is ``p_i V_i I``
    also at a free surface, where the pair forms' is not (its neighbours lie to one side), and
    the pairs stay equal and opposite, with zero torque per particle (``A M^T = -p V I`` is
    symmetric). The viscous force is the pair kernel's, whose pressure is none for an
    ``isotropic`` material (``sph_pair_force``). ``Material.pressure_force = "isotropic"``
    selects it (docs/method.md §6); it is refused with floor images, whose pressure is a pair
    force. ``counters`` (the solver's guard counters, ``Solver.guard_counts``) counts at
    ``COUNT_PRESSURE_REGULARISED`` the particles whose map was regularised; None: not counted."""
    if model.image_plane is not None:
        # Model and Solver.step refuse it before any kernel; this guards a direct call.
        raise ValueError("Material.pressure_force = 'isotropic' is not allowed with floor images "
                         "(add_ground(images=True)): their pressure is a pair force of the floor's mirror images; use a "
                         "particle or ghost floor or a collider")
    h = model.scalar(model.support_radius)
    rho_p = pressure_density(model, state_out)
    mats = model.material_arrays()
    launch_pressure_forces(model, state_in, state_out, hand_adjoint)
    model.launches(isotropic_kernels(model.scalar).isotropic_pressure_forces, model.particle_count,
                   [state_in.x, model.particle_mass, state_out.density, rho_p, model.particle_rest_density,
                    model.particle_material, mats, state_out.neighbors, state_out.neighbor_count, h],
                   [state_out.force, counters if counters is not None else _no_counters(model.device)],
                   device=model.device)


def _no_counters(device) -> wp.array:
    """Where a direct call of the isotropic launch counts nothing: a scratch of the guard
    counters' size (``COUNT_PRESSURE_REGULARISED`` its last slot), new at each call: one kept
    by the module would be written by every model and thread that called; only a direct call
    (a test) allocates it, the solver passes its own counters."""
    return wp.zeros(COUNT_PRESSURE_REGULARISED + 1, dtype=wp.int32, device=device)
