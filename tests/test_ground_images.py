"""The imaged ground (``SceneBuilder.add_ground(images=True)``) is a rough floor of the fits
whatever its positive friction, and a frictionless one at friction 0, where the images move
with their particles: docs/physics.md, "The imaged ground is rough whatever its friction"."""

import warnings

import numpy as np
import pytest

import warp as wp

import warp_esph as we

from energy_fd import corotated_psi, image_energy_share

DX = 0.02


def test_the_imaged_grounds_friction_picks_how_its_images_move():
    """Friction 0 makes the images move with their particles (``Model.image_motion``, the
    kernels' ``images`` argument 2); any positive friction keeps them at rest (1); no images, 0."""
    def motion(friction, images=True):
        b = we.SceneBuilder(spacing=DX)
        b.add_box((0.0, 0.03, 0.0), (0.04,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0))
        b.add_ground(0.0, friction=friction, images=images)
        m = b.finalize()
        assert m.image_args()[3] == m.image_motion
        return m.image_motion

    assert motion(0.0) == we.model.IMAGES_MOVING == 2
    assert motion(1e-3) == motion(5.0) == we.model.IMAGES_AT_REST == 1
    assert motion(0.0, images=False) == we.model.IMAGES_NONE == 0


@pytest.mark.parametrize("built, written, refused", [
    (0.0, 0.5, "plane_friction"), (0.3, 0.0, "plane_friction"), (0.3, 0.7, None),
    (0.0, None, "plane_offset"), (0.3, None, "plane_normal")])
def test_an_imaged_grounds_friction_or_plane_written_after_the_build_is_refused_at_the_step(built, written, refused):
    """The images are made with the model: at rest or moving with their particles as the
    ground's friction was positive or 0 (``Model.image_motion``), at the plane it was built at.
    Written in place afterwards (a caller, an optimiser of ``plane_friction``'s gradient), a
    frictionless imaged ground given a friction ran on frictionless, a rough one given
    friction 0 ran rough, and a moved ground left its images under the old plane, all without
    a word; the step now refuses each by name before any launch (``Model.check_colliders``).
    A positive friction changed to another positive one is the contact's and runs."""
    b = we.SceneBuilder(spacing=DX)
    b.add_box((0.0, 2.0 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0))
    b.add_plane((1.0, 0.0, 0.0), -1.0)  # a plane before the ground: its row is found by its images
    b.add_ground(0.0, friction=built, images=True)
    m = b.finalize()
    s = we.Solver(m)
    a, c = m.state(), m.state()
    s.step(a, c, 1e-4)
    if written is not None:
        m.plane_friction.assign(np.array([0.2, written], dtype=np.float32))
    elif refused == "plane_offset":
        m.plane_offset.assign(np.array([-1.0, 0.005], dtype=np.float32))
    else:
        m.plane_normal.assign(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.1]], dtype=np.float32))
    if refused is None:
        s.step(a, c, 1e-4)
        return
    want = {"plane_friction": rf"model.plane_friction\[1\] = {written!r} is not allowed: the imaged ground was built "
                              rf"with friction {built!r}, so its images (move|stand still).*add_ground\(friction={written!r}, "
                              r"images=True\)",
            "plane_offset": r"model.plane_offset\[1\] = 0.005 is not allowed: the imaged ground's images are made at "
                            r"the plane it was built at \(normal \(0.0, 1.0, 0.0\), offset 0.0\)",
            "plane_normal": r"model.plane_normal\[1\] = \(0.0, 1.0, 0.1\) is not allowed"}[refused]
    before = c.x.numpy().copy()
    with pytest.raises(ValueError, match=want):
        s.step(a, c, 1e-4)
    np.testing.assert_array_equal(c.x.numpy(), before)  # refused before any launch


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -0.5])
@pytest.mark.parametrize("built", [0.0, 0.3])
def test_an_imaged_grounds_friction_not_a_finite_number_at_least_0_is_refused_at_the_build_and_at_the_step(built, bad):
    """``add_ground`` refuses a friction that is NaN, inf or negative by name; written into
    ``plane_friction`` after the build, the step took it without a word on a rough imaged
    ground (neither 0 nor changed from 0: the imaged ground's rule of ``check_colliders``) and ran the contact on it,
    and on a frictionless one advised building again with that friction. The step now refuses
    it by name, before any launch."""
    b = we.SceneBuilder(spacing=DX)
    b.add_box((0.0, 2.0 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0))
    with pytest.raises(ValueError, match=rf"^friction = {bad!r} is not allowed: must be "):
        b.add_ground(0.0, friction=bad, images=True)
    b.add_ground(0.0, friction=built, images=True)
    m = b.finalize()
    s = we.Solver(m)
    a, c = m.state(), m.state()
    s.step(a, c, 1e-4)
    m.plane_friction.assign(np.array([bad], dtype=np.float32))
    before = c.x.numpy().copy()
    with pytest.raises(ValueError, match=rf"^model.plane_friction\[0\] = {bad!r} is not allowed: the imaged ground's friction "
                                         rf"is a finite number >= 0 \(built {built!r}; add_ground's friction\)$"):
        s.step(a, c, 1e-4)
    np.testing.assert_array_equal(c.x.numpy(), before)  # refused before any launch


