"""Bad input is refused before any kernel runs, each with its own message naming the
parameter, the value and what is allowed."""

import math
import warnings

import numpy as np
import pytest
import warp as wp

import warp_esph as we

DOUGH = we.Material.preset("dough")


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"mu": -1.0, "lam": 1.0}, r"Material\.mu = -1\.0 is not allowed: must be > 0"),
        ({"mu": 0.0, "lam": 1.0}, r"Material\.mu = 0\.0 .* > 0"),
        ({"mu": float("nan"), "lam": 1.0}, r"Material\.mu = nan .* finite"),
        ({"mu": float("inf"), "lam": 1.0}, r"Material\.mu = inf .* finite"),
        ({"mu": "soft", "lam": 1.0}, r"Material\.mu = 'soft' .* number"),
        ({"mu": 3.0, "lam": -2.5}, r"Material\.lam = -2\.5 .* > -2 mu / 3 = -2"),
        ({"mu": 1.0, "lam": 1.0, "yield_stress": -5.0}, r"Material\.yield_stress = -5\.0 .* >= 0"),
        ({"mu": 1.0, "lam": 1.0, "flow_rate": -0.1}, r"Material\.flow_rate = -0\.1 .* >= 0"),
        ({"mu": 1.0, "lam": 1.0, "density": 0.0}, r"Material\.density = 0\.0 .* > 0"),
        ({"mu": 1.0, "lam": 1.0, "pressure_stiffness": -1.0}, r"Material\.pressure_stiffness = -1\.0 .* >= 0"),
        ({"mu": 1.0, "lam": 1.0, "viscosity": -1.0}, r"Material\.viscosity = -1\.0 .* >= 0"),
        ({"mu": 1.0, "lam": 1.0, "model": "plastic"}, r"Material\.model = 'plastic' .* one of 'linear'"),
        ({"mu": 1.0, "lam": 1.0, "hardening": float("nan")}, r"Material\.hardening = nan .* finite"),
        ({"mu": True, "lam": 1.0}, r"Material\.mu = True .* number"),
        ({"mu": 1.0, "lam": 1.0, "elastic_force": "exact"}, r"Material\.elastic_force = 'exact' .* one of 'paper', 'variational'"),
        ({"mu": 1.0, "lam": 1.0, "elastic_force": "variational", "deformation": "additive"},
         r"Material\.elastic_force = 'variational' is not allowed with deformation = 'additive': .* use deformation = 'incremental' or 'rest'"),
    ],
)
def test_material_rejects(kwargs, match):
    with pytest.raises(ValueError, match=match):
        we.Material(**kwargs)


