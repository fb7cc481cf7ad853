"""Built-in scenes and the TOML scene-file loader."""

import math
import os
import pathlib
import re
import textwrap

import numpy as np
import pytest

import warp_esph as we
from warp_esph import PRESETS
from warp_esph import scenes
from warp_esph.scenes import (DEFAULT_SCENE, FIGURE_SCENES, SCENES, Scene, get_scene, load_scaled_scene, load_scene,
                              load_scene_file)
from warp_esph.simulate import simulate


DOCS = pathlib.Path(__file__).resolve().parent.parent / "docs"
#: The everyday scenes (a few thousand particles); the paper's figure scenes, at the
#: paper's particle counts, are tested in test_figures.py.
EVERYDAY = [name for name in SCENES if name not in FIGURE_SCENES]


#: Scales below 0.35 for scenes whose thinnest body is one particle layer there (refused as
#: under-resolved: the star is 4 cm thick, the squeeze-flow disc 2 cm).
TINY = {"star": 0.5, "lab_squeeze_flow": 0.4}


# Its bodies are coarse on purpose (a tiny scene, or one torn apart): the run's under-resolution warning is expected.
@pytest.mark.filterwarnings("ignore:the deformation fit was skipped:RuntimeWarning")
@pytest.mark.parametrize("name", EVERYDAY)
def test_scene_builds_and_runs_two_frames_tiny(name):
    scene = get_scene(name, scale=TINY.get(name, 0.35))
    assert isinstance(scene, Scene) and scene.name == name and scene.description
    assert scene.frames >= 1 and scene.fps > 0
    model = scene.builder.finalize()
    assert 10 <= model.particle_count <= 400
    state = simulate(model, 2, fps=scene.fps, dt=scene.dt, progress=False)
    x, v = state.x.numpy(), state.v.numpy()
    assert np.isfinite(x).all() and np.isfinite(v).all()
    assert not np.array_equal(x, model.particle_x0)  # it moved (gravity)


@pytest.mark.parametrize("name", EVERYDAY)
def test_scale_sets_the_resolution(name):
    full = get_scene(name).builder
    half = get_scene(name, scale=0.5).builder
    assert half.spacing == pytest.approx(2 * full.spacing)
    assert 300 <= full.particle_count <= 5000  # a few thousand at most at scale 1
    assert half.particle_count < full.particle_count / 4


def test_default_scene_and_lookup(tmp_path):
    assert DEFAULT_SCENE == "dough_drop" and list(SCENES)[0] == DEFAULT_SCENE
    assert load_scene(None, scale=0.3).name == "dough_drop"
    assert load_scene("star", scale=0.5).name == "star"
    with pytest.raises(ValueError, match="did you mean 'rubber_bounce'"):
        get_scene("rubber_bonce")
    with pytest.raises(ValueError, match="scale"):
        get_scene("star", scale=0)
    path = tmp_path / "s.toml"
    path.write_text('[[bodies]]\nshape = "sphere"\nmaterial = "clay"\ncenter = [0, 1, 0]\nradius = 0.1\n')
    scene = load_scene(str(path))
    assert scene.name == "s" and scene.frames == 60 and scene.fps == 30 and scene.dt is None


def _doc_example() -> str:
    text = (DOCS / "scene_format.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, flags=re.S)
    assert blocks, "no TOML example in docs/scene_format.md"
    return blocks[0]


def test_documented_example_loads(tmp_path):
    (tmp_path / "meshes").mkdir()
    # A closed unit cube for the example's mesh body.
    verts = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    faces = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in verts) + "".join(f"f {a} {b} {c} {d}\n" for a, b, c, d in faces)
    (tmp_path / "meshes" / "part.obj").write_text(obj)
    path = tmp_path / "example.toml"
    path.write_text(_doc_example())
    scene = load_scene_file(path, scale=0.5)
    b = scene.builder
    assert scene.name == "dough_and_ball" and scene.frames == 60 and scene.fps == 30 and scene.dt is None
    assert b.spacing == pytest.approx(0.02) and b.support_radius == pytest.approx(0.04)
    assert (b.fit, b.contact_ramp) == ("curvature_corrected", 1.0)
    names = [body.name for body in b._bodies]
    assert names[:2] == ["slab", "ball"] and len(names) == 5
    assert len(b.planes) == 2 and len(b.spheres) == 1 and len(b.boxes) == 1
    # The ball falls at 1 m/s and spins at 6 rad/s about z through its centroid.
    ball = b._bodies[1]
    x, v = b._points[1], b._velocities[1]
    r = x - x.mean(axis=0)
    assert np.allclose(v, np.array([0.0, -1.0, 0.0]) + np.cross([0.0, 0.0, 6.0], r), atol=1e-12)
    assert ball.count == len(x) and np.allclose(v.mean(axis=0), [0.0, -1.0, 0.0], atol=1e-12)
    # preset + E/nu: the preset's plastic settings, the new stiffness, pressure from the new bulk modulus.
    soft = b._materials[0]
    assert soft.youngs_modulus == pytest.approx(1.5e4) and soft.yield_stress == PRESETS["dough"].yield_stress
    assert soft.pressure_force == "energy_spiky"  # the default force, and its default k_p share
    assert soft.pressure_stiffness == pytest.approx(0.46 * soft.bulk_modulus / soft.density)
    assert math.isinf(b._materials[1].yield_stress)


BASE = textwrap.dedent(
    """
    [scene]
    spacing = 0.05

    [materials.m]
    preset = "dough"

    [[bodies]]
    shape = "sphere"
    material = "m"
    center = [0, 0.2, 0]
    radius = 0.1

    [[colliders]]
    type = "plane"
    normal = [0, 1, 0]
    offset = 0.0
    """
)