def test_the_colliders_are_checked_on_the_values_read_with_the_parameters(monkeypatch):
    """The check of the imaged plane (``Model.check_colliders``, then ``check_image_plane``) read
    the plane arrays at every step, on a GPU a transfer of its own (each read of a device array
    waits for the device). The step's one read of the parameter arrays now brings every static
    collider's values (on a GPU copied into the same buffer, ``Model._read_staged``, run here on
    the CPU in place of its views, ``_staged_reads``): a step reads none of its own, the values
    read are the arrays' (the imaged ground in row 1, after another plane; a sphere), and a
    write is still refused at the next step; called outside a step, the check reads them itself."""
    b = we.SceneBuilder(spacing=DX)
    b.add_box((0.0, 2.0 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0))
    b.add_plane((1.0, 0.0, 0.0), -1.0)
    b.add_ground(0.0, friction=0.3, images=True)
    b.add_sphere_collider((0.0, 1.0, 0.0), 0.25, friction=0.2)
    m = b.finalize()
    monkeypatch.setattr(m, "_staged_reads", True, raising=False)
    own = []
    values = m._collider_values
    monkeypatch.setattr(m, "_collider_values", lambda: own.append(1) or values())
    s = we.Solver(m)
    a, c = m.state(), m.state()
    for _ in range(3):
        s.step(a, c, 1e-4)
        a, c = c, a
    assert own == []
    rows, colliders = m._read_staged()
    np.testing.assert_array_equal(colliders, np.array(
        [0.5, 0.3, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0,  # the planes' frictions, offsets, normals
         0.2, 0.25, 0.0, 1.0, 0.0], dtype=np.float32))  # the sphere's friction, radius, centre (no box: none of its)
    np.testing.assert_array_equal(rows, np.stack([getattr(m, f).numpy() for f in m.MATERIAL_FIELDS]))
    m.plane_offset.assign(np.array([-1.0, 0.005], dtype=np.float32))
    with pytest.raises(ValueError, match=r"^model.plane_offset\[1\] = 0.005 is not allowed"):
        s.step(a, c, 1e-4)
    assert own == []
    with pytest.raises(ValueError, match=r"^model.plane_offset\[1\] = 0.005 is not allowed"):
        m.check_colliders()
    assert own == [1]
    m.plane_offset.assign(np.array([-1.0, 0.0], dtype=np.float32))
    m.sphere_radius.assign(np.array([-0.25], dtype=np.float32))
    with pytest.raises(ValueError, match=r"^model.sphere_radius\[0\] = -0.25 is not allowed: must be finite and > 0 "
                                         r"\(built 0.25\)$"):
        s.step(a, c, 1e-4)
    assert own == [1]


