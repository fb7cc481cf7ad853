"""The rollout as a torch.autograd.Function (warp_esph.torch)."""

import sys

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.rollout import Rollout

torch = pytest.importorskip("torch")

from warp_esph.torch import RolloutModule, require_torch, rollout_positions  # noqa: E402


def _cube(yield_stress=10.0, flow_rate=50.0):
    """27 particles, stretched and squeezed so they yield within a few steps (float64).

    No SPH pressure: its clamp max(p, 0) has its kink exactly at the rest density, where
    every particle starts, so a finite difference of x0 would straddle it."""
    mat = we.Material(mu=1.0e3, lam=1.5e3, yield_stress=yield_stress, flow_rate=flow_rate, hardening=200.0,
                      pressure_stiffness=0.0, density=1000.0)
    # Support radius 2.5 dx: no lattice distance (1, 1.41, 1.73, 2, 2.24, 2.45 dx) is near it, so a
    # finite difference of x0 does not straddle a neighbour entering the support (a kink).
    b = we.SceneBuilder(spacing=0.02, support_radius=0.05)
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), mat)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    # Jitter: exact distance ties would let a finite difference flip the neighbour choice.
    model.particle_x0 += np.random.default_rng(5).normal(scale=2e-5, size=model.particle_x0.shape)
    model.particle_v0 = 20.0 * model.particle_x0 * np.array([1.0, -0.5, 0.0])
    return model


def test_gradcheck_parameters_and_initial_state():
    model = _cube()
    assert model.particle_count == 27
    rollout = Rollout(model, 3, 1.0e-3, frames=[2, 3])
    log_p = torch.log(torch.tensor([[1.0e3], [1.5e3], [10.0], [50.0], [200.0]], dtype=torch.float64)).requires_grad_()
    x0 = torch.tensor(model.particle_x0, dtype=torch.float64, requires_grad=True)
    v0 = torch.tensor(model.particle_v0, dtype=torch.float64, requires_grad=True)
    names = ["mu", "lam", "yield_stress", "flow_rate", "hardening"]

    def positions(log_p, x0, v0):
        return rollout_positions(rollout, {n: torch.exp(log_p[k]) for k, n in enumerate(names)}, x0=x0, v0=v0)

    out = positions(log_p, x0, v0)
    assert out.shape == (2, 27, 3) and out.dtype == torch.float64
    # The rollout yields (so yield_stress, flow_rate and hardening matter).
    grads = torch.autograd.grad(out.square().sum(), log_p)[0]
    assert torch.all(grads.abs() > 0)
    # atol 1e-10: rtol x |J| is below 1e-8 on 99 % of the Jacobian's entries (hardening's
    # largest is 9.6e-10), so an atol of 1e-8 held them to far less than rtol and passed a
    # doubled adjoint of the hardening; the central differences' round-off needs 1.7e-12 (measured).
    assert torch.autograd.gradcheck(positions, (log_p, x0, v0), eps=1e-6, atol=1e-10, rtol=1e-5)


@pytest.mark.parametrize("motion", ["velocity", "keyframes"])
def test_gradcheck_under_a_moving_tool_with_view_and_non_contiguous_inputs(motion):
    """Under a plate that presses on the cube (the contact's force about 46 N in the second
    step), every input's gradient matches central differences: the five parameters, ``x0`` as a
    non-contiguous view of a wider leaf and ``v0`` as a transposed one. A float32 ``mu`` into
    the float64 model gets the float64 gradient, rounded. eps = 1e-7: the contact's smoothstep
    curves the positions within 1e-5 m of ``x0`` (a difference of 1e-6 is 3e-4 off there)."""
    from warp_esph import tools  # noqa: PLC0415

    kind = None if motion == "velocity" else tools.Keyframes(times=(0.0, 0.003), positions=((0.0, 0.021, 0.0),
                                                                                            (0.0, 0.018, 0.0)))
    model = _cube_under_plate(kind)
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    names = ["mu", "lam", "yield_stress", "flow_rate", "hardening"]
    log_p = torch.log(torch.tensor([[1.0e3], [1.5e3], [10.0], [50.0], [200.0]], dtype=torch.float64)).requires_grad_()
    wide = torch.zeros(27, 5, dtype=torch.float64)
    wide[:, 1:4] = torch.from_numpy(model.particle_x0)
    wide.requires_grad_()
    vt = torch.tensor(model.particle_v0.T.copy(), requires_grad=True)
    assert not wide[:, 1:4].is_contiguous() and not vt.t().is_contiguous()

    def positions(log_p, wide, vt):
        return rollout_positions(rollout, {n: torch.exp(log_p[k]) for k, n in enumerate(names)}, x0=wide[:, 1:4], v0=vt.t())

    positions(log_p, wide, vt)
    assert np.abs(rollout.step_forces()).max() > 10.0  # the plate presses
    # atol 3e-10: at 1e-8 the random projections passed a doubled adjoint of the yield stress;
    # the differences' round-off at eps = 1e-7 needs 2.8e-11 entry by entry (measured).
    assert torch.autograd.gradcheck(positions, (log_p, wide, vt), eps=1e-7, atol=3e-10, rtol=1e-5, fast_mode=True)
    mu32 = torch.tensor([1.0e3], dtype=torch.float32, requires_grad=True)
    rollout_positions(rollout, {"mu": mu32}).square().sum().backward()
    assert mu32.grad.dtype == torch.float32
    assert mu32.grad.item() == np.float32(_mu_gradient(rollout))


def test_one_v0_for_every_particle_runs_as_the_same_v0_per_particle_and_gets_their_summed_gradient():
    """``Rollout.forward`` took ``alpha0`` as one number for every particle but refused one
    ``(3,)`` ``v0``; both it and the bridge now take one velocity for every particle, whose
    gradient is the sum of the particles' (autograd's, through the expansion)."""
    model = _cube()
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    v = torch.tensor([0.2, -0.1, 0.05], dtype=torch.float64, requires_grad=True)
    each = v.detach().expand(27, 3).clone().requires_grad_()
    out_one = rollout_positions(rollout, v0=v)
    (g_one,) = torch.autograd.grad(out_one.square().sum(), v)
    out_each = rollout_positions(rollout, v0=each)
    (g_each,) = torch.autograd.grad(out_each.square().sum(), each)
    assert torch.equal(out_one, out_each)
    assert g_one.shape == (3,) and bool((g_one.abs() > 0).all())
    torch.testing.assert_close(g_one, g_each.sum(dim=0), rtol=1e-12, atol=0.0)
    np.testing.assert_array_equal(rollout.forward(v0=v.detach().numpy()), out_one.detach().numpy())
    with pytest.raises(ValueError, match=r"^x0 with shape \(3,\) is not allowed: must be a torch tensor of shape \(27, 3\)$"):
        rollout_positions(rollout, x0=torch.zeros(3, dtype=torch.float64))
    # A NaN in the one velocity is refused as that velocity (it was "first at index 0").
    with pytest.raises(ValueError, match=r"^v0 = \[0\.2, nan, 0\.05\] is not allowed: the one v0 given for every "
                                         r"particle has non-finite values$"):
        rollout_positions(rollout, v0=torch.tensor([0.2, float("nan"), 0.05], dtype=torch.float64))


