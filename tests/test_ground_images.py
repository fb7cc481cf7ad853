"""The imaged ground (``SceneBuilder.add_ground(images=True)``) is a rough floor of the fits
whatever its friction: docs/physics.md, "The imaged ground is rough whatever its friction"."""

import warnings

import numpy as np
import pytest

import warp as wp

import warp_esph as we

DX = 0.02


def test_a_frictionless_imaged_ground_is_refused():
    """``friction = 0`` asks for a floor the images cannot be (below), so it is refused by
    name; any positive friction is taken, and so is friction 0 without the images."""
    b = we.SceneBuilder(spacing=DX)
    with pytest.raises(ValueError, match=r"friction = 0 is not allowed with images = True: the images are a rough floor"):
        b.add_ground(0.0, friction=0.0, images=True)
    assert not b.planes  # nothing half-added
    b.add_ground(0.0, friction=1e-3, images=True)
    we.SceneBuilder(spacing=DX).add_ground(0.0, friction=0.0)


def _thrown_box(friction, images, v0=0.5, steps=125):
    """A 4^3 elastic box (2 cm spacing, E 200 kPa, float64, the default solver) standing on
    the ground, given ``v0`` sideways, ``steps`` steps at half the stable step (0.01 s on the
    images): its mean x-velocity at the end, the ground's reported x-force averaged over the
    steps, the momentum's x-rate, and the end state's velocities."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 2.0 * DX, 0.0), (4 * DX,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0))
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
    vel = a.v.numpy()
    p1 = float((mass * vel[:, 0]).sum())
    return p1 / mass.sum(), reported, (p1 - p0) / (steps * dt), vel


def test_the_imaged_ground_holds_a_sliding_box_whatever_its_friction():
    """The images are at rest over each step in the fits, so a bottom layer sliding over them
    is sheared and its stress pulls the body back, and the body rests off the plane, where
    the friction acts: the box thrown at 0.5 m/s from half a spacing above the plane keeps
    0.196 of its speed after 0.01 s (0.0978 m/s; asked: below half), to the bit the same with
    friction 0.01 and 5; the ground's row reports the force (the momentum's rate, 20.4 N against
    the box's 5.0 N weight). On the plain frictionless ground it keeps its speed to round-off."""
    vx, reported, rate, vel = _thrown_box(0.01, True)
    vx5, reported5, rate5, vel5 = _thrown_box(5.0, True)
    print(f"imaged ground: vx {vx:.6f}, reported {reported:.6g} N, momentum rate {rate:.6g} N")
    np.testing.assert_array_equal(vel5, vel)  # the friction does not reach the images
    assert vx < 0.25
    assert reported == pytest.approx(rate, rel=1e-9)
    vx_plain, _, _, _ = _thrown_box(0.0, False)
    assert vx_plain == pytest.approx(0.5, abs=1e-12)
