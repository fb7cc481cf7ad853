"""The isotropic pressure force (``Material.pressure_force = "isotropic"``,
``pressure.launch_isotropic_pressure_forces``; docs/method.md §6, docs/physics.md "Still open",
the SPH pressure bullet): each particle's pressure applied as the stress ``-p_i I`` through its
neighbourhood's moment matrix, so that its own forces' virial is ``p_i V_i I`` at a free
surface too."""

import contextlib

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.sim import pressure


def _compressed_block(dtype=wp.float64, viscosity=0.0):
    """A 4-across ``isotropic`` block compressed by 5 % and jittered, stepped once so that its
    neighbour rows and densities are those of the compressed positions (``start``: the
    positions)."""
    mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, elastic_force="variational", viscosity=viscosity,
                                 pressure_force="isotropic")
    b = we.SceneBuilder(spacing=0.01)
    b.add_box(np.full(3, 0.02), np.full(3, 0.04), mat)
    model = b.finalize(dtype=dtype)
    rng = np.random.default_rng(1)
    x0 = model.particle_x0
    c = x0.mean(0)
    start, out = model.state(), model.state()
    start.x.assign(c + 0.95 * (x0 - c) + 0.05 * model.spacing * rng.normal(size=x0.shape))
    start.v.assign(0.05 * rng.normal(size=x0.shape))
    we.Solver(model, fused=False).step(start, out, 1.0e-6)
    return model, start, out


@contextlib.contextmanager
def _as(model, force):
    """Within the block ``model``'s one material has ``pressure_force = force`` at the same
    ``k_p`` (``energy_spiky``: the pair force of the same pressure, density and rest density)."""
    before = model.materials[0]
    model.set_material(0, before.replace(pressure_force=force, pressure_stiffness=before.pressure_stiffness))
    try:
        yield model
    finally:
        model.set_material(0, before)


def _own_pressure_forces(model, start, out, i, launch):
    """The pressure forces of particle ``i``'s own pressure alone (every other particle's rest
    density raised past its density, so its clamped pressure is 0), by ``launch``."""
    rest = model.particle_rest_density.numpy()
    keep = rest.copy()
    rest[np.arange(len(rest)) != i] = 1.0e30
    model.particle_rest_density.assign(rest)
    try:
        out.force.zero_()
        launch(model, start, out)
    finally:
        model.particle_rest_density.assign(keep)
    return out.force.numpy().copy()


def _forces(launch, model, start, out):
    out.force.zero_()
    launch(model, start, out)
    return out.force.numpy().copy()


def test_a_surface_particles_isotropic_pressure_has_an_isotropic_virial_and_exact_momenta():
    """A corner particle's own pressure forces have the virial ``p V I`` to round-off (float64),
    where the default pair force's (``energy_spiky``) pushes along its neighbours' directions;
    their sum and torque vanish, and so do those of every particle's together."""
    model, start, out = _compressed_block()
    x = start.x.numpy()
    i = int(np.argmin(x.sum(1)))  # a corner: every neighbour to one side
    rho = out.density.numpy()
    rho_p = pressure.pressure_density(model, out).numpy()
    k = model.pressure_stiffness.numpy()[0]
    p = k * (rho_p[i] - model.particle_rest_density.numpy()[i])
    assert p > 0.0
    pV = p * model.particle_mass.numpy()[i] / rho[i]

    f = _own_pressure_forces(model, start, out, i, pressure.launch_isotropic_pressure_forces)
    virial = (x - x[i]).T @ f
    assert np.abs(virial - pV * np.eye(3)).max() < 1e-9 * pV
    scale = np.abs(f).max()
    assert scale > 0.0
    assert np.abs(f.sum(0)).max() < 1e-12 * scale
    assert np.abs(np.cross(x - x.mean(0), f).sum(0)).max() < 1e-12 * scale * model.spacing

    with _as(model, "energy_spiky"):
        plain = _own_pressure_forces(model, start, out, i, pressure.launch_pressure_forces)
    v_plain = (x - x[i]).T @ plain
    # The pair force's virial at the corner is not isotropic: its deviator reaches 0.19 of its
    # mean normal part here (and the mean is 0.27 p V).
    mean = np.trace(v_plain) / 3.0
    assert mean > 0.0
    assert np.abs(v_plain - mean * np.eye(3)).max() > 0.1 * mean

    f = _forces(pressure.launch_isotropic_pressure_forces, model, start, out)
    assert np.abs(f.sum(0)).max() < 1e-12 * np.abs(f).max()
    assert np.abs(np.cross(x - x.mean(0), f).sum(0)).max() < 1e-12 * np.abs(f).max() * model.spacing


