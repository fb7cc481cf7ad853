"""Surfaces from particles (marching cubes), surfaces in USD, and meshio export round trips."""

import os
import re

import meshio
import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

import warp_esph as we
from warp_esph.cli import main
from warp_esph.export import export_frames
from warp_esph.meshes import lattice_points, signed_volume
from warp_esph.render import UsdFrames
from warp_esph.surface import particle_surface


def _edges_closed(tri: np.ndarray) -> bool:
    """Every undirected edge is used by exactly two triangles, once in each direction."""
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    directed, counts = np.unique(e, axis=0, return_counts=True)
    if (counts != 1).any():
        return False
    key = {tuple(x) for x in directed.tolist()}
    return all((b, a) in key for a, b in key)


@pytest.mark.parametrize("n", [6, 16])
def test_block_surface_is_closed_outward_and_where_the_material_ends(n):
    dx = 0.01
    pts = lattice_points(np.zeros(3), np.full(3, n * dx), dx)  # the material fills [0, n dx]^3
    v, tri = particle_surface(pts, dx)
    assert len(tri) > 100 and tri.min() >= 0 and tri.max() < len(v)
    assert _edges_closed(tri)
    vol = signed_volume(v, tri)
    assert vol > 0  # outward
    # Faces within 0.15 dx of the block's faces; volume within a few per cent (edges round off).
    assert np.abs(v.min(axis=0) - 0.0).max() < 0.15 * dx and np.abs(v.max(axis=0) - n * dx).max() < 0.15 * dx
    assert vol == pytest.approx((n * dx) ** 3, rel=0.08 if n == 6 else 0.02)


@pytest.mark.parametrize("offset", [1e4, 1e6])
def test_a_block_far_from_the_origin_gets_the_surface_it_gets_there(offset):
    """The field was computed in float32 world coordinates: 10 km out a block's surface was 1.6 mm
    off with 930 vertices for its 750, 1000 km out a shape of its own, at 1e12 m none, without a
    word (float64 runs and the builder place bodies there). It is computed about the grid's corner."""
    dx = 0.02
    pts = lattice_points(np.full(3, -0.05), np.full(3, 0.05), dx)
    v0, t0 = particle_surface(pts, dx)
    v, tri = particle_surface(pts + offset, dx)
    np.testing.assert_array_equal(tri, t0)
    np.testing.assert_allclose(v - offset, v0, rtol=0.0, atol=1e-6 + 4.0 * float(np.spacing(offset)))


def test_separate_clusters_give_separate_components():
    dx = 0.01
    a = lattice_points(np.zeros(3), np.full(3, 0.06), dx)
    b = a + np.array([0.2, 0.0, 0.0])
    v, tri = particle_surface(np.concatenate([a, b]), dx)
    left = v[tri].mean(axis=1)[:, 0] < 0.13
    assert left.any() and (~left).any()
    assert signed_volume(v, tri[left]) == pytest.approx(signed_volume(v, tri[~left]), rel=1e-3)


def _model():
    b = we.SceneBuilder(spacing=0.03)
    b.add_box((0.0, 0.2, 0.0), (0.15, 0.15, 0.15), we.Material.preset("dough"), name="block")
    b.add_sphere((0.4, 0.3, 0.0), 0.08, we.Material.preset("rubber"), name="ball", velocity=(0.0, -1.0, 0.0))
    b.add_ground()
    return b.finalize()


def _open(path) -> Usd.Stage:
    return Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(path)))


def test_writer_surfaces_one_mesh_per_body_per_frame(tmp_path):
    model = _model()
    path = tmp_path / "s.usdc"
    with we.UsdWriter(path, model, 30.0, surface=True) as writer:
        we.simulate(model, 2, fps=30.0, writer=writer, progress=False)
    stage = _open(path)
    for body in ("block", "ball"):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/Surfaces/{body}"))
        assert mesh, body
        assert mesh.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
        for t in (0.0, 2.0):
            pts = np.asarray(mesh.GetPointsAttr().Get(t))
            counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(t))
            idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(t))
            assert len(pts) > 0 and (counts == 3).all() and len(idx) == 3 * len(counts)
            assert idx.min() >= 0 and idx.max() < len(pts)
            assert _edges_closed(idx.reshape(-1, 3))
            ext = np.asarray(mesh.GetExtentAttr().Get(t))
            np.testing.assert_allclose(ext, [pts.min(axis=0), pts.max(axis=0)], atol=1e-6)
    # The particles are still the Points prims; the renderer ignores the surfaces.
    assert [n for n, _ in UsdFrames(path).bodies] == ["block", "ball"]


