"""What the step's host-side shortcuts must keep: a value read through a kept view, or
computed once, is still the value the caller set between steps (docs/performance.md,
"Host work of a small step")."""

import math
import warnings

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph import checks, tools
from warp_esph.sim import solver as solver_mod


def _block(tool=None, dtype=wp.float32):
    b = we.SceneBuilder(spacing=0.02)
    b.add_box(center=(0.0, 0.05, 0.0), size=(0.06, 0.06, 0.06), material=we.Material.preset("dough"))
    b.add_ground()
    if tool is not None:
        tool(b)
    return b.finalize(device="cpu", dtype=dtype)


@pytest.mark.parametrize("value, allow_inf", [(math.nan, False), (math.nan, True), (math.inf, False),
                                              (-math.inf, False)])
def test_number_refuses_a_plain_float_as_any_other_number(value, allow_inf):
    """A plain float takes a shortcut past the checks no float can fail: NaN (and inf unless
    allowed) is still refused, in the words numpy's float gets."""
    with pytest.raises(ValueError) as plain:
        checks.number("dt", value, allow_inf=allow_inf)
    with pytest.raises(ValueError) as other:
        checks.number("dt", np.float64(value), allow_inf=allow_inf)
    assert str(plain.value) == str(other.value).replace(repr(np.float64(value)), repr(value))
    assert "dt = " in str(plain.value) and "must be a finite number" in str(plain.value)
    assert checks.number("t", math.inf, allow_inf=True) == math.inf
    assert math.copysign(1.0, checks.number("t", -0.0)) == -1.0


def test_a_nan_dt_or_time_is_refused_by_the_step():
    model = _block()
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    with pytest.raises(ValueError, match=r"dt = nan is not allowed: must be a finite number"):
        solver.step(a, b, math.nan)
    a.time = math.nan
    with pytest.raises(ValueError, match=r"state_in.time = nan is not allowed"):
        solver.step(a, b, 1.0e-4)


def test_gravity_set_between_steps_is_read_by_the_dt_check():
    """The dt check's length of gravity is kept by value: gravity set between steps, so
    strong that float32 no longer resolves a step's fall, refuses the dt the step before took."""
    model = _block()
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    dt = 0.5 * model.stable_dt()
    solver.step(a, b, dt)
    model.gravity = (0.0, -1.0e13, 0.0)
    with pytest.raises(ValueError, match=r"one step's fall under gravity"):
        solver.step(b, a, dt)
    model.gravity = (0.0, -9.81, 0.0)
    solver.step(b, a, dt)


def _keyframed(b):
    b.add_tool("box", half_extents=(0.1, 0.01, 0.1), name="press",
               motion=tools.Keyframes(times=(0.0, 1.0), positions=((0.0, 0.2, 0.0), (0.0, 0.1, 0.0))))


def test_keyframe_times_swapped_for_another_array_are_read():
    """The step reads the keyframe times through a view kept with their array: an array put in
    its place between steps (as an optimiser's own may be) is the one checked and read."""
    model = _block(_keyframed)
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    dt = 0.5 * model.stable_dt()
    solver.step(a, b, dt)
    ts = model.tools
    ts.keyframe_times = wp.array([1.0, 0.0], dtype=wp.float32, device="cpu")
    with pytest.raises(ValueError, match=r"keyframe_times of tool 'press' = \[1.0, 0.0\] is not allowed"):
        solver.step(b, a, dt)
    # Valid times in a new array move the press as they say: at twice the speed.
    ts.keyframe_times = wp.array([0.0, 0.5], dtype=wp.float32, device="cpu")
    solver.step(b, a, dt)
    p = a.tool_pose_p.numpy()
    assert p[1, 1] == pytest.approx(0.2 - 0.2 * float(a.time), rel=1e-5)


def test_keyframe_times_written_in_place_are_read():
    """The kept view is of the array's memory, not a copy of its values: times written into
    the same array between steps (``assign``, or through ``numpy()``, as an optimiser's
    in-place update does) are the ones checked and sampled at the next step."""
    model = _block(_keyframed)
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    dt = 0.5 * model.stable_dt()
    solver.step(a, b, dt)
    kt = model.tools.keyframe_times
    kt.assign(np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match=r"keyframe_times of tool 'press' = \[1.0, 0.0\] is not allowed"):
        solver.step(b, a, dt)
    kt.assign(np.array([0.0, 0.5]))
    solver.step(b, a, dt)
    assert a.tool_pose_p.numpy()[1, 1] == pytest.approx(0.2 - 0.2 * float(a.time), rel=1e-5)
    kt.numpy()[1] = 0.25
    solver.step(a, b, dt)
    assert b.tool_pose_p.numpy()[1, 1] == pytest.approx(0.2 - 0.4 * float(b.time), rel=1e-5)


