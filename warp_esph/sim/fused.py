"""The forward-only schedule of the step, used when no ``wp.Tape`` is recording.

``constitutive_forces`` does, per particle, what ``plasticity.constitutive_update``,
``forces.elastic_forces`` and ``pressure.pressure_forces`` do in three launches, calling
the same functions for every formula (``plasticity.guarded_flow_step``,
``forces.principal_stress`` / ``corotated_principal_stress`` / ``polynomial_stress``,
``forces.elastic_pair_force`` / ``variational_pair_force``, ``pressure.sph_pair_force``).
What it saves:

* one SVD of ``F`` instead of four: the plastic flow ``F_e = F + U diag(g - sigma) V^T``
  (``isotropic.isotropic_change``, compensated into ``F_lo``) keeps the singular vectors,
  so the stress reuses ``U, g, V`` instead of decomposing ``F_e``
  again (and the SVD maps' own decompositions, there for their adjoints, are gone);
  the stress is an isotropic function of ``F_e``, so the result is the same up to
  round-off (in float32 closer to a float64 step than the differentiable kernels:
  one SVD's error instead of two);
* the divided differences the SVD maps' adjoints need are not computed;
* the stress and ``F^-1`` of particle ``i`` are used where they are computed (they are
  still written to the state), and one loop over the neighbours applies the elastic
  pair force and the SPH pressure and viscosity forces, with each particle's pressure
  and volume ``m / rho`` computed once, in the neighbour pass.

``update_deformation`` is ``deformation.update_deformation`` with the neighbourhood
guard evaluated on the fit's own moment matrix (the neighbour pass then skips it).

Neither has a generated adjoint: under a tape the solver either launches them unrecorded
and records hand-written adjoints in their place (``Solver.fast_under_tape``), or launches
the differentiable kernels.
``tests/test_physics.py::test_fused_step_matches_the_differentiable_step`` compares
the two.
"""
import contextlib
import functools
import types

import warp as wp

from .._types import type_set
from . import deformation, forces, isotropic, materials, neighbors, plasticity, pressure, smoothing
from .replay import kept_through_backward, weak_tape
from .roundoff import compensated_sum

#: Where each body's skipped fits are counted (``deformation.COUNT_BODY``).
COUNT_BODY = deformation.COUNT_BODY
#: ``KeptFits``' states of a particle: sealed among its own resting set this step; its fit's
#: moments and guard kept too.
KEPT_MARKED = 1
KEPT_FIT = 2


class KeptFits:
    """What the fused step keeps of particles sealed among their own resting set
    (``keep_marks``): pinned to a set at rest (``ToolSet.still_particles``), every particle of
    the set at its place with no round-off carried, and every candidate of the neighbour
    search (all within ``h`` + skin, complete until the search builds them again) of the
    same set. Such a particle's row is every particle within ``h`` of its place, each at its
    place, whatever the free particles do, so it is out of reach (``out_of_reach``, without
    reading the row) and its fit's ``A``, guard and fade, the same bits at every step, are
    summed once and kept (``update_deformation``). Rows within ``h`` only (not those the
    paper's force stretches, whose reach follows each step's ``F``), untaped, without images.
    A particle's mark drops at a step where it is not sealed: its set set moving, a particle
    of the set off its place, a free particle among its candidates.

    A cache of the solver's, not of a state: ``Solver.scratch.kept_fits`` (``StepScratch``),
    made at the first step that keeps any, each solver its own (never the model's). Per
    particle it holds the mark ``kept`` (0, ``KEPT_MARKED``, ``KEPT_FIT``), ``sealed`` (found
    again after each build of the search's candidates, ``sealed_at``) and the kept ``A``,
    guard ``code`` and fade ``scale``; per set, ``moved``. Each step that keeps fits checks
    them against its own ``state_in``: the set at rest and each of its particles at its place
    with no round-off carried, read from ``state_in`` (``set_moved``), and the seals on the
    search's candidates, which ``NeighborSearch.update`` has just checked against
    ``state_in``'s positions, whatever state they were built from (built again where not
    complete for them). A state swapped in (another run's, its free particles elsewhere),
    one stepped twice or one moved by hand is thus stepped as a new solver steps it, to the
    bit (``tests/test_determinism.py``). A step that keeps none (taped, the non-fused
    kernels, rows reaching ``h sigma_max(F)``, floor images, no set at rest) reads nothing
    here and drops every mark (``keep_fits``), so the next that keeps sums its fits afresh."""

    def __init__(self, model):
        n, dev = model.particle_count, model.device
        self.kept = wp.zeros(n, dtype=wp.int32, device=dev)
        self.sealed = wp.zeros(n, dtype=wp.int32, device=dev)
        self.A = wp.zeros(n, dtype=model.types.mat33, device=dev)
        self.code = wp.zeros(n, dtype=wp.int32, device=dev)
        self.scale = wp.zeros(n, dtype=model.scalar, device=dev)
        self.moved = wp.zeros(model.tools.count + 1, dtype=wp.int32, device=dev)
        #: The search's ``rebuilds`` when ``sealed`` was last found (None: never).
        self.sealed_at = None
        #: Whether this step keeps fits (``keep_fits``).
        self.on = False