@pytest.mark.parametrize("fmt", ["vtu", "ply"])
def test_meshio_export_round_trip(tmp_path, fmt, capfd):
    model = _model()
    path = tmp_path / "e.usdc"
    with we.UsdWriter(path, model, 30.0) as writer:
        we.simulate(model, 2, fps=30.0, writer=writer, progress=False)
    out = tmp_path / fmt
    capfd.readouterr()
    files = export_frames(path, fmt, out)
    # Quietly: meshio warns once per file of a type the format lacks (64-bit integers in PLY).
    assert "Warning" not in "".join(capfd.readouterr()), fmt
    frames = [f for f in files if f.endswith(f".{fmt}")]
    assert [os.path.basename(f) for f in frames] == [f"frame_0000{k}.{fmt}" for k in range(3)]
    data = UsdFrames(path)
    for k, file in enumerate(frames):
        mesh = meshio.read(file)
        ref = data.arrays(k)
        n = model.particle_count
        np.testing.assert_allclose(mesh.points, ref["points"], atol=1e-6)
        pd = mesh.point_data
        if fmt == "vtu":
            vel, sv = pd["velocity"], pd["singular_values"]
        else:
            vel = np.stack([pd[f"velocity_{c}"] for c in "xyz"], axis=1)
            sv = np.stack([pd[f"singular_values_{c}"] for c in "012"], axis=1)
        assert vel.shape == (n, 3) and sv.shape == (n, 3)
        np.testing.assert_allclose(vel, ref["velocities"], atol=1e-6)
        np.testing.assert_allclose(sv, ref["singular_values"], atol=1e-6)
        np.testing.assert_allclose(pd["alpha"], ref["alpha"], atol=1e-7)
        body = np.asarray(pd["body_id"]).astype(int)
        assert (body[: model.bodies[0].count] == 0).all() and (body[model.bodies[0].count:] == 1).all()
        assert set(np.asarray(pd["material_id"]).astype(int)) == {0, 1}
        assert sum(len(c.data) for c in mesh.cells) == n  # one vertex cell per particle
    if fmt == "vtu":
        pvd = (out / "frames.pvd").read_text()
        assert pvd.count("<DataSet") == 3 and 'timestep="0.0333333333"' in pvd and "frame_00002.vtu" in pvd


def test_run_with_surface_export_and_preview(tmp_path, capsys):
    path = tmp_path / "dd.usdc"
    assert main(["run", "dough_drop", "--scale", "0.3", "--frames", "2", "--no-progress", "-o", str(path),
                 "--surface", "--export", "vtu", "--preview"]) == 0
    out = capsys.readouterr().out
    assert "surfaces:" in out and "exported 4 files" in out and "preview:" in out
    assert sorted(os.listdir(tmp_path / "dd.usdc_vtu")) == ["frame_00000.vtu", "frame_00001.vtu", "frame_00002.vtu", "frames.pvd"]
    assert (tmp_path / "dd.usdc.png").stat().st_size > 1000
    stage = _open(path)
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/World/Surfaces/dough")).GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    # The export command on its own, ply, some frames.
    assert main(["export", str(path), "--format", "ply", "--frames", "0,2", "-o", str(tmp_path / "p")]) == 0
    assert sorted(os.listdir(tmp_path / "p")) == ["frame_00000.ply", "frame_00002.ply"]
    assert main(["export", str(tmp_path / "nope.usdc")]) == 2
    assert "nope.usdc" in capsys.readouterr().err


def test_scattered_particles_get_an_empty_surface_and_one_warning(tmp_path):
    b = we.SceneBuilder(spacing=0.02)
    b.add_particles(lattice_points(np.zeros(3), np.full(3, 0.1), 0.02), we.Material.preset("clay"), name="c")
    model = b.finalize()
    state = model.state()
    x = model.particle_x0.copy()
    x[0] = (5000.0, 0.0, 0.0)  # a grid over 5 km at 1 cm cells would not fit
    state.x.assign(x.astype(np.float32))
    with pytest.raises(ValueError, match="grid would have"):
        particle_surface(x, model.spacing)
    path = tmp_path / "far.usdc"
    with pytest.warns(UserWarning, match="no surface for body 'c'") as record:
        with we.UsdWriter(path, model, 30.0, surface=True) as writer:
            writer.write_frame(0, state)
            writer.write_frame(1, state)
    assert len([r for r in record if "no surface" in str(r.message)]) == 1
    stage = _open(path)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Surfaces/c"))
    assert len(mesh.GetPointsAttr().Get(1.0)) == 0


def test_particles_spread_past_float32_are_refused_not_scattered_past_the_grid():
    """A spread of 1e37 m overflowed the float32 grid count to inf, cast to a grid of 2 nodes,
    and the particles were added past its end: a segmentation fault. A count of 3e6 nodes per
    axis wrapped the int64 product."""
    for far in (1e37, 3e4):
        pts = np.array([[0.0, 0.0, 0.0], [far, far, far]], dtype=np.float32)
        with pytest.raises(ValueError, match=r"cell = 0.01 is not allowed: the grid would have [0-9.e+]+ nodes"):
            particle_surface(pts, 0.02)


def test_points_that_are_not_n_by_3_real_numbers_are_refused_not_reshaped():
    """Points were reshaped to (-1, 3) whatever they were: three (x, y) pairs became two
    points of mixed coordinates, a (3, 4) array four points, and complex values lost their
    imaginary parts, each meshed without a word; text failed in numpy, naming nothing."""
    for points, kind in ((np.zeros((3, 2)), r"float64 values of shape \(3, 2\)"),
                         (np.zeros((3, 4)), r"float64 values of shape \(3, 4\)"),
                         (np.zeros((1, 3)) + 1j, r"complex128 values of shape \(1, 3\)"),
                         ("abc", r"<U3 values of shape \(\)")):
        with pytest.raises(ValueError, match=rf"^points = .* is not allowed: must be real numbers of shape \(n, 3\), not {kind}$"):
            particle_surface(points, 0.02)
    one = particle_surface([0.1, 0.2, 0.3], 0.02)[0]  # one point as (3,): a sphere of radius 0.55 dx around it
    np.testing.assert_allclose(np.linalg.norm(one - [0.1, 0.2, 0.3], axis=1), 0.011, rtol=0.1)