def _thrown_box(friction, images, v0=0.5, steps=125, viscosity=0.0):
    """A 4^3 elastic box (2 cm spacing, E 200 kPa, float64, the default solver) standing on
    the ground, given ``v0`` sideways, ``steps`` steps at half the stable step (0.01 s on the
    images): its mean x-velocity at the end, the ground's reported x-force averaged over the
    steps, the momentum's x-rate, and the end state (``State``)."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 2.0 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0, viscosity=viscosity))
    b.add_ground(0.0, friction=friction, images=images)
    m = b.finalize(dtype=wp.float64)
    s = we.Solver(m)
    dt = 0.5 * m.stable_dt(fit=s.asked_fit)
    a, c = m.state(), m.state()
    v = a.v.numpy()
    v[:, 0] = v0
    a.v.assign(v)
    mass = m.particle_mass.numpy()
    p0 = float((mass * a.v.numpy()[:, 0]).sum())
    reported = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(steps):
            s.step(a, c, dt)
            a, c = c, a
            reported += s.collider_reactions(a)["plane0"][0][0] / steps
    p1 = float((mass * a.v.numpy()[:, 0]).sum())
    return p1 / mass.sum(), reported, (p1 - p0) / (steps * dt), a


def test_the_imaged_ground_holds_a_sliding_box_whatever_its_friction():
    """The images are at rest over each step in the fits, so a bottom layer sliding over them
    is sheared and its stress pulls the body back, and the body rests off the plane, where
    the friction acts: the box thrown at 0.5 m/s from half a spacing above the plane keeps
    0.196 of its speed after 0.01 s (0.0978 m/s; asked: below half), to the bit the same with
    friction 0.01 and 5; the ground's row reports the force (the momentum's rate, 20.4 N against
    the box's 5.0 N weight). On the plain frictionless ground it keeps its speed to round-off."""
    vx, reported, rate, end = _thrown_box(0.01, True)
    vx5, reported5, rate5, end5 = _thrown_box(5.0, True)
    print(f"imaged ground: vx {vx:.6f}, reported {reported:.6g} N, momentum rate {rate:.6g} N")
    np.testing.assert_array_equal(end5.v.numpy(), end.v.numpy())  # the friction does not reach the images
    assert vx < 0.25
    assert reported == pytest.approx(rate, rel=1e-9)
    vx_plain, _, _, _ = _thrown_box(0.0, False)
    assert vx_plain == pytest.approx(0.5, abs=1e-12)


@pytest.mark.parametrize("viscosity", [0.0, 1.0])
def test_a_box_slides_on_the_frictionless_imaged_ground_as_it_rests_there(viscosity):
    """With friction 0 the images move with their particles over each step (the fits' image
    pairs ``J(x_j) u_j - u_i``, each image's own fit, the SPH viscosity's ``J(x_j) v_j``), so
    sliding shears nothing: the box thrown at 0.5 m/s from half a spacing above the images keeps
    its speed to round-off after 0.01 s (measured: within 1e-16; on the rough imaged ground
    0.196 of it, above), the ground reports no sideways force, and the thrown box is the box
    left at rest there, moved along: its F, its images' F and its heights the same within
    1e-12 (measured 7e-16), with and without viscosity (1 Pa s, which the images at rest turn
    into a drag)."""
    vx, reported, rate, thrown = _thrown_box(0.0, True, viscosity=viscosity)
    _, _, _, still = _thrown_box(0.0, True, v0=0.0, viscosity=viscosity)
    print(f"frictionless imaged ground: vx {vx!r}, reported {reported:.3g} N, momentum rate {rate:.3g} N")
    assert vx == pytest.approx(0.5, abs=1e-12)
    assert abs(reported) < 1e-9 and abs(rate) < 1e-9
    for name in ("F", "F_image"):
        np.testing.assert_allclose(getattr(thrown, name).numpy(), getattr(still, name).numpy(), rtol=0.0, atol=1e-12,
                                   err_msg=name)
    np.testing.assert_allclose(thrown.x.numpy()[:, 1], still.x.numpy()[:, 1], rtol=0.0, atol=1e-12)
    # Not vacuous: the box settles onto the images (F off I by its weight).
    assert np.abs(still.F.numpy() - np.eye(3)).max() > 1e-3


