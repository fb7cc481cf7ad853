"""Parameters written by a fit or by torch are the ones the step uses: whether SPH
pressure and viscosity run, and the stable time step the solver warns against, follow
the model's parameter arrays, not the materials the model was built with."""

import warnings

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.rollout import Rollout


def _cube(pressure_stiffness, viscosity):
    """A squeezed cube (float64): pressure and viscosity both move its particles."""
    mat = we.Material(mu=1.0e3, lam=1.5e3, density=1000.0, pressure_stiffness=pressure_stiffness, viscosity=viscosity)
    b = we.SceneBuilder(spacing=0.02, support_radius=0.05)
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), mat)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    # Squeezed: above the rest density, so the (clamped) pressure pushes outwards.
    model.particle_x0 *= 0.9
    model.particle_v0 = 5.0 * model.particle_x0 * np.array([1.0, -0.5, 0.0])
    return model


@pytest.mark.parametrize("fused", [True, False])
def test_parameters_set_on_a_rollout_switch_the_sph_kernels_on(fused):
    """A model built with k_p = eta = 0 whose fit sets them runs exactly the step of a
    model built with those values (before, it never ran the SPH kernels)."""
    k_p, eta, steps, dt = 2.0, 0.5, 6, 1.0e-4
    reference = Rollout(_cube(k_p, eta), steps, dt).forward()
    plain = Rollout(_cube(0.0, 0.0), steps, dt).forward()
    # The SPH forces matter here: without them the end positions differ.
    assert np.abs(reference - plain).max() > 1e-7

    model = _cube(0.0, 0.0)
    rollout = Rollout(model, steps, dt)
    rollout.set_parameters({"pressure_stiffness": k_p, "viscosity": eta})
    np.testing.assert_allclose(rollout.forward(), reference, rtol=0.0, atol=1e-12)

    # The untaped fast path of a Solver decides the same way.
    solver = we.Solver(model, fused=fused)
    states = [model.state(requires_grad=False), model.state(requires_grad=False)]
    for k in range(steps):
        solver.step(states[k % 2], states[(k + 1) % 2], dt)
    np.testing.assert_allclose(states[steps % 2].x.numpy(), reference[-1], rtol=0.0, atol=1e-9)


def test_stable_dt_follows_the_parameter_arrays():
    model = _cube(0.0, 0.0)
    solver = we.Solver(model)
    before = model.stable_dt()
    eta = 100.0
    Rollout(model, 1, 1.0e-5).set_parameters({"viscosity": eta})
    viscous = 0.3 / 12.0 * 1000.0 * model.support_radius**2 / eta
    assert model.stable_dt() == pytest.approx(min(before, viscous), rel=1e-12, abs=0.0)
    assert viscous < before
    with pytest.warns(RuntimeWarning, match="stability limit"):
        solver.check_dt(0.5 * (viscous + before))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver.check_dt(0.5 * viscous)


def _stepped_flowing_box():
    """``(model, solver, a, c, dt)``: a box that can flow, without SPH, after one step from ``a``
    into ``c`` (the parameter questions' tests)."""
    mat = we.Material(mu=1.0e3, lam=1.5e3, density=1000.0, yield_stress=50.0, flow_rate=10.0, viscosity=0.0,
                      pressure_stiffness=0.0, elastic_force="variational")
    b = we.SceneBuilder(spacing=0.02, support_radius=0.05)
    b.add_box((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), mat)
    model = b.finalize()
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    dt = 0.5 * model.stable_dt()
    solver.step(a, c, dt)
    return model, solver, a, c, dt


def test_a_step_reads_the_parameter_arrays_back_once_and_still_sees_every_write(monkeypatch):
    """The start of a step asks three questions of the parameter arrays (the fit and control
    by material, the stable step, whether SPH runs): one read-back answers them (each read of
    a device array waits for the device; it was 9 of a step's 12; on the CPU the read stacks
    views of the arrays). A write between steps, as a fit or torch makes in place, is still
    seen by the next step."""
    model, solver, a, c, dt = _stepped_flowing_box()
    assert solver.fit == "linear" and not model.sph_active  # it can flow; no SPH
    reads, parameter_reads = [], []
    original = wp.array.numpy
    monkeypatch.setattr(wp.array, "numpy", lambda self: reads.append(self.shape) or original(self))
    read_parameters = type(model)._read_parameters

    def counted(self):
        if self._held_parameters is None:  # a read of the arrays, not of the step's held answer
            parameter_reads.append(1)
        return read_parameters(self)

    monkeypatch.setattr(type(model), "_read_parameters", counted)
    solver.step(c, a, dt)
    monkeypatch.setattr(wp.array, "numpy", original)
    monkeypatch.setattr(type(model), "_read_parameters", read_parameters)
    assert len(parameter_reads) == 1 and len(reads) <= 3, (parameter_reads, reads)
    # In place, between steps: viscosity on (SPH runs, the step limit falls), flow off (the
    # material is elastic only: "auto" picks the curvature-corrected fit).
    model.viscosity.assign(np.array([100.0], dtype=np.float32))
    model.flow_rate.assign(np.array([0.0], dtype=np.float32))
    with pytest.warns(RuntimeWarning, match="stability limit"):
        solver.step(a, c, dt)
    assert model.sph_active and solver.fit == "curvature_corrected"
    assert model.stable_dt() < dt


def test_the_steps_questions_of_unchanged_parameters_are_answered_once(monkeypatch):
    """Each step asked whether the materials can flow (twice: the fit by material and the rest
    model) and whether SPH runs, computing each answer again from the same parameter rows:
    about 30 us of the fit example's 0.55 ms step at 142 particles. The answers are kept with
    the rows' bytes: steps at unchanged parameters compute none, and a write in place is
    answered anew."""
    model, solver, a, c, dt = _stepped_flowing_box()
    # The questions' own answers counted, each computed where the memo (Model._answer) runs
    # it: counting a numpy function they call (np.isfinite) counted any step code calling it.
    answered = []
    ask = model._answer
    monkeypatch.setattr(model, "_answer",
                        lambda question, answer: ask(question, lambda rows: answered.append(question[0]) or answer(rows)))
    for _ in range(3):
        solver.step(c, a, dt)
        a, c = c, a
    assert answered == [] and solver.fit == "linear" and not model.sph_active
    model.flow_rate.assign(np.array([0.0], dtype=np.float32))  # elastic now: answered anew
    solver.step(c, a, dt)
    assert set(answered) == {"elastic_only", "sph_active"} and solver.fit == "curvature_corrected"
    model.flow_rate.assign(np.array([10.0], dtype=np.float32))  # and back
    solver.step(a, c, dt)
    assert solver.fit == "linear"