def test_backward_leaves_the_model_holding_the_values_it_held():
    """A backward whose forward's values had been replaced since (set_parameters, a later
    forward, set_material) re-ran that forward, right, but left the model holding them: the
    user's later values were undone without a word, and the next plain run used the old ones."""
    model = _cube()
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])

    def mu():
        return torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)

    ref = mu()
    rollout_positions(rollout, {"mu": ref}).square().sum().backward()
    assert ref.grad.abs().item() > 0.0
    for change in ("set_parameters", "later forward", "set_material"):
        m = mu()
        loss = rollout_positions(rollout, {"mu": m}).square().sum()
        if change == "set_parameters":
            rollout.set_parameters({"mu": np.array([2.0e3])})
        elif change == "later forward":
            rollout_positions(rollout, {"mu": torch.tensor([2.0e3], dtype=torch.float64)})
        else:
            model.set_material(0, model.materials[0].replace(mu=2.0e3, yield_stress=20.0))
        loss.backward()
        assert m.grad.item() == pytest.approx(ref.grad.item(), rel=1e-12, abs=0.0), change  # this forward's gradient
        assert rollout.get_parameters()["mu"].tolist() == [2.0e3], change  # and the model as it was
        if change == "set_material":
            assert rollout.get_parameters()["yield_stress"].tolist() == [20.0] and model.materials[0].mu == 2.0e3
    # A material change set_parameters cannot put back: refused, as Rollout.backward refuses it.
    loss = rollout_positions(rollout, {"mu": mu()}).square().sum()
    model.set_material(0, model.materials[0].replace(clamp_pressure=not model.materials[0].clamp_pressure))
    with pytest.raises(RuntimeError, match=r"^backward is not allowed: materials\[0\]\.clamp_pressure changed since this "
                                           r"forward"):
        loss.backward()


def _cube_under_plate(motion=None):
    """``_cube``'s 27 particles with a plate pressing on the top layer (y = 0.02) from the first
    step (float64): the tool's motion, gravity (against the plate) and the contact law matter."""
    from warp_esph import tools  # noqa: PLC0415

    model = _cube()
    b = we.SceneBuilder(spacing=0.02, support_radius=0.05)
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), model.materials[0])
    if motion is None:
        motion = tools.Velocity(position=(0.0, 0.021, 0.0), velocity=(0.0, -1.0, 0.0))
    b.add_tool("plane", normal=(0.0, -1.0, 0.0), motion=motion)
    with_tool = b.finalize(dtype=wp.float64, requires_grad=True)
    with_tool.particle_x0[:], with_tool.particle_v0[:] = model.particle_x0, model.particle_v0
    return with_tool


def _mu():
    return torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)


def _mu_gradient(rollout):
    """The gradient of the squared positions' sum with respect to mu = 1000, through the bridge."""
    m = _mu()
    rollout_positions(rollout, {"mu": m}).square().sum().backward()
    return m.grad.item()


@pytest.mark.parametrize("change", ["particle_v0", "particle_x0", "tool velocity"])
def test_backward_re_runs_its_forward_from_the_start_and_tools_that_forward_ran_with(change):
    """A backward that re-ran its forward (the rollout had run since) started it from the
    model's ``particle_x0`` / ``particle_v0`` and ran the tools' arrays as they were then, not
    as that forward had: set for a later forward, they gave the gradient of another point
    without a word (measured: the shear modulus's gradient 2.2 times its own for a doubled particle_v0).
    The re-run takes the forward's; the model keeps what was set since."""
    mu, gradient = _mu, _mu_gradient
    model = _cube_under_plate()
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    ref = gradient(rollout)
    m = mu()
    loss = rollout_positions(rollout, {"mu": m}).square().sum()
    if change == "tool velocity":
        new = 2.0 * model.tools.velocity.numpy()
        model.tools.velocity.assign(new)
    else:
        new = getattr(model, change) * (2.0 if change == "particle_v0" else 1.02)
        setattr(model, change, new)
        # The model holds this very array: compared with it, a write into it in place would
        # compare it with itself.
        new = new.copy()
    rollout_positions(rollout, {"mu": torch.tensor([1.0e3], dtype=torch.float64)})  # a later forward
    loss.backward()
    assert m.grad.item() == pytest.approx(ref, rel=1e-12, abs=0.0)
    # The model keeps what was set, and the change matters (the gradient there is another).
    now = model.tools.velocity.numpy() if change == "tool velocity" else getattr(model, change)
    np.testing.assert_array_equal(now, new)
    assert abs(gradient(rollout) - ref) > 1e-3 * abs(ref)


@pytest.mark.parametrize("change", ["dt", "gravity", "contact_ramp"])
def test_backward_re_runs_its_forward_at_the_dt_gravity_and_contact_law_that_forward_ran_with(change):
    """A backward that re-ran its forward (the rollout had run since) ran it at ``rollout.dt``,
    the model's gravity and contact ramp as they were then, not as that forward had: set for a
    later forward, they gave the gradient of another run without a word (measured: dt 1 -> 2 ms,
    the shear modulus's gradient 6.5 times its own). The re-run takes the forward's; the
    rollout and model keep what was set since."""
    model = _cube_under_plate()
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    owner, new = {"dt": (rollout, 2.0e-3), "gravity": (model, (0.0, -300.0, 0.0)),
                  "contact_ramp": (model, 0.0)}[change]
    ref = _mu_gradient(rollout)
    m = _mu()
    loss = rollout_positions(rollout, {"mu": m}).square().sum()
    setattr(owner, change, new)
    rollout_positions(rollout, {"mu": torch.tensor([1.0e3], dtype=torch.float64)})  # a later forward
    loss.backward()
    assert m.grad.item() == pytest.approx(ref, rel=1e-12, abs=0.0)
    # The setting kept, and it matters (the gradient there is another).
    assert getattr(owner, change) == new
    assert abs(_mu_gradient(rollout) - ref) > 1e-3 * abs(ref)


def test_a_checkpointed_backward_refuses_a_dt_or_gravity_set_since_its_forward():
    """A checkpointed backward re-runs its segments, and ran them at the dt and gravity it found:
    set after the forward, they gave the gradient of another run (measured: dt 1 -> 2 ms, mu's
    5.1 times its own; gravity 9.81 -> 300 m/s^2, 0.57 times), through ``Rollout.backward``
    and the bridge alike. ``Rollout.backward`` refuses such a change by name, as it refuses a
    parameter's; the bridge re-runs its forward at the forward's settings. A solver setting the bridge cannot put back (the model's
    hourglass strength) is refused by name."""
    model = _cube_under_plate()
    rollout = Rollout(model, 4, 1.0e-3, frames=[4], checkpoint_every=2)
    ref = _mu_gradient(rollout)
    g = np.ones((1, 27, 3))
    for name, owner, new, shown in (("dt", rollout, 2.0e-3, r"dt \(0\.001, now 0\.002\)"),
                                    ("gravity", model, (0.0, -300.0, 0.0), r"gravity \(\(0\.0, -9\.81, 0\.0\), now "
                                                                            r"\(0\.0, -300\.0, 0\.0\)\)")):
        old = getattr(owner, name)
        rollout.forward()
        setattr(owner, name, new)
        with pytest.raises(RuntimeError, match=rf"^backward\(\) is not allowed: {shown} changed since forward\(\)"):
            rollout.backward(g)
        setattr(owner, name, old)
        m = _mu()
        loss = rollout_positions(rollout, {"mu": m}).square().sum()
        setattr(owner, name, new)
        loss.backward()
        assert m.grad.item() == pytest.approx(ref, rel=1e-12, abs=0.0), name
        assert getattr(owner, name) == new
        setattr(owner, name, old)
    loss = rollout_positions(rollout, {"mu": _mu()}).square().sum()
    model.hourglass = 0.1
    with pytest.raises(RuntimeError, match=r"^backward is not allowed: the solver's hourglass \(0\.0, now 0\.1\) changed "
                                           r"since this forward"):
        loss.backward()
    assert rollout.get_parameters()["mu"].tolist() == [1.0e3]