def _floating_block(friction, fit=None):
    """A 4^3 elastic block (2 cm spacing, E 200 kPa, float64, no gravity, undamped) floating
    with its bottom layer 0.75 spacings over the imaged ground of ``friction``, given random
    velocities of 1 mm/s and zero mean: the model, solver, two states and half the stable step."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 2.25 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0))
    b.add_ground(0.0, friction=friction, images=True)
    m = b.finalize(dtype=wp.float64)
    s = we.Solver(m, fit=fit)
    a, c = m.state(), m.state()
    v = 1e-3 * np.random.default_rng(3).normal(size=(m.particle_count, 3))
    a.v.assign(v - v.mean(axis=0))
    return m, s, a, c, 0.5 * m.stable_dt(fit=s.asked_fit)


def test_an_undamped_block_hovering_on_the_rough_imaged_ground_keeps_its_energy():
    """The rough imaged ground's images keep their own F whatever their share of particles
    within ``h`` (``deformation.floor_image_share`` 1 for images at rest), so the work of each
    image's energy is stored where the next step reads it. The floating block of
    ``_floating_block`` on the rough ground (friction 1; its bottom layer's images have too
    few particles near them to be their own, once a share of 0.45-0.63) rings over 0.25 s
    (about 14 periods of its slowest shear mode): its kinetic energy about its mean velocity,
    largest over the last 0.05 s against the first 0.05 s, measured 0.99 times (4.8e-7 J
    both); with the images' F blended towards their particles' by that share (before), 6.2
    times (3.1e-6 J), growing 1000-fold by 0.5 s (docs/physics.md, "Where the imaged ground's
    images store no energy")."""
    m, s, a, c, dt = _floating_block(1.0)
    mass = m.particle_mass.numpy()[:, None]
    times, energy = [], []
    for k in range(1, int(round(0.25 / dt)) + 1):
        s.step(a, c, dt)
        a, c = c, a
        if k % 20 == 0:
            v = a.v.numpy()
            v = v - (mass * v).sum(axis=0) / mass.sum()
            times.append(k * dt)
            energy.append(0.5 * float((mass * v * v).sum()))
    t, e = np.array(times), np.array(energy)
    early, late = e[t <= 0.05].max(), e[t > 0.2].max()
    print(f"rough imaged ground: kinetic energy {early:.3e} J over the first 0.05 s, {late:.3e} J over the last")
    assert a.x.numpy()[:, 1].min() > 0.6 * DX  # hovering where the images' share was fractional
    assert late < 2.0 * early, (early, late)


@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
def test_a_block_floating_on_the_frictionless_imaged_ground_is_its_own_mirror_image(fit):
    """On the frictionless imaged ground the images are the particles' mirror: each image's F
    is its particle's mirrored, ``R F R``, also where few particles are within ``h`` of it (its
    own fit, the mirror of its particle's) and where its particle is beyond ``h`` (its
    particle's new F mirrored, ``deformation.particle_f_for_image``), so the block and its
    images are one mirror-symmetric body and no sideways force acts. A 4^3 elastic block
    (float64, no gravity) floating with its bottom layer 0.75 spacings over the plane, given
    random velocities of 1 mm/s and zero mean, over 0.01 s: measured ``F_image - R F R``
    1.0e-15 / 1.6e-15 and a sideways momentum of 4e-20 kg m/s (linear / corrected fit; the
    block weighs 0.51 kg; 2.2e-16 and 2e-18 / 2e-17 kg m/s with the images' F blended towards
    their particles' where few particles were near them, before). Blended towards the unmirrored ``F`` the images' F were off by
    4.3e-4 / 3.3e-4 and the block gained 3.2e-5 / 3.5e-5 kg m/s sideways; over 2 s such a
    block's kinetic energy grew 850x (docs/physics.md)."""
    m, s, a, c, dt = _floating_block(0.0, fit)
    mass = m.particle_mass.numpy()[:, None]
    for _ in range(int(round(0.01 / dt))):
        s.step(a, c, dt)
        a, c = c, a
    R = np.diag([1.0, -1.0, 1.0])
    F, Fg, x = a.F.numpy(), a.F_image.numpy(), a.x.numpy()
    mirror = np.abs(Fg - R @ F @ R).max()
    sideways = np.abs((mass * a.v.numpy()).sum(axis=0)[[0, 2]]).max()
    print(f"{fit}: F_image - R F R {mirror:.3g}, sideways momentum {sideways:.3g} kg m/s, lowest {x[:, 1].min() / DX:.3f} dx")
    assert x[:, 1].min() > 0.5 * DX  # above the images' depth ramp: the mirror throughout
    assert np.abs(F - np.eye(3)).max() > 1e-5  # not vacuous: the block deforms
    assert mirror < 1e-13
    assert sideways < 1e-15


@pytest.mark.parametrize("fused, fit", [(True, "linear"), (False, "curvature_corrected")])
def test_an_undamped_block_resting_below_half_a_spacing_on_the_frictionless_imaged_ground_gains_no_energy(fused, fit):
    """Below half a spacing the frictionless imaged ground's images are no mirrors (held on the
    depth ramp, ``deformation.image_depth``); its force is minus the gradient of the energy it
    stores, ``(1 - c) E_i + c E_g`` with the image's share ``c`` 1/2 within ``h - dx/2`` of the
    plane, fading to 0 at ``h`` (``forces.image_energy_share``, ``forces.moving_image_forces``;
    no particle of this block reaches the fade: measured), so an undamped body resting there keeps its energy but for
    the step's own error. A 4 x 3 x 4 elastic block (5 mm spacing, mu 3.6 kPa, nu 0.2, 1000
    kg/m^3, no SPH pressure, float64, gravity) let go with its bottom layer 0.4 spacings up and
    random velocities of 2 mm/s, at half the stable step for 0.2 s: its total energy (the
    kinetic of the half-step velocities' mean, gravity's, and ``V psi(F)`` stored, shared with
    the image's as the force shares them) against its start. The bound: the step's own error, first order
    in the step and of either sign (the fits' F updated from the step's positions), was
    measured from 0.025 (a block floating free) to 0.09 (this form, a larger block with the SPH
    pressure) of the ringing's kinetic energy a second (docs/physics.md, "The frictionless
    imaged ground below half a spacing"): the bound is twice the largest, 0.2 a second of the
    largest kinetic energy over the run, 1.2e-7 J here. Measured a rise of 2.7e-8 / 4.4e-8 J
    (the linear fit, fused / the corrected fit), the ringing's kinetic energy up to 2.9e-6 /
    3.1e-6 J; as built before (each image's reaction left to the floor, its F blended towards
    its particle's) 2.2e-4 / 2.8e-5 J by 0.2 s, against bounds of 6.9e-6 / 7.1e-7 J (its
    ringing growing with the gain), and 1.9e-2 J by 1 s with the bottom layer on the plane."""
    dx, mu, nu, g = 0.005, 3600.0, 0.2, 9.81
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -g, 0.0))
    b.add_box((0.0, 1.4 * dx, 0.0), (4 * dx, 3 * dx, 4 * dx),
              we.Material.from_young(2 * mu * (1 + nu), nu, density=1000.0, pressure_stiffness=0.0))
    b.add_ground(0.0, friction=0.0, images=True)
    m = b.finalize(dtype=wp.float64)
    s = we.Solver(m, fused=fused, fit=fit)
    a, c = m.state(), m.state()
    v = 2e-3 * np.random.default_rng(0).normal(size=(m.particle_count, 3))
    a.v.assign(v - v.mean(axis=0))
    dt = 0.5 * m.stable_dt(fit=s.asked_fit)
    mass, V, h = m.particle_mass.numpy(), m.particle_volume.numpy(), m.support_radius
    total, kinetic, lowest = [], [], []
    for k in range(int(round(0.2 / dt))):
        sample = k % 4 == 0
        if sample:
            x, v0, F, Fg = a.x.numpy(), a.v.numpy(), a.F.numpy(), a.F_image.numpy()
        s.step(a, c, dt)
        if sample:
            vbar = 0.5 * (v0 + c.v.numpy())
            ke = 0.5 * float((mass[:, None] * vbar * vbar).sum())
            psi, psi_g = corotated_psi(m, F), corotated_psi(m, Fg)
            share = image_energy_share(x[:, 1], h, dx)
            stored = float((V * ((1.0 - share) * psi + share * psi_g)).sum())
            total.append(ke + g * float((mass * x[:, 1]).sum()) + stored)
            kinetic.append(ke)
            lowest.append(x[:, 1].min())
        a, c = c, a
    rise = max(total) - total[0]
    bound = 0.2 * 0.2 * max(kinetic)
    print(f"fused {fused}, {fit}: total energy rise {rise:.3g} J (bound {bound:.3g}), largest kinetic {max(kinetic):.3g} J, "
          f"lowest {min(lowest) / dx:.2f}-{max(lowest) / dx:.2f} dx")
    assert max(lowest) < 0.5 * dx  # not vacuous: the lowest particles' images are no mirrors throughout
    assert rise < bound, (rise, bound)