def test_material_accepts_inf_yield_and_converts_young():
    m = we.Material.from_young(1.0e5, 0.25, yield_stress=math.inf)
    assert m.youngs_modulus == pytest.approx(1.0e5)
    assert m.poisson_ratio == pytest.approx(0.25)
    assert not m.plastic
    with pytest.raises(ValueError, match=r"nu = 0\.5 .* \(-1, 0\.5\)"):
        we.Material.from_young(1.0e5, 0.5)
    with pytest.raises(ValueError, match=r"preset = 'jelly' .* one of 'dough'"):
        we.Material.preset("jelly")


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: we.SceneBuilder(spacing=0.0), r"spacing = 0\.0 .* > 0"),
        (lambda: we.SceneBuilder(spacing=0.01, support_radius=0.05), r"support_radius = 0\.05 .* \[1\.5 \* spacing, 3\.0 \* spacing\]"),
        (lambda: we.SceneBuilder(spacing=0.01, support_radius=0.01), r"support_radius = 0\.01 is not allowed: must be in \[1\.5 \* spacing, 3\.0 \* spacing\] = \[0\.015, 0\.03\]"),
        (lambda: we.SceneBuilder(gravity=(0.0, -9.81)), r"gravity = \(0\.0, -9\.81\) .* 3 numbers"),
        (lambda: we.SceneBuilder().add_box((0, 0, 0), (0.1, -0.1, 0.1), DOUGH), r"size = \(0\.1, -0\.1, 0\.1\) .* every component must be > 0"),
        (lambda: we.SceneBuilder().add_box((0, float("nan"), 0), (0.1, 0.1, 0.1), DOUGH), r"center\[1\] = nan .* finite"),
        (lambda: we.SceneBuilder(spacing=0.1).add_sphere((0, 0, 0), 0.01, DOUGH), r"body 'sphere0' has no particles"),
        (lambda: we.SceneBuilder().add_sphere((0, 0, 0), 0.1, "dough"), r"material = 'dough' .* warp_esph\.Material"),
        (lambda: we.SceneBuilder().add_cylinder((0, 0, 0), 0.1, 0.2, DOUGH, axis="w"), r"axis = 'w' .* one of 'x', 'y', 'z'"),
        (lambda: we.SceneBuilder().add_star((0, 0, 0), 0.1, 0.2, 0.05, DOUGH), r"inner_radius = 0\.2 .* < outer_radius = 0\.1"),
        (lambda: we.SceneBuilder().add_ground(friction=-0.1), r"friction = -0\.1 .* >= 0"),
        (lambda: we.SceneBuilder().add_sphere_collider((0, 0, 0), -1.0), r"radius = -1\.0 .* > 0"),
        (lambda: we.SceneBuilder().add_box_collider((0, 0, 0), (1, 0, 1)), r"half_extents = \(1, 0, 1\) .* > 0"),
        (lambda: we.SceneBuilder().add_plane((0, 0, 0), 0.0), r"normal = \(0, 0, 0\) .* non-zero"),
        (lambda: we.SceneBuilder().finalize(), r"the scene has no bodies"),
        (lambda: _one_box().finalize(dtype="float16"), r"dtype = 'float16' is not allowed: use wp\.float32 or wp\.float64 \(or 'float32'/'float64', numpy's float32/float64 or 'f4'/'f8'\)$"),
        (lambda: _one_box().finalize(dtype="f2"), r"dtype = 'f2' is not allowed: use wp\.float32 or wp\.float64"),
        (lambda: _one_box().finalize(dtype=None), r"dtype = None is not allowed: use wp\.float32 or wp\.float64"),
        # A value, not a type: numpy reads a numpy number (or bytes) as its dtype, and a model
        # was built from np.float64(1.0).
        (lambda: _one_box().finalize(dtype=np.float64(1.0)), r"^dtype = np\.float64\(1\.0\) is not allowed: use wp\.float32 or wp\.float64"),
        (lambda: _one_box().finalize(dtype=b"f8"), r"^dtype = b'f8' is not allowed: use wp\.float32 or wp\.float64"),
        (lambda: _one_box().finalize(dtype=float), r"dtype = float is not allowed: Warp reads it as float32, numpy as float64"),
        (lambda: _one_box().finalize(dtype="float"), r"dtype = 'float' is not allowed: Warp reads it as float32, numpy as float64"),
        (lambda: _one_box().finalize(device="tpu"), r"device = 'tpu' is not allowed"),
        (lambda: _one_box(name="a").add_box((1, 0, 0), (0.1, 0.1, 0.1), DOUGH, name="a"), r"name = 'a' .* exists already"),
        # Names reach one-line messages, the force log's rows and the USD file's custom data: a
        # newline split every message naming the body, a NUL or ESC went into the files as it was.
        (lambda: we.SceneBuilder().add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, name="a\nb"),
         r"^name = 'a\\nb' is not allowed: it names the body in messages, .*so it must be one line of text \(no control"),
        (lambda: _one_box().add_tool("sphere", radius=0.05, position=(2, 2, 2), name="t\x1b[31m"),
         r"^name = 't\\x1b\[31m' is not allowed: it names the tool or pinned set .*one line of text"),
        (lambda: _one_box().pin(body=0, name="p\x00"), r"^name = 'p\\x00' is not allowed: .*one line of text"),
        (lambda: _one_box().add_particle_floor(0, margin=0.0, name="f\u2028"), r"^name = 'f\\u2028' is not allowed: .*one line"),
        # As a bidirectional control or another invisible format character (Unicode Cf): taken,
        # and printed in messages, where 'evil\u202etxt.exe' shows as 'evilexe.txt'.
        (lambda: we.SceneBuilder().add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, name="evil\u202etxt.exe"),
         r"^name = 'evil\\u202etxt\.exe' is not allowed: it names the body .*no invisible format characters \(Unicode "
         r"category Cf"),
        (lambda: _one_box().add_tool("sphere", radius=0.05, position=(2, 2, 2), name="t\u2067"),
         r"^name = 't\\u2067' is not allowed: it names the tool or pinned set .*no invisible format characters"),
        (lambda: _one_box().pin(body=0, name="p\ufeff"), r"^name = 'p\\ufeff' is not allowed: .*no invisible format"),
        # Said only 'must be a new non-empty string', naming no clash.
        (lambda: _two_tools_named("t"), r"^name = 't' is not allowed: a tool of that name exists already; tools and pinned "
                                        r"sets share one set of names"),
        (lambda: we.SceneBuilder().add_particles(np.zeros((4, 2)), DOUGH), r"positions with shape \(4, 2\) .* \(N, 3\)"),
        # Said 'it is smaller than the spacing', a shape's words, of no positions at all.
        (lambda: we.SceneBuilder().add_particles(np.zeros((0, 3)), DOUGH),
         r"^positions with shape \(0, 3\) is not allowed: body 'particles0' would have no particles; give at least one"),
        # Any kind was kept: 'xx' named the body 'xx0', 3 named it '30'.
        (lambda: we.SceneBuilder().add_particles([(0.0, 0.5, 0.0)], DOUGH, kind="xx"),
         r"^kind = 'xx' is not allowed: must be one of 'particles', 'box', 'sphere', 'cylinder', 'star', 'mesh'"),
        (lambda: we.SceneBuilder().add_particles([(0.0, 0.5, 0.0)], DOUGH, kind=3), r"^kind = 3 is not allowed: must be one of"),
        (lambda: we.SceneBuilder().add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, velocity=(1, 2)), r"velocity with shape \(2,\) is not allowed: must be 3 finite numbers or one per particle"),
        (lambda: we.SceneBuilder().add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, angular_velocity=(1, float("nan"), 0)), r"angular_velocity\[1\] = nan .* finite"),
    ],
)
def test_builder_rejects(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize("dtype, scalar", [(np.dtype("float64"), wp.float64), (np.dtype("float32"), wp.float32),
                                           (np.float64, wp.float64), ("float64", wp.float64), ("float32", wp.float32),
                                           ("f8", wp.float64), ("f4", wp.float32)])
def test_finalize_takes_a_numpy_dtype_as_its_precision(dtype, scalar):
    """``finalize(dtype=np.dtype("float64"))``, a numpy dtype as ``scalar_type`` documents, builds
    the model in that precision: it compared equal to ``wp.float64``, was kept as the numpy
    dtype, and finalize failed with an AttributeError on its ``__name__``. numpy's names of
    the two, 'f8' and 'f4', are read as numpy reads them (np.dtype("f8") was taken, "f8"
    refused)."""
    model = _one_box().finalize(dtype=dtype)
    assert model.scalar is scalar
    assert model.state().x.dtype is (wp.vec3d if scalar is wp.float64 else wp.vec3f)


def _two_tools_named(name):
    b = _one_box()
    for x in (2.0, 3.0):
        b.add_tool("sphere", radius=0.05, position=(x, 2.0, 2.0), name=name)


def _one_box(name=None):
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, name=name)
    return b