def test_a_tool_parameter_is_refused_as_an_input_and_its_gradient_is_left_on_the_tools():
    """A tool's friction given to ``rollout_positions`` was refused as 'must be one of mu, lam,
    ...', which did not say where a tool's parameter goes: it is refused as a tool parameter,
    set on ``model.tools``, whose gradient the bridge's backward leaves on the tools' array; that
    gradient matches central differences of the bridge's loss."""
    model = _cube_under_plate()
    model.tools.friction.assign(np.array([0.3]))
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    with pytest.raises(ValueError, match=r"^parameter 'friction' is not allowed: it is a tool parameter, not an input of "
                                         r"the torch bridge \(set model\.tools\.friction before the forward; the backward "
                                         r"leaves its gradient on model\.tools\.friction\.grad\); the bridge takes mu, lam"):
        rollout_positions(rollout, {"friction": torch.tensor([0.3], dtype=torch.float64, requires_grad=True)})
    with pytest.raises(ValueError, match=r"^parameter 'velocity' is not allowed: it is a tool parameter"):
        RolloutModule(rollout, ["velocity"], log_space=False)
    weights = torch.from_numpy(np.random.default_rng(1).normal(size=(1, 27, 3)))

    def loss():
        return (rollout_positions(rollout, {"mu": _mu()}) * weights).sum()

    loss().backward()
    g = model.tools.friction.grad.numpy()[0]
    e = 1.0e-6
    model.tools.friction.assign(np.array([0.3 + e]))
    up = loss().item()
    model.tools.friction.assign(np.array([0.3 - e]))
    down = loss().item()
    assert g != 0.0 and g == pytest.approx((up - down) / (2.0 * e), rel=1e-6)


def test_a_scripted_motion_changed_since_the_forward_is_refused_where_a_backward_calls_it_again():
    """A Scripted motion is a Python callable, called again by a checkpointed backward's re-run
    of its segments and by the bridge's re-run of its forward: one changed since (here its
    closure's speed, doubled for a later forward) gave the gradient of another trajectory
    without a word (measured: the shear modulus's 0.58 times its own). Each re-run checks the
    poses it is given against the forward's and refuses another by tool and time (also at a
    second backward, ``retain_graph``, which had gone through the refused run's tape); the same
    motion, set back, gives the forward's gradient."""
    from warp_esph import tools  # noqa: PLC0415

    speed = [1.0]
    model = _cube_under_plate(tools.Scripted(lambda t: ((0.0, 0.021 - speed[0] * t, 0.0), (0.0, 0.0, 0.0, 1.0))))
    gone = r"the Scripted motion of tool 'plane_tool0' gives position \[0\.0, 0\.019.*\] at t = 0\.001 s, where"
    with pytest.warns(UserWarning, match="Scripted motions, evaluated on the host"):  # once per tool set
        for every in (None, 2):
            rollout = Rollout(model, 4, 1.0e-3, frames=[4], checkpoint_every=every)
            ref = _mu_gradient(rollout)
            for later in (True, False):
                m = _mu()
                loss = rollout_positions(rollout, {"mu": m}).square().sum()
                speed[0] = 2.0
                if later:
                    rollout_positions(rollout, {"mu": torch.tensor([1.0e3], dtype=torch.float64)})
                if later or every:
                    words = (r"^backward is not allowed: " + gone + r" this forward had") if later else \
                        (r"^backward\(\) is not allowed: " + gone + r" forward\(\) had")
                    with pytest.raises(RuntimeError, match=words):
                        loss.backward(retain_graph=True)
                    with pytest.raises(RuntimeError, match=words):  # again: the refused run is not the forward's
                        loss.backward()
                    speed[0] = 1.0
                    m = _mu()
                    loss = rollout_positions(rollout, {"mu": m}).square().sum()
                    if later:
                        rollout_positions(rollout, {"mu": torch.tensor([1.1e3], dtype=torch.float64)})
                loss.backward()  # a full tape's recorded poses, without a re-run: its own gradient
                speed[0] = 1.0
                assert m.grad.item() == pytest.approx(ref, rel=1e-12, abs=0.0), (every, later)
                assert rollout.get_parameters()["mu"].tolist() == [1.0e3 if not later else 1.1e3]


def test_a_rollout_s_steps_frames_and_segments_are_fixed_once_made():
    """``rollout.frames`` or ``rollout.steps`` set after the rollout was made (between a torch
    forward and its backward, say) was taken without a word and ran half of it: frames = (3,)
    on a rollout of frames (2, 3) still returned both, steps = 5 ran five steps and returned the
    third's positions. Each is refused by name; the rollout runs as made."""
    model = _cube()
    rollout = Rollout(model, 3, 1.0e-3, frames=[2, 3], checkpoint_every=2)
    mu = _mu()
    out = rollout_positions(rollout, {"mu": mu})
    for name, value in (("steps", 5), ("frames", (3,)), ("segment", 3), ("checkpointing", False),
                        ("segments", [(0, 3)]), ("taped", False)):
        was = getattr(rollout, name)
        with pytest.raises(ValueError, match=rf"^Rollout\.{name} = .* is not allowed: this rollout's states, frame slots "
                                             rf"and force rows were made for {name} = "):
            setattr(rollout, name, value)
        assert getattr(rollout, name) == was
    out.square().sum().backward()
    assert mu.grad.item() == pytest.approx(_mu_gradient(Rollout(model, 3, 1.0e-3, frames=[2, 3])), rel=1e-9, abs=0.0)


def test_backward_after_the_rollout_was_released_re_runs_its_forward():
    """``rollout.release()`` between a torch forward and its backward freed the run, and the
    backward raised Rollout's 'backward() before forward(): run forward() first', a call the
    bridge's user never makes; it re-runs the forward, as after another forward."""
    model = _cube()
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    ref = torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)
    rollout_positions(rollout, {"mu": ref}).square().sum().backward()
    mu = torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)
    loss = rollout_positions(rollout, {"mu": mu}).square().sum()
    rollout.release()
    loss.backward()
    assert mu.grad.item() == pytest.approx(ref.grad.item(), rel=1e-12, abs=0.0) and ref.grad.item() != 0.0


