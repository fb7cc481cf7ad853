"""Mesh loading, checking and inside-sampling (warp_esph.meshes) and SceneBuilder.add_mesh."""

import json
import math
import os
import pathlib
import re
import tempfile
import warnings

import hypothesis.strategies as st
import numpy as np
import pytest
import warp.examples
from hypothesis import given, settings

import warp_esph
from warp_esph import meshes

ASSETS = pathlib.Path(warp.examples.get_asset_directory())
BUNNY = ASSETS / "bunny.usd"
BEAR = ASSETS / "bear.usd"

# Measured on Warp's bunny.usd: bounding box (metres, Y up) and divergence-theorem volume.
BUNNY_LO = (-0.9557561, 0.0211633, -0.5424289)
BUNNY_HI = (0.6571599, 1.6401116, 0.6880714)
BUNNY_VOLUME = 0.8758004  # m^3


def cube(lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)):
    """An axis-aligned box as 8 points and 12 outward-facing triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    unit = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    tris = np.array(
        [[0, 3, 2], [0, 2, 1], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
         [2, 3, 7], [2, 7, 6], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]],
        dtype=np.int32,
    )  # fmt: skip
    return lo + unit * (hi - lo), tris


def icosphere(radius=1.0, subdivisions=3):
    """A closed triangulated sphere: an icosahedron split ``subdivisions`` times."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
             (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    verts = [np.array(v, float) / np.linalg.norm(v) for v in verts]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]  # fmt: skip
    for _ in range(subdivisions):
        mid, new = {}, []

        def midpoint(a, b):
            key = (min(a, b), max(a, b))
            if key not in mid:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                mid[key] = len(verts) - 1
            return mid[key]

        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return radius * np.array(verts), np.array(faces, dtype=np.int32)


def open_edges(triangles):
    """Edges not shared by exactly two triangles (computed independently of meshes.py)."""
    counts = {}
    for tri in np.asarray(triangles):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            key = (min(a, b), max(a, b))
            counts[key] = counts.get(key, 0) + 1
    return sum(1 for c in counts.values() if c != 2)


def write_usd(path, meshes_by_path, meters_per_unit=1.0, xform=None):
    """A USD stage with Mesh prims {prim path: (points, faceVertexCounts, faceVertexIndices)};
    ``meters_per_unit=None`` leaves the stage's metersPerUnit unauthored."""
    from pxr import Gf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    if meters_per_unit is not None:
        UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    root = UsdGeom.Xform.Define(stage, "/root")
    if xform is not None:
        translate, scale = xform
        root.AddTranslateOp().Set(Gf.Vec3d(*translate))
        root.AddScaleOp().Set(Gf.Vec3f(*scale))
    for prim_path, (pts, counts, idx) in meshes_by_path.items():
        mesh = UsdGeom.Mesh.Define(stage, prim_path)
        mesh.GetPointsAttr().Set([Gf.Vec3f(*map(float, p)) for p in pts])
        mesh.GetFaceVertexCountsAttr().Set([int(c) for c in counts])
        mesh.GetFaceVertexIndicesAttr().Set([int(i) for i in idx])
    stage.GetRootLayer().Save()


# Unit cube as 6 outward quads (USD counter-clockwise), for fan triangulation.
QUAD_CUBE = (
    cube()[0],
    [4] * 6,
    [0, 3, 2, 1, 4, 5, 6, 7, 0, 1, 5, 4, 2, 3, 7, 6, 0, 4, 7, 3, 1, 2, 6, 5],
)


# ------------------------------------------------------------------------ sampling
def test_unit_cube_gives_one_point_per_cell():
    pts, tris = meshes.load_mesh(cube())
    assert meshes.signed_volume(pts, tris) == pytest.approx(1.0)
    inside = meshes.sample_inside(pts, tris, 0.1)
    # Cell-centred lattice: 10 points per axis at 0.05, 0.15, ..., 0.95.
    assert inside.shape == (1000, 3)
    axis = 0.05 + 0.1 * np.arange(10)
    for k in range(3):
        np.testing.assert_allclose(np.unique(inside[:, k].round(9)), axis, atol=1e-9)


def test_cube_far_from_origin_and_inverted_still_fills():
    pts, tris = cube(lo=(1.0e4, -2.0e4, 5.0e3), hi=(1.0e4 + 1.0, -2.0e4 + 1.0, 5.0e3 + 1.0))
    assert len(meshes.sample_inside(*meshes.load_mesh((pts, tris)), 0.1)) == 1000
    p, t = meshes.load_mesh((pts, tris[:, ::-1]))  # inward-facing: turned outward
    assert meshes.signed_volume(p, t) == pytest.approx(1.0)
    assert len(meshes.sample_inside(p, t, 0.1)) == 1000


def test_a_part_wound_inward_is_turned_outward_unless_it_is_a_cavity():
    """Each separate part of a mesh faces outward, whichever way it was wound, except one
    inside an outward part, which is a cavity. The whole mesh was oriented by its total
    volume only: a second cube wound the other way was left facing inward and got no
    particles, without a word (1000 instead of 1125)."""
    def join(*parts):
        points = np.concatenate([p for p, _ in parts])
        offsets = np.cumsum([0] + [len(p) for p, _ in parts[:-1]])
        return points, np.concatenate([t + o for (_, t), o in zip(parts, offsets)])

    big, small = cube(), cube(lo=(3.0, 0.0, 0.0), hi=(3.5, 0.5, 0.5))
    for a, b in ((big, small), ((big[0], big[1][:, ::-1]), small), (big, (small[0], small[1][:, ::-1]))):
        p, t = meshes.load_mesh(join(a, b))
        assert meshes.signed_volume(p, t) == pytest.approx(1.125)
        assert len(meshes.sample_inside(p, t, 0.1)) == 1125
    hole = cube(lo=(0.3, 0.3, 0.3), hi=(0.7, 0.7, 0.7))
    for outer in (big, (big[0], big[1][:, ::-1])):  # the cavity wound inward; or the whole mesh inverted
        inner = (hole[0], hole[1][:, ::-1]) if outer is big else hole
        p, t = meshes.load_mesh(join(outer, inner))
        assert meshes.signed_volume(p, t) == pytest.approx(1.0 - 0.4**3)
        assert len(meshes.sample_inside(p, t, 0.1)) == 1000 - 64  # the cavity's 4^3 cells stay empty