@pytest.mark.parametrize(
    "old, new, pattern",
    [
        ("radius = 0.1", "raduis = 0.1", r"unknown key 'raduis' in \[\[bodies\]\] #1 \(shape 'sphere'\); did you mean 'radius'\?"),
        ("radius = 0.1", "radius = 0.1\nsize = [1, 1, 1]", r"unknown key 'size' in \[\[bodies\]\] #1"),
        ("spacing = 0.05", "spacing = 0.05\nsubsteps = 3", r"unknown key 'substeps' in \[scene\]"),
        ('preset = "dough"', 'preset = "dough"\nyeild_stress = 5', r"'yeild_stress' in \[materials\.m\]; did you mean 'yield_stress'"),
        ("offset = 0.0", "ofset = 0.0", r"unknown key 'ofset' in \[\[colliders\]\] #1 \(type 'plane'\); did you mean 'offset'"),
        ("[scene]", "[scenes]", r"unknown key 'scenes' at the top level; did you mean 'scene'"),
        ("radius = 0.1", 'radius = "0.1"', r"key 'radius' in \[\[bodies\]\] #1 \(shape 'sphere'\) must be a number, not str"),
        ("radius = 0.1", "radius = true", r"key 'radius' .* must be a number, not bool"),
        ("spacing = 0.05", "spacing = [0.05]", r"key 'spacing' in \[scene\] must be a number"),
        ('preset = "dough"', 'preset = "dough"\nclamp_pressure = 1', r"key 'clamp_pressure' in \[materials\.m\] must be true or false"),
        ('shape = "sphere"', 'shape = "sphear"', r"shape = 'sphear' .* did you mean 'sphere'"),
        ('type = "plane"', 'type = "wall"', r"type = 'wall' .*allowed: ground, plane, sphere, box"),
        ("radius = 0.1", "", r"missing key 'radius' in \[\[bodies\]\] #1"),
        ("offset = 0.0", "", r"missing key 'offset' in \[\[colliders\]\] #1"),
        ("radius = 0.1", "radius = -0.1", r"\[\[bodies\]\] #1 \(shape 'sphere'\): radius = -0.1 is not allowed"),
        ('preset = "dough"', 'preset = "dough"\nE = 1e4', r"\[materials\.m\] gives E without nu"),
        ('preset = "dough"', 'preset = "dough"\ndensity = 0', r"\[materials\.m\]: density = 0 is not allowed"),
        ("spacing = 0.05", "spacing = 0.05\nsupport_radius = 0.5", r"\[scene\]: support_radius = .* is not allowed"),
        ("spacing = 0.05", "spacing = 0.05\nframes = 0", r"\[scene\]: frames = 0 is not allowed"),
        ("spacing = 0.05", "spacing = = 0.05", r"invalid TOML"),
        ("[scene]", '[solver]\nfit = "quadratic"\n[scene]',
         r"fit = 'quadratic' in \[solver\] is not allowed \(allowed: auto, linear, curvature_corrected\)"),
        ("[scene]", '[solver]\ncontact = "contiuous"\n[scene]',
         r"contact = 'contiuous' in \[solver\] is not allowed; did you mean 'continuous'\? \(allowed: instant, continuous\)"),
        ("[scene]", '[solver]\nfitt = "linear"\n[scene]', r"unknown key 'fitt' in \[solver\]; did you mean 'fit'"),
        ("[scene]", "[solver]\nfit = 2\n[scene]", r"key 'fit' in \[solver\] must be a string, not int"),
        ("[scene]", "[solver]\nhourglass = -0.1\n[scene]",
         r"key 'hourglass' in \[solver\] must be a number >= 0 and <= 1000 \(0: off\), not float -0\.1"),
        ("[scene]", '[solver]\nhourglass = "0.1"\n[scene]',
         r"key 'hourglass' in \[solver\] must be a number >= 0 and <= 1000 \(0: off\), not str '0\.1'"),
        ("[scene]", "[solver]\nhourglass = nan\n[scene]", r"key 'hourglass' in \[solver\] must be a number >= 0"),
        ("radius = 0.1", "radius = 0.1\nfloor_margin = -0.1",
         r"\[\[bodies\]\] #1 \(shape 'sphere'\): floor_margin = -0\.1 is not allowed: must be >= 0"),
        ("radius = 0.1", "radius = 0.1\nfloor_margin = 0.1\nfloor_layers = 0",
         r"\[\[bodies\]\] #1 \(shape 'sphere'\): floor_layers = 0 is not allowed: must be an integer >= 1"),
        ("radius = 0.1", "radius = 0.1\nfloor_margin = 0.1\nfloor_layers = 9",
         r"floor_layers = 9 is not allowed: must be an integer in \[1, 8\]"),
        ("radius = 0.1", "radius = 0.1\nfloor_layers = 2", r"floor_layers = 2 is not allowed without floor_margin"),
        ("radius = 0.1", "radius = 0.1\nfloor_elastic = true", r"floor_elastic = True is not allowed without floor_margin"),
        ("radius = 0.1", "radius = 0.1\nfloor_ghost = true", r"floor_ghost = True is not allowed without floor_margin"),
        ("radius = 0.1", "radius = 0.1\nfloor_margin = 0.1\nfloor_slip = true",
         r"\(shape 'sphere'\): floor_slip = True is not allowed without floor_ghost = True"),
        ("radius = 0.1", "radius = 0.1\nfloor_margin = 0.1\nfloor_ghost = 1",
         r"key 'floor_ghost' in \[\[bodies\]\] #1 .* must be true or false, not int 1"),
        ("radius = 0.1", "radius = 0.1\nfloor_margin = 0.1\nfloor_ghost = true\nfloor_elastic = true",
         r"\(shape 'sphere'\): floor_elastic = True is not allowed with floor_ghost = True"),
        ("radius = 0.1", "radius = 0.1\nfloor_margin = 100.0", r"\(shape 'sphere'\): floor_margin = 100\.0 is not allowed: .*2000 spacings"),
        ("radius = 0.1", 'radius = 0.1\nfloor_margin = "wide"', r"key 'floor_margin' in \[\[bodies\]\] #1 .* must be a number, not str"),
        ("radius = 0.1", "radius = 0.1\nfloor = 2", r"unknown key 'floor' in \[\[bodies\]\] #1"),
        ('preset = "dough"', 'preset = "dough"\npressure_force = "spikey"',
         r"\[materials\.m\]: pressure_force = 'spikey' is not allowed: must be one of 'energy', 'spiky', 'energy_spiky', 'isotropic'"),
    ],
)
def test_scene_file_errors_name_file_table_and_key(tmp_path, old, new, pattern):
    assert old in BASE
    path = tmp_path / "bad.toml"
    path.write_text(BASE.replace(old, new, 1))
    with pytest.raises(ValueError, match=pattern) as info:
        load_scene_file(path)
    assert str(path) in str(info.value)


_TOOL = '[[tools]]\nshape = "sphere"\nradius = 0.05\n'


@pytest.mark.parametrize(
    "changes, pattern",
    [
        ({'preset = "dough"': 'preset = "dough"\nmu = 1e39\nlam = 1e39'},
         # The advice names both spellings, the command's and Python's (it named dtype=float64 only).
         r"\[materials\.m\]: mu = 1e\+39 is not allowed in float32: must be at most 3\.4e\+38; "
         r"use dtype=float64 \(--dtype float64\) or a smaller value$"),
        # The Lame parameters of the E and nu given were named as keys the table does not hold ('mu = 3.84615e-40').
        ({'preset = "dough"': 'preset = "dough"\nE = 1e-39\nnu = 0.3'},
         r"\[materials\.m\]: E = 1e-39 is not allowed in float32: with nu = 0\.3 it gives mu = E / \(2 \(1 \+ nu\)\) = "
         r"3\.84615e-40: must be 0 or at least 1\.18e-38 in size; use dtype=float64 \(--dtype float64\) or a larger value$"),
        ({'preset = "dough"': 'E = 1e39\nnu = 0.3'},
         r"\[materials\.m\]: E = 1e\+39 is not allowed in float32: with nu = 0\.3 it gives mu = .* = 3\.84615e\+38: must "
         r"be at most 3\.4e\+38"),
        ({'preset = "dough"': 'preset = "dough"\nviscosity = 1e-39'},
         r"\[materials\.m\]: viscosity = 1e-39 is not allowed in float32: must be 0 or at least 1\.18e-38"),
        ({"center = [0, 0.2, 0]": "center = [1e7, 0.2, 0]"},
         r"\[\[bodies\]\] #1 \(shape 'sphere'\): center puts particles 1e\+07 m from the origin, which is not allowed in float32"),
        ({"radius = 0.1": "radius = 0.1\nvelocity = [1e39, 0, 0]"},
         r"\[\[bodies\]\] #1 \(shape 'sphere'\): velocity .* beyond 3\.4e\+38 m/s, which is not allowed in float32"),
        ({"spacing = 0.05": "spacing = 0.05\ngravity = [0, -1e39, 0]"},
         r"\[scene\]: gravity = \[0\.0, -1e\+39, 0\.0\] is not allowed in float32"),
        ({"spacing = 0.05": "spacing = 2e-5", "radius = 0.1": "radius = 4e-5"},
         r"\[scene\]: support_radius = 4e-05 \(given, or 2 x spacing\) is not allowed in float32"),
        ({"offset = 0.0": "offset = -1e39"},
         r"\[\[colliders\]\] #1 \(type 'plane'\): offset = -1e\+39 is not allowed in float32"),
        ({'type = "plane"\nnormal = [0, 1, 0]\noffset = 0.0': 'type = "ground"\nfriction = 1e39'},
         r"\[\[colliders\]\] #1 \(type 'ground'\): friction = 1e\+39 is not allowed in float32"),
        ({'type = "plane"\nnormal = [0, 1, 0]\noffset = 0.0': 'type = "ground"\nheight = -1e39'},
         r"\[\[colliders\]\] #1 \(type 'ground'\): height = -1e\+39 is not allowed in float32"),
        ({"[scene]": _TOOL + "position = [0, 1e20, 0]\n[scene]"},
         r"\[\[tools\]\] #1 \(shape 'sphere'\): position = \[0\.0, 1e\+20, 0\.0\] is not allowed in float32"),
        ({"[scene]": _TOOL + "keyframe_times = [1.0, 1.000000001]\nkeyframe_positions = [[0, 1, 0], [0, 1, 0]]\n[scene]"},
         r"\[\[tools\]\] #1 \(shape 'sphere'\): keyframe_times = \[1\.0, 1\.000000001\] is not allowed in float32: "
         r"1\.0 and 1\.000000001 are equal.*; use dtype=float64 \(--dtype float64\) or times further apart$"),
        ({"[scene]": '[[pins]]\nbody = "sphere0"\nangular_velocity = [0, 1e20, 0]\n[scene]'},
         r"\[\[pins\]\] #1: angular_velocity = \[0\.0, 1e\+20, 0\.0\] is not allowed in float32"),
    ],
)
def test_scene_file_numbers_beyond_float32_name_file_table_and_key(tmp_path, changes, pattern):
    """finalize refuses numbers the model's precision cannot hold; for a scene file its
    message named neither the file nor the key (``Material.mu = 1e+39 (material 0)``,
    ``add_ground height (add_plane offset)``, ``body velocities beyond ...``). float64 takes them."""
    import warp as wp  # noqa: PLC0415

    text = BASE
    for old, new in changes.items():
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "big.toml"
    path.write_text(text)
    scene = load_scene_file(path)
    with pytest.raises(ValueError, match="^" + re.escape(f"{path}: ") + pattern):
        scene.builder.finalize(dtype=wp.float32)
    scene.builder.finalize(dtype=wp.float64)