def test_a_cut_row_counted_after_the_first_step_warns():
    """The cut-row warning reads the counters through a view kept with their array: a count
    that appears at a later step (here written in place, then in an array put in their place)
    warns at that step."""
    model = _block()
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    dt = 0.5 * model.stable_dt()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver.step(a, b, dt)
    solver.scratch.counters.numpy()[solver_mod.COUNT_NEIGHBORS_CUT] = 1
    with pytest.warns(RuntimeWarning, match="a neighbour row was cut"):
        solver.step(b, a, dt)
    fresh = we.Solver(model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fresh.step(a, b, dt)
    counts = np.zeros(fresh.scratch.counters.shape[0], dtype=np.int32)
    counts[solver_mod.COUNT_NEIGHBORS_CUT] = 1
    fresh.scratch.counters = wp.array(counts, dtype=wp.int32, device="cpu")
    with pytest.warns(RuntimeWarning, match="a neighbour row was cut"):
        fresh.step(b, a, dt)


def test_a_scripted_tools_step_motion_beside_a_keyframed_one():
    """The step's displacement and rotation rows are differenced on the host for a scripted
    motion only (another's are computed by the pose kernel): a turning, rising scripted sphere
    beside a keyframed press gets its own, the press its keyframes'."""
    turn = 0.002

    def pose(t):
        return (0.3, 0.1 + 2.0 * t, 0.0), (0.0, 0.0, math.sin(turn * t / 2.0e-4), math.cos(turn * t / 2.0e-4))

    def both(b):
        _keyframed(b)
        b.add_tool("sphere", radius=0.02, name="ball", motion=tools.Scripted(pose))

    model = _block(both, dtype=wp.float64)
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    dt = 1.0e-4
    solver.step(a, b, dt)
    dp, dr = b.tool_pose_dp.numpy(), b.tool_pose_dr.numpy()
    # Rows 2k + 1: tool k's motion over the step.
    np.testing.assert_allclose(dp[1], (0.0, -0.1 * dt, 0.0), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(dr[1], 0.0, atol=1e-15)
    np.testing.assert_allclose(dp[3], (0.0, 2.0 * dt, 0.0), rtol=1e-9)
    np.testing.assert_allclose(dr[3], (0.0, 0.0, 2.0 * turn * dt / 2.0e-4), rtol=1e-9)


def test_keyframe_sampling_of_a_list_finds_the_segment_searchsorted_finds():
    """The step samples its keyframe times as a list (bisect) where other readers pass arrays
    (searchsorted): the same segment and weight, at a keyframe's own time the one it starts."""
    ts = [0.0, 0.1, 0.3, 0.7]
    for t in (-1.0, 0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 2.0, np.nextafter(0.3, 0.0), np.nextafter(0.3, 1.0)):
        got = tools.sample_times(ts, float(t))
        want = tools.sample_times(np.array(ts), float(t))
        assert got[:2] == want[:2] and float(got[2]) == float(want[2]), (t, got, want)
    assert tools.sample_times(ts, 0.1)[:2] == (1, 2)


def test_the_host_quaternion_arithmetic_keeps_numpys_norm():
    """The scripted pose's checks and step rotation take ``np.linalg.norm``'s formula directly:
    bit for bit what the norm gives, over quaternions of every scale."""
    rng = np.random.default_rng(7)
    for scale in (1.0e-150, 1.0e-5, 1.0, 3.0e7, 1.0e150):
        for q in rng.normal(size=(200, 4)) * scale:
            v = np.array(q) / float(np.abs(q).max())
            assert checks.unit_vector("q", q, 4) == tuple(float(c) for c in v / np.linalg.norm(v))
            u = np.asarray(q) / np.linalg.norm(q)
            assert np.array_equal(tools._np_conj(q), np.array([-u[0], -u[1], -u[2], u[3]]))
            sv = float(np.linalg.norm(u[:3]))
            assert np.array_equal(tools._np_log(q), u[:3] * (2.0 * math.atan2(sv, u[3]) / sv))