def test_two_outputs_with_one_stem_keep_their_own_pictures_and_frames(tmp_path, capsys, monkeypatch):
    """-o a.usdc and -o a.usda in one folder: the preview, the exported frames and the
    checkpoint are named from the whole output name, so neither run overwrites the other's.
    The previews are drawn 80 x 60 (the command's own path and names, a smaller picture):
    what is asked here is where they go; the full-size 1600 x 1200 drawing, about half
    this test's CPU, is ``test_run_with_surface_export_and_preview``'s."""
    from warp_esph import render

    full = render.render_usd
    monkeypatch.setattr(render, "render_usd", lambda path, output=None, **kw: full(path, output, width=80, height=60, **kw))
    runs = {"a.usdc": "0.3", "a.usda": "0.35"}  # two sizes: the files differ in what they hold
    for name, scale in runs.items():
        assert main(["run", "dough_drop", "--scale", scale, "--frames", "1", "--no-progress", "-o", str(tmp_path / name),
                     "--export", "ply", "--preview", "--checkpoint-every", "1"]) == 0
    capsys.readouterr()
    for name in runs:
        assert (tmp_path / f"{name}.png").stat().st_size > 1000 and (tmp_path / f"{name}.checkpoint.npz").exists()
        frames = sorted(os.listdir(tmp_path / f"{name}_ply"))
        assert frames == ["frame_00000.ply", "frame_00001.ply"]
    counts = {name: len(meshio.read(tmp_path / f"{name}_ply" / "frame_00001.ply").points) for name in runs}
    assert counts["a.usdc"] < counts["a.usda"], counts  # each folder holds its own run's particles
    assert not (tmp_path / "a.png").exists() and not (tmp_path / "a_ply").exists()
    # The export and render commands' defaults follow the same rule.
    assert main(["export", str(tmp_path / "a.usda"), "--format", "vtu", "--frames", "1"]) == 0
    assert os.listdir(tmp_path / "a.usda_vtu") and not (tmp_path / "a.usdc_vtu").exists()


def test_an_interrupted_export_keeps_its_finished_frames_whole_and_listed(tmp_path, monkeypatch):
    """Each frame is written beside its name and renamed over it, and ``frames.pvd`` lists
    the frames finished also when the export stops: Ctrl-C inside a write left a truncated
    ``.vtu`` (over an earlier export's frame too) and no ``frames.pvd``. A frame named twice
    is refused, as every frame selection refuses it (it was counted twice and listed twice,
    then written once)."""
    import meshio

    from test_render import write_clusters
    from warp_esph.export import export_frames

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    out = tmp_path / "vtu"
    with pytest.raises(ValueError, match=r"^frames = '0,0,1' is not allowed: it names frame 0 twice; name each frame once$"):
        export_frames(path, "vtu", out, frames="0,0,1")
    assert not out.exists()
    files = export_frames(path, "vtu", out, frames="0,1")
    assert [os.path.basename(f) for f in files] == ["frame_00000.vtu", "frame_00001.vtu", "frames.pvd"]
    assert (out / "frames.pvd").read_text().count("<DataSet") == 2
    real = meshio.write

    def interrupted(name, mesh, *a, **k):
        if "frame_00001" in str(name):
            with open(name, "w") as f:
                f.write("<VTKFile")  # a few bytes, then Ctrl-C
            raise KeyboardInterrupt
        return real(name, mesh, *a, **k)

    monkeypatch.setattr(meshio, "write", interrupted)
    before = (out / "frame_00001.vtu").read_bytes()
    with pytest.raises(KeyboardInterrupt):
        export_frames(path, "vtu", out)
    assert sorted(os.listdir(out)) == ["frame_00000.vtu", "frame_00001.vtu", "frames.pvd"]
    assert (out / "frame_00001.vtu").read_bytes() == before
    pvd = (out / "frames.pvd").read_text()
    assert pvd.count("<DataSet") == 1 and "frame_00000.vtu" in pvd
    monkeypatch.setattr(meshio, "write", real)
    assert len(meshio.read(out / "frame_00001.vtu").points) == 125
    for bad, needle in ((None, "output = None is not allowed: must be a path"),
                        ("", "output = '' is not allowed: must be a path")):
        with pytest.raises(ValueError, match=needle):
            export_frames(path, "vtu", bad)


@pytest.mark.parametrize("pvd_fails", [False, True])
def test_a_full_disk_mid_export_is_exit_4_naming_the_file_and_what_is_kept(tmp_path, monkeypatch, capsys, pvd_fails):
    """A write error while a frame is written (write() on a full disk names no file) was exit 2,
    as bad input, with the bare '[Errno 28] No space left on device'; where the collection then
    failed too, its error stood in place of the frame's."""
    import errno

    from test_render import write_clusters
    from warp_esph import export as export_module

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    real = meshio.write

    def full(name, mesh, *a, **k):
        if "frame_00002" in str(name):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(name, mesh, *a, **k)

    monkeypatch.setattr(meshio, "write", full)
    if pvd_fails:
        def no_room(*a, **k):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(export_module, "open", no_room, raising=False)
    out = tmp_path / "vtu"
    assert main(["export", str(path), "-o", str(out)]) == 4
    err = capsys.readouterr().err
    listed = "" if pvd_fails else "; frames.pvd lists them"
    assert err == (f"warp-esph: error: cannot write {out / 'frame_00002.vtu'}: No space left on device "
                   f"(2 of the 3 frames are written whole in {out}{listed})\n")
    kept = ["frame_00000.vtu", "frame_00001.vtu"]
    assert sorted(os.listdir(out)) == kept + ([] if pvd_fails else ["frames.pvd"])
    for name in kept:
        assert len(meshio.read(out / name).points) == 125


def test_an_export_whose_sigterm_landed_in_a_finalizer_does_not_exit_0(tmp_path, monkeypatch, capsys):
    """A signal that lands in a finalizer cannot be raised there (Python drops it): the export
    finished and exited 0 though it was told to stop; it now exits 143 with its files whole."""
    import signal

    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=2)
    real = meshio.write

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)

    def write(*args, **kwargs):
        Finalized()
        return real(*args, **kwargs)

    monkeypatch.setattr(meshio, "write", write)
    out = tmp_path / "vtu"
    assert main(["export", str(path), "-o", str(out)]) == 143
    assert capsys.readouterr().err == "warp-esph: terminated\n"
    assert sorted(os.listdir(out)) == ["frame_00000.vtu", "frame_00001.vtu", "frames.pvd"]


