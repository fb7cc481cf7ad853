"""The Tresca ground (``SceneBuilder.add_ground(friction=0, images=True, shear_cap=K)``): the
frictionless imaged ground holding each base particle tangentially up to ``K`` times its
material's shear yield stress over the area it stands for (``sim/colliders.py``,
``tresca_traction``; docs/physics.md, "The Tresca ground (built)")."""

import dataclasses
import math

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from run_files import box_on_ground
from taped_loss import random_weights, set_first_material, taped_rollout_loss
from warp_esph.builder import finalize_worlds
from warp_esph.cli import main
from warp_esph.scene_file import load_scene_file

G = 9.81
THETA = math.radians(20.0)
DX = 0.005


def _strip_builder(cap_over_load, tool=False):
    """A stiff elastic block 6 x 4 x 6 spacings (5 mm) on the Tresca ground (K = 1) under
    gravity tilted by 20 degrees, its yield stress (no flow: ``flow_rate = 0``) making the
    base's hold ``tau_y`` the load ``rho h g sin(theta)`` times ``cap_over_load``. ``tool``:
    a sphere tool parked far away, so the tools' integrator runs the step."""
    h, rho = 4 * DX, 1000.0
    cap = cap_over_load * rho * h * G * math.sin(THETA)
    mat = we.Material(mu=2.0e5, lam=3.0e5, density=rho, viscosity=0.5, yield_stress=cap * math.sqrt(2.0), flow_rate=0.0)
    b = we.SceneBuilder(spacing=DX, gravity=(G * math.sin(THETA), -G * math.cos(THETA), 0.0))
    b.add_box((0.0, h / 2, 0.0), (6 * DX, h, 6 * DX), mat)
    b.add_ground(0.0, friction=0.0, images=True, shear_cap=1.0)
    if tool:
        b.add_tool("sphere", radius=0.01, position=(0.0, 1.0, 0.0))
    return b, cap, h, rho


def _strip(cap_over_load, tool=False):
    b, cap, h, rho = _strip_builder(cap_over_load, tool)
    return b.finalize(), cap, h, rho


def _slide(model, duration, fused=True):
    """Steps ``model`` for ``duration``; the times, the mean x position, the ground's reaction
    row's x force at each step, and the last state."""
    s = we.Solver(model, fused=fused)
    dt = 0.9 * model.stable_dt()
    a, c = model.state(), model.state()
    ts, xs, fx = [], [], []
    for k in range(1, int(round(duration / dt)) + 1):
        s.step(a, c, dt)
        a, c = c, a
        ts.append(k * dt)
        xs.append(a.x.numpy().astype(np.float64)[:, 0].mean())
        fx.append(float(a.collider_force.numpy()[0, 0]))
    return np.array(ts), np.array(xs), np.array(fx), a, dt


@pytest.mark.parametrize("cap_over_load", [0.5, 2.0])
def test_a_strip_on_the_tresca_ground_slides_at_the_excess_over_its_hold_and_sticks_under_it(cap_over_load):
    """The strip's load ``rho h g sin(theta)`` twice the hold ``tau_y``: it slides at ``g
    sin(theta) - tau_y / (rho h)`` (measured 1.6793 against 1.6776 m/s^2 over the second half of
    20 ms), the ground's row pulling back ``tau_y`` times the base's area (0.03017 against 0.03020
    N); half of it: it stays (mean speed 4e-4 m/s after 20 ms, where it would slide at 0.067 m/s).
    Both ways the row's impulse is the strip's momentum change less gravity's (to 1e-6): the
    traction is in it. Without the traction (``model.shear_cap = 0``) the strip slides at g
    sin(theta) in both."""
    model, cap, h, rho = _strip(cap_over_load)
    ts, xs, fx, last, dt = _slide(model, 0.02)
    v = last.v.numpy().astype(np.float64)[:, 0].mean()
    mass = model.particle_mass.numpy().astype(np.float64).sum()
    drive = G * math.sin(THETA)
    np.testing.assert_allclose(fx.sum() * dt, mass * v - mass * drive * ts[-1], rtol=1e-4)
    second = ts >= 0.5 * ts[-1]
    if cap_over_load < 1.0:
        accel = 2.0 * np.polyfit(ts[second], xs[second], 2)[0]
        assert accel == pytest.approx(drive - cap / (rho * h), rel=5e-3)
        assert fx[second].mean() == pytest.approx(-cap * (6 * DX) ** 2, rel=5e-3)
    else:
        assert abs(v) < 0.03 * drive * ts[-1]  # its elastic ringing: 0.6 % (free: 100 %)