@pytest.mark.parametrize("fit", ["linear", "curvature_corrected"])
def test_the_frictionless_imaged_ground_fits_a_thin_layers_mirror_symmetric_motion_exactly(fit):
    """What the images are for (docs/physics.md, "The ground collider's thin-layer strength"):
    the bottom layer's fit is an interior one. A layer two particles thick, its bottom layer
    0.75 spacings above the plane (every particle's fit holds images), moved by a velocity
    ``G x`` that the mirror keeps (``G R = R G``: stretched and sheared along the floor, squeezed
    towards it, no force at F = I): on the frictionless imaged ground one step gives every
    particle and every image ``F = I + dt G`` (measured: within 1e-19), as inside a body; on
    the rough imaged ground, whose images stand still, the bottom layer's is off by most of
    the increment (measured 1.5e-4 / 1.8e-4, linear / corrected, of its 2e-4)."""
    G = np.array([[2.0, 0.0, 0.5], [0.0, -1.5, 0.0], [-0.7, 0.0, 1.0]])
    dt = 1.0e-4
    errors = {}
    for friction in (0.0, 0.5):
        b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
        b.add_box((0.0, 1.25 * DX, 0.0), (6 * DX, 2 * DX, 6 * DX),
                  we.Material.from_young(2e5, 0.3, density=1000.0, pressure_stiffness=0.0))
        b.add_ground(0.0, friction=friction, images=True)
        m = b.finalize(dtype=wp.float64)
        s = we.Solver(m, fit=fit)
        a, c = m.state(), m.state()
        a.v.assign(a.x.numpy() @ G.T)
        s.step(a, c, dt)
        exact = np.eye(3) + dt * G
        errors[friction] = max(np.abs(c.F.numpy() - exact).max(), np.abs(c.F_image.numpy() - exact).max())
    print(f"{fit}: F - (I + dt G) {errors}")
    assert errors[0.0] < 1e-14
    assert errors[0.5] > 0.3 * dt * np.abs(G).max()