def test_export_says_nothing_of_a_stored_view_it_does_not_use(tmp_path, capsys):
    """The run's suggested camera view is render's: export warned that a file's NaN view was
    'left out' of an export that never reads it. Render still warns (test_render)."""
    import warnings  # noqa: PLC0415

    from pxr import Vt  # noqa: PLC0415

    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.2, 0.0), (0.15, 0.15, 0.15), we.Material.preset("dough"), name="block")
    model = b.finalize()
    path = tmp_path / "v.usda"
    with we.UsdWriter(path, model, 30.0) as writer:
        writer.write_frame(0, model.state())
    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.customLayerData = {**dict(layer.customLayerData), "warp_esph:view": Vt.DoubleArray([np.nan, 20.0])}
    layer.Save()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        export_frames(path, "ply", tmp_path / "ply")
    capsys.readouterr()
    assert main(["export", str(path), "--format", "vtu", "-o", str(tmp_path / "vtu")]) == 0
    out = capsys.readouterr()
    assert "warning" not in out.err and "view" not in out.err + out.out
    assert (tmp_path / "vtu" / "frame_00000.vtu").is_file()
    with pytest.warns(UserWarning, match=r"v.usda: its warp_esph:view = \[nan, 20.0\] is no"):
        assert UsdFrames(path).view is None  # read where it is used


def _foreign_cm_usd(path) -> tuple[str, np.ndarray]:
    """Another program's USD in centimetres: /World moved up 50 cm, a body 'cloud' (8 points at
    frames 0, 1, 2, 5 cm wide) turned 90 degrees about y at frame 2 by its own transform, and a
    body 'late' sampled at frames 0 and 2 only. Returns the path and cloud's points (cm)."""
    from pxr import Gf, Vt

    p = np.random.default_rng(0).uniform(0.0, 10.0, (8, 3))
    stage = Usd.Stage.CreateNew(str(path))
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(30)
    world.AddTranslateOp().Set(Gf.Vec3d(0.0, 50.0, 0.0))
    cloud = UsdGeom.Points.Define(stage, "/World/cloud")
    late = UsdGeom.Points.Define(stage, "/World/late")
    for f in (0, 1, 2):
        cloud.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy((p + f).astype(np.float32)), float(f))
    cloud.GetWidthsAttr().Set(Vt.FloatArray([5.0] * 8))
    for f in (0, 2):
        late.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy((p[:3] + 100.0 * f).astype(np.float32)), float(f))
    spin = cloud.AddRotateYOp()
    spin.Set(0.0, 1.0)
    spin.Set(90.0, 2.0)
    stage.Save()
    return str(path), p


def test_render_export_and_fit_targets_read_a_foreign_usd_alike_in_metres_and_world_coordinates(tmp_path):
    """Fit targets read another program's particles in metres and world coordinates and refuse
    a body without a sample at a frame; render and export read them in the file's local units
    (100 x too far for centimetres, off by the transforms) and drew or wrote a body whose
    samples skipped a frame where USD holds or interpolates it. Now all three read through
    UsdFrames.arrays: in metres and world coordinates, a body without a sample left out."""
    from warp_esph.fit import load_target

    path, p = _foreign_cm_usd(tmp_path / "cm.usda")
    cloud = [p + 0.0, p + 1.0, (p + 2.0)[:, [2, 1, 0]] * [1.0, 1.0, -1.0]]  # frame 2 turned about y
    cloud = 0.01 * (np.stack(cloud) + [0.0, 50.0, 0.0])
    files = export_frames(path, "vtu", tmp_path / "out")
    read = [meshio.read(f) for f in files if f.endswith(".vtu")]
    np.testing.assert_allclose(read[1].points, cloud[1], rtol=1e-5, atol=1e-7)  # 'late' is not held at frame 1
    np.testing.assert_allclose(read[2].points[:8], cloud[2], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(read[2].points[8:], 0.01 * (p[:3] + 200.0 + [0.0, 50.0, 0.0]), rtol=1e-5)
    data = UsdFrames(path)
    parts = data.particles(1)
    np.testing.assert_array_equal(parts["body"], 0)
    np.testing.assert_allclose(parts["points"], cloud[1], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(parts["radius"], 0.025, rtol=1e-6)  # 5 cm wide
    lo, hi = data.bounds([1])
    assert lo == pytest.approx(cloud[1].min(axis=0), rel=1e-5) and hi == pytest.approx(cloud[1].max(axis=0), rel=1e-5)
    target = load_target(path, body="cloud")
    np.testing.assert_array_equal(target.data, np.stack([data.arrays(1)["points"], data.arrays(2)["points"][:8]]))


def test_exported_velocities_carry_the_motion_of_a_time_sampled_transform(tmp_path):
    """Another program's body moved by its own time-sampled transform (3 cm a frame at 30 fps
    along x, after a fixed quarter turn about y), its points and velocities still in its own
    frame: the positions were exported moving at 0.9 m/s, their velocities as the transform's
    linear part of the local ones alone (0 here but for the local 10 cm/s), in another frame
    of motion than the positions. The transform's rate is added, at every frame."""
    from pxr import Gf, Vt

    p = np.random.default_rng(1).uniform(0.0, 10.0, (6, 3))
    stage = Usd.Stage.CreateNew(str(tmp_path / "moving.usda"))
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(30)
    cloud = UsdGeom.Points.Define(stage, "/World/cloud")
    slide = cloud.AddTranslateOp()
    cloud.AddRotateYOp().Set(90.0)
    for f in range(4):
        cloud.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p.astype(np.float32)), float(f))
        cloud.GetVelocitiesAttr().Set(Vt.Vec3fArray([Gf.Vec3f(0.0, 10.0, 0.0)] * 6), float(f))
        slide.Set(Gf.Vec3d(3.0 * f, 0.0, 0.0), float(f))
    stage.Save()
    files = export_frames(tmp_path / "moving.usda", "vtu", tmp_path / "out")
    for f, file in enumerate(files[:4]):
        mesh = meshio.read(file)
        np.testing.assert_allclose(mesh.points[:, 0], 0.01 * (p[:, 2] + 3.0 * f), atol=1e-7)  # the quarter turn: x = z
        np.testing.assert_allclose(mesh.point_data["velocity"], np.tile([0.9, 0.1, 0.0], (6, 1)), atol=1e-9)