def test_the_tools_integrator_runs_the_tresca_ground_as_the_plain_one():
    """With a tool in the scene the step integrates in the tools' kernel (``ToolSet.integrate``),
    which runs the same static colliders: a sliding strip with a tool parked far away moves as
    without it, to the bit."""
    plain, tooled = (_slide(_strip(0.5, tool=t)[0], 0.002)[3] for t in (False, True))
    np.testing.assert_array_equal(plain.x.numpy(), tooled.x.numpy())
    np.testing.assert_array_equal(plain.collider_force.numpy(), tooled.collider_force.numpy())


def test_worlds_and_the_unfused_step_run_the_tresca_ground_as_one_world_does():
    """Two worlds in one model (``finalize_worlds``), the strip sliding past its hold in one and
    held in the other, each as its own model runs it, and the unfused step's integration the
    fused one's (the same launch after forces that differ by round-off): the traction reads
    each particle's own material and world row."""
    dur = 0.002
    worlds = finalize_worlds([_strip_builder(0.5)[0], _strip_builder(2.0)[0]])
    both = _slide(worlds, dur)[3]
    n = worlds.particle_count // 2
    for w, r in enumerate((0.5, 2.0)):
        alone = _slide(_strip(r)[0], dur)[3]
        np.testing.assert_array_equal(both.x.numpy()[w * n:(w + 1) * n], alone.x.numpy())
        np.testing.assert_array_equal(both.collider_force.numpy()[w], alone.collider_force.numpy()[0])
    fused, unfused = (_slide(_strip(0.5)[0], dur, fused=f)[3] for f in (True, False))
    np.testing.assert_allclose(unfused.x.numpy(), fused.x.numpy(), rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(unfused.collider_force.numpy(), fused.collider_force.numpy(), rtol=1e-4)


def test_the_shear_cap_written_after_a_step_holds_in_the_next():
    """``model.shear_cap`` written after the model has stepped: the next step from the strip at
    rest holds with the new value (the static colliders' struct was filled once and kept the
    first: the strip given 0 after 30 steps slid as at 1). At 0 every particle gains exactly
    ``g sin(theta) dt`` along x and the row's x force is zero; given 1 back, the first step again
    to the bit; ``static_colliders`` (a checkpoint's fingerprint) records the value that runs. A
    value the ground cannot take is refused by name and the old one kept."""
    model = _strip(0.5)[0]
    s = we.Solver(model)
    dt = 0.9 * model.stable_dt()

    def first_step():
        out = model.state()
        s.step(model.state(), out, dt)
        return out.v.numpy()[:, 0], float(out.collider_force.numpy()[0, 0])

    held, row_held = first_step()
    model.shear_cap = 0.0
    free, row_free = first_step()
    np.testing.assert_allclose(free, G * math.sin(THETA) * dt, rtol=1e-5)
    assert row_free == pytest.approx(0.0, abs=1e-6 * abs(row_held)) and held.min() < 0.9 * free.min()
    assert model.static_colliders()[0][0] == dataclasses.replace(model.planes[0], shear_cap=0.0)  # as it runs
    model.shear_cap = 1.0
    np.testing.assert_array_equal(first_step()[0], held)
    assert model.static_colliders()[0][0] is model.planes[0]
    for bad, said in ((-1.0, r"^shear_cap = -1\.0 is not allowed: must be >= 0"), (math.nan, r"^shear_cap = nan is not allowed")):
        with pytest.raises(ValueError, match=said):
            model.shear_cap = bad
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.03, 0.0), (0.06,) * 3, we.Material.preset("dough"))
    b.add_ground(0.0, friction=0.5, images=True)
    rough = b.finalize()
    with pytest.raises(ValueError, match=r"^model\.shear_cap = 1\.0 is not allowed: the hold is the frictionless imaged ground's"):
        rough.shear_cap = 1.0
    assert model.shear_cap == 1.0 and rough.shear_cap == 0.0 and rough.shear_cap_plane is None