def test_the_isotropic_pressure_keeps_the_viscous_force_and_replaces_the_pair_pressure():
    """With viscosity and the pressure both on, the SPH force is the viscous force of the pair
    kernel (``energy_spiky``'s at ``k_p = 0``) plus the isotropic pressure force: the pair
    pressure is gone (its force would differ), the viscosity stays."""
    model, start, out = _compressed_block(viscosity=5.0)
    both = _forces(pressure.launch_isotropic_pressure_forces, model, start, out)
    # The pair kernel of an isotropic material: its viscosity alone.
    visc = _forces(pressure.launch_pressure_forces, model, start, out)
    k = model.pressure_stiffness.numpy()
    model.pressure_stiffness.zero_()
    try:
        assert np.abs(_forces(pressure.launch_isotropic_pressure_forces, model, start, out) - visc).max() \
            <= 1e-12 * np.abs(visc).max()
        with _as(model, "energy_spiky"):
            model.pressure_stiffness.zero_()
            spiky_visc = _forces(pressure.launch_pressure_forces, model, start, out)
        assert np.abs(spiky_visc - visc).max() <= 1e-12 * np.abs(visc).max()
    finally:
        model.pressure_stiffness.assign(k)
    with _as(model, "energy_spiky"):
        pairs = _forces(pressure.launch_pressure_forces, model, start, out)
    iso = both - visc
    assert np.abs(visc).max() > 0.0 and np.abs(iso).max() > 0.0
    assert np.abs((pairs - visc) - iso).max() > 0.1 * np.abs(iso).max()


def _numpy_isotropic_forces(model, x, out):
    """The isotropic pressure forces from docs/method.md §6 in numpy, every pair within ``h``
    found afresh: ``M_i = -p_i V_i (A_i + e (tr A_i / 3) I)^-1``, ``A_i = sum_j w_ij x_ij
    x_ij^T``, ``w = (1 - r/h)^2 h / r``, ``e`` the smoothstep from ``ISOTROPIC_REGULARISATION``
    at ``q = 0`` to 0 at ``ISOTROPIC_Q_FULL``; ``g_ij = w_ij M_i x_ij`` added to ``i``, taken
    from ``j``. Also each particle's ``q``."""
    h = model.support_radius
    mat = model.particle_material.numpy()
    k = model.pressure_stiffness.numpy()[mat]
    p = k * np.maximum(pressure.pressure_density(model, out).numpy() - model.particle_rest_density.numpy(), 0.0)
    V = model.particle_mass.numpy() / out.density.numpy()
    f = np.zeros_like(x)
    q = np.full(len(x), np.nan)
    for i in range(len(x)):
        d = x - x[i]
        r = np.linalg.norm(d, axis=1)
        near = (r > 0.0) & (r < h)
        w = (1.0 - r[near] / h) ** 2 * h / r[near]
        A = np.einsum("n,ni,nj->ij", w, d[near], d[near])
        a = np.trace(A) / 3.0
        if a <= 0.0:
            continue
        q[i] = np.linalg.det(A) / a ** 3
        t = np.clip(q[i] / pressure.ISOTROPIC_Q_FULL, 0.0, 1.0)
        e = pressure.ISOTROPIC_REGULARISATION * (1.0 - t * t * (3.0 - 2.0 * t))
        M = -p[i] * V[i] * np.linalg.inv(A + e * a * np.eye(3))
        g = w[:, None] * (d[near] @ M.T)
        f[i] += g.sum(0)
        f[np.flatnonzero(near)] -= g
    return f, q


@pytest.mark.parametrize("offset", [None, 0.0, 0.1])
def test_the_isotropic_pressure_forces_are_the_map_of_an_independent_numpy_sum(offset):
    """The kernel's forces (viscosity off) against ``_numpy_isotropic_forces`` to round-off
    (float64): in the compressed block (``offset`` None, every ``q`` at least
    ``ISOTROPIC_Q_FULL``: the map is ``A^-1``) and in the compressed one-layer sheet with its
    middle particle on the plane or 0.1 dx off it (the regularised map)."""
    if offset is None:
        model, start, out = _compressed_block()
        x = start.x.numpy()
    else:
        model, start, out, x, _ = _sheet(offset)
    f = _forces(pressure.launch_isotropic_pressure_forces, model, start, out)
    ref, q = _numpy_isotropic_forces(model, x, out)
    assert ((q >= pressure.ISOTROPIC_Q_FULL).all() if offset is None else (q < pressure.ISOTROPIC_Q_FULL).any())
    assert np.abs(ref).max() > 0.0
    assert np.abs(f - ref).max() < 1e-9 * np.abs(ref).max()