@wp.kernel(enable_backward=False, module="unique")
def keep_marks(pin: wp.array(dtype=wp.int32), cand: wp.array2d(dtype=wp.int32), cand_count: wp.array(dtype=wp.int32),
               recheck: int, still: wp.array(dtype=wp.int32), moved: wp.array(dtype=wp.int32),
               sealed: wp.array(dtype=wp.int32), kept: wp.array(dtype=wp.int32)):
    """``KeptFits``' marks of this step. With ``recheck`` (candidates built since the last
    marks) ``sealed``: 1 where a pinned particle's candidates are all of its own set, so its
    row holds them alone until the candidates are built again. ``kept``: 0 unless sealed, its
    set at rest (``still``) and every particle of the set at its place (``moved`` 0);
    else at least ``KEPT_MARKED``, what is kept from earlier steps staying kept."""
    i = wp.tid()
    if recheck != 0:
        s = int(0)
        own = pin[i]
        if own >= 0:
            s = int(1)
            k = int(0)
            while s != 0 and k < cand_count[i]:
                if pin[cand[i, k]] != own:
                    s = 0
                k += 1
        sealed[i] = s
    at_rest = still[i]
    if sealed[i] != 0 and at_rest != 0 and moved[at_rest] == 0:
        kept[i] = wp.max(kept[i], KEPT_MARKED)
    else:
        kept[i] = 0


def keep_fits(model, state_in, scratch, search, keep: bool):
    """``keep_marks`` of this step on ``search``'s candidates (after its update: complete for
    the positions ``state_in`` holds) into ``scratch.kept_fits``, where ``keep`` (the step is
    the fused one, untaped, its rows within ``h``), a pinned set is at rest and the model has
    no images; else the step keeps none (``KeptFits.on`` False)."""
    still = model.tools.still_particles() if keep and model.tools is not None else None
    k = scratch.kept_fits
    if still is None or model.image_plane is not None:
        if k is not None and k.on:
            # No marks run while none is kept, so nothing checks what was kept against those
            # steps; a set at rest again is at its rest places (still_particles), so the sums
            # would hold, but the cache does not rest on that: the next step that keeps sums afresh.
            k.kept.zero_()
            k.on = False
        return
    if k is None:
        k = scratch.kept_fits = KeptFits(model)
    k.on = True
    recheck = int(search.rebuilds != k.sealed_at)
    k.sealed_at = search.rebuilds
    k.moved.zero_()
    n = model.particle_count
    model.launches(kernels(model.scalar, model.fit_weight).set_moved, n,
                   [still, state_in.x, state_in.x_lo, model.tools.rest_x], [k.moved], device=model.device,
                   record_tape=False)
    model.launches(keep_marks, n, [model.tools.pin, search.candidates, search.candidate_count, recheck, still, k.moved],
                   [k.sealed, k.kept], device=model.device, record_tape=False)