def test_a_run_nothing_goes_back_through_records_no_tape():
    """Under ``torch.no_grad()``, or with no input that requires grad, the bridge recorded a tape
    of every step for nothing, and a ``Rollout(taped=False)``, made for such runs, was refused
    as 'taped = True is not allowed', a value its caller never gave. Such a run is untaped now
    (the same positions; a new rollout's taped states are never allocated), and a
    ``Rollout(taped=False)`` is refused in the bridge's words only where an input requires grad."""
    model = _cube()
    ref = Rollout(model, 3, 1.0e-3, frames=[2, 3])
    mu = torch.tensor([1.2e3], dtype=torch.float64, requires_grad=True)
    expected = rollout_positions(ref, {"mu": mu})
    assert expected.requires_grad
    for taped in (True, False):
        rollout = Rollout(model, 3, 1.0e-3, frames=[2, 3], taped=taped)
        with torch.no_grad():
            out = rollout_positions(rollout, {"mu": mu})
        assert torch.equal(out, expected.detach()) and not out.requires_grad
        assert torch.equal(rollout_positions(rollout, {"mu": mu.detach()}), expected.detach())
        assert rollout.memory_bytes()["taped_states"] == 0
    with pytest.raises(ValueError, match=r"^rollout is not allowed with inputs that require grad: it was made with "
                                         r"taped = False"):
        rollout_positions(rollout, {"mu": mu})
    # The taped graph made before the untaped runs still gives its own gradient.
    expected.square().sum().backward()
    g = mu.grad.item()
    mu.grad = None
    rollout_positions(ref, {"mu": mu}).square().sum().backward()
    assert mu.grad.item() == pytest.approx(g, rel=1e-12, abs=0.0) and g != 0.0


def test_each_start_is_checked_once_per_forward_and_backward(start_checks):
    """x0's check (``check_initial``: its search for coincident particles, 17 ms at 64k
    particles) ran in ``rollout_positions``, again in the forward, and a third time where the
    backward re-ran that forward: once per start now, and the re-run starts from the values
    checked, also where the tensor was changed in place since (its gradient is the forward's)."""
    model = _cube()
    rollout = Rollout(model, 2, 1.0e-3, frames=[2])
    calls = start_checks

    def start():
        return torch.tensor(model.particle_x0, dtype=torch.float64, requires_grad=True)

    v0 = torch.tensor(model.particle_v0, dtype=torch.float64)  # stretching: x0 matters within the steps
    ref = start()
    rollout_positions(rollout, x0=ref, v0=v0).square().sum().backward()
    assert calls == ["x0", "v0"]
    calls.clear()
    # Two forwards, then one backward through both: the first's re-runs its forward.
    x, other = start(), start()
    with torch.no_grad():
        other[0, 0] += 1.0e-3
    loss = rollout_positions(rollout, x0=x, v0=v0).square().sum()
    later = rollout_positions(rollout, x0=other).square().sum()
    with torch.no_grad():
        x[0, 0] += 1.0  # in place, after its forward
    (loss + 0.0 * later).backward()
    assert calls == ["x0", "v0", "x0"]
    np.testing.assert_allclose(x.grad.numpy(), ref.grad.numpy(), rtol=1e-12, atol=1e-15)


def test_a_torch_iteration_reads_the_parameters_whole_and_writes_only_changed_values(monkeypatch):
    """A forward and backward read each parameter array apart 27 times (``get_parameters`` three
    times, ``set_parameters`` once; a wait for the device each on a GPU), and wrote every given
    value, also one the array held. They are read whole now (``Model._read_parameters``), and
    only a changed value is written; the gradient is the same."""
    model = _cube()
    rollout = Rollout(model, 2, 1.0e-3, frames=[2])
    ref = torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)  # the material's mu
    rollout_positions(rollout, {"mu": ref}).square().sum().backward()
    fields = {id(getattr(model, name)): name for name in model.MATERIAL_FIELDS}
    reads, writes = [], []
    real_numpy, real_assign = wp.array.numpy, wp.array.assign

    def numpy(a):
        if id(a) in fields:
            reads.append(fields[id(a)])
        return real_numpy(a)

    def assign(a, src):
        if id(a) in fields:
            writes.append(fields[id(a)])
        return real_assign(a, src)

    monkeypatch.setattr(wp.array, "numpy", numpy)
    monkeypatch.setattr(wp.array, "assign", assign)
    same = torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)
    rollout_positions(rollout, {"mu": same, "yield_stress": torch.tensor([10.0], dtype=torch.float64)}).square().sum().backward()
    assert reads == [] and writes == []
    assert same.grad.item() == ref.grad.item()
    rollout_positions(rollout, {"mu": torch.tensor([2.0e3], dtype=torch.float64, requires_grad=True)}).square().sum().backward()
    assert reads == [] and writes == ["mu"]
    assert rollout.get_parameters()["mu"].tolist() == [2.0e3]


def test_a_forward_that_blows_up_to_non_finite_values_raises_not_a_nan_tensor():
    """A rollout that blew up handed torch a tensor of NaN positions, and the loop went on with
    NaN losses. The bridge raises ``NonFiniteRollout`` (also a ``FloatingPointError``) naming
    the step, particle and stable step, and the model keeps the values it held: a run of them
    after the refusal is finite. The rollout runs the incremental composition (an explicit
    ``fit``): its first step of 2 s flings the particles out of each other's support, and the run
    of the held values coasts 2.4 m (measured), as it did on the rest model while an inverted rest
    fit kept ``F = I``. On the rest model, whose inverted fits are now taken with their energy
    continued through det = 0, that run takes the fit of the cube stretched 41-fold and mirrored
    in one step (its neighbour rows cut, with a warning) and reaches 7e19 m in its three steps: a
    blow-up of its own, finite only for being short."""
    from warp_esph.rollout import NonFiniteRollout  # noqa: PLC0415

    b = we.SceneBuilder(spacing=0.02, support_radius=0.05, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), we.Material(mu=1.0e3, lam=1.5e3, pressure_stiffness=0.0), name="cube")
    model = b.finalize(dtype=wp.float32, requires_grad=True)
    model.particle_v0 = 20.0 * model.particle_x0 * np.array([1.0, -0.5, 0.0])
    with pytest.warns(RuntimeWarning, match="above the explicit stability limit"):
        rollout = Rollout(model, 3, 2.0, frames=[3], solver=we.Solver(model, fit="curvature_corrected"))
    assert not rollout.solver.rest_model
    # float32 holds 3e38 m/s, but not the position it reaches in one step of 2 s.
    mu = torch.tensor([2e3], dtype=torch.float64, requires_grad=True)
    v0 = torch.tensor([3e38, 0.0, 0.0], dtype=torch.float64)
    with pytest.warns(RuntimeWarning, match="above the explicit stability limit"):  # said again by the step
        with pytest.raises(FloatingPointError, match=r"^the rollout blew up: particle 0 of body 'cube' has a non-finite "
                                                     r"position or velocity after step 1 of 3, .*use a smaller dt") as info:
            rollout_positions(rollout, {"mu": mu}, v0=v0)
    assert isinstance(info.value, NonFiniteRollout) and info.value.step == 1
    assert rollout.get_parameters()["mu"].tolist() == [1.0e3]
    assert bool(torch.isfinite(rollout_positions(rollout, {"mu": torch.tensor([2.0e3], dtype=torch.float64)})).all())