@pytest.mark.parametrize(
    "changes, pattern",
    [
        ({"[scene]": _TOOL.replace("0.05", "0.03") + 'name = "ball"\nkeyframe_times = [0.0, 1.0]\n'
                     "keyframe_positions = [[-0.025, 0.175, -0.025], [0, 0.3, 0]]\n[scene]"},
         r"\[\[tools\]\] #1 \(shape 'sphere'\): body 'sphere0' is not allowed where it is: 1 of its particles start "
         r"inside tool 'ball' at its first pose, up to 0\.03 m deep"),
        ({"offset = 0.0": "offset = 0.25"},
         r"\[\[colliders\]\] #1 \(type 'plane'\): body 'sphere0' is not allowed where it is: .* start inside plane0"),
        ({"radius = 0.1": 'radius = 0.1\n[[bodies]]\nshape = "box"\nmaterial = "m"\ncenter = [0, 0.2, 0]\nsize = [0.1, 0.1, 0.1]'},
         r"\[\[bodies\]\] #2 \(shape 'box'\): bodies 'box1' and 'sphere0' are not allowed to overlap"),
        ({}, r"\[scene\]: particles = 32 is not allowed on cpu: a model and two states of them need about"),
    ],
)
def test_scene_file_bodies_refused_where_they_start_name_file_and_table(tmp_path, monkeypatch, changes, pattern):
    """finalize's refusals of where the bodies start (inside a tool at its first pose, inside
    a static collider, overlapping another body) and of a model too large for the memory named
    neither the scene file nor its table, as its other refusals do; ``plane0`` and ``sphere0``
    are no names of the file's."""
    from warp_esph import builder  # noqa: PLC0415

    if not changes:
        monkeypatch.setattr(builder, "_device_memory", lambda dev: 1000)
    text = BASE
    for old, new in changes.items():
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "where.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match="^" + re.escape(f"{path}: ") + pattern):
        load_scene_file(path).builder.finalize()


def test_scene_file_body_started_a_little_inside_a_collider_is_placed_on_it_naming_file_and_table(tmp_path):
    """A body 0.1 spacings inside the file's plane is placed on it at finalize; the warning
    names the file and the collider's table, as the refusal of a deeper start does."""
    path = tmp_path / "low.toml"
    path.write_text(BASE)
    low = float(np.concatenate(load_scene_file(path).builder._points)[:, 1].min())
    path.write_text(BASE.replace("offset = 0.0", f"offset = {low + 0.005!r}"))
    with pytest.warns(UserWarning) as caught:
        model = load_scene_file(path).builder.finalize()
    said = [str(w.message) for w in caught if "start inside" in str(w.message)]
    assert len(said) == 1 and said[0].startswith(f"{path}: [[colliders]] #1 (type 'plane'): body 'sphere0': "), said
    assert re.search(r"start inside plane0, up to 0\.005 m deep \(0\.1 spacings\); they are placed on its surface", said[0])
    assert float(model.particle_x0[:, 1].min()) == pytest.approx(low + 0.005, abs=1e-7)