def test_a_step_with_the_isotropic_option_differs_from_energy_spikys_by_the_pressure_forces_alone():
    """A step with ``pressure_force = "isotropic"`` differs from one with ``energy_spiky`` at the
    same ``k_p`` by the isotropic pressure force less the pair force's, and by nothing else
    (the elastic force, the viscosity and the densities are the same)."""
    model, start, iso_out = _compressed_block(viscosity=5.0)
    probe = model.state()
    with _as(model, "energy_spiky"):
        plain = model.state()
        we.Solver(model, fused=False).step(start, plain, 1.0e-6)
        for name in ("density", "neighbors", "neighbor_count"):
            getattr(probe, name).assign(getattr(plain, name))
        pressure.pressure_density(model, probe).assign(plain.pressure_density)
        pairs = _forces(pressure.launch_pressure_forces, model, start, probe)
    iso = _forces(pressure.launch_isotropic_pressure_forces, model, start, probe)
    assert np.array_equal(plain.density.numpy(), iso_out.density.numpy())
    assert np.array_equal(plain.pressure_density.numpy(), iso_out.pressure_density.numpy())
    difference = iso_out.force.numpy().astype(np.float64) - plain.force.numpy()
    assert np.abs(iso - pairs).max() > 0.0
    assert np.abs(difference - (iso - pairs)).max() < 1e-9 * np.abs(iso - pairs).max()


def _isotropic_block(dtype=wp.float64, viscosity=5.0, **builder):
    """``_compressed_block``'s block and start with ``Material.pressure_force = "isotropic"`` (its
    default ``k_p``, ``energy_spiky``'s), not stepped."""
    mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, elastic_force="variational", viscosity=viscosity,
                                 pressure_force="isotropic")
    b = we.SceneBuilder(spacing=0.01)
    b.add_box(np.full(3, 0.02), np.full(3, 0.04), mat)
    if builder:
        b.add_ground(0.0, **builder)
    model = b.finalize(dtype=dtype)
    rng = np.random.default_rng(1)
    x0 = model.particle_x0
    c = x0.mean(0)
    start = model.state()
    start.x.assign(c + 0.95 * (x0 - c) + 0.05 * model.spacing * rng.normal(size=x0.shape))
    start.v.assign(0.05 * rng.normal(size=x0.shape))
    return model, start


@pytest.mark.parametrize("fused", [False, True])
def test_the_isotropic_option_is_energy_spikys_pressure_and_runs_unfused(fused):
    """``pressure_force = "isotropic"`` is ``energy_spiky``'s pressure (its spiky density, rest
    density and default ``k_p``) applied through the moments: its step's forces differ from the
    default's, and a fused solver runs it on the unfused kernels (its step is the unfused
    solver's bit for bit)."""
    model, start = _isotropic_block()
    assert model.materials[0].pressure_stiffness == pytest.approx(
        model.materials[0].replace(pressure_force="energy_spiky").pressure_stiffness)
    out = model.state()
    we.Solver(model, fused=fused).step(start, out, 1.0e-6)
    unfused = model.state()
    we.Solver(model, fused=False).step(start, unfused, 1.0e-6)
    for name in ("force", "density", "pressure_density", "x", "v", "F"):
        assert np.array_equal(getattr(out, name).numpy(), getattr(unfused, name).numpy()), name

    default, _ = _isotropic_block()
    default.set_material(0, default.materials[0].replace(pressure_force="energy_spiky"))
    assert np.array_equal(default.particle_rest_density.numpy(), model.particle_rest_density.numpy())
    plain = default.state()
    we.Solver(default, fused=fused).step(start, plain, 1.0e-6)
    assert np.abs(out.force.numpy() - plain.force.numpy()).max() > 1e-3 * np.abs(out.force.numpy()).max()


def test_the_isotropic_option_is_refused_where_it_is_not_built():
    """Beside another pressure force in one model (built or by ``set_material``), with floor
    images and with the yield test's pair pressure stress: a ValueError naming the option, the
    last before the step writes anything of ``state_out``."""
    iso = we.Material.from_young(1.0e5, 0.3, pressure_force="isotropic")
    b = we.SceneBuilder(spacing=0.01)
    b.add_box(np.full(3, 0.02), np.full(3, 0.04), iso)
    b.add_box((0.08, 0.02, 0.02), np.full(3, 0.04), iso.replace(pressure_force="spiky"))
    with pytest.raises(ValueError, match=r"pressure_force = 'isotropic' \(material 0\) is not allowed beside "
                                         r"pressure_force = 'spiky' \(material 1\)"):
        b.finalize()
    with pytest.raises(ValueError, match="'isotropic' .* not allowed beside pressure_force = 'energy'"):
        b2 = we.SceneBuilder(spacing=0.01)
        b2.add_box(np.full(3, 0.02), np.full(3, 0.04), iso)
        b2.add_box((0.08, 0.02, 0.02), np.full(3, 0.04), iso.replace(viscosity=1.0))
        two = b2.finalize()
        two.set_material(1, iso.replace(viscosity=1.0, pressure_force="energy"))
    model, start = _isotropic_block(dtype=wp.float32)
    out = model.state()
    with pytest.raises(ValueError, match=r"yield_with_pressure=True\) is not allowed with Material\.pressure_force = "
                                         "'isotropic'"):
        we.Solver(model, yield_with_pressure=True).step(start, out, 1.0e-6)
    assert not out.density.numpy().any() and not out.force.numpy().any()