def test_torch_adam_drives_a_fit():
    """torch.optim.Adam on a RolloutModule (log-space parameter) recovers the flow rate from 2x."""
    steps, frames = 12, [4, 8, 12]
    target = torch.from_numpy(Rollout(_cube(flow_rate=50.0), steps, 1.0e-3, frames=frames).forward())
    module = RolloutModule(Rollout(_cube(flow_rate=100.0), steps, 1.0e-3, frames=frames), ["flow_rate"])
    assert isinstance(module, torch.nn.Module) and len(list(module.parameters())) == 1
    opt = torch.optim.Adam(module.parameters(), lr=0.1)
    losses = []
    # Adam's momentum overshoots: the flow rate swings about 50 (37.8 at the 17th iterate,
    # 54.5 at the 39th, measured) with a period of about 30 iterates, so where one iterate
    # lands in a swing is chance. 60 iterates and the last ten: their largest loss is
    # 1.8e-3 of the first (measured), the last flow rate 48.5.
    for _ in range(60):
        opt.zero_grad()
        # In millimetres: Adam's eps (1e-8) would swamp gradients of a loss in m^2 (~1e-10).
        loss = ((module() - target) * 1e3).square().mean()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert max(losses[-10:]) < 1e-2 * losses[0]
    assert module.values()["flow_rate"].item() == pytest.approx(50.0, rel=0.1)
    assert module.rollout.model.flow_rate.numpy()[0] == pytest.approx(module.values()["flow_rate"].item(), rel=0.1)


def test_a_tensor_without_values_to_read_is_refused_by_name():
    """A meta tensor (shapes, no values) or a sparse one reached torch's own 'Cannot copy out
    of meta tensor' or 'can't convert Sparse layout tensor to numpy', naming no input."""
    model = _cube()
    rollout = Rollout(model, 2, 1.0e-3)
    n = model.particle_count
    for name, t, kw in (("mu", torch.ones(1, device="meta"), "params"),
                        ("mu", torch.ones(1, dtype=torch.float64).to_sparse(), "params"),
                        ("x0", torch.ones(n, 3, device="meta"), "x0"),
                        ("v0", torch.zeros(n, 3, dtype=torch.float64).to_sparse(), "v0")):
        where = "on the meta device \\(no values\\)" if t.is_meta else "of layout torch.sparse_coo"
        with pytest.raises(ValueError, match=rf"^{name} {where} is not allowed: must be a dense tensor with values"):
            rollout_positions(rollout, {name: t} if kw == "params" else None, **({} if kw == "params" else {kw: t}))


def test_inputs_are_checked_and_missing_torch_is_explained(monkeypatch):
    model = _cube()
    rollout = Rollout(model, 2, 1.0e-3)
    with pytest.raises(ValueError, match="one value per material"):
        rollout_positions(rollout, {"mu": torch.ones(3, dtype=torch.float64)})
    with pytest.raises(ValueError, match="must be one of"):
        rollout_positions(rollout, {"young": torch.ones(1, dtype=torch.float64)})
    with pytest.raises(ValueError, match=r"params = \['mu'\] is not allowed: must be a mapping \{name: tensor of one "
                                         r"value per material\}$"):
        rollout_positions(rollout, ["mu"])  # was read as character pairs: "parameter 'm'"
    # A bool tensor or value ran as a shear modulus of 1 Pa (Material refuses it).
    for value in (torch.tensor([True]), True, torch.tensor([1.0 + 0j])):
        with pytest.raises(ValueError, match="mu = .* is not allowed: must be numbers, one per material"):
            rollout_positions(rollout, {"mu": value})
    with pytest.raises(ValueError, match="shape"):
        rollout_positions(rollout, x0=torch.zeros(5, 3, dtype=torch.float64))
    # An integer input gave integer positions, each truncated to 0; log_space="no" read as True.
    pos = rollout_positions(rollout, {"viscosity": torch.tensor([0])})
    assert pos.dtype == torch.float64 and float(pos.abs().max()) > 0.0
    with pytest.raises(ValueError, match="log_space = 'no' is not allowed: must be True or False"):
        RolloutModule(rollout, ["mu"], log_space="no")
    # A tensor that carries a gradient given to Material lost it in float() without a word.
    import warp_esph as we  # noqa: PLC0415

    with pytest.raises(ValueError, match="Material.mu = .* is not allowed: must be a plain number: float\\(\\) would drop"):
        we.Material(mu=torch.tensor(1.0e3, dtype=torch.float64, requires_grad=True), lam=1.0e3)
    assert we.Material(mu=torch.tensor(1.0e3, dtype=torch.float64), lam=1.0e3).mu == 1.0e3
    # None was a TypeError; a name given twice registered one parameter without a word.
    for params, words in ((None, "params = None is not allowed: give a parameter name"),
                          ([], "params = \\[\\] is not allowed"), (["mu", "mu"], "a parameter is named twice")):
        with pytest.raises(ValueError, match=words):
            RolloutModule(rollout, params)
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(ImportError, match="pip install torch"):
        require_torch()


def test_elastic_models_refused_starts_and_input_kinds():
    """From a fuzz of the torch interface. An elastic material (yield_stress = inf, the
    default) failed every backward that had to redo its forward (``set_parameters`` refused
    the inf it restores), so ``gradcheck`` failed on any elastic model; it now matches
    central differences. A call refused for its ``v0`` left the model running its new
    parameters; a float16 input made float16 positions (1.7 mm off at 5 m) and bfloat16 a
    TypeError; bool and complex starts ran as 1 m/s and as their real parts; per-material
    tensors in a list that require grad were a RuntimeError."""
    model = _cube(yield_stress=float("inf"))
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    mu = torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)
    rollout_positions(rollout, {"mu": mu * 1.1})  # another forward since: the backward redoes its own
    # atol 1e-10: the positions' derivatives in mu are 1.4e-8 at most (median 2.5e-11), so an
    # atol of 1e-8 passed a gradient half as large again; round-off needs 1.7e-12 (measured).
    assert torch.autograd.gradcheck(lambda m: rollout_positions(rollout, {"mu": m}), (mu,), eps=1e-6, atol=1e-10,
                                    rtol=1e-5)
    with pytest.raises(ValueError, match="yield_stress = .* is not allowed in log space: values must be finite and > 0"):
        RolloutModule(rollout, ["yield_stress"])
    before = model.mu.numpy().copy()
    with pytest.raises(ValueError, match="v0"):
        rollout_positions(rollout, {"mu": torch.tensor([5e3], dtype=torch.float64)},
                          v0=torch.full((27, 3), float("nan"), dtype=torch.float64))
    np.testing.assert_array_equal(model.mu.numpy(), before)
    exact = rollout_positions(rollout, {"mu": torch.tensor([1e3], dtype=torch.float64)})
    for dtype in (torch.float16, torch.bfloat16, torch.float32):
        out = rollout_positions(rollout, {"mu": torch.tensor([1e3], dtype=dtype)})
        assert out.dtype == torch.float64 and torch.equal(out, exact)  # 1e3 is exact in each
    for bad in (torch.ones((27, 3), dtype=torch.bool), torch.zeros((27, 3), dtype=torch.complex128)):
        with pytest.raises(ValueError, match=f"v0 of dtype {bad.dtype} is not allowed: must be real numbers"):
            rollout_positions(rollout, {}, v0=bad)
    for bad in ([torch.tensor(True)], [torch.tensor(1.0e3 + 5.0j)]):  # in a list they ran as 1 Pa / the real part
        with pytest.raises(ValueError, match="mu = .* is not allowed: must be numbers, one per material"):
            rollout_positions(rollout, {"mu": bad})
    two = _cube()
    two.set_material(0, two.materials[0])
    t = torch.tensor(1.0e3, dtype=torch.float64, requires_grad=True)
    out = rollout_positions(Rollout(two, 2, 1.0e-3), {"mu": [t]})
    (g,) = torch.autograd.grad(out.square().sum(), t)
    assert float(g) != 0.0