@settings(max_examples=25, deadline=None)
@given(
    lo=st.tuples(*[st.floats(-2.0, 2.0)] * 3),
    size=st.tuples(*[st.floats(0.1, 0.6)] * 3),
    dx=st.sampled_from([0.02, 0.05, 0.1]),
)
def test_box_mesh_count_is_analytic_and_matches_add_box(lo, size, dx):
    lo, size = np.array(lo), np.array(size)
    pts, tris = meshes.load_mesh(cube(lo, lo + size))
    expected = np.prod(np.floor(size / dx + 1e-9))
    inside = meshes.sample_inside(pts, tris, dx)
    assert len(inside) == expected
    # Same lattice convention as SceneBuilder.add_box of the same box.
    b = warp_esph.SceneBuilder(spacing=dx)
    b.add_box(lo + size / 2, size, warp_esph.Material.preset("dough"))
    np.testing.assert_allclose(np.sort(inside, axis=0), np.sort(b._points[0], axis=0), atol=1e-9)


def test_sphere_volume_from_point_count():
    r, dx = 0.5, 0.04
    pts, tris = meshes.load_mesh(icosphere(r, 3))
    volume = meshes.signed_volume(pts, tris)
    assert volume == pytest.approx(4 / 3 * math.pi * r**3, rel=0.03)  # faceted, slightly smaller
    inside = meshes.sample_inside(pts, tris, dx)
    assert len(inside) * dx**3 == pytest.approx(volume, rel=0.05)
    assert np.all(np.linalg.norm(inside, axis=1) < r)


def test_mesh_smaller_than_spacing_is_rejected():
    # Two 1 cm cubes 10 cm apart: the one lattice point (the box centre) is between them.
    (a, ta), (b, tb) = cube((0, 0, 0), (0.01, 0.01, 0.01)), cube((0.1, 0, 0), (0.11, 0.01, 0.01))
    pts, tris = meshes.load_mesh((np.concatenate([a, b]), np.concatenate([ta, tb + 8])))
    with pytest.raises(ValueError, match=r"spacing = 0\.5 is not allowed.*no lattice point"):
        meshes.sample_inside(pts, tris, 0.5)
    with pytest.raises(ValueError, match=r"spacing = -1 is not allowed"):
        meshes.sample_inside(pts, tris, -1)
    with pytest.raises(ValueError, match=r"^mesh \(points, triangles\) is not allowed: triangle indices"):
        meshes.sample_inside(pts, tris + 1, 0.01)


# ------------------------------------------------------------------------- file I/O
@pytest.mark.parametrize("ext", [".obj", ".stl", ".ply", ".off", ".vtk"])
def test_meshio_round_trip(tmp_path, ext, capfd):
    pts, tris = icosphere(0.3, 2)
    path = tmp_path / f"ball{ext}"
    meshes.write_mesh(path, pts, tris)
    # Nothing on the caller's stdout: a .ply printed meshio's "Warning: PLY doesn't support
    # 64-bit integers. Casting down to 32-bit." at every write.
    assert capfd.readouterr() == ("", "")
    p, t = meshes.load_mesh(path)
    assert len(p) == len(pts) and len(t) == len(tris)  # STL's repeated corners merged again
    assert open_edges(t) == 0
    assert meshes.signed_volume(p, t) == pytest.approx(meshes.signed_volume(pts, tris), rel=1e-5)
    assert len(meshes.sample_inside(p, t, 0.05)) == len(meshes.sample_inside(pts, tris, 0.05))
    assert meshes.mesh_name(path) == "ball"
    assert meshes.load_mesh(str(path))[0].shape == p.shape


def test_obj_quads_and_tetrahedra_are_triangulated(tmp_path):
    import meshio

    pts = cube()[0]
    quads = np.array(QUAD_CUBE[2]).reshape(6, 4)
    meshio.write_points_cells(tmp_path / "quads.obj", pts, [("quad", quads)])
    # Kuhn split of the unit cube into six tetrahedra along the diagonal 0 -> 6.
    tets = np.array([[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]])
    meshio.write_points_cells(tmp_path / "tets.vtu", pts, [("tetra", tets)])
    for name in ("quads.obj", "tets.vtu"):
        p, t = meshes.load_mesh(tmp_path / name)
        assert t.shape == (12, 3)
        assert meshes.signed_volume(p, t) == pytest.approx(1.0)
        assert len(meshes.sample_inside(p, t, 0.1)) == 1000


