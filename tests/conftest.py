"""Test configuration: one Warp kernel cache for every test process, quiet output."""

import gc
import os
import pathlib

# Must be set before warp is imported anywhere: every test run and every subprocess
# (CLI tests) then load kernels compiled once instead of compiling them again.
os.environ.setdefault("WARP_CACHE_PATH", str(pathlib.Path(__file__).resolve().parent.parent / ".warp_cache"))
# One OpenBLAS thread per test process: the workers (`-n 2`) already fill the cores, and a
# BLAS pool per worker on top of them spins against the other worker. Measured on the shared
# 2-core machine: the 192 x 192 eigenproblems of test_elastic_force's linear-stiffness test
# took 6.7 s of CPU with the pool and 2.6 s without. OpenBLAS reads it when it loads, with
# numpy's first import: here, in init_warp below (Warp imports numpy), after this line, since
# the installed pytest plugins (xdist, hypothesis, platformdirs) import no numpy. So it holds
# in a plain `pytest` run as in the xdist workers and the subprocesses the tests start:
# scipy-openblas reported 1 thread in each (2, the core count, without it). A plugin that
# imported numpy before this file would leave this process's pool at its default; a value
# already in the environment is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest  # noqa: E402

from warp_esph.startup import init_warp  # noqa: E402

init_warp()  # wp.config.log_level = WARNING, and no native CUDA-driver note on a CPU machine

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

import warp_esph as we  # noqa: E402

# Under CI=true the property tests draw the same examples every run (a failure there is
# reproducible from the log); locally they explore new ones and keep failures in the database.
from hypothesis import settings  # noqa: E402

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI", "").lower() == "true":
    settings.load_profile("ci")

DOUGH_SCENE = """
[scene]
name = "dough_block"
spacing = 0.02
support_radius = 0.05
frames = {frames}
fps = 30

[materials.dough]
mu = 2000.0
lam = 3000.0
density = 1000.0
yield_stress = {yield_stress}
flow_rate = {flow_rate}
viscosity = 2.0

[[bodies]]
shape = "box"
name = "dough"
material = "dough"
center = [0.0, 0.045, 0.0]
size = [0.08, 0.08, 0.08]
velocity = [0.0, -1.0, 0.0]

[[colliders]]
type = "ground"
height = 0.0
friction = 0.5
"""