def test_the_hold_fades_with_where_each_base_particle_starts_the_step():
    """One step of a 4 x 2 x 4 block (float64) sliding at 1 m/s along x and falling at 2 m/s,
    its base particles lifted to 16 heights from 0.3 to 1.45 spacings, with ``shear_cap`` 1 and
    0 from the same state: each particle's tangential speed loses ``w tau_y dt / (rho dx)``
    (far past the rounding), ``w`` 1 to 0.75 spacings, ``1 - t^2 (3 - 2 t)`` of ``t = (d -
    0.75 dx) / (0.5 dx)`` to 1.25, 0 beyond, of its height ``d`` at the step's start (its drift
    moves it 0.1 spacing: a band read after it is off by up to 0.3 of the hold); its position
    loses ``dt`` times that velocity (the drift's share of the velocity removed). Seen failing
    with the band hard at 1.25 spacings, read after the drift, and without the position's share."""
    dx, dt, ys = 0.02, 1e-3, 60.0
    mat = we.Material.from_young(5e3, 0.3, density=1000.0, yield_stress=ys, flow_rate=50.0, viscosity=1.0)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, dx, 0.0), (4 * dx, 2 * dx, 4 * dx), mat, velocity=(1.0, -2.0, 0.0))
    b.add_ground(0.0, friction=0.0, images=True, shear_cap=1.0)
    model = b.finalize(dtype=wp.float64)
    x0 = model.particle_x0.copy()
    base = np.flatnonzero(x0[:, 1] < dx)
    assert len(base) == 16
    x0[x0[:, 1] > dx, 1] = 2.5 * dx  # the upper layer out of the band and clear of the base
    d = np.linspace(0.3, 1.45, 16) * dx
    x0[base, 1] = d
    model.particle_x0 = x0
    s = we.Solver(model)

    def step():
        out = model.state()
        s.step(model.state(), out, dt)
        return out.x.numpy(), out.v.numpy()

    x_held, v_held = step()
    model.shear_cap = 0.0
    x_free, v_free = step()
    tangential = lambda v: np.hypot(v[:, 0], v[:, 2])  # noqa: E731
    w = (tangential(v_free) - tangential(v_held)) / (ys / math.sqrt(2.0) * dt / (1000.0 * dx))
    t = np.clip((d / dx - 0.75) / 0.5, 0.0, 1.0)
    np.testing.assert_allclose(w[base], 1.0 - t * t * (3.0 - 2.0 * t), rtol=0.0, atol=1e-9)
    np.testing.assert_array_equal(w[np.setdiff1d(np.arange(model.particle_count), base)], 0.0)
    np.testing.assert_allclose(x_held - x_free, dt * (v_held - v_free), rtol=0.0, atol=1e-15)


#: Each particle's elastic ``F`` at the start of the flowing window and of the one hardened step:
#: an isochoric stretch whose deviatoric stress ``|2 mu dev sigma|`` (about 620 Pa) is above every
#: hardened yield stress they read (80 Pa in the window, up to 260 Pa in the step), so that every
#: particle flows in every step and its ``alpha`` grows.
FLOWING_F = np.diag([1.12, 1.0 / 1.12, 1.0])