def test_usd_quads_transform_units_and_prim_path(tmp_path):
    path = tmp_path / "boxes.usda"
    small = (cube()[0] * 0.5, *QUAD_CUBE[1:])
    write_usd(path, {"/root/box": QUAD_CUBE, "/root/small": small}, meters_per_unit=0.01,
              xform=((10.0, 0.0, 0.0), (2.0, 2.0, 2.0)))  # fmt: skip
    # Unit cube scaled by 2, moved 10 units along x, in centimetres.
    p, t = meshes.load_mesh(path, prim_path="/root/box")
    assert t.shape == (12, 3)
    np.testing.assert_allclose(p.min(axis=0), [0.10, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(p.max(axis=0), [0.12, 0.02, 0.02], atol=1e-7)
    assert len(meshes.sample_inside(p, t, 0.002)) == 1000
    p2, _ = meshes.load_mesh(path, prim_path="/root/small")
    np.testing.assert_allclose(p2.max(axis=0) - p2.min(axis=0), [0.01] * 3, atol=1e-7)


def test_usd_without_prim_path_reads_the_one_mesh_the_stage_shows(tmp_path):
    """The first Mesh prim in file order was read even when the stage does not show it (a
    hidden stand-in, a guide, a proxy), and of several shown ones the first without a word."""
    from pxr import Usd, UsdGeom

    path = tmp_path / "kinds.usda"
    half = (cube()[0] * 0.5, *QUAD_CUBE[1:])
    write_usd(path, {"/root/a_hidden": half, "/root/b_group/part": half, "/root/c_guide": half,
                     "/root/d_proxy": half, "/root/e_inactive": half, "/root/f_shown": QUAD_CUBE})
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Imageable(stage.GetPrimAtPath("/root/a_hidden")).MakeInvisible()
    UsdGeom.Xform.Define(stage, "/root/b_group").MakeInvisible()  # hidden by its parent
    UsdGeom.Imageable(stage.GetPrimAtPath("/root/c_guide")).CreatePurposeAttr(UsdGeom.Tokens.guide)
    UsdGeom.Imageable(stage.GetPrimAtPath("/root/d_proxy")).CreatePurposeAttr(UsdGeom.Tokens.proxy)
    stage.GetPrimAtPath("/root/e_inactive").SetActive(False)
    stage.GetRootLayer().Save()
    p, _ = meshes.load_mesh(path)
    np.testing.assert_allclose(p.max(axis=0) - p.min(axis=0), [1.0] * 3, atol=1e-7)
    # Named, a hidden one is read.
    p, _ = meshes.load_mesh(path, prim_path="/root/a_hidden")
    np.testing.assert_allclose(p.max(axis=0) - p.min(axis=0), [0.5] * 3, atol=1e-7)

    # Two shown: refused, naming both (the builder and scene files pass it on).
    UsdGeom.Imageable(stage.GetPrimAtPath("/root/c_guide")).GetPurposeAttr().Set(UsdGeom.Tokens.default_)
    stage.GetRootLayer().Save()
    two = r"^prim_path = None is not allowed: '.*kinds\.usda' has 2 visible Mesh prims \('/root/c_guide', " \
          r"'/root/f_shown'\); pass prim_path= the one to read \(or make the others invisible\)$"
    with pytest.raises(ValueError, match=two):
        meshes.load_mesh(path)
    with pytest.raises(ValueError, match=two):
        warp_esph.SceneBuilder(spacing=0.1).add_mesh(path, warp_esph.Material.preset("dough"))
    b = warp_esph.SceneBuilder(spacing=0.1)
    assert b._bodies[b.add_mesh(path, warp_esph.Material.preset("dough"), prim_path="/root/f_shown")].count == 1000

    # None shown of several: refused, naming them.
    for shown in ("/root/c_guide", "/root/f_shown"):
        UsdGeom.Imageable(stage.GetPrimAtPath(shown)).MakeInvisible()
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"^prim_path = None is not allowed: '.*kinds\.usda' has 5 Mesh prims and none "
                                         r"is visible \(each is invisible or of purpose guide or proxy: '/root/a_hidden', "
                                         r"'/root/b_group/part', .*'/root/f_shown'\); pass prim_path= the one to read$"):
        meshes.load_mesh(path)

    # A stage's only Mesh prim is read whatever it shows (a collision mesh is often a guide).
    only = tmp_path / "only.usda"
    write_usd(only, {"/root/collision": QUAD_CUBE})
    stage = Usd.Stage.Open(str(only))
    UsdGeom.Imageable(stage.GetPrimAtPath("/root/collision")).CreatePurposeAttr(UsdGeom.Tokens.guide)
    stage.GetRootLayer().Save()
    assert meshes.load_mesh(only)[1].shape == (12, 3)


def test_a_mesh_tool_takes_prim_path_as_add_mesh_does(tmp_path):
    """A USD file that shows several Mesh prims needs prim_path, which a mesh tool had not."""
    from warp_esph.scenes import load_scene_file

    path = tmp_path / "two.usda"
    write_usd(path, {"/root/box": QUAD_CUBE, "/root/small": (cube()[0] * 0.5, *QUAD_CUBE[1:])})
    b = warp_esph.SceneBuilder(spacing=0.1)
    with pytest.raises(ValueError, match=r"^prim_path = None is not allowed: '.*two\.usda' has 2 visible Mesh prims"):
        b.add_tool("mesh", mesh=path)
    b.add_tool("mesh", mesh=path, prim_path="/root/small", scale=2.0, name="cutter")
    pts = b.tools[-1].mesh_points
    np.testing.assert_allclose(pts.max(axis=0) - pts.min(axis=0), [1.0] * 3, atol=1e-7)
    with pytest.raises(ValueError, match=r"^prim_path = '/root/box' is not allowed for shape 'sphere': its options are radius$"):
        b.add_tool("sphere", radius=0.1, prim_path="/root/box")
    (tmp_path / "tool.toml").write_text(
        '[[bodies]]\nshape = "box"\nmaterial = "dough"\ncenter = [0, 2, 0]\nsize = [0.2, 0.2, 0.2]\n'
        '[[tools]]\nshape = "mesh"\nfile = "two.usda"\nprim_path = "/root/box"\n')
    pts = load_scene_file(tmp_path / "tool.toml").builder.tools[0].mesh_points
    np.testing.assert_allclose(pts.max(axis=0) - pts.min(axis=0), [1.0] * 3, atol=1e-7)


def test_run_refuses_an_output_that_is_a_mesh_its_scene_reads(tmp_path, monkeypatch, capsys):
    """part.toml beside its mesh part.usdc: the default output part.usdc replaced the mesh with
    the run's particles (exit 0), and the scene could not be run again."""
    from warp_esph.cli import main

    monkeypatch.chdir(tmp_path)
    write_usd(tmp_path / "part.usdc", {"/root/box": (cube()[0] * 0.2, *QUAD_CUBE[1:])})
    write_usd(tmp_path / "cutter.usda", {"/root/box": QUAD_CUBE})
    (tmp_path / "part.toml").write_text(
        '[scene]\nspacing = 0.05\nframes = 1\n'
        '[[bodies]]\nshape = "mesh"\nmaterial = "dough"\nfile = "part.usdc"\ntranslation = [0, 0.01, 0]\n'
        '[[tools]]\nshape = "mesh"\nfile = "cutter.usda"\nposition = [0, 2, 0]\n[[colliders]]\ntype = "ground"\n')
    mesh_bytes = {name: (tmp_path / name).read_bytes() for name in ("part.usdc", "cutter.usda")}
    for extra, needle in (([], "the default output = 'part.usdc' is not allowed: it is the mesh of [[bodies]] #1 of part.toml"),
                          (["-o", str(tmp_path / "cutter.usda")], "it is the mesh of [[tools]] #1 of part.toml")):
        assert main(["run", "part.toml", "--no-progress", *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("warp-esph: error: ") and len(err.strip().splitlines()) == 1, err
        assert needle in err and "which the run would overwrite; give another --output" in err, err
        assert {name: (tmp_path / name).read_bytes() for name in mesh_bytes} == mesh_bytes  # both meshes as they were
    # A hard link to the mesh is written as a file of its own (the output's name is replaced): the
    # mesh keeps its data, and the run was refused as writing over it.
    os.link(tmp_path / "part.usdc", tmp_path / "linked.usdc")
    assert main(["run", "part.toml", "--no-progress", "-o", "linked.usdc"]) == 0
    capsys.readouterr()
    assert {name: (tmp_path / name).read_bytes() for name in mesh_bytes} == mesh_bytes
    assert (tmp_path / "linked.usdc").read_bytes() != mesh_bytes["part.usdc"]
    assert main(["run", "part.toml", "--no-progress", "-o", "run.usdc"]) == 0  # and the scene still runs

def test_fit_refuses_an_output_that_is_a_mesh_its_scene_reads(tmp_path, monkeypatch, capsys):
    """``fit part.toml -o part.usdc`` (or ``--output-dir`` holding the mesh as fitted.usdc)
    replaced the mesh the scene reads with the fit's JSON (or fitted run), and the scene could
    not be run or fitted again. Refused as ``run`` refuses it, one line, exit 2."""
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    toml = ('[scene]\nspacing = 0.05\nframes = 1\n'
            '[[bodies]]\nshape = "mesh"\nmaterial = "dough"\nfile = "{}"\ntranslation = [0, 0.01, 0]\n'
            '[[colliders]]\ntype = "ground"\n')
    (tmp_path / "part.toml").write_text(toml.format("part.usdc"))
    (tmp_path / "inside.toml").write_text(toml.format("out/fitted.usdc"))
    for name in ("part.usdc", "out/fitted.usdc"):
        write_usd(tmp_path / name, {"/root/box": (cube()[0] * 0.2, *QUAD_CUBE[1:])})
    x0 = load_scene("part.toml").builder.finalize().particle_x0
    np.savez(tmp_path / "t.npz", positions=x0[None], frames=[1])
    mesh_bytes = {name: (tmp_path / name).read_bytes() for name in ("part.usdc", "out/fitted.usdc", "t.npz")}
    for scene, extra, needle in (
            ("part.toml", ["-o", "part.usdc"], "--output = 'part.usdc' is not allowed: it is the mesh of [[bodies]] #1 of "
                                               "part.toml"),
            ("inside.toml", ["--output-dir", "out"], "--output-dir out: fitted.usdc = 'out/fitted.usdc' is not allowed: "
                                                     "it is the mesh of [[bodies]] #1 of inside.toml")):
        assert main(["fit", scene, "--target", "t.npz", "--params", "yield_stress", "--iterations", "0",
                     "--no-progress", "--no-diagnostics", *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("warp-esph: error: ") and len(err.strip().splitlines()) == 1, err
        assert needle in err and "which the fit would overwrite; write the results elsewhere" in err, err
        assert {name: (tmp_path / name).read_bytes() for name in mesh_bytes} == mesh_bytes  # the meshes as they were
    assert not (tmp_path / "out" / "fit.json").exists()
    # Hard links to the target and the mesh are written as files of their own (-o's name is
    # replaced): both keep their data, and the fit was refused as writing over them.
    for link, of in (("t_link.json", "t.npz"), ("part_link.json", "part.usdc")):
        os.link(tmp_path / of, tmp_path / link)
        assert main(["fit", "part.toml", "--target", "t.npz", "--params", "yield_stress", "--iterations", "0",
                     "--no-progress", "--no-diagnostics", "-o", link]) == 0, capsys.readouterr().err
        assert {name: (tmp_path / name).read_bytes() for name in mesh_bytes} == mesh_bytes
        assert isinstance(json.loads((tmp_path / link).read_text()), dict), link  # the fit's JSON


def test_fit_refusing_an_output_that_is_a_mesh_its_scene_reads_names_a_long_scene_path_by_its_ends(tmp_path, capsys):
    """The refusal above names the scene whose mesh the output is: a scene path over
    checks.PATH_SHOWN_WHOLE characters by its ends (checks.shown_path), as it names the
    output and the mesh; it was named whole, a path with spaces whole on the command line."""
    from warp_esph.checks import PATH_SHOWN_WHOLE, shown_path
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    folder = tmp_path / ("a long folder " + "d" * PATH_SHOWN_WHOLE)
    folder.mkdir()
    scene = folder / "part.toml"
    scene.write_text('[scene]\nspacing = 0.05\nframes = 1\n'
                     '[[bodies]]\nshape = "mesh"\nmaterial = "dough"\nfile = "part.usdc"\ntranslation = [0, 0.01, 0]\n'
                     '[[colliders]]\ntype = "ground"\n')
    write_usd(folder / "part.usdc", {"/root/box": (cube()[0] * 0.2, *QUAD_CUBE[1:])})
    np.savez(tmp_path / "t.npz", positions=load_scene(str(scene)).builder.finalize().particle_x0[None], frames=[1])
    mesh = (folder / "part.usdc").read_bytes()
    assert main(["fit", str(scene), "--target", str(tmp_path / "t.npz"), "--params", "yield_stress", "--iterations", "0",
                 "--no-progress", "--no-diagnostics", "-o", str(folder / "part.usdc")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("warp-esph: error: ") and len(err.strip().splitlines()) == 1, err
    assert (f"--output = {shown_path(folder / 'part.usdc')} is not allowed: it is the mesh of [[bodies]] #1 of "
            f"{shown_path(scene, False)} {shown_path(folder / 'part.usdc')} of this fit") in err, err
    assert str(folder) not in err
    assert (folder / "part.usdc").read_bytes() == mesh


def test_a_mesh_file_in_a_folder_named_in_bytes_that_are_not_utf8_is_refused_naming_what_is_allowed(tmp_path, capsys,
                                                                                                     monkeypatch):
    """USD takes file names as UTF-8: a scene file's mesh in a folder named b'\\xfb' was refused
    as "pxr cannot open it (UnicodeEncodeError: 'utf-8' codec can't encode ...)", which said
    neither what was wrong nor what is allowed."""
    from warp_esph.cli import main

    odd = tmp_path / os.fsdecode(b"\xfb")  # a name Linux holds, which Python keeps as a surrogate escape
    write_usd(tmp_path / "part.usdc", {"/root/box": (cube()[0] * 0.2, *QUAD_CUBE[1:])})
    odd.mkdir()
    os.rename(tmp_path / "part.usdc", odd / "part.usdc")  # (pxr cannot write it there either)
    (odd / "part.toml").write_text('[scene]\nspacing = 0.05\nframes = 1\n'
                                   '[[bodies]]\nshape = "mesh"\nmaterial = "dough"\nfile = "part.usdc"\n')
    monkeypatch.chdir(odd)  # the scene named as part.toml: the line quotes the mesh's path alone
    assert main(["run", "part.toml", "-o", str(tmp_path / "run.usdc"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("warp-esph: error: ") and len(err.strip().splitlines()) == 1, err
    assert f"[[bodies]] #1 (shape 'mesh'): mesh {str(odd / 'part.usdc')!r} is not allowed: USD names its files in UTF-8 " \
           "text" in err and "give a path of UTF-8 text" in err and "codec" not in err, err
    assert not (tmp_path / "run.usdc").exists()


def test_usd_without_meters_per_unit_is_read_in_centimetres_with_a_warning(tmp_path):
    """USD's fallback is 0.01 m per unit; a file modelled in metres without the metadata came
    in 100 x too small without a word."""
    plain = tmp_path / "plain.usda"
    write_usd(plain, {"/root/box": QUAD_CUBE}, meters_per_unit=None)
    said = r"plain\.usda.*does not author metersPerUnit, so USD's fallback of 0\.01 m per unit \(centimetres\) is " \
           r"assumed \(USD's rule\); if the mesh is in metres, author metersPerUnit = 1 in the file"
    with pytest.warns(UserWarning, match=said):
        p, _ = meshes.load_mesh(plain)
    np.testing.assert_allclose(p.max(axis=0) - p.min(axis=0), [0.01] * 3, atol=1e-9)
    dough = warp_esph.Material.preset("dough")
    b = warp_esph.SceneBuilder(spacing=0.1)
    with pytest.warns(UserWarning, match=said):
        assert b._bodies[b.add_mesh(plain, dough, scale=100.0)].count == 1000  # scaled to metres
    # Authored (centimetres too): the file says what it means, so nothing is said.
    authored = tmp_path / "authored.usda"
    write_usd(authored, {"/root/box": QUAD_CUBE}, meters_per_unit=0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p2, _ = meshes.load_mesh(authored)
        b = warp_esph.SceneBuilder(spacing=0.1)
        assert b._bodies[b.add_mesh(authored, dough, scale=100.0)].count == 1000
    np.testing.assert_array_equal(p2, p)


# --------------------------------------------------------------------- Warp's assets
def test_bunny_loads_closed_with_measured_size_and_volume():
    p, t = meshes.load_mesh(BUNNY)
    assert p.shape == (6102, 3) and t.shape == (12200, 3)
    assert open_edges(t) == 0
    np.testing.assert_allclose(p.min(axis=0), BUNNY_LO, atol=1e-6)
    np.testing.assert_allclose(p.max(axis=0), BUNNY_HI, atol=1e-6)
    assert meshes.signed_volume(p, t) == pytest.approx(BUNNY_VOLUME, rel=1e-6)
    np.testing.assert_array_equal(meshes.load_mesh(str(BUNNY), prim_path="/root/bunny")[1], t)
    assert meshes.mesh_name(BUNNY) == "bunny"


def test_bunny_sampling_matches_its_volume():
    p, t = meshes.load_mesh(BUNNY)
    # Full size (1.6 m tall) at 4 cm: 13692 points measured.
    full = meshes.sample_inside(p, t, 0.04)
    assert 13_300 <= len(full) <= 14_100
    assert len(full) * 0.04**3 == pytest.approx(BUNNY_VOLUME, rel=0.05)
    # Scaled to 16 cm at 1 cm: 894 points measured.
    small = meshes.sample_inside(p * 0.1, t, 0.01)
    assert 850 <= len(small) <= 940
    assert len(small) * 0.01**3 == pytest.approx(meshes.signed_volume(p * 0.1, t), rel=0.05)


def test_bear_loads():
    p, t = meshes.load_mesh(BEAR)
    assert open_edges(t) == 0
    np.testing.assert_allclose(p.max(axis=0) - p.min(axis=0), [4.89, 5.542, 9.78], rtol=1e-4)
    assert meshes.signed_volume(p, t) == pytest.approx(98.429, rel=1e-4)


def test_builder_add_mesh_bunny():
    dough = warp_esph.Material.preset("dough")
    b = warp_esph.SceneBuilder(spacing=0.01)
    # The bunny is 1.6 m tall: at 1 cm it would be 876k particles, so it is scaled to 16 cm.
    k = b.add_mesh(BUNNY, dough, scale=0.1, translation=(0.0, 0.05, 0.0))
    p, t = meshes.load_mesh(BUNNY)
    expected = meshes.sample_inside(p * 0.1 + [0.0, 0.05, 0.0], t, 0.01)
    model = b.finalize()
    assert model.particle_count == len(expected) == b.particle_count
    assert model.bodies[k].name == "bunny" and model.bodies[k].count == len(expected)
    # A (points, triangles) tuple gets a generic name.
    k2 = b.add_mesh(cube((1.0, 0.0, 0.0), (1.1, 0.1, 0.1)), dough)
    assert b._bodies[k2].name == "mesh1" and b._bodies[k2].count == 1000


def test_add_mesh_refuses_a_translation_beyond_float64_naming_it():
    """A translation that put the mesh beyond float64's reach collapsed its lattice, and the
    spacing was blamed ('no lattice point falls inside it')."""
    dough = warp_esph.Material.preset("dough")
    b = warp_esph.SceneBuilder(spacing=0.1)
    with pytest.raises(ValueError, match=r"^translation = \(1e\+300, 0\.0, 0\.0\) is not allowed for mesh \(points, "
                                         r"triangles\): it places the mesh's points up to 1e\+300 m from the origin; they "
                                         r"must be within 4\.5e\+11 m \(farther out float64 does not resolve the spacing 0\.1\); pass a "
                                         r"translation that brings them nearer$"):
        b.add_mesh(cube(), dough, translation=(1e300, 0, 0))
    # Without a translation the mesh's own coordinates are named, not the default (0, 0, 0).
    with pytest.raises(ValueError, match=r"^mesh \(points, triangles\) is not allowed: its points \(scale 1, no "
                                         r"translation\) lie up to 1e\+12 m from the origin"):
        b.add_mesh(cube((1e12, 0, 0), (1e12 + 1, 1, 1)), dough)
    with pytest.raises(ValueError, match=r"^translation = \(1e\+20, 0\.0, 0\.0\) is not allowed for mesh '.*bunny\.usd'"):
        b.add_mesh(BUNNY, dough, scale=0.1, translation=(1e20, 0, 0))
    # Checked before the file is read, and refused by name.
    with pytest.raises(ValueError, match=r"^translation\[1\] = nan is not allowed: must be a finite number$"):
        b.add_mesh("missing.obj", dough, translation=(0, float("nan"), 0))
    with pytest.raises(ValueError, match=r"^scale = 1e\+300 is not allowed for mesh \(points, triangles\): it takes the "
                                         r"mesh's points beyond a float64$"):
        b.add_mesh(cube((0, 0, 0), (1e10, 1e10, 1e10)), dough, scale=1e300)
    assert b.particle_count == 0
    # Where it is placed counts: a mesh modelled far out may be moved back, and within reach
    # a far translation is the builder's to take (a float32 model refuses it at finalize).
    assert b._bodies[b.add_mesh(cube((1e13, 0, 0), (1e13 + 1, 1, 1)), dough, translation=(-1e13, 0, 0))].count == 1000
    assert b._bodies[b.add_mesh(cube(), dough, translation=(4e11, 0, 0))].count == 1000


def test_add_mesh_of_one_file_twice_gets_unique_default_names(tmp_path):
    """The default name was the file's name for every body of the file, so the second was
    refused ('a body of that name exists already'); other default names are unique."""
    dough = warp_esph.Material.preset("dough")
    b = warp_esph.SceneBuilder(spacing=0.05)
    names = [b.add_mesh(BUNNY, dough, scale=0.1, translation=(x, 0.0, 0.0)) for x in (0.0, 0.5)]
    b.add_box((1.5, 0.05, 0.0), (0.1, 0.1, 0.1), dough, name="bunny_2")
    names.append(b.add_mesh(BUNNY, dough, scale=0.1, translation=(1.0, 0.0, 0.0)))
    assert [b._bodies[k].name for k in names] == ["bunny", "bunny_1", "bunny_3"]
    assert [x.name for x in b.finalize().bodies] == ["bunny", "bunny_1", "bunny_2", "bunny_3"]
    # A name given is still the caller's: taken, it is refused.
    with pytest.raises(ValueError, match=r"^name = 'bunny' is not allowed: a body of that name exists already$"):
        b.add_mesh(BUNNY, dough, scale=0.1, translation=(2.0, 0.0, 0.0), name="bunny")
    # Scene files pass it on.
    from warp_esph.scenes import load_scene_file

    meshes.write_mesh(tmp_path / "part.obj", *cube((0.0, 0.0, 0.0), (0.1, 0.1, 0.1)))
    body = '[[bodies]]\nshape = "mesh"\nmaterial = "dough"\nfile = "part.obj"\ntranslation = [{x}, 0.2, 0.0]\n'
    (tmp_path / "two.toml").write_text("".join(body.format(x=x) for x in (0.0, 0.5)))
    assert [x.name for x in load_scene_file(tmp_path / "two.toml").builder._bodies] == ["part", "part_1"]


def test_a_mesh_file_name_with_a_newline_gives_a_one_line_default_name(tmp_path):
    """A body's name must be one line of text (it names the body in one-line messages and the
    USD file); a default made from a file's name only labels, so its line breaks are cleaned,
    not refused under a name the caller never gave."""
    dough = warp_esph.Material.preset("dough")
    meshes.write_mesh(tmp_path / "pa\nrt\x1b.obj", *cube((0.0, 0.0, 0.0), (0.1, 0.1, 0.1)))
    b = warp_esph.SceneBuilder(spacing=0.05)
    k = b.add_mesh(str(tmp_path / "pa\nrt\x1b.obj"), dough)
    assert b._bodies[k].name == "pa_rt_"
    with pytest.raises(ValueError, match=r"^name = 'pa\\nrt' is not allowed: .*one line of text"):
        b.add_mesh(str(tmp_path / "pa\nrt\x1b.obj"), dough, translation=(1.0, 0.0, 0.0), name="pa\nrt")
    # So are its invisible format characters (a right-to-left override), which a name refuses.
    meshes.write_mesh(tmp_path / "ev\u202eil.obj", *cube((0.0, 0.0, 0.0), (0.1, 0.1, 0.1)))
    k = b.add_mesh(str(tmp_path / "ev\u202eil.obj"), dough, translation=(2.0, 0.0, 0.0))
    assert b._bodies[k].name == "ev_il"


def test_mesh_name():
    assert meshes.mesh_name("/a/b/bunny.usd") == "bunny"
    assert meshes.mesh_name(pathlib.Path("my.model.obj")) == "my.model"
    assert meshes.mesh_name("part.vol.gz") == "part"
    assert meshes.mesh_name(b"dough.stl") == "dough"


# ------------------------------------------------------------------------ validation
def _bad_meshes():
    pts, tris = cube()
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], float)
    tet = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]])
    nan = pts.copy()
    nan[3, 1] = np.nan
    flipped = tris.copy()
    flipped[5] = flipped[5, ::-1]
    return {
        "empty": ((np.zeros((0, 3)), np.zeros((0, 3), int)), r"is empty"),
        "no triangles": ((pts, np.zeros((0, 3), int)), r"is empty"),
        "bad points shape": ((pts[:, :2], tris), r"points with shape \(8, 2\).*\(N, 3\)"),
        "bad triangle shape": ((pts, tris.reshape(-1, 4)), r"triangles with shape \(9, 4\)"),
        "fractional indices": ((pts, tris + 0.5), r"dtype float64.*integer"),
        "index too large": ((pts, np.where(tris == 7, 8, tris)), r"indices must be in \[0, 7\].*\[0, 8\]"),
        "negative index": ((pts, np.where(tris == 0, -1, tris)), r"indices must be in \[0, 7\].*\[-1, 7\]"),
        "non-finite": ((nan, tris), r"1 of its 8 points are not finite"),
        "zero area": ((line, tet), r"degenerate: all its triangles have zero area"),
        "zero volume": ((flat, np.array([[0, 1, 2], [0, 2, 1]])), r"degenerate: it encloses no volume"),
        "open": ((pts, tris[:-1]), r"not closed \(3 edges are not shared by exactly two triangles\)"),
        "non-manifold": ((pts, np.concatenate([tris, tris[:2], tris[:2, ::-1]])), r"not closed \(5 edges"),
        "inconsistent": ((pts, flipped), r"not consistently oriented \(3 edges"),
        # The imaginary parts were dropped with a numpy warning, strings parsed as numbers.
        "complex points": ((pts + 0j, tris), r"points must be an \(N, 3\) array of numbers"),
        "string points": ((pts.astype(str), tris), r"points must be an \(N, 3\) array of numbers"),
    }


@pytest.mark.parametrize("case", list(_bad_meshes()))
def test_bad_arrays_are_rejected(case):
    source, pattern = _bad_meshes()[case]
    with pytest.raises(ValueError, match=r"^mesh \(points, triangles\) is not allowed: .*" + pattern):
        meshes.load_mesh(source)


def test_bad_files_are_rejected(tmp_path):
    def rejects(source, *needles, **kw):
        with pytest.raises(ValueError) as info:
            meshes.load_mesh(source, **kw)
        for needle in needles:
            assert needle in str(info.value), str(info.value)

    missing = tmp_path / "nope.obj"
    rejects(missing, repr(str(missing)), "file not found")
    rejects(tmp_path, repr(str(tmp_path)), "not a file")
    (tmp_path / "points.xyz").write_text("0 0 0\n")
    rejects(tmp_path / "points.xyz", "points.xyz", "unsupported extension '.xyz'", ".usd", ".obj", ".stl")
    (tmp_path / "junk.stl").write_text("hello world\n")
    rejects(tmp_path / "junk.stl", "junk.stl", "meshio cannot read it")
    (tmp_path / "junk.vtu").write_text("<x")  # meshio calls sys.exit on this one
    rejects(tmp_path / "junk.vtu", "junk.vtu", "meshio cannot read it")
    (tmp_path / "junk.usda").write_text("#usda 1.0\n(((\n")
    rejects(tmp_path / "junk.usda", "junk.usda", "pxr cannot open it")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    rejects(tmp_path / "points.obj", "points.obj", "no triangles")
    meshes.write_mesh(tmp_path / "open.obj", *cube()[0:1], cube()[1][:-1])
    rejects(tmp_path / "open.obj", "open.obj", "not closed (3 edges")

    write_usd(tmp_path / "quad.usda", {"/root/sheet": (cube()[0][:4], [4], [0, 1, 2, 3])})
    rejects(tmp_path / "quad.usda", "quad.usda", "/root/sheet", "not closed (4 edges")
    write_usd(tmp_path / "bad_counts.usda", {"/root/m": (cube()[0], [2, 3], [0, 1, 2, 3, 4])})
    rejects(tmp_path / "bad_counts.usda", "bad_counts.usda", "1 faces have fewer than 3 vertices")
    write_usd(tmp_path / "empty.usda", {})
    rejects(tmp_path / "empty.usda", "empty.usda", "no UsdGeom.Mesh prim")

    rejects(BUNNY, "prim_path = '/root/nothing'", "bunny.usd", "no prim there", prim_path="/root/nothing")
    rejects(BUNNY, "prim_path = '/root'", "Xform prim, not a Mesh", prim_path="/root")
    rejects(BUNNY, "prim_path = 'bunny'", "absolute prim path", prim_path="bunny")
    rejects(BUNNY, "prim_path = 3", prim_path=3)
    rejects(tmp_path / "open.obj", "prim_path = '/x'", "only for USD files", prim_path="/x")
    rejects(cube(), "prim_path = '/x'", "only for USD files", prim_path="/x")
    rejects(5, "source = 5", "file path or a (points, triangles) tuple")
    rejects((1, 2, 3), "source with 3 items", "(points, triangles)")


def test_a_missing_or_unreadable_source_is_refused_naming_the_callers_parameter(tmp_path):
    """``add_mesh("x")`` was refused as ``mesh 'x' is not allowed: file not found``, where
    add_mesh's parameter is ``source``; a mesh tool's and a MeshLoss's is ``mesh``."""
    from warp_esph.losses import MeshLoss

    material = warp_esph.Material(mu=1e3, lam=1e3)
    missing = str(tmp_path / "nope.obj")
    (tmp_path / "points.xyz").write_text("0 0 0\n")
    for source, reason in ((missing, "file not found"), (str(tmp_path), "it is not a file"),
                           (str(tmp_path / "points.xyz"), "unsupported extension '.xyz'; must be one of .usd")):
        with pytest.raises(ValueError, match="^source = " + re.escape(repr(source)) + " is not allowed: " + re.escape(reason)):
            warp_esph.SceneBuilder(spacing=0.05).add_mesh(source, material)
        with pytest.raises(ValueError, match="^source = " + re.escape(repr(source)) + " is not allowed: "):
            meshes.load_mesh(source)
        with pytest.raises(ValueError, match="^mesh = " + re.escape(repr(source)) + " is not allowed: " + re.escape(reason)):
            warp_esph.SceneBuilder(spacing=0.05).add_tool("mesh", mesh=source)
        with pytest.raises(ValueError, match="^mesh = " + re.escape(repr(source)) + " is not allowed: " + re.escape(reason)):
            MeshLoss(source, frames=[1])
    # A tuple of three items was refused to a mesh tool as 'source with 3 items'.
    with pytest.raises(ValueError, match=r"^mesh with 3 items is not allowed: a tuple must be \(points, triangles\)"):
        warp_esph.SceneBuilder(spacing=0.05).add_tool("mesh", mesh=(1, 2, 3))


def test_a_source_of_arrays_that_is_not_the_pair_is_refused_on_one_line():
    """A list ``[points, triangles]`` (not the tuple) was refused with numpy's repr of both
    arrays, a message of twenty lines; it is one line, cut as other values are."""
    with pytest.raises(ValueError) as info:
        meshes.load_mesh(list(cube()))
    text = str(info.value)
    assert "\n" not in text and len(text) < 200, text
    assert re.fullmatch(r"source = \[array\(\[\[-?\d.*\.\.\. is not allowed: must be a mesh file path or a \(points, "
                        r"triangles\) tuple", text), text


def test_headers_that_declare_more_than_the_file_holds_are_refused_at_once(tmp_path):
    """meshio's PLY reader walked 400 million declared faces past the end of a 148-byte
    body (longer than 10 minutes), and its PLY and OFF readers loop for ever on a header
    cut short; the header is now checked against the file's size first."""
    import time

    pts, tris = icosphere(0.3, 1)
    for ext in (".ply", ".off"):
        meshes.write_mesh(tmp_path / f"good{ext}", pts, tris)
    good_ply = (tmp_path / "good.ply").read_bytes()
    good_off = (tmp_path / "good.off").read_bytes()
    cases = {
        "faces.ply": (good_ply.replace(b"element face 80", b"element face 400000000"), "declares 42 vertex, 400000000 face"),
        "verts.ply": (good_ply.replace(b"element vertex 42", b"element vertex 4200"), "declares 4200 vertex, 80 face"),
        "cut.ply": (good_ply[: good_ply.index(b"end_header")], "no 'ply' first line and 'end_header' line"),
        "cut.off": (b"OFF\n", "it must start with 'OFF' and a line '<vertices> <faces> <edges>'"),
        "big.off": (good_off.replace(b"42 80 0", b"42 80000000 0"), "declares 42 vertices and 80000000 faces"),
    }
    for name, (data, needle) in cases.items():
        (tmp_path / name).write_bytes(data)
        start = time.perf_counter()
        with pytest.raises(ValueError) as info:
            meshes.load_mesh(tmp_path / name)
        assert time.perf_counter() - start < 5.0
        assert str(info.value).startswith(f"mesh {str(tmp_path / name)!r} is not allowed: ") and needle in str(info.value)
    # Finite but huge coordinates (a damaged binary PLY) once ended in an OverflowError.
    meshes.write_mesh(tmp_path / "huge.ply", pts * 1e200, tris)
    with pytest.raises(ValueError, match=r"huge\.ply' is not allowed: its points span 6e\+199 .* must be at most 1e\+30"):
        meshes.load_mesh(tmp_path / "huge.ply")
    # The checks let every good file through.
    for ext in (".ply", ".off"):
        assert len(meshes.load_mesh(tmp_path / f"good{ext}")[1]) == len(tris)


def test_other_formats_are_read_in_a_child_with_a_time_limit(tmp_path, monkeypatch):
    """Formats whose meshio reader was not checked run in a child process: a reader that
    does not finish within the limit is stopped and the file refused by name."""
    pts, tris = icosphere(0.3, 1)
    meshes.write_mesh(tmp_path / "ball.vtk", pts, tris)
    p, t = meshes.load_mesh(tmp_path / "ball.vtk")
    assert meshes.signed_volume(p, t) == pytest.approx(meshes.signed_volume(pts, tris), rel=1e-6)
    monkeypatch.setattr(meshes, "_CHILD_SECONDS", 0.01)  # no Python starts in 10 ms
    with pytest.raises(ValueError, match=r"ball\.vtk' is not allowed: meshio did not finish reading it within 0\.0[0-9]* s"):
        meshes.load_mesh(tmp_path / "ball.vtk")


@settings(max_examples=40, deadline=None)
@given(
    ext=st.sampled_from([".obj", ".stl", ".ply", ".off", ".vtk", ".vtu", ".msh", ".usda", ".usdc", ".usd"]),
    data=st.one_of(
        st.binary(max_size=300),
        st.text(alphabet="vf0123456789 .-\n#", max_size=200).map(str.encode),
    ),
)
def test_reader_errors_never_escape(ext, data):
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "fuzz" + ext)
        with open(path, "wb") as f:
            f.write(data)
        try:
            p, t = meshes.load_mesh(path)
        except ValueError as e:
            assert "fuzz" + ext in str(e)
        else:  # whatever was read must be a valid closed mesh
            assert p.shape[1] == 3 and t.shape[1] == 3 and open_edges(t) == 0


def test_a_mesh_the_reader_refuses_is_said_by_the_readers_words_not_its_exception_class(tmp_path):
    """'meshio cannot read it (ValueError: could not convert string to float: ...)': the class
    meshio raised led its reason, in the file read here and in the one read in a child process;
    an exception without words was said by its class alone ('KeyError: no details'). The
    readers' words are kept; a key that is missing, or a reason not given, is said as such."""
    from warp_esph.checks import read_reason

    (tmp_path / "junk.stl").write_text("hello world\n")
    (tmp_path / "junk.msh").write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\nx\n")
    for name, why in (("junk.stl", "could not convert string to float: 'hello'"),
                      ("junk.msh", "string or file could not be read to its end due to unmatched data")):
        with pytest.raises(ValueError) as e:
            meshes.load_mesh(tmp_path / name)
        assert str(e.value) == f"mesh '{tmp_path / name}' is not allowed: meshio cannot read it ({why})"
    assert read_reason(KeyError("points")) == "no 'points'"
    assert read_reason(EOFError()) == "it ends early"
    assert read_reason(ValueError("  ")) == "its reader gave no reason"


def test_file_identity_reads_inode_0_as_no_identity(tmp_path, monkeypatch):
    """``checks.file_identity`` compares device and inode, which Python's ``os.stat`` promises
    identify a file only where the inode is not 0: on a file system that numbers none, every
    file read (dev, 0) and two distinct targets were one file (refused as given twice), an
    output any input. Such a file is its real path, as a missing one is."""
    from warp_esph import checks

    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    a.write_bytes(b"a")
    b.write_bytes(b"b")
    os.link(a, tmp_path / "hard.npz")
    assert checks.file_identity(a) == checks.file_identity(tmp_path / "hard.npz") != checks.file_identity(b)
    real_stat = os.stat

    def no_inodes(path, *args, **kwargs):
        st = real_stat(path, *args, **kwargs)
        return os.stat_result((st.st_mode, 0, *tuple(st)[2:]))

    monkeypatch.setattr(os, "stat", no_inodes)
    assert checks.file_identity(a) != checks.file_identity(b)
    assert checks.file_identity(a) == checks.file_identity(str(tmp_path / "." / "a.npz"))  # its real path