def test_the_output_is_of_every_given_tensor_s_dtype_and_tensors_on_two_devices_are_refused():
    """The output took the first given tensor's dtype and device: a float32 model gave float32
    positions for a float16 ``v0`` and a float64 ``mu``, float64 for the two swapped; and a
    ``mu`` on one device with an ``x0`` on another sent the positions (and every gradient) to
    ``x0``'s, where torch refused ``mu``'s gradient at the backward, naming no input (or, as here
    on a host without CUDA, the copy out failed). The dtype is promoted over every given float
    tensor and the model's precision; tensors on two devices are refused by name before
    anything runs. (A CUDA tensor cannot be made here: a tensor that reports ``cuda:0`` stands
    in for one.)"""

    class Elsewhere(torch.Tensor):
        @property
        def device(self):
            return torch.device("cuda", 0)

    b = we.SceneBuilder(spacing=0.02, support_radius=0.05)
    b.add_box((0.0, 0.0, 0.0), (0.04, 0.04, 0.04), we.Material(mu=1.0e3, lam=1.5e3))
    single = Rollout(b.finalize(dtype=wp.float32, requires_grad=True), 2, 1.0e-3)
    v = torch.tensor([0.25, -0.5, 0.0])
    one = rollout_positions(single, {"mu": torch.tensor([2.0e3], dtype=torch.float64)}, v0=v.half())
    other = rollout_positions(single, {"mu": torch.tensor([2.0e3], dtype=torch.float16)}, v0=v.double())
    assert one.dtype == other.dtype == torch.float64 and torch.equal(one, other)
    assert rollout_positions(single, v0=v.half()).dtype == torch.float32  # the model's precision at least

    model = _cube()
    rollout = Rollout(model, 2, 1.0e-3)
    runs, before = rollout.forward_count, rollout.get_parameters()["mu"].copy()
    x0 = torch.tensor(model.particle_x0).as_subclass(Elsewhere).requires_grad_()
    with pytest.raises(ValueError, match=r"^mu on cpu and x0 on cuda:0 are not allowed together: give every tensor on "
                                         r"one device"):
        rollout_positions(rollout, {"mu": torch.tensor([2.0e3], dtype=torch.float64, requires_grad=True)}, x0=x0)
    assert rollout.forward_count == runs and rollout.get_parameters()["mu"].tolist() == before.tolist()


def test_a_start_the_builder_would_refuse_is_refused_before_anything_runs():
    """``x0`` with every particle at one point (which ``SceneBuilder`` refuses) ran and
    returned the start moved only by gravity; the bridge now refuses it, a non-finite ``x0``
    or ``v0`` and a start that is no tensor by name, before the parameters are set or any
    step runs. ``Rollout.forward`` refuses the same starts."""
    model = _cube()
    rollout = Rollout(model, 2, 1.0e-3)
    x = torch.tensor(model.particle_x0, dtype=torch.float64)
    mu_before, runs = model.mu.numpy().copy(), rollout.forward_count
    mu = {"mu": torch.tensor([5.0e3], dtype=torch.float64)}
    with pytest.raises(ValueError, match=r"^x0 is not allowed: 26 particles coincide with another \(first: particle 0 "
                                         r"at \[0.0, 0.0, 0.0\]\); each particle needs a place of its own"):
        rollout_positions(rollout, mu, x0=torch.zeros(27, 3, dtype=torch.float64))
    twice = x.clone()
    twice[5] = twice[3]
    with pytest.raises(ValueError, match=r"^x0 is not allowed: 1 particles coincide with another \(first: particle 3 "):
        rollout_positions(rollout, mu, x0=twice.requires_grad_())
    for label, bad in (("x0", x.clone().index_fill_(0, torch.tensor([4]), float("nan"))),
                       ("v0", torch.zeros(27, 3, dtype=torch.float64).index_fill_(0, torch.tensor([7]), float("inf")))):
        with pytest.raises(ValueError, match=rf"^{label} is not allowed: it has non-finite values \(first at index "
                                             rf"{4 if label == 'x0' else 7}\)"):
            rollout_positions(rollout, mu, **{label: bad})
    with pytest.raises(ValueError, match=r"^x0 = array\(.* is not allowed: must be a torch tensor of shape \(27, 3\)"):
        rollout_positions(rollout, mu, x0=model.particle_x0)
    with pytest.raises(ValueError, match=r"^v0 with shape \(27,\) is not allowed: must be a torch tensor of shape"):
        rollout_positions(rollout, mu, v0=torch.zeros(27, dtype=torch.float64))
    # Nothing ran and the model keeps its parameters.
    assert rollout.forward_count == runs
    np.testing.assert_array_equal(model.mu.numpy(), mu_before)
    with pytest.raises(ValueError, match=r"^x0 is not allowed: 26 particles coincide"):
        rollout.forward(x0=np.zeros((27, 3)))
    assert rollout.forward_count == runs
    # A start whose particles are apart (the jittered lattice, moved) runs.
    out = rollout_positions(rollout, mu, x0=x + 0.01)
    assert out.shape == (1, 27, 3) and bool(torch.isfinite(out).all())