def test_the_benchmarks_context_runs_the_isotropic_option_unfused():
    """``benchmarks/isotropic_pressure.py``: a ``Solver`` made in ``isotropic_pressure()`` runs
    unfused on a model made ``isotropic`` (each material keeping its ``k_p``), whose step is
    that of a model built ``isotropic`` bit for bit; ``on=False`` leaves the force alone;
    outside the block ``Solver`` is as before."""
    from benchmarks.isotropic_pressure import isotropic_pressure

    model, start = _isotropic_block()
    built = model.state()
    we.Solver(model, fused=False).step(start, built, 1.0e-6)
    default, _ = _isotropic_block()
    default.set_material(0, default.materials[0].replace(pressure_force="energy_spiky"))
    k_p = default.materials[0].pressure_stiffness
    with isotropic_pressure(False):
        assert not we.Solver(default).fused and default.materials[0].pressure_force == "energy_spiky"
    with isotropic_pressure():
        s = we.Solver(default)
    assert not s.fused and default.materials[0].pressure_force == "isotropic"
    assert default.materials[0].pressure_stiffness == k_p
    out = default.state()
    s.step(start, out, 1.0e-6)
    assert np.array_equal(out.force.numpy(), built.force.numpy())
    assert we.Solver(default).fused


def test_the_column_history_reports_the_end_once_with_its_rate():
    """``column_history`` (``isotropic_pressure.py column --every``): a run whose end came just
    after a report (101 steps, a report every 50) printed its state at step 100 and again at
    101, the second with a NaN rate (one sample since the report). Now a report within a tenth
    of the interval of the end is left to the end's, which reports once, its rate fitted over
    the last tenth of the interval as every other report's."""
    from benchmarks import validation as v
    from benchmarks.isotropic_pressure import column_history

    mat = we.Material.from_young(1.5e5, 0.3, density=v.RHO, yield_stress=1.0e3)
    printed = []
    with column_history(1.0, 2, 2.0, printed.append) as rows:
        model = v._free_column(we, mat, 2, 2, 0.01)[0]
        solver = we.Solver(model)
        v._swap_run(model, solver, model.state(), model.state(), 0.5 * model.stable_dt(), 101)
    per = 101 / 2.0  # steps per period: a report every round(per) = 50 steps
    assert [r["period"] for r in printed] == pytest.approx([50 / per, 101 / per]), printed
    assert rows == printed and all(np.isfinite(r["rate_pct_per_s"]) for r in printed), printed


def _sheet(offset):
    """A one-particle-thick 5 x 5 sheet of ``isotropic`` material compressed in its plane to
    0.85 of its spacing, its middle particle ``i`` moved ``offset`` spacings out of the plane,
    stepped once for its neighbour rows and densities: ``(model, start, out, x, i)``."""
    dx = 0.01
    mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, elastic_force="variational", pressure_force="isotropic")
    g = dx * np.stack(np.meshgrid(np.arange(5), np.arange(5), indexing="ij"), -1).reshape(-1, 2)
    pts = np.stack([g[:, 0], np.zeros(len(g)), g[:, 1]], 1) + 0.05
    b = we.SceneBuilder(spacing=dx)
    b.add_particles(pts, mat)
    model = b.finalize(dtype=wp.float64)
    c = pts.mean(0)
    x = c + 0.85 * (pts - c)
    i = len(pts) // 2
    x[i, 1] += offset * dx
    start, out = model.state(), model.state()
    start.x.assign(x)
    we.Solver(model, fused=False).step(start, out, 1.0e-9)
    return model, start, out, x, i


def _sheet_own_forces(offset):
    """``_sheet``'s middle particle's pressure ``p V`` and its own pressure forces (every other
    particle's pressure off), with the positions."""
    model, start, out, x, i = _sheet(offset)
    p = model.pressure_stiffness.numpy()[0] * (pressure.pressure_density(model, out).numpy()[i]
                                               - model.particle_rest_density.numpy()[i])
    pV = p * model.particle_mass.numpy()[i] / out.density.numpy()[i]
    return pV, _own_pressure_forces(model, start, out, i, pressure.launch_isotropic_pressure_forces), x, i