def test_default_body_names_skip_a_name_the_caller_took():
    """An unnamed body's default is ``<kind><index>``, the first one free: a body the caller
    named ``'box1'`` made the next unnamed box's default a clash (refused as 'exists
    already', for a name the caller never wrote)."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, name="box1")
    b.add_box((1, 0, 0), (0.1, 0.1, 0.1), DOUGH)
    b.add_box((2, 0, 0), (0.1, 0.1, 0.1), DOUGH)
    assert [bd.name for bd in b.finalize().bodies] == ["box1", "box2", "box3"]


def test_solver_rejects_bad_dt_and_warns_above_stability_limit():
    model = _one_box().finalize()
    solver = we.Solver(model)
    a, b = model.state(), model.state()
    for bad, match in ((0.0, r"dt = 0\.0 .* > 0"), (-1e-4, r"dt = -0\.0001 .* > 0"), (float("nan"), r"dt = nan .* finite")):
        with pytest.raises(ValueError, match=match):
            solver.step(a, b, bad)
    with pytest.raises(ValueError, match="pass two states"):
        solver.step(a, a, 1e-4)
    limit = model.stable_dt()
    with pytest.warns(RuntimeWarning, match=r"above the explicit stability limit " + f"{limit:.3g}"):
        solver.step(a, b, 2 * limit)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver.step(a, b, 0.5 * limit)
    with pytest.raises(ValueError, match=r"min_neighbors = 0 is not allowed: must be an integer >= 1"):
        we.Solver(model, min_neighbors=0)


def test_a_min_neighbors_no_particle_has_is_refused_or_said_after_the_first_step():
    """``min_neighbors=30`` (the paper's row width) against the 26 lattice neighbours within
    h = 2 spacings dropped every particle's deformation update at every step: the box never
    deformed elastically and slumped like a liquid, with only the guard count to say so; above
    the row width it can never be met, and is refused. The default says nothing."""
    model = _one_box().finalize()
    with pytest.raises(ValueError, match=r"^min_neighbors = 97 is not allowed: must be at most the model's "
                                         r"max_neighbors = 96"):
        we.Solver(model, min_neighbors=97)
    solver = we.Solver(model, min_neighbors=30)
    a, b = model.state(), model.state()
    with pytest.warns(RuntimeWarning, match=r"^min_neighbors = 30: every particle's deformation update was dropped in "
                                            r"the first step.*an interior lattice particle has 26 at h = 2 spacings"):
        solver.step(a, b, 1e-4)
    assert solver.guard_counts()["few_neighbors"] == model.particle_count
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        we.Solver(model).step(a, b, 1e-4)
    # A scene whose rows are narrower than the default guard (max_neighbors = 4, which
    # SceneBuilder allows; a scene file is refused when read) was refused naming
    # min_neighbors = 6, which the user never set.
    narrow = we.SceneBuilder(spacing=0.02, max_neighbors=4)
    narrow.add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH)
    narrow = narrow.finalize()
    with pytest.raises(ValueError, match=r"^max_neighbors = 4 is not allowed with the default min_neighbors = 6: "):
        we.Solver(narrow)
    we.Solver(narrow, min_neighbors=4)


def test_a_states_time_stays_a_python_float_whatever_type_the_user_gave():
    """``state.time = np.float32(0)`` and a ``np.float32`` dt made the time a float32 (NumPy
    keeps the array scalar's type over a Python float), so every later step's time was summed
    in float32: after 2000 steps of 1e-4 s it read 0.2000028 where the steps sum to 0.19999999."""
    b = we.SceneBuilder(spacing=0.05)
    b.add_particles([(0.0, 0.5, 0.0)], DOUGH)
    model = b.finalize()
    solver = we.Solver(model)
    a, c = model.state(), model.state()
    a.time = np.float32(0.0)
    dt = np.float32(1e-4)
    exact = 0.0
    for _ in range(2000):
        solver.step(a, c, dt)
        a, c = c, a
        exact += float(dt)
    assert type(a.time) is float
    assert a.time == exact


def test_solver_rejects_bad_neighbor_skin_and_fused():
    model = _one_box().finalize()
    for bad, allowed in ((-0.1, r"must be in \[0\.0, 1\.0\]"), (1.5, r"must be in \[0\.0, 1\.0\]"),
                         (float("nan"), "must be a finite number")):
        with pytest.raises(ValueError, match=rf"neighbor_skin = {bad!r} is not allowed: {allowed}"):
            we.Solver(model, neighbor_skin=bad)
    with pytest.raises(ValueError, match=r"fused = 1 is not allowed: must be True or False"):
        we.Solver(model, fused=1)


def test_overlapping_bodies_are_refused_by_name():
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, name="first")
    b.add_sphere((0.04, 0.0, 0.0), 0.05, DOUGH, name="second")
    with pytest.raises(ValueError, match=r"bodies 'first' and 'second' are not allowed to overlap"):
        b.finalize()
    ok = we.SceneBuilder(spacing=0.02)
    ok.add_box((0, 0, 0), (0.1, 0.1, 0.1), DOUGH, name="first")
    ok.add_box((0.1, 0, 0), (0.1, 0.1, 0.1), DOUGH, name="touching")  # nearest particles one spacing apart
    assert ok.finalize().particle_count == 250
    # Two copies of a body offset by less than half a spacing fell in different half-spacing
    # cells throughout and passed (0.1 dx apart; spheres offset 0.25 dx: 121 of 200 passed).
    rng = np.random.default_rng(0)
    for offset in [(0.002, 0.0, 0.0)] + [tuple(0.005 * d / np.linalg.norm(d)) for d in rng.normal(size=(10, 3))]:
        twin = we.SceneBuilder(spacing=0.02)
        twin.add_sphere((0.0, 0.3, 0.0), 0.05, DOUGH, name="a")
        twin.add_sphere(tuple(np.add((0.0, 0.3, 0.0), offset)), 0.05, DOUGH, name="b")
        with pytest.raises(ValueError, match=r"bodies '[ab]' and '[ab]' are not allowed to overlap"):
            twin.finalize()