def test_tensors_given_to_the_numpy_side_are_read_or_refused_by_name():
    """The rollout, the losses and the builder read their arrays with numpy: a torch tensor
    that requires grad (a target or a start straight out of a torch pipeline) failed there
    with torch's own RuntimeError, naming no parameter, and a bfloat16 one with a TypeError;
    an ``(n, 3)`` tensor as the one frame's gradient was split into n frames. Now a tensor
    is copied to the host (float64; the float32 model takes it as it takes numpy float64),
    and one that requires grad is refused by name, since reading it would drop its gradient."""
    from warp_esph.losses import PositionLoss  # noqa: PLC0415

    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.0, 0.0), (0.04, 0.04, 0.04), we.Material(mu=1.0e3, lam=1.5e3))
    model = b.finalize(dtype=wp.float32, requires_grad=True)
    n = model.particle_count
    rollout = Rollout(model, 1, 1.0e-3)
    target = model.particle_x0.astype(np.float64) + 1e-3
    want = rollout.value_and_grad(PositionLoss({1: target}))[0]
    assert rollout.value_and_grad(PositionLoss({1: torch.tensor(target)}))[0] == want
    rounded = torch.tensor(target, dtype=torch.bfloat16)
    assert rollout.value_and_grad(PositionLoss({1: rounded}))[0] == rollout.value_and_grad(PositionLoss({1: rounded.double()}))[0]
    g = np.ones((n, 3))
    assert np.array_equal(rollout.backward(torch.tensor(g))[1]["v0"], rollout.backward(g)[1]["v0"])
    grad = "is not allowed: it is a torch tensor that requires grad, and reading its values would drop its gradient"
    for call in (lambda t: PositionLoss({1: t}), lambda t: rollout.forward(v0=t),
                 lambda t: rollout.backward([t]), lambda t: we.SceneBuilder(spacing=0.02).add_particles(t, we.Material(mu=1e3, lam=1e3))):
        with pytest.raises(ValueError, match=grad):
            call(torch.tensor(target, requires_grad=True))
    with pytest.raises(ValueError, match=rf"^mu = .* {grad}"):
        rollout.set_parameters({"mu": torch.tensor([2.0e3], requires_grad=True)})
    # One tensor per material in a list: numpy read each with torch's own RuntimeError.
    with pytest.raises(ValueError, match=rf"^mu = .* {grad}"):
        rollout.set_parameters({"mu": [torch.tensor(2.0e3, requires_grad=True)]})
    rollout.set_parameters({"mu": [torch.tensor(2.0e3)]})
    assert rollout.get_parameters()["mu"].tolist() == [2.0e3]
    # A lazily negated view (its negative bit set): numpy() refused it with torch's own error.
    z = torch.tensor([1.0 - 3.0e3j], dtype=torch.complex128).conj()
    rollout.set_parameters({"mu": z.imag})
    assert z.imag.is_neg() and rollout.get_parameters()["mu"].tolist() == [3.0e3]
    with pytest.raises(ValueError, match=r"^mu = .* is not allowed: must be numbers, one per material$"):
        rollout.set_parameters({"mu": z})  # a conjugated complex one: complex, refused as such
    v = torch.full((n, 3), 0.1j, dtype=torch.complex128).conj().imag  # -0.1 m/s each, its negative bit set
    assert v.is_neg()
    np.testing.assert_array_equal(rollout_positions(rollout, {"mu": z.imag}, v0=v).numpy(),
                                  rollout_positions(rollout, {"mu": z.imag.resolve_neg()}, v0=v.resolve_neg()).numpy())
    # No values to read: torch's 'Cannot copy out of meta tensor' and 'can't convert Sparse
    # layout tensor to numpy' named no input.
    for t, where in ((torch.empty(n, 3, device="meta"), r"on the meta device \(no values\)"),
                     (torch.zeros(n, 3).to_sparse(), r"of layout torch\.sparse_coo")):
        for name, call in (("x0", lambda t: rollout.forward(x0=t)), ("targets at step 1", lambda t: PositionLoss({1: t}))):
            with pytest.raises(ValueError, match=rf"^{name} = .* is not allowed: it is a torch tensor {where}; give a "
                                                 r"dense tensor with values"):
                call(t)


def test_a_tensor_that_requires_grad_is_refused_by_name_at_the_other_numpy_entry_points(tmp_path):
    """The savers, the fit's target, a loss's particle mask and the slump and force losses'
    inputs read their arrays with numpy: a tensor that requires grad failed there with
    torch's own RuntimeError ("Can't call numpy() on Tensor that requires grad"), naming no
    parameter. Each now refuses it by the parameter's name, as the rollout's inputs do."""
    from warp_esph.fit import _target_loss, save_target  # noqa: PLC0415
    from warp_esph.losses import PositionLoss, ReactionForceLoss, SlumpLoss  # noqa: PLC0415
    from warp_esph.meshes import write_mesh  # noqa: PLC0415

    def t(shape):
        return torch.zeros(shape, dtype=torch.float64, requires_grad=True)

    grad = "is not allowed: it is a torch tensor that requires grad, and reading its values would drop its gradient"
    calls = {
        "positions": lambda: save_target(tmp_path / "t.npz", t((1, 4, 3)), [0]),
        "points": lambda: write_mesh(tmp_path / "m.obj", t((3, 3)), np.array([[0, 1, 2]])),
        "target": lambda: _target_loss(t((4, 3)), [1]),
        "particles": lambda: PositionLoss(np.zeros((2, 3)), frames=[1], particles=t(2)),
        "center": lambda: SlumpLoss(0.1, None, 3, 0.02, center=t(2)),
        "positions at step 1": lambda: SlumpLoss(0.1, None, 1, 0.02).value_and_grad({1: t((4, 3))}),
        "targets": lambda: ReactionForceLoss(t(2), "tool", steps=[5, 10], window=2, components="y"),
    }
    for name, call in calls.items():
        with pytest.raises(ValueError, match=rf"^{name} = tensor\(.* {grad}"):
            call()
    assert not (tmp_path / "t.npz").exists() and not (tmp_path / "m.obj").exists()
    # Without requires grad the same tensors are read as numpy (a detached target is saved).
    save_target(tmp_path / "t.npz", t((1, 4, 3)).detach() + 1.0, [0])
    np.testing.assert_array_equal(np.load(tmp_path / "t.npz")["positions"], np.ones((1, 4, 3)))


def test_a_parameter_tensor_of_a_non_real_dtype_is_refused_naming_its_dtype():
    """``x0`` / ``v0`` of a bool or complex dtype were refused naming the dtype; a parameter
    tensor's refusal showed its values alone (``mu = tensor([1.+0.j])``: a complex128 and a
    complex64 one read the same, and a long tensor is shortened past its dtype)."""
    rollout = Rollout(_cube(), 2, 1.0e-3)
    for t in (torch.tensor([True]), torch.tensor([1.0 + 0j], dtype=torch.complex64), torch.ones(1, dtype=torch.complex128)):
        with pytest.raises(ValueError, match=rf"^mu = .* \(dtype {t.dtype}\) is not allowed: must be numbers, one per "
                                             r"material$"):
            rollout_positions(rollout, {"mu": t})
    with pytest.raises(ValueError, match=r"^mu = .* \(dtype bool\) is not allowed: must be numbers, one per material$"):
        rollout_positions(rollout, {"mu": np.array([True])})


@pytest.mark.parametrize("dtype", [wp.float64, wp.float32])
def test_the_bridge_s_gradients_are_the_rollout_tape_s_bitwise_and_repeat(dtype):
    """In the model's precision, the bridge's gradients are ``Rollout.backward``'s (the Warp
    tape's) to the bit, for the inputs that require grad only (``v0`` here does not); a second
    backward through the same graph (``retain_graph``) adds the same gradient again; and a call
    with the same inputs after calls with others gives the same positions and gradients bitwise
    (nothing of the other calls is left in the model or the rollout)."""
    model = _cube()
    if dtype is wp.float32:
        b = we.SceneBuilder(spacing=0.02, support_radius=0.05)
        b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), model.materials[0])
        single = b.finalize(dtype=wp.float32, requires_grad=True)
        single.particle_x0, single.particle_v0 = model.particle_x0, model.particle_v0
        model = single
    tdtype = torch.float64 if dtype is wp.float64 else torch.float32
    rollout = Rollout(model, 3, 1.0e-3, frames=[2, 3])
    w = torch.from_numpy(np.random.default_rng(2).normal(size=(2, 27, 3))).to(tdtype)
    x0_values = torch.tensor(model.particle_x0, dtype=tdtype)
    v0 = torch.tensor(model.particle_v0, dtype=tdtype)

    def run():
        mu = torch.tensor([1.0e3], dtype=tdtype, requires_grad=True)
        x0 = x0_values.clone().requires_grad_()
        out = rollout_positions(rollout, {"mu": mu, "yield_stress": torch.tensor([10.0], dtype=tdtype)}, x0=x0, v0=v0)
        loss = (out * w).sum()
        loss.backward(retain_graph=True)
        first = (mu.grad.clone(), x0.grad.clone())
        loss.backward()
        assert torch.equal(mu.grad, 2 * first[0]) and torch.equal(x0.grad, 2 * first[1])
        assert v0.grad is None and out.dtype == tdtype
        return out.detach(), first

    out, (g_mu, g_x0) = run()
    rollout.set_parameters({"mu": np.array([1.0e3]), "yield_stress": np.array([10.0])})
    expected = rollout.forward(x0=x0_values.numpy(), v0=v0.numpy())
    _, grads = rollout.backward(w.numpy())
    np.testing.assert_array_equal(out.numpy(), expected)
    assert g_mu.dtype == tdtype and g_mu.numpy().tolist() == grads["mu"].tolist()
    np.testing.assert_array_equal(g_x0.numpy(), grads["x0"])
    # Other inputs in between, then the same ones again.
    rollout_positions(rollout, {"mu": torch.tensor([3.0e3], dtype=tdtype, requires_grad=True)},
                      v0=torch.ones(3, dtype=tdtype)).sum().backward()
    with torch.no_grad():
        rollout_positions(rollout, {"flow_rate": torch.tensor([80.0], dtype=tdtype)}, x0=x0_values + 0.001)
    rollout_positions(rollout, {"flow_rate": torch.tensor([50.0], dtype=tdtype)})  # the cube's own flow rate back
    again, (h_mu, h_x0) = run()
    assert torch.equal(again, out) and torch.equal(h_mu, g_mu) and torch.equal(h_x0, g_x0)