@pytest.mark.parametrize("hardening", [2000.0, -1000.0])
def test_the_hold_reads_each_particles_hardened_yield_stress_and_none_where_softening_took_it(hardening):
    """One step (float64) of a 4 x 2 x 4 block sliding at 1 m/s on the Tresca ground, its base
    particles at 16 plastic strains ``alpha`` from 0 to 0.1 (``State.alpha``, each its own):
    each base particle's tangential speed loses ``(Y + K alpha) dt / (sqrt(2) rho dx)``, the
    yield stress ``Y + K alpha`` the plastic flow reads, hardened (``K`` = 2000 Pa) or softened
    (``K`` = -1000 Pa, down to 0 at ``alpha`` = 0.06): beyond it no hold at all, the step's
    velocity the free ground's to the bit (a negative hold would push). The tools' integrator
    (a sphere tool parked far away) gives the same step to the bit. Every particle starts at
    ``FLOWING_F`` and flows in the step, so that the ``alpha`` the hold reads is the step's
    start's, as the flow's yield test reads it, not the one the flow writes. Seen failing with the
    hold read from the yield stress alone (every particle losing the same ``Y``) and from
    ``state_out.alpha`` (the flowed one)."""
    dx, dt, ys, rho = 0.02, 1e-3, 60.0, 1000.0
    mat = we.Material.from_young(5e3, 0.3, density=rho, yield_stress=ys, flow_rate=50.0, viscosity=1.0,
                                 hardening=hardening)

    def block(tool):
        b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0))
        b.add_box((0.0, dx, 0.0), (4 * dx, 2 * dx, 4 * dx), mat, velocity=(1.0, 0.0, 0.0))
        b.add_ground(0.0, friction=0.0, images=True, shear_cap=1.0)
        if tool:
            b.add_tool("sphere", radius=0.01, position=(0.0, 1.0, 0.0))
        return b.finalize(dtype=wp.float64)

    model = block(False)
    base = np.flatnonzero(model.particle_x0[:, 1] < dx)
    assert len(base) == 16
    alpha = np.zeros(model.particle_count)
    alpha[base] = np.linspace(0.0, 0.1, 16)

    def step(model):
        a, out = model.state(), model.state()
        a.alpha.assign(alpha)
        # Every particle flows in the step: the hold must read alpha before the flow raises it.
        a.F.assign(np.broadcast_to(FLOWING_F, (model.particle_count, 3, 3)))
        we.Solver(model).step(a, out, dt)
        assert (out.alpha.numpy()[base] - alpha[base]).min() > 1e-4
        return out.v.numpy()

    held = step(model)
    np.testing.assert_array_equal(step(block(True)), held)
    model.shear_cap = 0.0
    free = step(model)
    lost = np.hypot(free[:, 0], free[:, 2]) - np.hypot(held[:, 0], held[:, 2])
    stress = np.maximum(ys + hardening * alpha[base], 0.0)
    np.testing.assert_allclose(lost[base], stress / math.sqrt(2.0) * dt / (rho * dx), rtol=1e-9, atol=1e-15)
    if hardening < 0.0:
        gone = base[ys + hardening * alpha[base] <= 0.0]
        assert len(gone) == 7
        np.testing.assert_array_equal(held[gone], free[gone])


@pytest.mark.parametrize("call, said", [
    (dict(shear_cap=1.0, images=False, friction=0.0), r"shear_cap = 1\.0 is not allowed with images = False: "),
    (dict(shear_cap=1.0, images=True, friction=0.5), r"shear_cap = 1\.0 is not allowed with friction = 0\.5: "),
    (dict(shear_cap=-1.0, images=True, friction=0.0), r"shear_cap = -1\.0 is not allowed: must be >= 0"),
    (dict(shear_cap=float("nan"), images=True, friction=0.0), r"shear_cap = nan is not allowed"),
    (dict(shear_cap=float("inf"), images=True, friction=0.0), r"shear_cap = inf is not allowed"),
    (dict(shear_cap="1", images=True, friction=0.0), r"shear_cap = '1' is not allowed"),
])
def test_a_shear_cap_the_ground_cannot_take_is_refused_by_name(call, said):
    b = we.SceneBuilder(spacing=0.02)
    with pytest.raises(ValueError, match="^" + said):
        b.add_ground(0.0, **call)
    assert not b.planes


def test_the_tresca_ground_is_refused_beside_a_material_without_a_shear_yield_stress():
    """An elastic material (``yield_stress = inf``) or a non-Bingham model has no ``tau_y`` for
    the hold: refused at the build and by ``set_material``, naming the material; 0 and None
    are no cap, accepted with any material."""
    dough = we.Material.preset("dough")
    for bad in (we.Material.from_young(2e5, 0.3, density=1000.0), dataclasses.replace(dough, model="hyperelastic")):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.03, 0.0), (0.06,) * 3, bad)
        b.add_ground(0.0, friction=0.0, images=True, shear_cap=1.0)
        with pytest.raises(ValueError, match=r"^add_ground\(shear_cap = 1\.0\) is not allowed with material 0 \(model = "):
            b.finalize()
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.03, 0.0), (0.06,) * 3, dough)
    b.add_ground(0.0, friction=0.0, images=True, shear_cap=2.0)
    m = b.finalize()
    assert m.shear_cap == 2.0 and m.shear_cap_plane == 0
    with pytest.raises(ValueError, match=r"yield_stress = inf\): the ground holds its base up to shear_cap times"):
        m.set_material(0, dataclasses.replace(dough, yield_stress=math.inf))
    assert m.materials[0] == dough
    for off in (0.0, None):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.03, 0.0), (0.06,) * 3, we.Material.from_young(2e5, 0.3, density=1000.0))
        b.add_ground(0.0, friction=0.5, images=True, shear_cap=off)
        assert b.finalize().shear_cap == 0.0