def test_a_kernel_narrower_than_the_grid_cell_is_refused_not_an_empty_surface():
    """kernel_radius = 1e-6 fell between the grid's nodes: particle_surface returned no
    triangles without a word. A kernel of one cell still reaches a node (a surface)."""
    with pytest.raises(ValueError, match=r"^kernel_radius = 1e-06 is not allowed: must be >= the grid cell, 0\.01 \(spacing / 2\), "
                                         r"else the kernels fall between the grid's nodes and the surface is empty$"):
        particle_surface(np.zeros((1, 3)), 0.02, kernel_radius=1e-6)
    with pytest.raises(ValueError, match=r"^kernel_radius = 0\.004 is not allowed: must be >= the grid cell, 0\.005 \(cell\)"):
        particle_surface(np.zeros((1, 3)), 0.02, kernel_radius=0.004, cell=0.005)
    v, tri = particle_surface(np.zeros((1, 3)), 0.02, kernel_radius=0.01)
    assert len(tri) > 0 and np.abs(v).max() < 0.02


def test_a_radius_below_half_the_cells_diagonal_gets_a_finer_grid_or_is_refused_with_a_cell_given():
    """radius = 1e-6 missed every grid node around particles that sit off the grid: 20
    particles far apart got no triangle at all, without a word. A radius below half the
    default cell's diagonal (0.3 dx: a tighter surface around a dense body, taken before)
    now gets a finer cell, 2/sqrt(3) x radius, around every particle, a lone one too; where
    that grid is too large, or a cell is given, it is refused, naming the bound."""
    sparse = np.random.default_rng(0).uniform(0.0, 1.0, (20, 3))
    with pytest.raises(ValueError, match=r"^radius = 1e-06 is not allowed for these points: it needs a grid cell of at most "
                                         r"1\.155e-06 \(2/sqrt\(3\) x radius, .*\), and the grid would have .* nodes, more than "
                                         r"256\^3; give a larger radius$"):
        particle_surface(sparse, 0.02, radius=1e-6)
    with pytest.raises(ValueError, match=r"^radius = 0\.006 is not allowed with cell = 0\.01: must be >= half the grid cell's "
                                         r"diagonal, 0\.00866 \(sqrt\(3\)/2 x cell\), else a particle alone within the kernel "
                                         r"can fall between the grid's nodes and leave no surface; give a larger radius, or a "
                                         r"smaller cell \(or none: it is then fitted to the radius\)$"):
        particle_surface(sparse, 0.02, radius=0.006, cell=0.01)
    with pytest.raises(ValueError, match=r"^cell = 0\.02 is not allowed with the default radius, 0\.011 \(0\.55 x spacing\): "
                                         r"must be <= 0\.0127 \(2/sqrt\(3\) x radius\)"):
        particle_surface(sparse, 0.02, cell=0.02)
    for kw in (dict(radius=0.00866, cell=0.01), dict(cell=0.0127), dict(radius=0.006)):  # the bounds; a fitted cell
        v, tri = particle_surface(sparse, 0.02, **kw)
        gap = np.linalg.norm(sparse[:, None, :] - v[None, :, :], axis=2).min(axis=1)
        assert len(tri) > 0 and gap.max() < 0.012, kw  # a surface around every particle
    dx = 0.02
    g = np.arange(6) * dx
    block = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    lone = np.array([[0.5, 0.5, 0.5]])
    v, tri = particle_surface(np.vstack([block, lone]), dx, radius=0.3 * dx)
    near_block = v[np.linalg.norm(v - lone, axis=1) > 0.1]
    # Faces closer to the outer particles than the default radius's half spacing (measured 0.11 dx).
    beyond = np.concatenate([near_block.max(axis=0) - g[-1], -near_block.min(axis=0)])
    assert (beyond > 0.05 * dx).all() and (beyond < 0.2 * dx).all(), beyond / dx
    assert np.linalg.norm(v - lone, axis=1).min() < 0.3 * dx + 1e-6  # the lone particle has its own surface