def test_a_flat_layers_isotropic_pressure_pushes_within_it_and_stays_bounded_off_it():
    """A particle of a compressed one-layer sheet (its moment matrix singular in the plane's
    normal, or nearly so when it sits a little off the plane): its pressure still pushes its
    neighbours apart within the plane (a flat layer, a line or a pair of particles is not left
    without pressure), and its forces stay within a few ``p V / dx`` however close to the plane
    it sits, where ``A^-1`` alone gives ``p V / offset`` normal to it (and nothing at all on
    the plane); sum and torque exact."""
    dx = 0.01
    for offset in (0.0, 1.0e-4, 1.0e-3, 1.0e-2, 0.1, 0.2, 0.3):
        pV, f, x, i = _sheet_own_forces(offset)
        assert pV > 0.0
        scale = np.abs(f).max()
        # Measured: 0.30 p V / dx up to 0.01 dx off, 5.0 at 0.2 dx (the p V / d of the exact
        # map where its regularisation ends); the exact map alone gave 1000 at 0.001 dx.
        assert scale < 6.0 * pV / dx, offset
        assert np.abs(f.sum(0)).max() < 1e-12 * scale
        assert np.abs(np.cross(x - x.mean(0), f).sum(0)).max() < 1e-12 * scale * dx
        virial = (x - x[i]).T @ f
        # In the plane (x, z) most of p V I, as the isotropic stress would carry.
        assert virial[0, 0] > 0.8 * pV and virial[2, 2] > 0.8 * pV, offset


def test_the_isotropic_kernels_generated_adjoint_matches_central_differences_off_a_flat_layer():
    """Where the moments are regularised (a particle 0.1 dx off a compressed one-layer sheet,
    ``q`` below ``ISOTROPIC_Q_FULL``), Warp's generated adjoint of ``isotropic_pressure_forces``
    in the positions (densities held) is its float64 central difference."""
    model, start, out, x, i = _sheet(0.1)
    xs = x - x[i]
    r = np.linalg.norm(xs, axis=1)
    h = model.support_radius
    near = (r > 0) & (r < h)
    w = (1 - r[near] / h) ** 2 * h / r[near]
    A = (w[:, None, None] * xs[near][:, :, None] * xs[near][:, None, :]).sum(0)
    assert 0.0 < np.linalg.det(A) / (np.trace(A) / 3) ** 3 < pressure.ISOTROPIC_Q_FULL
    kernel = pressure.isotropic_kernels(wp.float64).isotropic_pressure_forces
    rng = np.random.default_rng(3)
    weights = wp.array(rng.normal(size=x.shape), dtype=wp.vec3d)
    counters = wp.zeros(pressure.COUNT_PRESSURE_REGULARISED + 1, dtype=wp.int32)

    def loss(pos, grad=False):
        xa = wp.array(pos, dtype=wp.vec3d, requires_grad=grad)
        f = wp.zeros(len(pos), dtype=wp.vec3d, requires_grad=grad)
        total = wp.zeros(1, dtype=wp.float64, requires_grad=grad)
        tape = wp.Tape()
        with tape:
            wp.launch(kernel, len(pos), [xa, model.particle_mass, out.density, pressure.pressure_density(model, out),
                                         model.particle_rest_density, model.particle_material, model.material_arrays(),
                                         out.neighbors, out.neighbor_count, wp.float64(h)], [f, counters])
            wp.launch(_dot, len(pos), [f, weights], [total])
        if grad:
            tape.backward(loss=total)
            return xa.grad.numpy().copy()
        return total.numpy()[0]

    g = loss(x, grad=True)
    assert np.abs(g).max() > 0.0
    eps = 1.0e-7 * model.spacing
    for k in (i, 0):
        for c in range(3):
            xp, xm = x.copy(), x.copy()
            xp[k, c] += eps
            xm[k, c] -= eps
            fd = (loss(xp) - loss(xm)) / (2 * eps)
            assert g[k, c] == pytest.approx(fd, rel=1e-5, abs=1e-7 * np.abs(g).max()), (k, c)


@wp.kernel(module="unique")
def _dot(f: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), total: wp.array(dtype=wp.float64)):
    wp.atomic_add(total, 0, wp.dot(f[wp.tid()], w[wp.tid()]))


def test_the_isotropic_pressure_with_floor_images_is_refused_before_any_kernel_runs():
    """Floor images, whose pressure is a pair force: ``finalize`` and ``set_material`` refuse
    the ``isotropic`` material where it is given (docs/errors.md: before any kernel runs), and
    a direct call of the launch on such a model is refused before it writes anything."""
    with pytest.raises(ValueError, match=r"Material\.pressure_force = 'isotropic' \(material 0\) is not allowed with "
                                         r"floor images \(add_ground\(images=True\)\)"):
        _isotropic_block(dtype=wp.float32, images=True)
    mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, elastic_force="variational")
    b = we.SceneBuilder(spacing=0.01)
    b.add_box(np.full(3, 0.02), np.full(3, 0.04), mat)
    b.add_ground(0.0, images=True)
    images = b.finalize(dtype=wp.float32)
    with pytest.raises(ValueError, match=r"'isotropic' \(material 0\) is not allowed with floor images"):
        images.set_material(0, mat.replace(pressure_force="isotropic"))
    assert images.materials[0].pressure_force == "energy_spiky"
    start, out = images.state(), images.state()
    with pytest.raises(ValueError, match=r"Material\.pressure_force = 'isotropic' is not allowed with floor images"):
        pressure.launch_isotropic_pressure_forces(images, start, out)
    assert not out.density.numpy().any() and not out.force.numpy().any()