def test_a_scene_files_ground_takes_shear_cap_and_the_cli_refuses_a_bad_one_in_one_line(tmp_path, capsys):
    path = tmp_path / "tresca.toml"
    scene = box_on_ground("tresca", 1, "m", "dough", "2e4") + "friction = FRICTION\nimages = true\nshear_cap = 1.0\n"
    path.write_text(scene.replace("FRICTION", "0.0"))
    assert load_scene_file(path).builder.finalize().shear_cap == 1.0
    path.write_text(scene.replace("FRICTION", "0.5"))
    assert main(["run", str(path), "-o", str(tmp_path / "t.usdc"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[[colliders]] #1 (type 'ground'): shear_cap = 1.0 is not allowed with friction = 0.5" in err
    assert not (tmp_path / "t.usdc").exists()


STEPS, DT = 8, 5e-4
#: The blocks' hardening (Pa) and their plastic strain at the start, about 0.05 (each particle its
#: own): the hold reads ``yield_stress + hardening alpha``, 20 Pa above the yield stress of 60.
HARDENING, ALPHA0 = 400.0, 0.05


def _grad_model(lift, speed, mu=None, yield_stress=None, hardening=None, v0=None):
    """A 3 x 2 x 3 yield-stress block (2 cm, float64) on the Tresca ground, its base ``lift``
    spacings above the plane (0.5: in the full hold; 0.9, 1.1: in its fade), moving at
    ``speed`` m/s along x (and a little along z) under gravity, hardening ``HARDENING``."""
    mat = we.Material.from_young(5e3, 0.3, density=1000.0, yield_stress=60.0, flow_rate=50.0, viscosity=1.0,
                                 hardening=HARDENING)
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0))
    b.add_box((0.0, 0.02 * (lift + 0.5), 0.0), (0.06, 0.04, 0.06), mat, velocity=(speed, 0.0, 0.25 * speed))
    b.add_ground(0.0, friction=0.0, images=True, shear_cap=1.0)
    m = b.finalize(dtype=wp.float64, requires_grad=True)
    m.particle_x0 += np.random.default_rng(3).normal(scale=2e-5, size=m.particle_x0.shape)
    set_first_material(m, mu=mu, yield_stress=yield_stress, hardening=hardening)
    if v0 is not None:
        v = m.particle_v0.copy()
        v[:, 0] = v0
        m.particle_v0 = v
    return m


def _grad_loss(model, grad=False, alpha0=ALPHA0):
    s = we.Solver(model)
    states = [model.state(requires_grad=True) for _ in range(STEPS + 1)]
    states[0].alpha.assign(alpha0 + ALPHA0 * np.random.default_rng(5).uniform(-0.5, 0.5, model.particle_count))
    loss, tape = taped_rollout_loss(s, states, DT, random_weights(model.particle_count, 7))
    if not grad:
        return loss.numpy()[0]
    tape.backward(loss)
    return (model.mu.grad.numpy()[0], model.yield_stress.grad.numpy()[0], model.hardening.grad.numpy()[0],
            states[0].v.grad.numpy()[:, 0].sum(), states[0].alpha.grad.numpy().sum())


@pytest.mark.parametrize("lift, speed", [(0.5, 0.3), (0.5, 0.002), (0.9, 0.3), (1.1, 0.002)])
def test_gradients_through_the_tresca_ground_match_central_differences(lift, speed):
    """mu, the yield stress and the hardening (which set the hold), the initial speed and the
    initial plastic strain ``alpha`` (which hardens it) through 8 steps of a block sliding (0.3
    m/s, past the hold) or sticking (2 mm/s, under it) on the Tresca ground, its base in the
    full hold or in its fade: the float64 tape against central differences at a relative step
    of 1e-5. The block does not flow in 8 steps: the hardening and ``alpha`` reach the loss
    through the hold alone. Seen failing with the hold read from the yield stress alone (their
    gradients 0 in the tape and the differences alike) and with it read from an untaped copy of
    ``alpha`` (the tape's ``alpha`` gradient 0, the differences' 2.6e-5 to 6.7e-4)."""
    g_mu, g_y, g_k, g_v, g_a = _grad_loss(_grad_model(lift, speed), grad=True)
    assert g_y != 0.0 and g_k != 0.0 and g_a != 0.0  # the hold reaches the loss: the check is not vacuous
    m0 = _grad_model(lift, speed)
    for value, key, p0 in ((g_mu, "mu", m0.materials[0].mu), (g_y, "yield_stress", 60.0), (g_k, "hardening", HARDENING),
                           (g_v, "v0", speed), (g_a, "alpha0", ALPHA0)):
        h = 1e-5 * p0
        at = [_grad_loss(_grad_model(lift, speed), alpha0=p0 + d) if key == "alpha0" else
              _grad_loss(_grad_model(lift, speed, **{key: p0 + d})) for d in (h, -h)]
        fd = (at[0] - at[1]) / (2 * h)
        print(key, value, fd)
        assert value == pytest.approx(fd, rel=1e-5, abs=1e-9 * abs(fd) + 1e-12), key



def _flowing_model(schedule, yield_stress=None, hardening=None):
    """``_grad_model``'s sliding block in the full hold (0.5 spacings up, 0.3 m/s), run by
    ``schedule``: the fused or unfused step, the tools' integrator (a sphere tool parked far
    away) or two worlds (the second block in the hold's fade, its own material)."""
    def builder(lift):
        mat = we.Material.from_young(5e3, 0.3, density=1000.0, yield_stress=60.0, flow_rate=50.0, viscosity=1.0,
                                     hardening=HARDENING)
        b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -G, 0.0))
        b.add_box((0.0, 0.02 * (lift + 0.5), 0.0), (0.06, 0.04, 0.06), mat, velocity=(0.3, 0.0, 0.075))
        b.add_ground(0.0, friction=0.0, images=True, shear_cap=1.0)
        if schedule == "tools":
            b.add_tool("sphere", radius=0.01, position=(0.0, 1.0, 0.0))
        return b
    if schedule == "worlds":
        m = finalize_worlds([builder(0.5), builder(0.9)], dtype=wp.float64, requires_grad=True)
    else:
        m = builder(0.5).finalize(dtype=wp.float64, requires_grad=True)
    m.particle_x0 += np.random.default_rng(3).normal(scale=2e-5, size=m.particle_x0.shape)
    set_first_material(m, yield_stress=yield_stress, hardening=hardening)
    return m