def test_a_ctrl_c_mid_export_says_which_frames_are_kept(tmp_path, monkeypatch, capsys):
    """An interrupted export (and a run's --export) said 'interrupted' and nothing of the
    frames written whole, where an interrupted run names the frames its file keeps; the run's
    line did not say that its USD holds the whole run."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    real = meshio.write

    def interrupted(name, mesh, *a, **k):
        if "frame_00001" in str(name):
            raise KeyboardInterrupt
        return real(name, mesh, *a, **k)

    monkeypatch.setattr(meshio, "write", interrupted)
    out = tmp_path / "vtu"
    assert main(["export", str(path), "-o", str(out)]) == 130
    assert capsys.readouterr().err == (f"warp-esph: interrupted: 1 of the 3 frames are written whole in {out}; "
                                       "frames.pvd lists them\n")
    assert sorted(os.listdir(out)) == ["frame_00000.vtu", "frames.pvd"]
    # One while the collection is written, every frame whole: the line said 'interrupted' alone.
    from warp_esph import export as export_module

    monkeypatch.setattr(meshio, "write", real)
    quoteattr = export_module.quoteattr
    monkeypatch.setattr(export_module, "quoteattr", lambda name: (_ for _ in ()).throw(KeyboardInterrupt))
    assert main(["export", str(path), "-o", str(tmp_path / "whole")]) == 130
    assert capsys.readouterr().err == (f"warp-esph: interrupted: 3 of the 3 frames are written whole in "
                                       f"{tmp_path / 'whole'}; frames.pvd is not written\n")
    monkeypatch.setattr(export_module, "quoteattr", quoteattr)
    monkeypatch.setattr(meshio, "write", interrupted)
    run = tmp_path / "run.usdc"
    assert main(["run", "--scale", "0.3", "--frames", "2", "--no-progress", "-o", str(run), "--export", "vtu"]) == 130
    err = capsys.readouterr().err
    assert err == (f"warp-esph: interrupted: --export vtu: 1 of the 3 frames are written whole in {run}_vtu; frames.pvd "
                   f"lists them; {run} holds the whole run\n")
    from PIL import Image

    Image.init()
    monkeypatch.setitem(Image.SAVE, "PNG", lambda im, fp, filename: (_ for _ in ()).throw(KeyboardInterrupt))
    assert main(["run", "--scale", "0.3", "--frames", "2", "--no-progress", "-o", str(run), "--preview"]) == 130
    assert capsys.readouterr().err == (f"warp-esph: interrupted: --preview: {run}.png is not written; {run} holds the "
                                       "whole run\n")


def test_a_frame_the_file_does_not_hold_is_refused_by_the_reader_not_read_as_no_particles(tmp_path):
    """``UsdFrames.arrays(99)`` of a 3-frame file (or -1) returned no particles, as if the
    bodies had left; ``True``, ``1.0`` and ``'1'`` were read as frame 1, a list or an array met
    a TypeError. ``parse_frames`` refused them for the commands; the reader did not."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    data = UsdFrames(path)
    assert len(data.arrays(np.int64(2))["points"]) == 125
    for bad in (99, -1, True, 1.0, "1", [0, 1], np.array([1]), None):
        with pytest.raises(ValueError, match=re.escape(f"frame = {bad!r} is not allowed: ") + "must be one of the file's "
                                             r"frames \(0\.\.2\)"):
            data.arrays(bad)
        with pytest.raises(ValueError, match=re.escape(f"frame = {bad!r} is not allowed")):
            data.particles(bad)


