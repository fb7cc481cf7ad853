"""Physics of the static colliders of ``SceneBuilder.add_box_collider`` and
``add_sphere_collider`` (``warp_esph/sim/colliders.py``) on an elastic block: Coulomb
sliding and sticking against closed-form values, and a resting body held at the surface
with a reaction that carries its weight.

Static colliders report no reaction force (a tool held in place, ``add_tool(...,
motion=None)``, does, docs/tools.md); here the reaction is read from the momentum balance:
the colliders are the only external force besides gravity, and the internal forces sum to
zero, so their force on the body is ``dP/dt - M g``."""

import numpy as np
import pytest

import warp_esph as we

G = 9.81
DT = 2.0e-4
TOP = 0.01  # the collider's top face: the block's bottom particle layer starts on it


def _block(friction, collider="box"):
    """A 3 x 3 x 3 elastic block (6 cm, 2 cm spacing, mildly viscous) whose bottom layer
    rests on the top of a static box or on the apex of a static sphere (R = 0.5 m)."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0))
    mat = we.Material.from_young(1e5, 0.3, density=1000.0, pressure_stiffness=0.0, elastic_force="variational",
                                 viscosity=1.0)
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), mat, name="block")
    if collider == "box":
        b.add_box_collider((0.0, TOP - 0.05, 0.0), (0.5, 0.05, 0.5), friction=friction)
    else:
        b.add_sphere_collider((0.0, TOP - 0.5, 0.0), 0.5, friction=friction)
    m = b.finalize()
    return m, we.Solver(m)


def _settle(m, s, steps=1500, relax=False):
    """``steps`` steps from rest; ``relax``: with kinetic damping (all velocities zeroed
    whenever the kinetic energy dropped since the last check, every 10 steps)."""
    a, c = m.state(), m.state()
    mass = m.particle_mass.numpy()[:, None]
    ke_prev = 0.0
    for k in range(steps):
        s.step(a, c, DT)
        a, c = c, a
        if relax and k % 10 == 0:
            v = a.v.numpy()
            ke = 0.5 * float((mass * v * v).sum())
            if ke < ke_prev:
                a.v.zero_()
                ke = 0.0
            ke_prev = ke
    return a, c


def _momentum(m, state):
    return (m.particle_mass.numpy()[:, None] * state.v.numpy().astype(np.float64)).sum(axis=0)


def test_block_sliding_on_a_box_decelerates_at_mu_g_then_stops():
    """Kinetic friction mu = 0.3 on a level box top, launched at 0.5 m/s: the centroid's
    acceleration while it slides is -mu g, it stops after v0 / (mu g) having slid
    v0^2 / (2 mu g), and then stays."""
    mu, v0 = 0.3, 0.5
    m, s = _block(mu)
    a, c = _settle(m, s)
    v = a.v.numpy()
    v[:, 0] += v0
    a.v.assign(v)
    x_start = a.x.numpy()[:, 0].mean()
    t_stop = v0 / (mu * G)
    xs, ts = [], []
    for k in range(int(1.5 * t_stop / DT)):
        s.step(a, c, DT)
        a, c = c, a
        xs.append(a.x.numpy()[:, 0].mean())
        ts.append((k + 1) * DT)
    xs, ts = np.array(xs), np.array(ts)
    sliding = ts < 0.8 * t_stop
    acc = 2.0 * np.polyfit(ts[sliding], xs[sliding], 2)[0]
    print(f"acceleration {acc:.4f} m/s^2 (-mu g = {-mu * G:.4f}); slid {xs[-1] - x_start:.5f} m "
          f"(v0^2 / (2 mu g) = {v0 ** 2 / (2 * mu * G):.5f})")
    assert acc == pytest.approx(-mu * G, rel=0.02)
    assert xs[-1] - x_start == pytest.approx(v0**2 / (2 * mu * G), rel=0.03)
    after = ts > 1.2 * t_stop
    assert np.ptp(xs[after]) < 1e-4  # stopped: it does not creep on
    # Never below the box top.
    assert a.x.numpy()[:, 1].min() > TOP - 1e-6


@pytest.mark.parametrize("mu", [0.2, 1.0])
def test_block_on_a_tilted_box_slides_below_tan_phi_and_stays_above(mu):
    """Gravity tilted by 20 degrees (the box top a slope, tan 20 deg = 0.364): with mu = 0.2
    the centroid accelerates at g (sin th - mu cos th); with mu = 1 (above twice tan th, so
    the sway after the sudden tilt cannot start a slip) it stays. The momentum balance
    gives the collider's force: normal g M cos th, tangential mu of it while sliding."""
    th = np.radians(20.0)
    m, s = _block(mu)
    a, c = _settle(m, s)
    m.gravity = (G * np.sin(th), -G * np.cos(th), 0.0)
    steps = 1000
    xs, p = [], [_momentum(m, a)]
    for _ in range(steps):
        s.step(a, c, DT)
        a, c = c, a
        xs.append(a.x.numpy()[:, 0].mean())
        p.append(_momentum(m, a))
    t = DT * np.arange(1, steps + 1)
    late = slice(steps // 2, steps)
    acc = 2.0 * np.polyfit(t[late], np.array(xs)[late], 2)[0]
    M = m.particle_mass.numpy().sum()
    reaction = (p[-1] - p[steps // 2]) / (DT * (steps - steps // 2)) - M * np.array(m.gravity)
    print(f"mu={mu}: acceleration {acc:.4f} m/s^2, reaction {reaction} N, weight {M * G:.4f} N")
    assert reaction[1] == pytest.approx(M * G * np.cos(th), rel=0.02)
    if mu < np.tan(th):
        assert acc == pytest.approx(G * (np.sin(th) - mu * np.cos(th)), rel=0.01)
        assert -reaction[0] / reaction[1] == pytest.approx(mu, rel=0.02)
    else:
        assert abs(xs[-1] - xs[0]) < 3e-4 and abs(acc) < 0.05  # stuck: only the elastic sway
        assert -reaction[0] == pytest.approx(M * G * np.sin(th), rel=0.05)  # static friction holds it
    assert a.x.numpy()[:, 1].min() > TOP - 1e-6


@pytest.mark.parametrize("collider", ["box", "sphere"])
def test_resting_block_carries_its_weight_without_penetration(collider):
    """Settled (with kinetic damping) on a box top or on a sphere's apex, then left alone
    for 0.1 s: it stays at rest, the colliders' force over that time is the weight, straight
    up, and no particle is inside."""
    m, s = _block(0.5, collider)
    a, c = _settle(m, s, 2500, relax=True)
    p0 = _momentum(m, a)
    n = 500
    for _ in range(n):
        s.step(a, c, DT)
        a, c = c, a
    M = m.particle_mass.numpy().sum()
    reaction = (_momentum(m, a) - p0) / (n * DT) - M * np.array(m.gravity)
    x = a.x.numpy().astype(np.float64)
    print(f"{collider}: reaction {reaction} N for the weight {M * G:.5f} N; speed {np.abs(a.v.numpy()).max():.2e} m/s")
    np.testing.assert_allclose(reaction, [0.0, M * G, 0.0], atol=1e-3 * M * G)
    assert np.abs(a.v.numpy()).max() < 1e-3
    if collider == "box":
        assert x[:, 1].min() > TOP - 1e-6
    else:
        assert np.linalg.norm(x - np.array([0.0, TOP - 0.5, 0.0]), axis=1).min() > 0.5 - 1e-6
        assert np.abs(x[:, [0, 2]].mean(axis=0)).max() < 1e-4  # stays over the apex