def _flowing_loss(model, schedule, grad=False, alpha0=ALPHA0):
    s = we.Solver(model, fused=schedule != "unfused")
    states = [model.state(requires_grad=True) for _ in range(STEPS + 1)]
    states[0].alpha.assign(alpha0 + ALPHA0 * np.random.default_rng(5).uniform(-0.5, 0.5, model.particle_count))
    states[0].F.assign(np.broadcast_to(FLOWING_F, (model.particle_count, 3, 3)))
    loss, tape = taped_rollout_loss(s, states, DT, random_weights(model.particle_count, 7))
    if not grad:
        return loss.numpy()[0]
    grown = states[-1].alpha.numpy() - states[0].alpha.numpy()
    assert grown.min() > 1e-3, grown.min()  # the base hardens inside the window, not only at its start
    tape.backward(loss)
    return model.yield_stress.grad.numpy()[0], model.hardening.grad.numpy()[0], states[0].alpha.grad.numpy().sum()


@pytest.mark.parametrize("schedule", ["fused", "unfused", "tools", "worlds"])
def test_gradients_through_a_flowing_hardening_base_match_central_differences(schedule):
    """The yield stress, the hardening and the initial ``alpha`` through 8 steps of a block
    sliding on the Tresca ground while it flows (``FLOWING_F``: its ``alpha`` grows by more
    than 1e-3 in the window, so the hold of each later step reads an ``alpha`` the flow wrote
    on the tape), in the fused and unfused steps, the tools' integrator and two worlds: the
    float64 tape against central differences at a relative step of 1e-5."""
    g_y, g_k, g_a = _flowing_loss(_flowing_model(schedule), schedule, grad=True)
    assert g_y != 0.0 and g_k != 0.0 and g_a != 0.0
    for value, key, p0 in ((g_y, "yield_stress", 60.0), (g_k, "hardening", HARDENING), (g_a, "alpha0", ALPHA0)):
        h = 1e-5 * p0
        at = [_flowing_loss(_flowing_model(schedule), schedule, alpha0=p0 + d) if key == "alpha0" else
              _flowing_loss(_flowing_model(schedule, **{key: p0 + d}), schedule) for d in (h, -h)]
        fd = (at[0] - at[1]) / (2 * h)
        print(schedule, key, value, fd)
        assert value == pytest.approx(fd, rel=1e-5, abs=1e-9 * abs(fd) + 1e-12), key