def test_the_reader_finds_a_frame_without_scanning_every_frame(tmp_path):
    """``UsdFrames`` checked a requested frame against its list of frames one by one: reading
    each of F frames cost O(F^2) comparisons. A frame is now found in a few comparisons of the
    sorted frames (here about 17 of 100000), and one it lacks is still refused."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    data = UsdFrames(path)
    compared = [0]

    class Frame(int):
        def __eq__(self, other):
            compared[0] += 1
            return int(self) == other

        def __lt__(self, other):
            compared[0] += 1
            return int(self) < other

        __hash__ = int.__hash__

    data.frames = [Frame(f) for f in range(100_000)]
    assert data._frame(99_998) == 99_998 and data.resolve(99_998) == 99_998
    assert compared[0] < 100, compared[0]
    with pytest.raises(ValueError, match=r"^frame = 100000 is not allowed: must be one of the file's frames \(0\.\.99999\)$"):
        data._frame(100_000)


def test_outputs_over_a_link_or_a_special_file_in_an_output_folder_are_refused_before_any_work(tmp_path, capsys):
    """``render -o link.png`` renamed its picture over the link, which became a regular file
    and left the file it linked to as it was; every command's output that is a symbolic link
    is refused now, as a device or a named pipe is, naming the option. A named pipe (or a
    link) where ``export -o dir`` writes a frame was refused only when that frame came, the
    frames before it written, naming ``path``, no option: such a file in an output folder is
    refused before the first frame, naming the option and the file (render's folder of
    pictures likewise)."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=2)
    (tmp_path / "real.png").write_bytes(b"kept")
    os.symlink("real.png", tmp_path / "link.png")
    capsys.readouterr()
    assert main(["render", str(path), "-o", str(tmp_path / "link.png"), "--frames", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"warp-esph: error: --output = '{tmp_path / 'link.png'}' is not allowed: it is a symbolic link (to "
                   "'real.png'), not a file; the output is written beside it and renamed over it, which would replace it: "
                   "give the path of the file it links to, or another name"]
    assert os.path.islink(tmp_path / "link.png") and (tmp_path / "real.png").read_bytes() == b"kept"
    out = tmp_path / "vtu"
    out.mkdir()
    os.mkfifo(out / "frame_00001.vtu")
    assert main(["export", str(path), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"warp-esph: error: --output = '{out}' is not allowed: '{out / 'frame_00001.vtu'}' in it is a named "
                   "pipe, not a file; the output is written beside it and renamed over it, which would replace it: remove "
                   "it, or give another folder"]
    assert sorted(os.listdir(out)) == ["frame_00001.vtu"]  # frame 0 was written before
    pictures = tmp_path / "pictures"
    pictures.mkdir()
    os.symlink(tmp_path / "real.png", pictures / "frame_00000.png")
    assert main(["render", str(path), "-o", str(pictures), "--frames", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: --output = '{pictures}' is not allowed: "
                                               f"'{pictures / 'frame_00000.png'}' in it is a symbolic link"), err
    assert (tmp_path / "real.png").read_bytes() == b"kept"


@pytest.mark.parametrize("command, name", [("export", "frame_00001.vtu"), ("export", "frames.pvd"),
                                           ("render", "frame_00001.png"), ("run", "frame_00001.vtu")])
def test_a_folder_where_a_folder_output_writes_a_file_is_refused_before_any_work(tmp_path, capsys, command, name):
    """A folder where ``export -o DIR`` (``render -o DIR``, ``run --export``) writes one of its
    files was met only when that file came: frame 0 written, then 'cannot write
    DIR/frame_00001.vtu: Is a directory', exit 4 as a full disk is, and ``run --export`` ran the
    whole simulation first. It is refused before any work, exit 2, naming the option and the
    folder in the way, as a named pipe there is."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    if command == "run":
        out, what = tmp_path / "r.usdc_vtu", "--export vtu's folder"
        argv = ["run", "--scale", "0.3", "--frames", "2", "--no-progress", "-o", str(tmp_path / "r.usdc"), "--export", "vtu"]
    else:
        write_clusters(path, [(0.0, 0.2, 0.0)], frames=2)
        out, what = tmp_path / "out", "--output"
        argv = [command, str(path), "-o", str(out)] + ["--width", "40", "--height", "30"] * (command == "render")
    (out / name).mkdir(parents=True)
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"warp-esph: error: {what} = '{out}' is not allowed: '{out / name}' in it is a folder, where a file is "
                   "written: remove it, or give another folder"]
    assert os.listdir(out) == [name] and not (tmp_path / "r.usdc").exists()


@pytest.mark.parametrize("command", ["export", "render", "sweep"])
def test_a_special_file_where_a_folder_output_goes_is_named_for_what_it_is(tmp_path, capsys, command):
    """``export a.usdc -o /dev/null`` said "it is a file; a folder is written there" of a
    device (a named pipe likewise): it is named as the link or device refusals of a file
    output name it."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=1)
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    argv = {"export": ["export", str(path)], "render": ["render", str(path)],
            "sweep": ["sweep", "dough_drop", "--scale", "0.3", "--param", "yield_stress=10,100", "--workers", "1"]}[command]
    capsys.readouterr()
    assert main([*argv, "-o", str(pipe)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"warp-esph: error: --output = '{pipe}' is not allowed: it is a named pipe; a folder is written there"]


@pytest.mark.parametrize("fmt", ["vtu", "ply"])
def test_an_export_into_a_folder_of_an_earlier_one_leaves_its_own_frames_alone(tmp_path, capsys, fmt):
    """An export of fewer frames into the folder of an earlier one left the earlier frames
    beside its own (a .vtu folder's frames.pvd listed only the new ones; a .ply folder said
    nothing of which were current). Only files of the export's own naming go: not another
    format's frames, nor any other file."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=4, shift=(0.01, 0.0, 0.0))
    out = tmp_path / "frames"
    assert main(["export", str(path), "--format", fmt, "-o", str(out)]) == 0
    others = ["frame_00003.png", "frame_00003.other.vtu", "frame_3.vtu", "notes.txt"] + ["frames.pvd"] * (fmt == "ply")
    for name in others:
        (out / name).write_text("not the export's")
    assert main(["export", str(path), "--format", fmt, "-o", str(out), "--frames", "1:2"]) == 0
    capsys.readouterr()
    own = ["frame_00001." + fmt, "frame_00002." + fmt] + ["frames.pvd"] * (fmt == "vtu")
    assert sorted(os.listdir(out)) == sorted(own + others)
    for name in others:
        assert (out / name).read_text() == "not the export's"
    # The frames written are this export's: frame 2's positions, moved twice from frame 0's.
    x = UsdFrames(str(path)).arrays(2)["points"]
    np.testing.assert_array_equal(meshio.read(out / f"frame_00002.{fmt}").points, x)
    if fmt == "vtu":
        pvd = (out / "frames.pvd").read_text()
        assert re.findall(r'file="([^"]+)"', pvd) == ["frame_00001.vtu", "frame_00002.vtu"]


def test_a_render_into_a_folder_of_an_earlier_one_leaves_its_own_pictures_alone(tmp_path, capsys):
    """As for export: a render of fewer frames into a folder of an earlier render's pictures
    left them beside its own; other files stay."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    out = tmp_path / "pictures"
    small = ["--width", "24", "--height", "16", "--supersample", "1", "--no-shadows"]
    assert main(["render", str(path), "-o", str(out), *small]) == 0
    assert sorted(os.listdir(out)) == [f"frame_{f:05d}.png" for f in range(3)]
    (out / "frame_00000.vtu").write_text("an export's frame")
    (out / "cover.png").write_text("not the render's")
    # A refused render removes nothing.
    assert main(["render", str(path), "-o", str(out), "--frames", "2", "--fit", "some", *small]) == 2
    assert len(os.listdir(out)) == 5
    assert main(["render", str(path), "-o", str(out), "--frames", "2", *small]) == 0
    capsys.readouterr()
    assert sorted(os.listdir(out)) == ["cover.png", "frame_00000.vtu", "frame_00002.png"]
    assert (out / "frame_00000.vtu").read_text() == "an export's frame"


@pytest.mark.parametrize("error", [ValueError, TypeError, RuntimeError])
def test_an_unexpected_error_mid_export_is_one_line_saying_what_is_written(tmp_path, monkeypatch, capsys, error):
    """An error of no kind export expects (a bug in a writer), raised once frames are written:
    a ValueError was exit 2, 'bad input', and the others a traceback, neither saying which
    files were written. Now one line naming it and where it was raised, exit 1, as run says it."""
    from test_cli import assert_one_line_error
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=4)
    real = meshio.write

    def broken(name, mesh, *a, **k):
        if "frame_00002" in str(name):
            raise error("the writer broke")
        return real(name, mesh, *a, **k)

    monkeypatch.setattr(meshio, "write", broken)
    out = tmp_path / "vtu"
    assert main(["export", str(path), "-o", str(out)]) == 1
    captured = capsys.readouterr()
    assert "wrote" not in captured.out
    assert_one_line_error(captured.err, f"the export stopped in frame 2: {error.__name__}: the writer broke (raised at "
                                        "test_export.py:", f"2 of the 4 frames are written whole in {out}; frames.pvd lists them)")
    assert sorted(os.listdir(out)) == ["frame_00000.vtu", "frame_00001.vtu", "frames.pvd"]
    assert re.findall(r'file="([^"]+)"', (out / "frames.pvd").read_text()) == ["frame_00000.vtu", "frame_00001.vtu"]


def test_a_frame_the_file_refuses_mid_export_or_render_is_still_bad_input(tmp_path, capsys):
    """A damaged frame (no finite position) met once frames are written is the input's fault:
    exit 2, naming the file, not an error of no kind expected."""
    from pxr import Usd, UsdGeom
    from test_cli import assert_one_line_error
    from test_render import write_clusters

    path = tmp_path / "anim.usda"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    stage = Usd.Stage.Open(str(path))
    prim = next(p for p in stage.GetPrimAtPath("/World").GetChildren() if p.IsA(UsdGeom.Points))
    n = len(UsdGeom.Points(prim).GetPointsAttr().Get(Usd.TimeCode(1.0)))
    UsdGeom.Points(prim).GetPointsAttr().Set([(np.nan, 0.0, 0.0)] * n, Usd.TimeCode(1.0))
    stage.GetRootLayer().Save()
    for argv in (["export", str(path), "-o", str(tmp_path / "vtu")],
                 ["render", str(path), "-o", str(tmp_path / "png"), "--width", "24", "--height", "16", "--supersample", "1"]):
        assert main(argv) == 2
        assert_one_line_error(capsys.readouterr().err, "frame 1 has no particle with a finite position")


@pytest.mark.parametrize("output", ["pictures", "movie.gif"])
def test_an_unexpected_error_mid_render_is_one_line_saying_what_is_written(tmp_path, monkeypatch, capsys, output):
    """As for export: a render stopped by an error of no kind expected (a bug in the renderer or
    the picture's writer) was a traceback, or for a ValueError exit 2, 'bad input'."""
    from test_cli import assert_one_line_error
    from test_render import write_clusters

    from warp_esph import render as render_module

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=3)
    out = tmp_path / output
    if output == "pictures":
        real = render_module.Renderer.render

        def broken(self, frame):
            if frame == 1:
                raise ZeroDivisionError("the renderer broke")
            return real(self, frame)

        monkeypatch.setattr(render_module.Renderer, "render", broken)
        needles = ("the render stopped in frame 1: ZeroDivisionError: the renderer broke (raised at test_export.py:",
                   f"1 of the 3 frames are written whole in {out})")
    else:
        def broken(img, part, **options):
            raise ValueError("the encoder broke")

        monkeypatch.setattr(render_module, "_save_image", broken)
        needles = ("the render stopped: ValueError: the encoder broke (raised at test_export.py:",
                   f"{out} is not written (a file of that name is left as it was))")
    assert main(["render", str(path), "-o", str(out), "--width", "24", "--height", "16", "--supersample", "1"]) == 1
    captured = capsys.readouterr()
    assert "wrote" not in captured.out
    assert_one_line_error(captured.err, *needles)
    assert sorted(os.listdir(tmp_path)) == ["anim.usdc"] + (["pictures"] if output == "pictures" else [])
    if output == "pictures":
        assert os.listdir(out) == ["frame_00000.png"]


@pytest.mark.parametrize("name", ["out.vtu", "out.PLY", "out.pvd"])
def test_an_output_named_as_a_frame_file_is_refused_naming_the_folder_it_would_be(tmp_path, capsys, name):
    """``export a.usdc -o out.vtu`` made a folder named ``out.vtu``: a user who named a file got
    a folder of ``frame_NNNNN.vtu`` files. A name ending as a frame file does (.vtu, .ply, .pvd)
    is refused before any work, saying what -o is; a folder of that name already there is a
    folder, and is written into as before."""
    from test_render import write_clusters

    path = tmp_path / "anim.usdc"
    write_clusters(path, [(0.0, 0.2, 0.0)], frames=2)
    out = tmp_path / name
    capsys.readouterr()
    assert main(["export", str(path), "--frames", "last", "-o", str(out)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"warp-esph: error: --output = '{out}' is not allowed: it names a file, and --output is the folder the frames' "
        "files are written into (frame_00000.vtu, frame_00001.vtu, ... and frames.pvd): give a folder's name"]
    assert not out.exists()
    with pytest.raises(ValueError, match=r"^output = .* is not allowed: it names a file, and output is the folder the "
                                          r"frames' files are written into \(frame_00000\.ply, frame_00001\.ply, \.\.\.\): "):
        export_frames(str(path), "ply", str(out))
    assert not out.exists()
    out.mkdir()  # a folder of that name is a folder
    assert main(["export", str(path), "--frames", "last", "-o", str(out)]) == 0
    assert sorted(os.listdir(out)) == ["frame_00001.vtu", "frames.pvd"]