def test_the_isotropic_pressure_adds_more_bulk_stiffness_than_energy_spikys_at_the_same_k_p():
    """The middle particle of an 8-across lattice compressed evenly by 0.1 % in each direction:
    with the default ``k_p = 0.46 K / rho0`` of both, the isotropic force's stress ``-p I`` adds
    0.44 ``K`` per unit volumetric strain, ``energy_spiky``'s pair virial (the stress it
    carries) 0.28 ``K``, so ``isotropic`` adds 1.6 x the pressure stiffness (and stays under
    the ``rho0 k_p = 0.46 K`` that ``Model.stable_dt`` allows for)."""
    added = {}
    for force in ("energy_spiky", "isotropic"):
        mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, elastic_force="variational", pressure_force=force)
        K = mat.lam + 2.0 * mat.mu / 3.0
        b = we.SceneBuilder(spacing=0.01)
        b.add_box(np.full(3, 0.02), np.full(3, 0.08), mat)
        model = b.finalize(dtype=wp.float64)
        x0 = model.particle_x0
        c = x0.mean(0)
        i = int(np.argmin(np.linalg.norm(x0 - c, axis=1)))
        start, out = model.state(), model.state()
        start.x.assign(c + 0.999 * (x0 - c))
        we.Solver(model, fused=False).step(start, out, 1.0e-9)
        ev = 3.0 * 0.001
        if force == "isotropic":
            p = model.pressure_stiffness.numpy()[0] * (pressure.pressure_density(model, out).numpy()[i]
                                                       - model.particle_rest_density.numpy()[i])
        else:
            sigma = wp.zeros(model.particle_count, dtype=wp.mat33d)
            pressure.launch_pressure_stress(model, start, out, sigma)
            p = -np.trace(sigma.numpy()[i]) / 3.0
        added[force] = p / (K * ev)
        assert model.pressure_stiffness.numpy()[0] * 1000.0 == pytest.approx(0.46 * K)
    assert added["isotropic"] == pytest.approx(0.44, abs=0.02)
    assert added["energy_spiky"] == pytest.approx(0.28, abs=0.02)
    assert added["isotropic"] < 0.46


def test_a_lone_pair_of_isotropic_particles_pushed_together_repels():
    """Two particles of an ``isotropic`` body of two, pushed from one spacing to half of it
    (each one's moments a single direction, singular): they push each other apart along their
    line, equal and opposite, with 0.97 of each one's ``p V`` as the virial along it (the
    added diagonal's 1 / (1 + 0.1 / 3)); ``A^-1``'s switch gave them no pressure at all."""
    dx = 0.01
    mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, elastic_force="variational", pressure_force="isotropic")
    b = we.SceneBuilder(spacing=dx)
    b.add_particles(np.array([[0.05, 0.05, 0.05], [0.05 + dx, 0.05, 0.05]]), mat)
    model = b.finalize(dtype=wp.float64)
    start, out = model.state(), model.state()
    x = np.array([[0.05, 0.05, 0.05], [0.05 + 0.5 * dx, 0.05, 0.05]])
    start.x.assign(x)
    we.Solver(model, fused=False).step(start, out, 1.0e-9)
    p = model.pressure_stiffness.numpy()[0] * (pressure.pressure_density(model, out).numpy()
                                               - model.particle_rest_density.numpy())
    pV = p * model.particle_mass.numpy() / out.density.numpy()
    assert (pV > 0.0).all()
    out.force.zero_()
    pressure.launch_isotropic_pressure_forces(model, start, out)
    f = out.force.numpy()
    assert f[0, 0] < 0.0 < f[1, 0]
    assert np.abs(f[:, 1:]).max() == 0.0 and f.sum(0) == pytest.approx(np.zeros(3), abs=1e-12 * np.abs(f).max())
    assert f[1, 0] * 0.5 * dx == pytest.approx(pV.sum() / (1.0 + 0.1 / 3.0), rel=1e-9)