def test_scene_loaded_a_little_inside_a_collider_is_warned_of_once_by_its_finalize(tmp_path):
    """``load_scene`` (the command's way in) builds the model once to check the bodies'
    resolution: that build warned of the start inside as well, so the same warning came twice,
    the first from inside the check. The scene's own ``finalize`` warns, once."""
    import warnings  # noqa: PLC0415

    path = tmp_path / "low.toml"
    path.write_text(BASE)
    low = float(np.concatenate(load_scene_file(path).builder._points)[:, 1].min())
    path.write_text(BASE.replace("offset = 0.0", f"offset = {low + 0.005!r}"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(path)
        at_load = [str(w.message) for w in caught if "start inside" in str(w.message)]
        model = scene.builder.finalize()
    said = [str(w.message) for w in caught if "start inside" in str(w.message)]
    assert at_load == [] and len(said) == 1, said
    assert float(model.particle_x0[:, 1].min()) == pytest.approx(low + 0.005, abs=1e-7)


def test_floor_keys_build_the_same_model_as_add_particle_floor(tmp_path):
    """``floor_margin`` / ``floor_layers`` / ``floor_elastic`` on a body are
    ``SceneBuilder.add_particle_floor``: the same particles, velocities, bodies, materials
    and pinned set."""
    from warp_esph import SceneBuilder  # noqa: PLC0415

    path = tmp_path / "floor.toml"
    path.write_text(BASE.replace("radius = 0.1", "radius = 0.1\nfloor_margin = 0.12\nfloor_layers = 3\nfloor_elastic = true", 1)
                    + '\n[[bodies]]\nshape = "box"\nmaterial = "m"\ncenter = [0.5, 0.2, 0]\nsize = [0.2, 0.1, 0.2]\n')
    b = load_scene_file(path).builder
    ref = SceneBuilder(spacing=0.05)
    mat = PRESETS["dough"]
    ref.add_sphere((0, 0.2, 0), 0.1, mat)
    assert ref.add_particle_floor(0, margin=0.12, layers=3, elastic=True) == "sphere0_floor"
    ref.add_box((0.5, 0.2, 0), (0.2, 0.1, 0.2), mat)
    assert b._materials == ref._materials and len(b._materials) == 2
    np.testing.assert_array_equal(np.concatenate(b._material_ids), np.concatenate(ref._material_ids))
    assert [(x.name, x.start, x.count) for x in b._bodies] == [(x.name, x.start, x.count) for x in ref._bodies]
    np.testing.assert_array_equal(np.concatenate(b._points), np.concatenate(ref._points))
    np.testing.assert_array_equal(np.concatenate(b._velocities), np.concatenate(ref._velocities))
    assert [p.name for p in b.pins] == ["sphere0_floor"]
    np.testing.assert_array_equal(b.pins[0].indices, ref.pins[0].indices)
    # Three layers under the sphere's footprint, one spacing apart, the top one a spacing
    # below its lowest particle; the box after it has none.
    sphere = b._bodies[0]
    floor = np.concatenate(b._points)[b.pins[0].indices]
    assert b.pins[0].indices.min() > sphere.start and b.pins[0].indices.max() == sphere.start + sphere.count - 1
    low = np.concatenate(b._points)[sphere.start:b.pins[0].indices.min(), 1].min()
    np.testing.assert_allclose(np.unique(np.round(floor[:, 1], 9)), low - 0.05 * np.arange(3, 0, -1), atol=1e-9)


# Its bodies are coarse on purpose (a tiny scene, or one torn apart): the run's under-resolution warning is expected.
@pytest.mark.filterwarnings("ignore:the deformation fit was skipped:RuntimeWarning")
def test_solver_table_sets_the_fit_and_contact_of_the_model_and_its_solver(tmp_path):
    """``[solver]`` reaches ``Solver(model)``: a step of the scene's model is, bit for bit, the
    step of a solver given the option explicitly, and differs from the linear fit's (an
    impact bends the surface, where the two fits differ)."""
    from warp_esph import Solver
    from warp_esph.model import DEFAULT_FIT
    from warp_esph.sim.colliders import CONTACT_RAMP, CONTINUOUS_CONTACT_RAMP

    text = BASE.replace("radius = 0.1", "radius = 0.1\nvelocity = [0, -4, 0]").replace("center = [0, 0.2, 0]", "center = [0, 0.15, 0]")
    plain = tmp_path / "plain.toml"
    plain.write_text(text)
    chosen = tmp_path / "chosen.toml"
    chosen.write_text('[solver]\nfit = "curvature_corrected"\ncontact = "continuous"\n' + text)
    m = load_scene_file(chosen).builder.finalize()
    base = load_scene_file(plain).builder.finalize()
    assert (m.fit, m.contact_ramp) == ("curvature_corrected", CONTINUOUS_CONTACT_RAMP)
    assert (base.fit, base.contact_ramp) == (DEFAULT_FIT, CONTACT_RAMP) and DEFAULT_FIT == "auto"
    # The default chooses by material: this dough can flow, so the paper's linear fit.
    assert Solver(m).fit == "curvature_corrected" and Solver(base).fit == "linear"

    def run(model, **kw):
        return simulate(model, 2, progress=False, solver=Solver(model, **kw)).x.numpy()

    x = run(m)
    base.contact_ramp = CONTINUOUS_CONTACT_RAMP
    assert np.array_equal(x, run(base, fit="curvature_corrected"))
    assert np.abs(x - run(base)).max() > 1e-6


def test_solver_table_sets_the_fit_weight_of_the_model_and_its_worlds(tmp_path):
    """``[solver] fit_weight`` naming the weight that is not the default reaches
    ``Model.fit_weight``, the worlds copied from the model and those made from builders; worlds
    of different weights are refused by name."""
    from warp_esph import SceneBuilder, finalize_worlds, replicate_worlds
    from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS

    other = next(w for w in FIT_WEIGHTS if w != DEFAULT_FIT_WEIGHT)
    plain, chosen = tmp_path / "plain.toml", tmp_path / "chosen.toml"
    plain.write_text(BASE)
    chosen.write_text(f'[solver]\nfit_weight = "{other}"\n' + BASE)
    m = load_scene_file(chosen).builder.finalize()
    assert (m.fit_weight, load_scene_file(plain).builder.finalize().fit_weight) == (other, DEFAULT_FIT_WEIGHT)
    assert replicate_worlds(m, 2).fit_weight == other
    b0, b1 = load_scene_file(chosen).builder, load_scene_file(plain).builder
    assert finalize_worlds([b0, b0]).fit_weight == other
    with pytest.raises(ValueError, match=rf"builders\[1\]\.fit_weight = '{DEFAULT_FIT_WEIGHT}' is not allowed: every world must "
                                         "have the fit_weight"):
        finalize_worlds([b0, b1])
    with pytest.raises(ValueError, match=r"fit_weight = 'cubic' is not allowed: must be one of 'poly6', 'biweight'"):
        SceneBuilder(fit_weight="cubic")


@pytest.mark.filterwarnings("ignore:the hourglass control .* can flow:RuntimeWarning")
# Its bodies are coarse on purpose (a tiny scene, or one torn apart): the run's under-resolution warning is expected.
@pytest.mark.filterwarnings("ignore:the deformation fit was skipped:RuntimeWarning")
def test_solver_table_sets_the_hourglass_control_of_the_model_and_its_solver(tmp_path):
    """``[solver] hourglass = 0.1`` reaches ``Solver(model)`` and the worlds copied from the
    model: a step is, bit for bit, that of ``Solver(model, hourglass=0.1)`` on the scene
    without it, and differs from the step without the control (an impact drives the
    non-affine offsets the control acts on)."""
    from warp_esph import SceneBuilder, Solver, finalize_worlds, replicate_worlds

    text = BASE.replace("radius = 0.1", "radius = 0.1\nvelocity = [0, -4, 0]").replace("center = [0, 0.2, 0]", "center = [0, 0.15, 0]")
    plain = tmp_path / "plain.toml"
    plain.write_text(text)
    chosen = tmp_path / "chosen.toml"
    chosen.write_text("[solver]\nhourglass = 0.1\n" + text)
    m = load_scene_file(chosen).builder.finalize()
    base = load_scene_file(plain).builder.finalize()
    assert (m.hourglass, base.hourglass) == (0.1, None)  # None: by the fit (0 for this dough)
    assert Solver(m).hourglass == 0.1 and Solver(base).hourglass == 0.0 and Solver(m, hourglass=0).hourglass == 0.0
    assert replicate_worlds(m, 2).hourglass == 0.1
    b0, b1 = load_scene_file(chosen).builder, load_scene_file(plain).builder
    assert finalize_worlds([b0, b0]).hourglass == 0.1
    with pytest.raises(ValueError, match=r"builders\[1\]\.hourglass = None is not allowed: every world must have the hourglass"):
        finalize_worlds([b0, b1])

    def run(model, **kw):
        return simulate(model, 2, progress=False, solver=Solver(model, **kw)).x.numpy()

    x = run(m)
    assert np.array_equal(x, run(base, hourglass=0.1))
    assert np.abs(x - run(base)).max() > 1e-6
    with pytest.raises(ValueError, match=r"hourglass = -1 is not allowed: must be >= 0"):
        SceneBuilder(hourglass=-1)
    with pytest.raises(ValueError, match=r"hourglass = 'x' is not allowed: must be a number"):
        m.hourglass = "x"
    assert m.hourglass == 0.1


# Its bodies are coarse on purpose (a tiny scene, or one torn apart): the run's under-resolution warning is expected.
@pytest.mark.filterwarnings("ignore:the deformation fit was skipped:RuntimeWarning")
def test_material_table_sets_the_pressure_force(tmp_path):
    """A material table's ``pressure_force`` becomes ``Material.pressure_force`` and changes
    the run (the two forms differ once the body is compressed)."""
    text = BASE.replace("radius = 0.1", "radius = 0.1\nvelocity = [0, -4, 0]").replace("center = [0, 0.2, 0]", "center = [0, 0.15, 0]")
    plain, spiky = tmp_path / "plain.toml", tmp_path / "spiky.toml"
    plain.write_text(text)
    spiky.write_text(text.replace('preset = "dough"', 'preset = "dough"\npressure_force = "spiky"', 1))
    a, b = load_scene_file(plain).builder.finalize(), load_scene_file(spiky).builder.finalize()
    assert [mat.pressure_force for mat in a.materials] == ["energy_spiky"]
    assert [mat.pressure_force for mat in b.materials] == ["spiky"]
    xa = simulate(a, 2, progress=False).x.numpy()
    xb = simulate(b, 2, progress=False).x.numpy()
    assert np.abs(xa - xb).max() > 1e-6


def test_solver_options_refuse_bad_names_in_python():
    import dataclasses

    from warp_esph import SceneBuilder, Solver
    from warp_esph.model import DEFAULT_FIT

    with pytest.raises(ValueError, match=r"fit = 'quad' is not allowed: must be one of 'auto', 'linear', 'curvature_corrected'"):
        SceneBuilder(fit="quad")
    with pytest.raises(ValueError, match=r"contact = 'soft' is not allowed: must be one of 'instant', 'continuous'"):
        SceneBuilder(contact="soft")
    with pytest.raises(ValueError, match=r"contact = 'continuous' and contact_ramp = 0.5 are not allowed together"):
        SceneBuilder(contact="continuous", contact_ramp=0.5)
    with pytest.raises(ValueError, match=r"contact_ramp = -1 is not allowed: must be >= 0"):
        SceneBuilder(contact_ramp=-1)
    # A touchdown spread over 1e300 steps' drift let every particle fall through.
    with pytest.raises(ValueError, match=r"contact_ramp = 1e\+300 is not allowed: must be at most 10"):
        SceneBuilder(contact_ramp=1e300)
    b = SceneBuilder(spacing=0.05)
    b.add_box(center=(0, 0, 0), size=(0.1, 0.1, 0.1), material=PRESETS["rubber"])
    model = b.finalize()
    with pytest.raises(ValueError, match=r"fit = 'quad' is not allowed"):
        model.fit = "quad"
    assert model.fit == DEFAULT_FIT
    # A Fig. 8 comparison model has the linear fit by default, and the additive one only
    # that: a chosen corrected fit is refused by the solver before any kernel runs.
    b = SceneBuilder(spacing=0.05)
    b.add_box(center=(0, 0, 0), size=(0.1, 0.1, 0.1), material=dataclasses.replace(PRESETS["rubber"], deformation="additive",
                                                                                   elastic_force="paper"))
    model = b.finalize()
    assert model.fit == "linear" and Solver(model).fit == "linear"
    model.fit = "curvature_corrected"
    with pytest.raises(ValueError, match="fit = 'curvature_corrected' is not allowed with a comparison deformation model"):
        Solver(model)


def test_scene_file_unreadable(tmp_path):
    with pytest.raises(ValueError, match="cannot read scene file .*nope.toml"):
        load_scene_file(tmp_path / "nope.toml")
    with pytest.raises(ValueError, match="no bodies"):
        (tmp_path / "empty.toml").write_text("[scene]\nspacing = 0.05\n")
        load_scene_file(tmp_path / "empty.toml")


@pytest.mark.parametrize("scale", [0.5, 0.7, 0.8, 1.0])
def test_lab_tools_start_touching_the_outer_particle_layers(scale):
    """The platen, the indenting ball, the bending pin and supports touch the particle
    centres of the outer layers at t = 0 (placed at the bodies' faces, half a spacing out,
    at scale 0.5 the ball and the pin never reached the material, their force stayed 0), and
    the beam has particle columns under the pin and over the supports (at scales other than 0.5
    and 1 they stood between two columns: the supports up to 0.32 mm below the beam at 0.8,
    the pin half a spacing off mid-span at 0.7), and its spacing is the scale's to 6 %."""
    def setup(name):
        model = get_scene(name, scale=scale).builder.finalize()
        x0 = model.particle_x0.astype(np.float64)
        return model, x0, x0[:, 1].min(), x0[:, 1].max()

    def pose(model, tool):
        return model.tools.pose_at(model.tools.index(tool), 0.0)[0]

    model, x0, lo, hi = setup("lab_compression")
    assert pose(model, "plate")[1] - 0.005 == pytest.approx(hi, abs=1e-7)  # the platen's bottom face
    assert pose(model, "base")[1] == pytest.approx(lo, abs=1e-7)
    model, x0, lo, hi = setup("lab_indentation")
    assert pose(model, "indenter")[1] - 0.02 == pytest.approx(hi, abs=1e-7)  # the ball's lowest point
    assert pose(model, "indenter")[1] - 0.02 - model.tools.pose_at(model.tools.index("indenter"), 1.0)[0][1] + 0.02 == \
        pytest.approx(0.004, abs=1e-7)  # 4 mm into the particles at t = 1 s
    model, x0, lo, hi = setup("lab_three_point_bending")
    assert pose(model, "loading_pin")[1] - 0.01 == pytest.approx(hi, abs=1e-7)
    for side, x in (("support_left", -0.09), ("support_right", 0.09)):
        assert pose(model, side)[1] + 0.01 == pytest.approx(lo, abs=1e-7)
        assert np.abs(x0[:, 0] - x).min() < 1e-7  # a column over the support's axis
    assert np.abs(x0[:, 0]).min() < 1e-7  # and one under the pin
    assert model.spacing == pytest.approx(0.005 / scale, rel=0.06)


def test_a_scene_files_collider_that_repeats_a_plane_is_refused_naming_its_table(tmp_path):
    """A ground on the file's plane is refused as add_ground twice is, naming the table it
    repeats, not a call the file never wrote."""
    path = tmp_path / "twice.toml"
    path.write_text(BASE + '\n[[colliders]]\ntype = "ground"\n')
    with pytest.raises(ValueError, match=r"^.*twice\.toml: \[\[colliders\]\] #2 \(type 'ground'\): it is \[\[colliders\]\] #1 "
                                         r"\(type 'plane'\), the plane y = 0 \(friction 0\.5\), again: .*; add each plane once$"):
        load_scene_file(str(path))


def test_ground_images_key_builds_the_ground_as_a_rough_floor(tmp_path):
    """``images = true`` on a ``ground`` collider is ``SceneBuilder.add_ground(images=True)``;
    a non-boolean is refused by name."""
    text = BASE.replace('type = "plane"\nnormal = [0, 1, 0]\noffset = 0.0', 'type = "ground"\nheight = 0.01\nimages = true')
    assert "images = true" in text
    path = tmp_path / "images.toml"
    path.write_text(text)
    model = load_scene_file(path).builder.finalize()
    assert model.image_plane == ((0.0, 1.0, 0.0), 0.01)
    path.write_text(text.replace("images = true", "images = 1"))
    with pytest.raises(ValueError, match=r"key 'images' in \[\[colliders\]\] #1 \(type 'ground'\) must be true or false"):
        load_scene_file(path)


@pytest.mark.parametrize("points", [2, 10**9])
def test_a_star_with_points_out_of_range_is_told_the_true_range(points):
    """A star needs at least 3 points; a count above the maximum was told "[1, 1000]"."""
    b = we.SceneBuilder(spacing=0.02)
    with pytest.raises(ValueError, match=rf"^points = {points} is not allowed: must be an integer in \[3, 1000\]$"):
        b.add_star((0.0, 0.1, 0.0), 0.1, 0.05, 0.04, we.Material.preset("dough"), points=points)



def test_load_scene_names_a_scene_that_is_no_name_or_path_and_a_scale_that_alone_fails():
    """``load_scene(3)`` and ``load_scene(b'star')`` raised TypeErrors ('expected str, bytes or
    os.PathLike object', 'endswith first arg must be bytes'); ``get_scene``/``load_scene`` at
    an absurd scale blamed the scene's body or centre, as the CLI's ``--scale`` no longer does."""
    for bad in (3, ["star"]):
        with pytest.raises(ValueError, match=re.escape(f"scene = {bad!r} is not allowed: must be a built-in scene name "
                                                       "or the path of a .toml scene file")):
            load_scene(bad)
    assert load_scene(b"star", scale=0.5).name == "star"  # a path in bytes, as os.fspath gives them
    with pytest.raises(ValueError, match=r"^scale = 1e-300 is not allowed for star: it builds at scale 1, but with its "
                                         r"spacing divided by 1e-300: body 'star' has no particles"):
        load_scene("star", scale=1e-300)
    with pytest.raises(ValueError, match=r"^scale = 1e\+300 is not allowed for dough_drop: it builds at scale 1, "):
        get_scene("dough_drop", scale=1e300)
    with pytest.raises(ValueError, match=r"^scale = nan is not allowed: must be a finite number$"):
        load_scene("star", scale=float("nan"))


def test_under_resolved_body_is_refused_naming_body_scale_and_the_least_scale(tmp_path):
    """At scale 0.3 the squeeze-flow disc (2 cm high) is one layer of 1.33 cm spacing: every
    particle's fit is skipped by the guards of paper §4, and the run answered nonsense with
    exit 0. It is refused where it is built, naming the body, the scale and the least scale
    that resolves it, which loads; a scene file's one-layer sheet likewise."""
    with pytest.raises(ValueError, match=r"^--scale = 0.3 is not allowed for lab_squeeze_flow: body 'sample' is "
                       r"under-resolved at spacing 0.0133: it is 1 particle layer thick, .* the smallest --scale above "
                       r"0.3 that resolves it is (\d\.\d+)$") as e:
        load_scaled_scene("lab_squeeze_flow", 0.3)
    least = float(str(e.value).rsplit(" ", 1)[1])
    model = load_scaled_scene("lab_squeeze_flow", least).builder.finalize()
    assert len(np.unique(np.round(model.particle_x0[:, 1], 6))) >= 2  # two layers at least
    with pytest.raises(ValueError, match="under-resolved"):
        load_scaled_scene("lab_squeeze_flow", least - scenes.SCALE_STEP)
    path = tmp_path / "sheet.toml"
    path.write_text('[scene]\nspacing = 0.02\n[[bodies]]\nshape = "box"\nname = "sheet"\nmaterial = "clay"\n'
                    'center = [0, 0.5, 0]\nsize = [0.2, 0.02, 0.2]\n')
    # As written (scale 1) the file's spacing is the fault; the scale names it only where given.
    with pytest.raises(ValueError, match=r"^.*sheet.toml: \[scene\] spacing = 0.02 is not allowed: body 'sheet' is "
                       r"under-resolved at spacing 0.02: it is 1 particle layer thick, and 100 of its 100 particles .* the "
                       r"largest spacing that resolves it is ([.\d]+) \(scale (\d[.\d]*)\)$") as e:
        load_scene(str(path))
    spacing, scale = re.search(r"is ([.\d]+) \(scale ([.\d]+)\)$", str(e.value)).groups()
    assert float(spacing) == pytest.approx(0.02 / float(scale))
    model = load_scene(str(path), scale=float(scale)).builder.finalize()
    assert len(np.unique(np.round(model.particle_x0[:, 1], 6))) == 2
    with pytest.raises(ValueError, match=r"^scale = 1.5 is not allowed for .*sheet.toml: body 'sheet' is under-resolved "
                       r"at spacing 0.0133: .* the smallest scale above 1.5 that resolves it is "):
        load_scene(str(path), scale=1.5)


def test_an_under_resolved_bodys_search_stopped_by_its_particle_bound_names_the_last_scale_it_checked(tmp_path, monkeypatch):
    """The search also stops at a scale whose model would pass its particle bound: that scale is
    not checked, and the refusal named it as the scale the search looked up to."""
    path = tmp_path / "wide_sheet.toml"
    path.write_text('[scene]\nspacing = 0.02\n[[bodies]]\nshape = "box"\nname = "sheet"\nmaterial = "clay"\n'
                    'center = [0, 0.5, 0]\nsize = [1.0, 0.02, 1.0]\n')
    monkeypatch.setattr(scenes, "SCALE_SEARCH", (scenes.SCALE_SEARCH[0], 1.0))  # the bound: its particles + 1000
    count = scenes._load(str(path), 1.05).builder._count  # the scene unchecked, as the search builds it
    checked, over = [], None
    for k in range(22, 60):  # scales 1.1, 1.15, ...: the first whose model passes the bound is not checked
        s = round(k * scenes.SCALE_STEP, 10)
        if scenes._load(str(path), s).builder._count > count + 1000:
            over = s
            break
        checked.append(s)
    assert over is not None and checked, (count, checked)
    with pytest.raises(ValueError, match=rf"; no scale up to {checked[-1]:g} resolves it \(at {over:g} it would hold "
                       r"\d+ particles, past the search's bound of \d+\); give the body more particle layers$"):
        load_scene(str(path), scale=1.05)


def test_an_under_resolved_body_no_scale_searched_resolves_says_how_far_it_looked(tmp_path, monkeypatch):
    """The search for a scale that resolves a refused scene is bounded (each scale tried builds
    the model): where none within it does, the refusal says how far it looked."""
    path = tmp_path / "sheet.toml"
    path.write_text('[scene]\nspacing = 0.02\n[[bodies]]\nshape = "box"\nname = "sheet"\nmaterial = "clay"\n'
                    'center = [0, 0.5, 0]\nsize = [0.2, 0.02, 0.2]\n')
    monkeypatch.setattr(scenes, "SCALE_SEARCH", (1.5, scenes.SCALE_SEARCH[1]))  # the sheet needs 2
    with pytest.raises(ValueError, match=r"body 'sheet' is under-resolved .*; no spacing down to 0.0133 \(scale 1.5\) "
                       r"resolves it; give the body more particle layers$"):
        load_scene(str(path))
    last = math.floor(1.5 * 1.05 / scenes.SCALE_STEP + 1e-9) * scenes.SCALE_STEP  # the last scale of the search from 1.05
    with pytest.raises(ValueError, match=rf"body 'sheet' is under-resolved .*; no scale up to {last:g} resolves it; give "
                       r"the body more particle layers$"):
        load_scene(str(path), scale=1.05)


def _material_of(tmp_path, table: str) -> we.Material:
    """The material of BASE's one body, its table ``[materials.m]`` given as ``table``."""
    path = tmp_path / "rheology.toml"
    path.write_text(BASE.replace('preset = "dough"', table, 1))
    return load_scene_file(path).builder.finalize().materials[0]


def test_a_material_table_takes_a_rheometers_values_as_from_rheology_does(tmp_path):
    """A lab's shear yield stress (a rheometer's) or uniaxial one (a compression test's) and
    plastic viscosity, written in a scene file's material table, give the material that
    ``Material.from_rheology`` gives (``tests/test_units.py`` checks that one in simple shear).
    Before, ``shear_yield_stress`` was an unknown key with the advice "did you mean
    'yield_stress'?", which would have set the yield stress sqrt(2) x too low."""
    rheometer = _material_of(tmp_path, "E = 2.0e4\nnu = 0.3\nshear_yield_stress = 50.0\nplastic_viscosity = 10.0")
    assert rheometer == we.Material.from_rheology(2.0e4, 0.3, shear_yield_stress=50.0, plastic_viscosity=10.0)
    assert rheometer.shear_yield_stress == pytest.approx(50.0) and rheometer.plastic_viscosity == pytest.approx(10.0)
    # From a preset: the preset's elastic constants set the flow rate of the viscosity given.
    dough = we.Material.preset("dough")
    pressed = _material_of(tmp_path, 'preset = "dough"\nuniaxial_yield_stress = 300.0\nplastic_viscosity = 50.0')
    assert pressed == dough.replace(yield_stress=math.sqrt(2.0 / 3.0) * 300.0, flow_rate=dough.mu / 50.0)
    assert pressed.uniaxial_yield_stress == pytest.approx(300.0)
    # inf: a material that never flows, as from_rheology's math.inf.
    assert _material_of(tmp_path, 'preset = "dough"\nplastic_viscosity = inf').flow_rate == 0.0


@pytest.mark.parametrize("table, message", [
    ('preset = "dough"\nshear_yield_stress = 50.0\nyield_stress = 70.0',
     r"\[materials.m\] gives yield_stress and shear_yield_stress: give one"),
    ('preset = "dough"\nshear_yield_stress = 50.0\nuniaxial_yield_stress = 80.0',
     r"\[materials.m\] gives shear_yield_stress and uniaxial_yield_stress: give one"),
    ('preset = "dough"\nplastic_viscosity = 10.0\nflow_rate = 5.0',
     r"\[materials.m\] gives flow_rate and plastic_viscosity: give one"),
    ('preset = "dough"\nmodel = "hyperelastic"\nshear_yield_stress = 50.0',
     r"\[materials.m\]: shear_yield_stress is not allowed for model = 'hyperelastic'.*'linear' or 'stvk'"),
    ('preset = "dough"\nplastic_viscosity = -1.0', r"\[materials.m\]: plastic_viscosity = -1.0? is not allowed: must be > 0"),
    # As Material.from_rheology's, by the value given: a yield stress past the floats had
    # made an elastic material without a word, a viscosity of 1e-320 was refused as
    # 'flow_rate = inf', a value the file never gave.
    # The advice in the file's terms (it had advised Material.from_young to a scene file).
    ('preset = "dough"\nshear_yield_stress = 1.5e308', r"\[materials.m\]: shear_yield_stress = 1.5e\+308 is not "
     r"allowed: yield_stress = sqrt\(2\) shear_yield_stress must be a finite number \(for a material that never yields, "
     r"leave shear_yield_stress out of the table and give yield_stress = inf\)$"),
    # plastic_viscosity is named only where the table gives it (it was advised out of tables without it).
    ('preset = "dough"\nshear_yield_stress = 1.5e308\nplastic_viscosity = 10', r"\[materials.m\]: shear_yield_stress = "
     r"1.5e\+308 is not allowed: .* \(for a material that never yields, leave shear_yield_stress and plastic_viscosity out "
     r"of the table and give yield_stress = inf\)$"),
    ('E = 1e5\nnu = 0.3\nshear_yield_stress = 1.3e308', r"\[materials.m\]: shear_yield_stress = 1.3e\+308 is "
     r"not allowed: yield_stress = sqrt\(2\) shear_yield_stress must be a finite number \(for a material that never "
     r"yields, leave shear_yield_stress out of the table\)$"),
    ('E = 1e5\nnu = 0.3\nplastic_viscosity = 1e-320', r"\[materials.m\]: plastic_viscosity = 1e-320 is not allowed "
     r"with E = 100000.0, nu = 0.3: flow_rate = mu / plastic_viscosity = 38461.5 / 9.99989e-321 = inf must be a finite"),
    # Without a flow rate the yield stress given had no effect (flow_rate 0: elastic), as a
    # from_rheology without plastic_viscosity, which that refuses.
    ('E = 2e4\nnu = 0.3\nshear_yield_stress = 50.0', r"\[materials.m\]: shear_yield_stress = 50.0 is not allowed "
     r"without plastic_viscosity or flow_rate: the default flow_rate is 0, so the material never flows"),
    # Past the model's precision, by the value given (it had named yield_stress = 1.41e+39,
    # a value the file never gave).
    ('E = 1e5\nnu = 0.3\nshear_yield_stress = 1e39\nplastic_viscosity = 10.0', r"\[materials.m\]: shear_yield_stress "
     r"= 1e\+39 is not allowed in float32: it gives yield_stress = sqrt\(2\) shear_yield_stress = 1\.41421e\+39: must "
     r"be at most 3\.4e\+38; use dtype=float64"),
    ('mu = 1e-300\nlam = 0.0\nplastic_viscosity = 1e100', r"\[materials.m\]: plastic_viscosity = 1e\+100 is not "
     r"allowed with mu = 1e-300: flow_rate = mu / plastic_viscosity = 1e-300 / 1e\+100 = 0 must be a finite number above 0"),
])
def test_a_material_tables_rheometer_values_are_refused_beside_what_they_set(tmp_path, message, table):
    with pytest.raises(ValueError, match=message):
        _material_of(tmp_path, table)


@pytest.mark.parametrize("table", ["bodies", "tools"])
def test_a_mesh_file_a_scene_cannot_read_is_refused_by_its_key_file_as_written(tmp_path, table):
    """A mesh body's or tool's ``file`` of a folder, an extension no reader knows, or an
    absolute path to nothing was refused as ``source = '/abs/path' ...`` (a body) or
    ``mesh = ...`` (a tool): add_mesh's and add_tool's parameters, not the file's key."""
    (tmp_path / "points.xyz").write_text("0 0 0\n")
    (tmp_path / "folder.obj").mkdir()
    missing = str(tmp_path / "none.obj")
    head = 'shape = "mesh"\nmaterial = "m"' if table == "bodies" else 'shape = "mesh"'
    for typed, reason in (("points.xyz", "unsupported extension '.xyz'; must be one of .usd"),
                          ("folder.obj", "it is not a file"), (missing, "file not found")):
        text = BASE + f'\n[[{table}]]\n{head}\nfile = {typed!r}\n'
        (tmp_path / "s.toml").write_text(text)
        with pytest.raises(ValueError, match=rf"s\.toml: \[\[{table}\]\] #\d \(shape 'mesh'\): file = "
                                             + re.escape(repr(typed)) + " is not allowed: " + re.escape(reason)):
            load_scene_file(str(tmp_path / "s.toml"))


def test_a_scene_file_named_without_its_extension_is_refused_naming_the_file(tmp_path, monkeypatch):
    """``warp-esph run mine`` beside ``mine.toml``: a bare name is a built-in scene's (a file is
    read only by a path), and the refusal listed the built-in scenes alone; it now names the
    file the user meant."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine.toml").write_text(BASE)
    with pytest.raises(ValueError, match=r"^scene = 'mine' is not allowed: unknown scene; the scene file 'mine.toml' is "
                                         r"here: give its path, 'mine.toml'; the built-in scenes are dough_drop, "):
        load_scene("mine")
    assert load_scene("mine.toml").name == "mine"
    with pytest.raises(ValueError, match=r"unknown scene \(did you mean 'star'\?\); the built-in scenes are "):
        load_scene("stat")



def test_a_scene_files_material_names_select_its_materials(tmp_path, two_materials_scene):
    """``Scene.material_index``: a scene file's material, by the name its table or a body gives
    it, is its material index (``fit --material soft``, ``sweep --param soft.yield_stress``;
    a user names the material as the file does, and was refused: 'give a material index or a
    body name'). A body's name comes first, as ever; another name is None."""
    (tmp_path / "two.toml").write_text(two_materials_scene)
    scene = load_scene_file(tmp_path / "two.toml")
    assert [m.yield_stress for m in scene.builder.finalize().materials] == [PRESETS["dough"].yield_stress,
                                                                             PRESETS["clay"].yield_stress]
    assert (scene.material_index("soft"), scene.material_index("clay"), scene.material_index("a")) == (0, 1, None)
    assert get_scene("dough_drop", scale=0.35).material_index("dough") is None  # a built-in scene names none


def test_a_scene_file_saved_with_a_byte_order_mark_is_read(tmp_path):
    """Notepad's UTF-8 starts with a byte-order mark, which TOML does not take: such a scene
    file was refused as 'invalid TOML: Invalid statement (at line 1, column 1)', a first line
    that reads right. It is read past, as in the JSON, CSV and point-cloud files; a byte that
    is not UTF-8 is still named by its place in the file."""
    text = textwrap.dedent("""\
        [scene]
        name = "bom"
        spacing = 0.05
        [[bodies]]
        shape = "box"
        center = [0.0, 0.2, 0.0]
        size = [0.2, 0.2, 0.2]
        material = "dough"
        """)
    plain, marked = tmp_path / "plain.toml", tmp_path / "marked.toml"
    plain.write_bytes(text.encode())
    marked.write_bytes(b"\xef\xbb\xbf" + text.encode())
    a, b = load_scene_file(plain), load_scene_file(marked)
    assert b.name == "bom" == a.name
    np.testing.assert_array_equal(b.builder.finalize().particle_x0, a.builder.finalize().particle_x0)
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b"\xef\xbb\xbf" + b'[scene]\nname = "\xff"\n')
    with pytest.raises(ValueError, match=r"bad\.toml: invalid TOML: not UTF-8 text \(byte 19\)$"):
        load_scene_file(bad)


@pytest.mark.parametrize("codec, mark", [("utf-16", b""), ("utf-16-be", b"\xfe\xff"), ("utf-16-le", b""), ("utf-16-be", b"")])
def test_text_inputs_saved_as_utf16_are_read(tmp_path, codec, mark):
    """Windows writes UTF-16 with a byte-order mark where a user saves 'Unicode Text' in Excel
    or redirects with PowerShell 5's '>': a scene file was 'not UTF-8 text (byte 0)', an
    --experiments file 'it is not text (a damaged or foreign file?)', and a force log or a point
    cloud was refused by a header shown as '\\ufffd\\ufffdf\\x00r\\x00...'. They are read as
    UTF-16, as the same text saved as UTF-8 is. Without the mark ('iconv -t UTF-16LE', Python's
    'utf-16-le') a scene file was 'Invalid initial character for a key part', a force log 'lacks
    the columns', an --experiments file 'not valid JSON: Expecting value', none a word of
    UTF-16: UTF-8 text holds no NUL byte, so such a file (its NULs on one side of its byte
    pairs, a non-Latin-1 '–' on the other) is read as UTF-16 of that byte order."""
    from warp_esph.checks import json_file
    from warp_esph.fit import load_target
    from warp_esph.losses import read_tools_csv

    def utf16(name, text):
        path = tmp_path / name
        path.write_bytes(mark + text.encode(codec))  # (utf-16 writes its own mark)
        return path

    scene = load_scene_file(utf16("s.toml", '# dough – 20 C\n[scene]\nname = "wide"\nspacing = 0.05\n[[bodies]]\nshape = "box"\n'
                                             'center = [0.0, 0.2, 0.0]\nsize = [0.2, 0.2, 0.2]\nmaterial = "dough"\n'))
    assert scene.name == "wide" and scene.builder.finalize().particle_x0.shape == (64, 3)
    assert json_file("--experiments", utf16("e.json", '[{"scene": "s.toml", "target": "t.npz"}]')) == [
        {"scene": "s.toml", "target": "t.npz"}]
    rows = read_tools_csv(utf16("log.csv", "frame\ttime\ttool\tfx\tfy\tfz\r\n0\t0\tplate\t0\t0\t0\r\n1\t0.0333333\tplate\t0\t-2.5\t0\r\n"))
    assert [(r["frame"], r["tool"], r["force"][1]) for r in rows] == [(0, "plate", 0.0), (1, "plate", -2.5)]
    cloud = load_target(utf16("c.xyz", "x,y,z\n0,0.1,0\n0.02,0.1,0\n"))
    assert cloud.kind == "points"
    np.testing.assert_array_equal(cloud.data, [[0.0, 0.1, 0.0], [0.02, 0.1, 0.0]])


@pytest.mark.parametrize("codec", ["utf-16-le", "utf-16-be"])
def test_utf16_without_a_mark_holding_a_character_ending_in_a_nul_byte_is_read_and_binary_is_not(tmp_path, codec):
    """UTF-16 without its mark was recognised by NULs on one side of its byte pairs alone: a
    character U+xx00 ('一' U+4E00, 'Ā' U+0100) puts a NUL on the other side, and such a scene
    file was read as UTF-8, 'Found invalid character '\\x00''. And an int16 .npy (NULs on one
    side, '\\x01\\x00' in its header) given as an --experiments file was read as UTF-16, 'not
    valid JSON: Expecting value', where it was 'it is not text'."""
    from warp_esph.checks import json_file

    path = tmp_path / "s.toml"
    path.write_bytes('# 一 dough, Ā\n[scene]\nname = "一"\nspacing = 0.05\n[[bodies]]\nshape = "box"\n'
                     'center = [0.0, 0.2, 0.0]\nsize = [0.2, 0.2, 0.2]\nmaterial = "dough"\n'.encode(codec))
    assert load_scene_file(path).name == "一"
    np.save(tmp_path / "i16.npy", np.arange(1, 200, dtype=np.int16 if codec == "utf-16-le" else ">i2"))
    with pytest.raises(ValueError, match=r"^--experiments .*i16\.npy is not valid JSON: it is not text \(a damaged or foreign file\?\)$"):
        json_file("--experiments", tmp_path / "i16.npy")


@pytest.mark.skipif(not os.path.isdir("/dev/fd"), reason="reads a pipe as /dev/fd/N")
def test_text_inputs_read_from_a_pipe_keep_their_first_bytes(tmp_path):
    """A shell's ``<(...)`` hands a pipe (``/dev/fd/63``): the look for a UTF-16 byte-order mark
    opened it and read its first two bytes, which its reader then lacked, so an --experiments
    or camera file read from one was 'not valid JSON: Expecting value: line 1 column 1' and a
    force log lost the 'fr' of its header. A pipe is read once, as UTF-8."""
    from warp_esph.checks import json_file
    from warp_esph.losses import read_tools_csv

    def piped(text):
        r, w = os.pipe()
        os.write(w, text.encode())  # (small: the pipe's buffer holds it)
        os.close(w)
        return r, f"/dev/fd/{r}"

    r, path = piped('[{"scene": "s.toml", "target": "t.npz"}]')
    try:
        assert json_file("--experiments", path) == [{"scene": "s.toml", "target": "t.npz"}]
    finally:
        os.close(r)
    r, path = piped("frame,time,tool,fx,fy,fz\n0,0,plate,0,0,0\n1,0.0333333,plate,0,-2.5,0\n")
    try:
        assert [(row["frame"], row["force"][1]) for row in read_tools_csv(path)] == [(0, 0.0), (1, -2.5)]
    finally:
        os.close(r)


def test_a_utf16_scene_file_that_does_not_decode_is_named_as_utf16(tmp_path):
    """A scene file with a UTF-16 byte-order mark is decoded as UTF-16; one cut short (an odd
    byte at its end) was refused as 'not UTF-8 text', the codec it was not read with."""
    cut = tmp_path / "cut.toml"
    cut.write_bytes('[scene]\nname = "cut"\n'.encode("utf-16") + b"x")
    with pytest.raises(ValueError, match=r"cut\.toml: invalid TOML: not UTF-16 text \(byte 44\)$"):
        load_scene_file(cut)


def test_a_scene_files_material_takes_the_pair_repulsion(tmp_path):
    """``pair_repulsion`` in a material table is ``Material.pair_repulsion`` (off without it);
    a negative one is refused naming the table, as the other fields."""
    path = tmp_path / "pairs.toml"
    path.write_text(BASE.replace('preset = "dough"', 'preset = "dough"\npair_repulsion = 2.0', 1))
    assert load_scene_file(path).builder.finalize().materials[0].pair_repulsion == 2.0
    path.write_text(BASE)
    assert load_scene_file(path).builder.finalize().materials[0].pair_repulsion == 0.0
    path.write_text(BASE.replace('preset = "dough"', 'preset = "dough"\npair_repulsion = -1', 1))
    with pytest.raises(ValueError, match=r"\[materials\.m\]: pair_repulsion = -1 is not allowed: must be >= 0"):
        load_scene_file(path)