def test_a_second_derivative_is_refused_saying_why_and_create_graph_keeps_the_first():
    """Differentiating the bridge's gradient again raised torch's 'trying to differentiate
    twice a function that was marked with @once_differentiable', naming no reason. It says
    now that second derivatives are not supported (Warp's tape adjoint is not differentiable
    again); the gradient taken with ``create_graph=True`` is the plain one, bit for bit."""
    from warp_esph.torch import SECOND_DERIVATIVES

    model = _cube()
    rollout = Rollout(model, 3, 1.0e-3, frames=[3])
    mu = torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)
    plain = torch.autograd.grad(rollout_positions(rollout, {"mu": mu}).square().sum(), mu)[0]
    (graphed,) = torch.autograd.grad(rollout_positions(rollout, {"mu": mu}).square().sum(), mu, create_graph=True)
    assert torch.equal(graphed.detach(), plain) and plain.abs().item() > 0.0
    with pytest.raises(RuntimeError) as e:
        graphed.sum().backward()
    assert str(e.value) == SECOND_DERIVATIVES
    assert "not supported" in SECOND_DERIVATIVES


def test_a_hessian_of_a_loss_linear_in_the_positions_is_refused_not_zero():
    """A loss linear in the positions (their sum) hands the bridge's backward an upstream
    gradient of constants, so no argument of the backward required a gradient and its result
    carried no graph: ``torch.autograd.functional.hessian`` read that as independent of mu and
    returned 0, where the module says a Hessian is refused (positions depend on mu nonlinearly).
    The gradient taken with ``create_graph=True`` is still the plain one."""
    from warp_esph.torch import SECOND_DERIVATIVES

    rollout = Rollout(_cube(), 3, 1.0e-3, frames=[3])
    mu = torch.tensor([1.0e3], dtype=torch.float64, requires_grad=True)
    plain = torch.autograd.grad(rollout_positions(rollout, {"mu": mu}).sum(), mu)[0]
    (graphed,) = torch.autograd.grad(rollout_positions(rollout, {"mu": mu}).sum(), mu, create_graph=True)
    assert torch.equal(graphed.detach(), plain)
    with pytest.raises(RuntimeError) as e:
        torch.autograd.functional.hessian(lambda m: rollout_positions(rollout, {"mu": m}).sum(), mu)
    assert str(e.value) == SECOND_DERIVATIVES


def test_a_forward_that_blows_up_while_finite_raises_not_a_result():
    """``rollout_positions(R, {"mu": 1e30})`` returned positions 1.5e5 m out of a 0.1 m box,
    finite, with only the stability warning: a torch optimiser took their loss as a result. The
    bridge applies the bounds ``fit`` fails its trials on (``Rollout.bounds_hit``,
    ``simulate.DivergenceMonitor``) and raises ``DivergedRollout`` (a ``FloatingPointError``)
    naming the particle and the stable step; the model keeps the values it held, and a run at a
    sound stiffness is returned as before."""
    from warp_esph.rollout import DivergedRollout  # noqa: PLC0415

    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.2, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"))
    b.add_ground()
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    # Stretched along x at 1 /s: falling as a whole it keeps F = I and no stiffness blows it up.
    model.particle_v0 = model.particle_v0 + (model.particle_x0 - model.particle_x0.mean(axis=0)) * np.array([1.0, 0.0, 0.0])
    rollout = Rollout(model, 2, 1e-4, frames=[1, 2])
    mu = rollout.get_parameters()["mu"].tolist()
    with pytest.warns(RuntimeWarning, match="above the explicit stability limit"):
        # (The speed bound trips first since the stretch, not round-off at F = I, seeds it.)
        with pytest.raises(FloatingPointError, match=r"^the rollout blew up while staying finite: .*\(particle \d+ of "
                                                     r"body 'box0', after step 2 of 2\).*use a smaller dt") as info:
            rollout_positions(rollout, {"mu": torch.tensor([1e30], dtype=torch.float64)})
    assert isinstance(info.value, DivergedRollout) and info.value.step == 2
    assert rollout.get_parameters()["mu"].tolist() == mu
    y = rollout_positions(rollout, {"mu": torch.tensor([2.0 * mu[0]], dtype=torch.float64)})
    assert float(y.abs().max()) < 0.3


def test_a_finite_blow_up_beside_a_scripted_tool_raises_as_the_sweep_fails_it():
    """The run ``blowup_cases`` describes (``sweep`` fails it, ``simulate.energy_growth``)
    was returned as a result: a scripted tool turns the divergence monitor's bounds off, and
    positions 30 m out, finite, went on to the caller's optimiser. The bridge now applies the
    sweep's energy test too and raises ``DivergedRollout`` naming the energy grown; at a
    stable stiffness the run is returned as before."""
    import warnings  # noqa: PLC0415

    from blowup_cases import BLOWN_MU, DT, HEALTHY_MU, STEPS, scripted_box_builder  # noqa: PLC0415
    from warp_esph.rollout import DivergedRollout  # noqa: PLC0415

    model = scripted_box_builder().finalize(dtype=wp.float64, requires_grad=True)
    rollout = Rollout(model, STEPS, DT, frames=[STEPS])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the dt past the stiff material's stable step
        warnings.filterwarnings("ignore", "tools .'far'. follow tools.Scripted motions", UserWarning)
        with pytest.raises(DivergedRollout, match=r"^the rollout blew up while staying finite: the simulation blew up: "
                                                  r"kinetic \+ gravitational energy grew by .*after step 30 of 30"):
            rollout_positions(rollout, {"mu": torch.tensor([BLOWN_MU], dtype=torch.float64)})
        y = rollout_positions(rollout, {"mu": torch.tensor([HEALTHY_MU], dtype=torch.float64)})
    assert bool(torch.isfinite(y).all()) and float(y.abs().max()) < 1.0