def test_a_model_of_several_materials_switches_to_and_from_the_isotropic_pressure_at_once():
    """Every material ``isotropic`` or none (``check_pressure_forces``), so one ``set_material``
    at a time cannot switch a model of two materials (here a body and its elastic particle
    floor): ``Model.set_materials`` switches them together, and back; the benchmarks' context
    (``benchmarks/isotropic_pressure.py``) uses it, so it runs such a model; a refused
    combination leaves the model as it was."""
    from benchmarks.isotropic_pressure import isotropic_pressure

    mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, yield_stress=100.0, flow_rate=10.0)
    b = we.SceneBuilder(spacing=0.01)
    b.add_box(np.full(3, 0.02), np.full(3, 0.04), mat, name="a")
    b.add_particle_floor("a", elastic=True, margin=0.02)
    model = b.finalize(dtype=wp.float32)
    assert len(model.materials) == 2
    before = list(model.materials)
    with isotropic_pressure():
        we.Solver(model)
    assert [m.pressure_force for m in model.materials] == ["isotropic", "isotropic"]
    assert [m.pressure_stiffness for m in model.materials] == [m.pressure_stiffness for m in before]
    assert model.material_pressure_force.numpy().tolist() == [3, 3]
    with pytest.raises(ValueError, match=r"'isotropic' \(material 1\) is not allowed beside pressure_force = 'energy'"):
        model.set_materials([before[0].replace(pressure_force="energy"), model.materials[1]])
    assert [m.pressure_force for m in model.materials] == ["isotropic", "isotropic"]
    model.set_materials(before)
    assert model.materials == before and model.material_pressure_force.numpy().tolist() == [2, 2]
def test_the_benchmarks_column_history_reports_the_run_it_watches_without_changing_it():
    """``benchmarks/isotropic_pressure.py --every``: the column's state is reported every given
    fraction of the run, its last report is the row's end (shortening, lean, closest
    neighbours, yield front), the column shortens between reports under its rising weight, and
    watching leaves the run as it was, bit for bit."""
    from benchmarks import validation
    from benchmarks.isotropic_pressure import column_history

    kw = dict(resolution=4, width=0.04, floor="slip_ghost_particles", periods=0.5, elastic_periods=0.05)
    plain = validation.near_yield_column(**kw)
    seen = []
    with column_history(0.25, 4, 0.5, out=seen.append) as rows:
        row = validation.near_yield_column(**kw)
    assert rows == seen and len(rows) == 2
    assert rows[0]["period"] == pytest.approx(0.25, abs=0.01) and rows[-1]["period"] == pytest.approx(0.5, abs=0.01)
    assert 0.0 < rows[0]["shortening"] < rows[-1]["shortening"]
    assert rows[-1]["shortening"] == row["shortening"] == plain["shortening"]
    assert rows[-1]["lean_dx"] == pytest.approx(row["lean"], rel=1e-12, abs=1e-15)
    assert rows[-1]["nearest_dx"] == row["nearest_neighbour_min"]
    assert np.isnan(rows[-1]["highest_yielded_depth"]) == np.isnan(row["highest_yielded_depth"])
    assert validation._swap_run is not None and validation._free_column.__name__ == "_free_column"


def _pair(requires_grad=False):
    """Two ``isotropic`` particles of a body of two pushed from one spacing to half of it (each
    one's moments a single direction: ``q = 0``)."""
    dx = 0.01
    mat = we.Material.from_young(1.0e5, 0.3, density=1000.0, elastic_force="variational", pressure_force="isotropic")
    b = we.SceneBuilder(spacing=dx)
    b.add_particles(np.array([[0.05, 0.05, 0.05], [0.05 + dx, 0.05, 0.05]]), mat)
    model = b.finalize(dtype=wp.float64, requires_grad=requires_grad)
    start = model.state()
    start.x.assign(np.array([[0.05, 0.05, 0.05], [0.05 + 0.5 * dx, 0.05, 0.05]]))
    return model, start


@pytest.mark.parametrize("scene", ["pair", "sheet", "block"])
@pytest.mark.parametrize("fused", [False, True])
def test_the_solver_counts_the_particles_whose_isotropic_pressure_map_is_regularised(scene, fused):
    """``Solver.guard_counts()["pressure_regularised"]``: the particle-steps whose moments had
    ``q < ISOTROPIC_Q_FULL`` (the map regularised), as an independent numpy sum of the
    moments finds them: every particle of a lone pair and of a one-layer sheet at every step,
    none of a compressed and jittered block (its surface included); ``reset_counts`` zeroes it."""
    if scene == "pair":
        model, start = _pair()
    elif scene == "sheet":
        model, start, _, _, _ = _sheet(0.0)
    else:
        model, start = _isotropic_block(viscosity=0.0)
    solver = we.Solver(model, fused=fused)
    a, b = model.state(), model.state()
    a.x.assign(start.x)
    steps = 3
    expected = 0
    for _ in range(steps):
        x = a.x.numpy()
        solver.step(a, b, 1.0e-7)
        _, q = _numpy_isotropic_forces(model, x, b)
        expected += int((q < pressure.ISOTROPIC_Q_FULL).sum())
        a, b = b, a
    counts = solver.guard_counts()
    assert counts["pressure_regularised"] == expected
    n = model.particle_count
    assert expected == {"pair": steps * n, "sheet": steps * n, "block": 0}[scene]
    solver.reset_counts()
    assert solver.guard_counts()["pressure_regularised"] == 0


