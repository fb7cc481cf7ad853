"""A pytest plugin that logs, for each test, the kernels it launches (``kernel_log``) and the
options of every taped step it takes: the audit behind docs/method.md, "Which test checks each
kernel's adjoint". Not loaded by the suite; run as

    KERNEL_AUDIT=audit.jsonl python -m pytest -p kernel_audit tests/test_gradients.py ...

(with ``tests`` on ``PYTHONPATH``). Each line of ``audit.jsonl`` is one test: its id, whether
its own source takes central differences (``fd``, by the words it uses: read the test to be
sure), the ``(kernel, "forward" | "adjoint", compiled module)`` it launched and, per taped step,
its options (deformation models, elastic and pressure forces, fit, floors, colliders, tools,
pins, fields, worlds, dtype)."""

import inspect
import json
import math
import os
import re

import pytest

_FD = re.compile(r"central|finite.diff|\bfd\b", re.I)


def step_options(solver, state_in) -> set:
    """What a taped ``solver.step(state_in, ...)`` runs, as words."""
    import warp as wp

    m = solver.model
    f = {"float64" if m.scalar is wp.float64 else "float32", f"fit={solver.fit}", f"fused={solver.fused}",
         f"fit_weight={m.fit_weight}", "worlds=1" if m.world_count == 1 else "worlds=n"}
    for mat in m.materials:
        f |= {f"deformation={mat.deformation}", f"elastic_force={mat.elastic_force}", f"model={mat.model}",
              f"pressure_force={mat.pressure_force}",
              "plastic" if math.isfinite(mat.yield_stress) and mat.flow_rate > 0 else "elastic"}
        if not mat.clamp_pressure:
            f.add("unclamped")
    if solver.hourglass > 0:
        f.add("hourglass")
    if solver.rest_model or state_in.rest_model:
        f.add("rest_model")
    if not solver.hand_adjoints:
        f.add("generated_adjoints")
    if m.image_plane is not None:
        f.add("floor_images")
    for b in m.bodies:
        if b.ghost_floor:
            f.add("ghost_floor_slip" if b.ghost_slip else "ghost_floor")
        if b.floor_material >= 0:
            f.add("elastic_particle_floor")
    f |= {name for name, items in (("static_plane", m.planes), ("static_sphere", m.spheres), ("static_box", m.boxes),
                                   ("force_field", m.force_fields)) if items}
    if m.tools is not None:
        f |= {f"tool_{c.kind}" for c in m.tools.colliders} | {f"motion_{type(c.motion).__name__}" for c in m.tools.colliders}
        f |= {f"pin_{type(p.motion).__name__}" for p in m.tools.pins}
    return f


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    from kernel_log import launched_kernels

    from warp_esph.sim import solver as solver_module
    from warp_esph.sim.replay import recording_tape

    out = os.environ.get("KERNEL_AUDIT", "kernel_audit.jsonl")
    names, variants, steps = set(), set(), set()
    step = solver_module.Solver.step

    def logged_step(self, state_in, state_out, dt):
        if recording_tape() is not None:
            steps.add(frozenset(step_options(self, state_in)))
        return step(self, state_in, state_out, dt)

    try:
        source = inspect.getsource(item.function)
    except (OSError, TypeError):
        source = ""
    solver_module.Solver.step = logged_step
    try:
        with launched_kernels(names, variants):
            outcome = yield
    finally:
        solver_module.Solver.step = step
    record = {"id": item.nodeid, "fd": bool(_FD.search(source)), "passed": outcome.excinfo is None,
              "kernels": sorted(map(list, variants)), "steps": [sorted(s) for s in steps]}
    with open(out, "a") as f:
        f.write(json.dumps(record) + "\n")