@pytest.fixture
def load_example():
    """A function loading ``examples/<name>.py`` as a module (the examples are no package)."""
    import importlib.util

    def load(name):
        spec = importlib.util.spec_from_file_location(name, pathlib.Path(__file__).resolve().parent.parent / "examples" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture
def start_checks(monkeypatch):
    """The names of the starts ``rollout.check_initial`` checks, in order, wherever the package
    calls it (the rollout, and the fit and torch bridge where imported): for the tests that a
    start is checked once, not at every evaluation."""
    import sys

    import warp_esph.rollout as rollout_module

    calls = []
    real = rollout_module.check_initial

    def counted(m, name, value):
        calls.append(name)
        return real(m, name, value)

    monkeypatch.setattr(rollout_module, "check_initial", counted)
    for name in ("warp_esph.fit", "warp_esph.torch"):
        if name in sys.modules:
            monkeypatch.setattr(sys.modules[name], "check_initial", counted, raising=False)
    return calls


@pytest.fixture
def dough_scene():
    """``dough_scene(yield_stress, flow_rate, frames=6)``: the TOML of a 64-particle dough
    block dropped on the ground at 1 m/s (the command-line fit tests' scene)."""

    def scene(yield_stress, flow_rate, frames=6):
        return DOUGH_SCENE.format(yield_stress=yield_stress, flow_rate=flow_rate, frames=frames)

    return scene


#: Two spheres of two materials: ``[materials.soft]`` (material 0, body 'a') and the preset
#: 'clay' a body names (material 1, body 'b').
TWO_MATERIALS_SCENE = """
[scene]
spacing = 0.05

[materials.soft]
preset = "dough"

[[bodies]]
shape = "sphere"
name = "a"
material = "soft"
center = [0, 0.2, 0]
radius = 0.1

[[bodies]]
shape = "sphere"
name = "b"
material = "clay"
center = [0.5, 0.2, 0]
radius = 0.1
"""


@pytest.fixture(scope="session")
def two_materials_scene():
    """The TOML of ``TWO_MATERIALS_SCENE``: material names that are no body's."""
    return TWO_MATERIALS_SCENE


@pytest.fixture(scope="session")
def dropped_cube():
    """``dropped_cube(yield_stress, flow_rate, size=0.1, fit_weight=None)``: a float64 model
    with gradients of a soft cube of side ``size`` (2 cm spacing: 125 particles at 0.1) hitting
    the ground at 1 m/s, the lattice jittered by 1e-3 of the spacing (seed 5); ``fit_weight``:
    the builder's (None: its default)."""

    def drop(yield_stress, flow_rate, size=0.1, fit_weight=None):
        b = we.SceneBuilder(spacing=0.02, **({} if fit_weight is None else {"fit_weight": fit_weight}))
        b.add_box((0.0, 0.055, 0.0), (size, size, size), we.Material(mu=2e3, lam=3e3, density=1000.0,
                                                                     yield_stress=yield_stress, flow_rate=flow_rate),
                  velocity=(0.0, -1.0, 0.0))
        b.add_ground(friction=0.5)
        model = b.finalize(dtype=wp.float64, requires_grad=True)
        model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
        model.compute_rest_density()
        return model

    return drop


@pytest.fixture(scope="session")
def run_once(request, tmp_path_factory):
    """``run_once(key, fn)``: ``fn()``'s result, computed once per test session, for the
    module fixtures of long runs (``shared_run``: under xdist the workers share it). Without
    workers it just calls ``fn``."""
    from shared_run import session_root, shared_run

    worker = getattr(request.config, "workerinput", None)
    root = None if worker is None else session_root(tmp_path_factory.getbasetemp(), worker["workerid"])
    if root is None:
        return lambda key, fn: fn()
    return lambda key, fn: shared_run(root, key, fn)


# The thin spread pile (a 4 s run shared by two tests through one module fixture, about a
# minute) goes first: with two workers (`-n 2 --dist worksteal`) it then runs beside the rest
# instead of near the end of one worker's half, where the other worker would wait for it.
FIRST = ("test_spread_pile_holds_the_theory_volume_and_slows_to_a_creep", "test_spread_radius_within_10_percent_of_roussel_coussot")


def pytest_collection_finish(session):
    """Move what importing Warp, the package and the test modules left (about 10^5 objects) to
    the permanent generation, once per test process: each of Python's automatic full
    collections traversed them all, 0.3-0.4 s a time, and they ran all through the suite.
    Objects the tests make are not frozen, so their cycles are still collected."""
    gc.collect()
    gc.freeze()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item, nextitem):
    """Freeze again at the end of each test file, its module fixtures torn down: the kernels
    its tests loaded and what they cached stay for the process, and the automatic full
    collections of the next file's tests would traverse them all again."""
    yield
    if nextitem is None or nextitem.path != item.path:
        gc.collect()
        gc.freeze()


@pytest.fixture
def thawed_heap():
    """The heap as in a user's process for a test of a peak: the frozen objects back in the
    collected generations, so the automatic full collections come as late as there, and cyclic
    garbage that would pile up between them shows in the peak instead of being freed early.
    Frozen again afterwards (one full collection)."""
    gc.unfreeze()
    try:
        yield
    finally:
        gc.collect()
        gc.freeze()


def pytest_collection_modifyitems(config, items):
    first = [item for item in items if item.name in FIRST and item.path.name == "test_validation_suite.py"]
    if first:
        items[:] = first + [item for item in items if item not in first]