def test_a_taped_step_and_its_backward_count_the_regularised_particles_once():
    """The count is a diagnostic off the gradient path: a step recorded on a ``wp.Tape`` counts
    the lone pair's two particles once, and the backward pass (Warp's generated adjoint, whose
    replayed forward skips the atomic count) adds none."""
    model, start = _pair(requires_grad=True)
    solver = we.Solver(model, fused=False)
    out = model.state()
    tape = wp.Tape()
    with tape:
        solver.step(start, out, 1.0e-7)
    assert solver.guard_counts()["pressure_regularised"] == 2
    seed = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    tape.backward(grads={out.v: wp.array(seed, dtype=wp.vec3d)})
    assert solver.guard_counts()["pressure_regularised"] == 2
    g = start.x.grad.numpy().copy()
    assert np.abs(g).max() > 0.0
    # A rollout reports it with the other guards' counts, its taped forward's steps once each.
    from warp_esph.rollout import Rollout

    rollout = Rollout(model, 2, 1.0e-7, frames=[2])
    rollout.forward(start.x.numpy())
    assert rollout.guard_counts()["pressure_regularised"] == 2 * 2
@pytest.mark.parametrize("case", ["column", "slump"])
def test_the_benchmark_passes_its_fit_weight_to_the_run_and_refuses_an_unknown_one(monkeypatch, capsys, case):
    """``benchmarks/isotropic_pressure.py --fit-weight``: the weight reaches the validation run
    (the column's and the slump's rows are compared poly6 against biweight, docs/physics.md),
    poly6 without it, and an unknown one is refused by name with the allowed ones."""
    from benchmarks import isotropic_pressure, validation

    seen = []

    def record(*args, **kwargs):
        seen.append(kwargs.get("fit_weight"))
        return {"fit_weight": kwargs.get("fit_weight")}

    monkeypatch.setattr(validation, "near_yield_column" if case == "column" else "slump", record)
    isotropic_pressure.main([case, "--fit-weight", "biweight", "--baseline"])
    isotropic_pressure.main([case, "--baseline"])
    assert seen == ["biweight", "poly6"]
    assert '"fit_weight": "biweight"' in capsys.readouterr().out
    monkeypatch.undo()
    with pytest.raises(ValueError, match=r"^fit_weight = 'gauss' is not allowed: must be one of 'poly6', 'biweight'"):
        isotropic_pressure.main([case, "--fit-weight", "gauss", "--baseline"])
def test_the_benchmarks_slump_save_writes_the_final_particles_without_changing_the_run(tmp_path, capsys):
    """``benchmarks/isotropic_pressure.py slump --save``: the .npz holds the slump's final
    particles (its free ones are the ones the row measured: their top and the axis layers'
    heights agree), their F and alpha as the run left them, and saving leaves the run as it
    was, bit for bit; a save path in no folder, or with the column case, is refused naming it."""
    from benchmarks import validation
    from benchmarks.isotropic_pressure import final_slump_state, main

    kw = dict(resolution=4, duration=0.02, samples=2)
    plain = validation.slump(0.3, **kw)
    path = tmp_path / "pile.npz"
    with final_slump_state(str(path)):
        row = validation.slump(0.3, **kw)
    assert validation.slump_model.__name__ == "slump_model" and validation._swap_run.__name__ == "_swap_run"
    assert row["h_over_H0"] == plain["h_over_H0"] and row["thickness_over_H0"] == plain["thickness_over_H0"]
    d = np.load(path)
    free, dx = d["free"], float(d["spacing"])
    assert free.sum() == row["particles"] and d["x"].shape == d["x0"].shape == (len(free), 3)
    assert d["F"].shape == (len(free), 3, 3) and d["alpha"].shape == d["volume"].shape == (len(free),)
    x = d["x"].astype(np.float64)[free]
    assert (x[:, 1].max() + 0.5 * dx) / 0.1 == pytest.approx(row["top_max_over_H0"], rel=1e-12, abs=0.0)
    # The release has moved the pile: its F is no longer the identity everywhere.
    assert np.abs(d["F"][free] - np.eye(3)).max() > 1e-6
    x0 = d["x0"].astype(np.float64)[free]
    depth0 = x0[:, 1].max() + 0.5 * dx - x0[:, 1]
    _, layers = validation.pile_profile(x0, x, depth0, np.zeros(len(x)), np.zeros(len(x)), 0.05, dx, 0.1)
    assert [L["y_over_H0"] for L in layers] == pytest.approx([L["y_over_H0"] for L in row["axis_layers"]], rel=1e-12)
    for argv in (["slump", "--save", str(tmp_path / "none" / "p.npz")], ["column", "--save", str(path)]):
        with pytest.raises(SystemExit):
            main(argv)
        assert "--save = " in capsys.readouterr().err