@functools.cache
def kernels(scalar, weight: str) -> types.SimpleNamespace:
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33
    sm = smoothing.funcs(scalar)
    iso = isotropic.funcs(scalar)
    fo = forces.funcs(scalar, weight)
    fw = smoothing.fit_weight_funcs(scalar, weight)
    sph_pair_force = pressure.funcs(scalar).sph_pair_force
    pair_repulsion_of = pressure.funcs(scalar).pair_repulsion_of
    pair_viscosity = pressure.funcs(scalar).pair_viscosity
    image_pressure_forces = pressure.funcs(scalar).image_pressure_forces
    guarded_flow_step = plasticity.funcs(scalar).guarded_flow_step
    guard_state = neighbors.guard_funcs(scalar).guard
    df = deformation.funcs(scalar, weight)
    image_update = deformation.image_update_funcs(scalar, weight, "linear").floor_image_update
    Materials = materials.struct(scalar)
    COROTATED = forces.COROTATED

    @wp.func
    def held_still(j: int, still: wp.array(dtype=wp.int32), x: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                   rest: wp.array(dtype=vec3)) -> int:
        """1 where particle ``j`` is pinned to a set at rest (``ToolSet.still_particles``: its
        set's number + 1) and starts the step at its pinned place ``rest`` with no round-off
        carried, where the pin puts it again: its displacement over the step is then 0."""
        out = int(0)
        if still[j] != 0:
            if x[j] == rest[j] and x_lo[j] == vec3():
                out = 1
        return out

    @wp.func
    def out_of_reach(i: int, still: wp.array(dtype=wp.int32), x: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                     rest: wp.array(dtype=vec3), nbr: wp.array2d(dtype=wp.int32), n: int) -> int:
        """1 where particle ``i`` and every particle in its row are ``held_still``, pinned to
        the same set, else 0. Its pair forces then act on that set alone, whose places the
        pins set, and every displacement its fit sums is 0, so ``dF = I``: nothing another
        particle reads comes of its neighbour passes, and the step leaves them out (the set's
        reaction row then sums the same forces less pairs that cancel, equal and opposite, to
        round-off; a pair with another set's particle would move both sets' rows by its share)."""
        out = held_still(i, still, x, x_lo, rest)
        k = int(0)
        while out != 0 and k < n:
            j = nbr[i, k]
            out = held_still(j, still, x, x_lo, rest)
            if still[j] != still[i]:
                out = 0
            k += 1
        return out

    @wp.kernel(enable_backward=False, module="unique")
    def constitutive_forces(
        x: wp.array(dtype=vec3),
        v: wp.array(dtype=vec3),
        F_in: wp.array(dtype=mat33),
        F_lo_in: wp.array(dtype=mat33),
        alpha_in: wp.array(dtype=scalar),
        material: wp.array(dtype=wp.int32),
        mat: Materials,
        body: wp.array(dtype=wp.int32),
        volume: wp.array(dtype=scalar),
        p: wp.array(dtype=scalar),
        vol: wp.array(dtype=scalar),
        rho: wp.array(dtype=scalar),
        rho_p: wp.array(dtype=scalar),
        vol_p: wp.array(dtype=scalar),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        h: scalar,
        dt: scalar,
        sph: int,
        min_neighbors: int,
        max_condition: scalar,
        mass: wp.array(dtype=scalar),
        rest_density: wp.array(dtype=scalar),
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        image_stress: wp.array(dtype=mat33),
        F_image: wp.array(dtype=mat33),
        reach: int,
        still: wp.array(dtype=wp.int32),
        x_lo: wp.array(dtype=vec3),
        rest: wp.array(dtype=vec3),
        kept: wp.array(dtype=wp.int32),
        F_out: wp.array(dtype=mat33),
        F_lo_out: wp.array(dtype=mat33),
        alpha_out: wp.array(dtype=scalar),
        stress_out: wp.array(dtype=mat33),
        F_inv_out: wp.array(dtype=mat33),
        f: wp.array(dtype=vec3),
        counters: wp.array(dtype=wp.int32),
        far: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        m = material[i]
        F = F_in[i]
        kind = mat.model[m]
        mu = mat.mu[m]
        lam = mat.lam[m]

        # 1. Plastic flow (plasticity.flow) with a single SVD.
        Fe = F
        Fe_lo = F_lo_in[i]
        a_new = alpha_in[i]
        U = mat33()
        s = vec3()
        V = mat33()
        have_svd = int(0)
        if mat.flow_rate[m] > scalar(0.0):
            U, s, V = iso.svd(F)
            have_svd = 1
            flowed, g, c, pw, a_flow = guarded_flow_step(
                s, mu, mat.yield_stress[m], mat.flow_rate[m], mat.hardening[m], a_new, dt, kind, counters
            )
            if flowed != 0:
                # As plasticity.flow: F + F_lo plus the flow's change, compensated.
                Fe, Fe_lo = compensated_sum(F, Fe_lo + iso.from_principal(U, g - s, V))
                s = g
                a_new = a_flow

        # 2. Stress P* (forces.stress, reusing the SVD) and F^-1.
        P = mat33()
        sk = fo.stress_model(mat, m)
        if sk >= 2 and sk != COROTATED:
            P = fo.polynomial_stress(Fe, mu, lam, sk)
        else:
            if have_svd == 0:
                U, s, V = iso.svd(Fe)
            if sk == COROTATED:
                P = iso.from_principal(U, fo.corotated_principal_stress(s, mu, lam), V)
            else:
                P = iso.from_principal(U, fo.principal_stress(s, mu, lam), V)
        Finv = wp.inverse(Fe)
        F_out[i] = Fe
        F_lo_out[i] = Fe_lo
        alpha_out[i] = a_new
        stress_out[i] = P
        F_inv_out[i] = Finv
        # (reach 0: no pinned set at rest, or images, whose own F the update writes.) The
        # paper's pair forces of a stressed particle are not central: their torque on the set
        # does not cancel, and leaving them out moved a floor's reaction torque by 1.2 % after a
        # thrown block had passed over it (docs/performance.md), so those run.
        out = int(0)
        if reach != 0 and (mat.elastic_force[m] != 0 or P == mat33()):
            if reach == 2 and kept[i] != 0:
                out = 1  # its row holds its own resting set's particles alone, at their places (keep_marks)
            else:
                out = out_of_reach(i, still, x, x_lo, rest, nbr, count[i])
        far[i] = out
        if out != 0:
            return

        # 3. Pair forces: elastic (forces.elastic_forces), then pressure and viscosity
        # (pressure.pressure_forces) with the pressure p, volume m / rho and pressure
        # density rho_p (sph 2: with its own m / rho_p, else rho_p is rho) of every particle
        # from the neighbour pass, each pair's share applied equal and opposite.
        xi = x[i]
        bi = body[i]
        Vol_i = volume[i]
        vi = v[i]
        Vi = scalar(0.0)
        Vpi = scalar(0.0)
        pi = scalar(0.0)
        rho_i = scalar(0.0)
        visc_i = mat.viscosity[m]
        form = mat.pressure_force[m]
        if sph != 0:
            Vi = vol[i]
            Vpi = Vi
            if sph == 2:
                Vpi = vol_p[i]
            pi = p[i]
            rho_i = rho_p[i]
        c_el = sm.elastic_coef(h)
        # Elastic force: 0 the paper's (eqs. 10-13), 1 variational, 2 none (a guarded
        # particle of the variational force).
        kind_el = mat.elastic_force[m]
        M = mat33()
        fi = vec3()
        if kind_el == 1:
            # The fit's moments of x alone (y = x: B - A = 0), A and the count only: B's sum cost
            # about 5 % of the step (docs/performance.md), and the same A to the bit.
            A, same = df.position_moments(i, x, body, nbr, count[i], h, gn, goff, gmin, images)
            # Faded where cond(A) passes max_condition or the count falls towards
            # min_neighbors - 1 (guards.guard).
            code, s_fit, ds_dA, ds_dn = guard_state(A, same, min_neighbors, max_condition)
            if code == 0:
                A_inv = wp.inverse(A)
                own, img, dc, ddc = fo.image_energy_share(xi, h, gn, goff, gmin, images)
                M = (s_fit * own) * fo.variational_map(Vol_i, P, Fe, A_inv)
                if images != 0:
                    # The image's own stress and F (State.F_image): its energy's work is stored there.
                    Ag = df.floor_image_moment(i, x, body, nbr, count[i], h, gn, goff, gmin)
                    Mg = (s_fit * img) * fo.image_map(Vol_i, image_stress[i], F_image[i], Ag)
                    fi = fo.floor_image_forces(i, x, body, nbr, count[i], M, Mg, h, gn, goff, gmin, images, f)
                    if images == 2:
                        fi += fo.image_share_force(Vol_i, s_fit, dc, P, Fe, image_stress[i], F_image[i], gn)
            else:
                kind_el = 2
        elif kind_el == 0 and images != 0:
            fi = fo.paper_image_forces(i, x, body, nbr, count[i], volume, P, Fe, Finv, h, gn, goff, gmin, f)
        c6 = sm.poly6_coef(h)
        cf = c6  # the fit's weight constant: poly6's unless the model chose another
        if wp.static(weight != "poly6"):
            cf = fw.coef(h)
        c_spiky = sm.spiky_coef(h)
        c_visc = sm.viscosity_coef(h)
        for k in range(count[i]):
            j = nbr[i, k]
            xj = x[j]
            fj = vec3()
            if body[j] == bi and kind_el == 1:
                g = fo.variational_pair_force(M, xj - xi, h, cf)
                fj = -g
                fi += g
            elif body[j] == bi and kind_el == 0:
                g = fo.elastic_pair_force(Vol_i * volume[j], P, Finv, xj - xi, h, c_el)
                fj = g
                fi -= g
            if sph != 0:
                eta = pair_viscosity(visc_i, mat.viscosity[material[j]])
                VV = Vi * vol[j]
                VVp = VV
                if sph == 2:
                    VVp = Vpi * vol_p[j]
                half = scalar(0.5) * sph_pair_force(VV, VVp, pi, p[j], rho_i, rho_p[j], form, eta, xi - xj, v[j] - vi, h,
                                                   c6, c_spiky, c_visc, pair_repulsion_of(i, j, mass, material, mat))
                fj -= half
                fi += half
            wp.atomic_add(f, j, fj)
        if sph != 0 and images != 0:
            fi += image_pressure_forces(i, x, v, nbr, count[i], Vi, Vpi, pi, rho_i, vi, mass, rho, rho_p, rest_density,
                                        material, mat, h, c6, c_spiky, c_visc, gn, goff, gmin, images)
        wp.atomic_add(f, i, fi)

    @wp.kernel(enable_backward=False, module="unique")
    def update_deformation(
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        x_lo: wp.array(dtype=vec3),
        y_lo: wp.array(dtype=vec3),
        u: wp.array(dtype=vec3),
        body: wp.array(dtype=wp.int32),
        nbr: wp.array2d(dtype=wp.int32),
        count: wp.array(dtype=wp.int32),
        F_prev: wp.array(dtype=mat33),
        F_prev_lo: wp.array(dtype=mat33),
        h: scalar,
        min_neighbors: int,
        max_condition: scalar,
        gn: vec3,
        goff: scalar,
        gmin: scalar,
        images: int,
        Fg_prev: wp.array(dtype=mat33),
        far: wp.array(dtype=wp.int32),
        with_kept: int,
        F_out: wp.array(dtype=mat33),
        F_out_lo: wp.array(dtype=mat33),
        guard: wp.array(dtype=wp.int32),
        counters: wp.array(dtype=wp.int32),
        Fg_out: wp.array(dtype=mat33),
        share_out: wp.array(dtype=scalar),
        kept: wp.array(dtype=wp.int32),
        kept_A: wp.array(dtype=mat33),
        kept_code: wp.array(dtype=wp.int32),
        kept_scale: wp.array(dtype=scalar),
    ):
        """deformation.update_deformation with the neighbourhood guard of
        neighbors.select_neighbors evaluated here, on the moment matrix A of the fit; of a
        particle out of reach (``far``, ``out_of_reach``) on A alone, its B - A being 0.
        ``with_kept`` (``KeptFits``): a far particle marked sealed (``KEPT_MARKED``) keeps its
        A, guard and fade, and one whose fit is kept (``KEPT_FIT``) takes them from there."""
        i = wp.tid()
        A = mat33()
        B = mat33()
        same = scalar(0.0)
        code = int(0)
        s = scalar(0.0)
        held = int(0)
        if with_kept != 0 and far[i] != 0:
            held = kept[i]
        if held == KEPT_FIT:
            # Its row and their places as when they were kept: the same A, guard and fade.
            A = kept_A[i]
            code = kept_code[i]
            s = kept_scale[i]
        else:
            if far[i] != 0:
                # The same A and count (position_moments: the same terms in the same order), so the
                # same guard and counts; B - A stays 0, so F + F_lo is carried as the fit would.
                A, same = df.position_moments(i, x, body, nbr, count[i], h, gn, goff, gmin, 0)
            elif images != 0:
                A, B, same = df.fit_sums(i, x, y, x_lo, y_lo, body, nbr, count[i], h, gn, goff, gmin, images)
            else:
                # Each particle's displacement from the launch before (u): one load per
                # neighbour instead of y, x_lo and y_lo, the same sums bit for bit.
                A, B, same = df.fit_pair_sums(i, x, u, u, u, body, nbr, count[i], h, 1, gn, goff, gmin, 0)
            code, s, ds_dA, ds_dn = guard_state(A, same, min_neighbors, max_condition)
            if held == KEPT_MARKED:
                kept_A[i] = A
                kept_code[i] = code
                kept_scale[i] = s
                kept[i] = KEPT_FIT
        guard[i] = code
        F_new, F_new_lo = df.deformation_update(A, B, code, s, F_prev[i], F_prev_lo[i], COUNT_BODY + body[i], counters)
        F_out[i] = F_new
        F_out_lo[i] = F_new_lo
        Fg_new = F_new
        c = scalar(0.0)
        if images != 0:
            Fg_new, c = image_update(i, x, y, x_lo, y_lo, body, nbr, count[i], h, gn, goff, gmin, images, code, s,
                                     Fg_prev[i], F_new)
        Fg_out[i] = Fg_new
        share_out[i] = c

    @wp.kernel(enable_backward=False, module="unique")
    def set_moved(still: wp.array(dtype=wp.int32), x: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                  rest: wp.array(dtype=vec3), moved: wp.array(dtype=wp.int32)):
        """``moved[k]`` 1 where a particle of the resting set ``k - 1`` (``still``) starts the
        step off its place or with round-off carried (not ``held_still``)."""
        i = wp.tid()
        k = still[i]
        if k != 0:
            if held_still(i, still, x, x_lo, rest) == 0:
                moved[k] = 1

    @wp.kernel(enable_backward=False, module="unique")
    def displacements(x: wp.array(dtype=vec3), y: wp.array(dtype=vec3), x_lo: wp.array(dtype=vec3),
                      y_lo: wp.array(dtype=vec3), u: wp.array(dtype=vec3)):
        """Each particle's ``deformation.displacement`` over the step, for ``update_deformation``."""
        i = wp.tid()
        u[i] = df.displacement(x[i], y[i], x_lo[i], y_lo[i])

    return types.SimpleNamespace(constitutive_forces=constitutive_forces, update_deformation=update_deformation,
                                 displacements=displacements, set_moved=set_moved)


def reach_args(model, state_in, scratch) -> tuple:
    """``constitutive_forces``' ``reach, still, x_lo, rest, kept``: whether it marks the
    particles out of reach (``out_of_reach``, into ``scratch.far``, which ``update_deformation``
    reads; 2: also taking those ``KeptFits`` marked as such), the tools' ``still_particles``,
    ``state_in.x_lo``, the pinned places and ``KeptFits.kept``; 0 where no pinned set is at
    rest, or where the model has images (a particle's update then also writes its image's F)."""
    still = model.tools.still_particles() if model.tools is not None else None
    if still is None or model.image_plane is not None:
        return 0, scratch.far, state_in.x_lo, state_in.x_lo, scratch.far
    k = scratch.kept_fits
    if k is not None and k.on:
        return 2, still, state_in.x_lo, model.tools.rest_x, k.kept
    return 1, still, state_in.x_lo, model.tools.rest_x, scratch.far


def launch_constitutive_forces(model, state_in, state_out, dt, scratch, sph: bool, tape=None):
    """Plastic flow, stress, ``F^-1`` and every pair force in one launch; with ``sph`` the
    SPH pressure and volume ``scratch.pressure``, ``scratch.sph_volume`` of the neighbour pass
    (and, where a material is ``energy_spiky``, the pressure density ``state_out.pressure_density``
    with its volume ``scratch.pressure_volume()``).

    With ``tape`` (a recording ``wp.Tape``, the states with gradients) the launch is not
    recorded; the tape gets, in its place, the adjoints of what the differentiable kernels
    compute from the same outputs: SPH pressure and viscosity, elastic forces (eqs. 10-13 and
    the variational force, each for its own particles), the constitutive update (hand-written
    for the linear and non-Newtonian models, Warp's generated adjoint for the polynomial ones)
    and the densities the neighbour pass summed (``pressure.launch_state_densities_adjoint``)."""
    S = model.scalar
    own = sph and model.separate_pressure_density
    # Recorded with its generated adjoint (no tape given while one records), which replays
    # the images' forces' scatter (kept_through_backward).
    with kept_through_backward(state_out.force) if tape is None else contextlib.nullcontext():
        model.launches(
            kernels(S, model.fit_weight).constitutive_forces,
            model.particle_count,
            [
                state_in.x, state_in.v, state_in.F, state_in.F_lo, state_in.alpha, model.particle_material, model.material_arrays(),
                model.particle_body, model.particle_volume, scratch.pressure, scratch.sph_volume, state_out.density,
                pressure.pressure_density(model, state_out), scratch.pressure_volume() if own else scratch.sph_volume,
                state_out.neighbors, state_out.neighbor_count, S(model.support_radius), S(dt), 2 if own else int(sph),
                scratch.min_neighbors, S(scratch.max_condition), model.particle_mass, model.particle_rest_density,
                *model.image_args(), *forces.image_constitutive(model, state_out), *reach_args(model, state_in, scratch),
            ],
            [state_out.F_flowed, state_out.F_flowed_lo, state_out.alpha, state_out.stress, state_out.F_inv, state_out.force,
             scratch.counters, scratch.far],
            device=model.device,
            record_tape=tape is None,
        )
    if tape is None:
        return
    # The tape keeps this backward: one holding the tape itself made a reference cycle, which
    # left every dropped tape (a checkpointed backward's segments', a full tape at the next
    # forward) with all its step records to the cyclic collector (about 5 kB a step pending).
    tape_ref = weak_tape(tape)

    def backward():
        live = tape_ref()  # refused before any launch where the tape was freed
        # Reverse order of the differentiable step: density, constitutive, elastic, pressure.
        # The pressure's pairs go with the variational force's scatter pass where there is one
        # (as this kernel applies both in one loop), else in a pass of their own.
        kinds = set(model.material_elastic_force.numpy().tolist())
        if sph and 1 not in kinds:
            pressure.launch_pressure_forces_adjoint(model, state_in, state_out)
        if 0 in kinds:
            forces.launch_elastic_forces_adjoint(model, state_in, state_out)
        if 1 in kinds:
            forces.launch_variational_forces_adjoint(model, state_in, state_out, scratch.min_neighbors,
                                                     scratch.max_condition, sph)
            if sph:
                pressure.launch_pressure_image_forces_adjoint(model, state_in, state_out)
        plasticity.launch_constitutive_update_adjoint(model, state_in, state_out, dt, scratch.counters, live)
        if sph:
            pressure.launch_state_densities_adjoint(model, state_in.x, state_out)

    arrays = [state_in.x, state_in.v, state_in.F, state_in.alpha, state_out.F_flowed, state_out.alpha, state_out.stress,
              state_out.F_inv, state_out.force, state_out.density]
    if model.separate_pressure_density:
        arrays.append(pressure.pressure_density(model, state_out))
    if model.image_plane is not None:
        arrays += [state_out.image_stress, state_out.F_image_flowed]
    arrays += [getattr(model, name) for name in model.MATERIAL_FIELDS]
    tape.record_func(backward, arrays)


def launch_update_deformation(model, state_in, state_out, scratch, tape=None):
    """``deformation.launch_update_deformation`` that also evaluates the neighbourhood
    guards (into ``state_out.guard``) on the fit's own moment matrix. With ``tape``: not
    recorded, ``deformation.update_deformation_adjoint`` recorded in its place."""
    S = model.scalar
    images = model.image_plane is not None
    u = scratch.displacement
    k = scratch.kept_fits
    if not images:
        model.launches(kernels(S, model.fit_weight).displacements, model.particle_count, [state_in.x, state_out.x, state_in.x_lo, state_out.x_lo],
                  [u], device=model.device, record_tape=False)
    model.launches(
        kernels(S, model.fit_weight).update_deformation,
        model.particle_count,
        [
            state_in.x, state_out.x, state_in.x_lo, state_out.x_lo, u, model.particle_body, state_out.neighbors,
            state_out.neighbor_count, state_out.F_flowed, state_out.F_flowed_lo, S(model.support_radius), scratch.min_neighbors,
            S(scratch.max_condition), *model.image_args(), deformation.image_F_flowed(model, state_out), scratch.far,
            int(k is not None and k.on),
        ],
        [state_out.F, state_out.F_lo, state_out.guard, scratch.counters, state_out.F_image, state_out.image_share,
         *((scratch.far, state_out.F, scratch.far, scratch.pressure) if k is None or not k.on else
           (k.kept, k.A, k.code, k.scale))],
        device=model.device,
        record_tape=tape is None,
    )
    if tape is not None:
        tape.record_func(lambda: deformation.launch_update_deformation_adjoint(model, state_in, state_out,
                                                                               max_condition=scratch.max_condition,
                                                                               min_neighbors=scratch.min_neighbors),
                         [state_in.x, state_out.x, state_out.F_flowed, state_out.F]
                         + ([state_out.F_image_flowed, state_out.F_image, state_out.image_share] if images else []))
