"""USD output: content, metadata, crash safety, append; and ``simulate``'s frame loop."""

import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

from run_files import open_fresh
from warp_esph import Material, SceneBuilder, Solver
from warp_esph.simulate import SimulationError, resolve_timestep, simulate
from warp_esph.usd import UsdFrames, UsdWriter

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SAMPLED = ("points", "velocities", "widths", "extent", "primvars:singular_values", "primvars:alpha")


@pytest.fixture(scope="module")
def model():
    """Two small bodies (two materials) and one collider of each kind."""
    b = SceneBuilder(spacing=0.04)
    b.add_box((0.0, 0.12, 0.0), (0.16, 0.12, 0.12), Material.preset("dough"), name="dough block")
    b.add_sphere((0.3, 0.15, 0.0), 0.07, Material.from_young(5.0e4, 0.3), name="ball")
    b.add_ground()
    b.add_plane((1.0, 0.0, 0.0), -1.0)
    b.add_sphere_collider((0.0, -0.5, 1.0), 0.2)
    b.add_box_collider((1.0, -0.5, 0.0), (0.1, 0.2, 0.3))
    return b.finalize()


def sampled_frames(stage: Usd.Stage, prim_path: str) -> dict:
    prim = stage.GetPrimAtPath(prim_path)
    return {name: prim.GetAttribute(name).GetTimeSamples() for name in SAMPLED}


def run_recorded(model, path, frames=3, **kw):
    """simulate with a UsdWriter; returns {frame: (x, v, F, alpha)} seen by the callback."""
    seen = {}

    def record(frame, state):
        seen[frame] = (state.x.numpy().copy(), state.v.numpy().copy(), state.F.numpy().copy(), state.alpha.numpy().copy())

    final = simulate(model, frames, fps=30, writer=UsdWriter(path, model, 30), progress=False, callback=record, **kw)
    return seen, final


@pytest.mark.parametrize("ext", ["usdc", "usda", "usd"])
def test_frames_positions_primvars_metadata(model, tmp_path, ext):
    path = tmp_path / f"out.{ext}"
    seen, final = run_recorded(model, path, frames=3)
    assert sorted(seen) == [0, 1, 2, 3]
    head = path.read_bytes()[:8]
    assert head.startswith(b"#usda") if ext == "usda" else head == b"PXR-USDC"
    # Only the published file is left: the working copies are gone.
    assert sorted(os.listdir(tmp_path)) == [path.name]

    stage = open_fresh(path)
    assert stage.GetTimeCodesPerSecond() == 30 and stage.GetFramesPerSecond() == 30
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 3
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")

    for body, prim_path in zip(model.bodies, ["/World/dough_block", "/World/ball"]):
        prim = stage.GetPrimAtPath(prim_path)
        assert prim.IsA(UsdGeom.Points)
        assert prim.GetCustomDataByKey("warp_esph:body_name") == body.name
        # One time sample per frame on every per-frame attribute.
        for name, times in sampled_frames(stage, prim_path).items():
            assert times == [0.0, 1.0, 2.0, 3.0], name
        pts = UsdGeom.Points(prim)
        s = slice(body.start, body.start + body.count)
        for frame, (x, v, F, alpha) in seen.items():
            np.testing.assert_array_equal(np.array(pts.GetPointsAttr().Get(frame)), x[s].astype(np.float32))
            np.testing.assert_array_equal(np.array(pts.GetVelocitiesAttr().Get(frame)), v[s].astype(np.float32))
            np.testing.assert_allclose(np.array(pts.GetWidthsAttr().Get(frame)), model.spacing, rtol=1e-6)
            lo, hi = np.array(pts.GetExtentAttr().Get(frame))
            assert np.all(lo <= x[s].min(axis=0)) and np.all(hi >= x[s].max(axis=0))
            pv = UsdGeom.PrimvarsAPI(prim)
            sv = np.array(pv.GetPrimvar("singular_values").Get(frame))
            np.testing.assert_allclose(sv, np.linalg.svd(F[s].astype(np.float64), compute_uv=False), rtol=1e-5, atol=1e-6)
            assert np.all(np.diff(sv, axis=1) <= 0)  # descending
            np.testing.assert_allclose(np.array(pv.GetPrimvar("alpha").Get(frame)), alpha[s], rtol=1e-6)
        pv = UsdGeom.PrimvarsAPI(prim)
        for name in ("singular_values", "alpha"):
            assert pv.GetPrimvar(name).GetInterpolation() == UsdGeom.Tokens.vertex
        mid = pv.GetPrimvar("material_id")
        assert mid.GetInterpolation() == UsdGeom.Tokens.constant and mid.Get() == body.material
        assert mid.GetAttr().GetTimeSamples() == []  # constant over time
    # The last frame is the state simulate returned.
    np.testing.assert_array_equal(seen[3][0], final.x.numpy())

    # Colliders.
    plane = stage.GetPrimAtPath("/World/Colliders/plane_0")
    assert plane.IsA(UsdGeom.Mesh)
    assert len(stage.GetPrimAtPath("/World/Colliders/plane_1").GetAttribute("points").Get()) == 4
    sphere = UsdGeom.Sphere(stage.GetPrimAtPath("/World/Colliders/sphere_0"))
    assert sphere and sphere.GetRadiusAttr().Get() == pytest.approx(0.2)
    box = stage.GetPrimAtPath("/World/Colliders/box_0")
    assert box.IsA(UsdGeom.Cube)
    # The cube's world box is the collider's box.
    bound = UsdGeom.Imageable(box).ComputeWorldBound(0, UsdGeom.Tokens.default_).ComputeAlignedRange()
    np.testing.assert_allclose(np.array(bound.GetMin()), [0.9, -0.7, -0.3], atol=1e-6)
    np.testing.assert_allclose(np.array(bound.GetMax()), [1.1, -0.3, 0.3], atol=1e-6)
    # The ground quad lies in y = 0 and faces +y.
    ground = np.array(plane.GetAttribute("points").Get())
    np.testing.assert_allclose(ground[:, 1], 0.0, atol=1e-6)
    assert np.cross(ground[1] - ground[0], ground[2] - ground[1])[1] > 0


def test_file_is_complete_after_every_frame(model, tmp_path):
    path = tmp_path / "live.usdc"
    checked = []

    def check(frame, state):
        stage = open_fresh(path)
        assert stage.GetEndTimeCode() == frame
        assert sampled_frames(stage, "/World/ball")["points"] == [float(f) for f in range(frame + 1)]
        np.testing.assert_array_equal(np.array(stage.GetPrimAtPath("/World/ball").GetAttribute("points").Get(frame)),
                                      state.x.numpy()[model.bodies[1].start:].astype(np.float32))
        checked.append(frame)

    simulate(model, 3, fps=30, writer=UsdWriter(path, model, 30), progress=False, callback=check)
    assert checked == [0, 1, 2, 3]


@pytest.mark.parametrize("ext", ["usdc", "usda"])
def test_interrupted_run_keeps_finished_frames(model, tmp_path, ext):
    path = tmp_path / f"stop.{ext}"

    def stop(frame, state):
        if frame == 3:
            raise KeyboardInterrupt

    writer = UsdWriter(path, model, 30)
    with pytest.raises(KeyboardInterrupt):
        simulate(model, 10, fps=30, writer=writer, progress=False, callback=stop)
    assert writer.closed and writer.frames_written == 4
    assert sorted(os.listdir(tmp_path)) == [path.name]
    stage = open_fresh(path)
    assert stage.GetEndTimeCode() == 3
    for prim_path in ("/World/dough_block", "/World/ball"):
        for name, times in sampled_frames(stage, prim_path).items():
            assert times == [0.0, 1.0, 2.0, 3.0], name


def test_a_close_interrupted_inside_is_finished_by_the_next(model, tmp_path):
    """A signal inside close() (while the stages are released) left the working copies beside
    the output, and every later close() returned at once: they stayed."""
    path = tmp_path / "closing.usdc"
    writer = UsdWriter(path, model, 30)
    release = writer._release

    def interrupted():
        release()
        raise KeyboardInterrupt

    writer._release = interrupted
    with pytest.raises(KeyboardInterrupt):
        writer.close()
    writer._release = release
    writer.close()
    assert writer.closed and sorted(os.listdir(tmp_path)) == [path.name]


def test_a_close_whose_clean_up_fails_lets_the_output_go(model, tmp_path, monkeypatch):
    """A clean-up that raised inside close() kept the output's lock until the writer was
    collected: a second writer of the path in this process was refused (OutputInUse) though
    the first was gone. The lock is now let go; a later close() of the first, once the second
    holds the file, leaves the second's working copies alone."""
    path = tmp_path / "held.usdc"
    first = UsdWriter(path, model, 30)

    def fails():
        raise PermissionError(13, "Permission denied", str(tmp_path / ".held.wa.usdc"))

    monkeypatch.setattr(first, "_remove_work_files", fails)
    with pytest.raises(PermissionError):
        first.close()
    monkeypatch.undo()
    # Its stages are gone: a frame is refused as by a closed writer (it was an IndexError).
    with pytest.raises(ValueError, match=rf"^cannot write frame 0: the writer of {re.escape(str(first.path))} is closed$"):
        first.write_frame(0, model.state())
    # simulate tells the writer its solver before each frame: refused alike (an IndexError).
    with pytest.raises(ValueError, match=rf"^cannot write frame 0: the writer of {re.escape(str(first.path))} is closed$"):
        simulate(model, 1, fps=30, writer=first, progress=False)
    second = UsdWriter(path, model, 30)  # refused before, the first still referenced here
    working = sorted(os.listdir(tmp_path))
    first.close()
    assert first.closed and sorted(os.listdir(tmp_path)) == working
    simulate(model, 2, fps=30, writer=second, progress=False)
    assert second.closed and sorted(os.listdir(tmp_path)) == [path.name]
    assert open_fresh(path).GetEndTimeCode() == 2


def test_simulation_error_names_step_particle_body(model, tmp_path):
    path = tmp_path / "nan.usdc"
    bad = model.bodies[1].start + 2  # a particle of "ball"

    def poison(frame, state):
        if frame == 2:
            v = state.v.numpy()
            v[bad] = np.nan
            state.v.assign(v)

    # One step of 1 ms per frame (below the stable step): the NaN has reached only the
    # poisoned particle's neighbours when the check after frame 3 finds it.
    writer = UsdWriter(path, model, 1000)
    with pytest.raises(SimulationError) as info:
        simulate(model, 6, fps=1000, substeps=1, writer=writer, progress=False, callback=poison)
    e = info.value
    assert isinstance(e, RuntimeError)
    assert e.step == 3 and e.frame == 3
    ball = model.bodies[1]
    assert ball.start <= e.particle <= bad and e.body == "ball"
    assert "step 3" in str(e) and f"particle {e.particle}" in str(e) and "'ball'" in str(e)
    assert writer.closed
    stage = open_fresh(path)
    assert stage.GetEndTimeCode() == 2  # frames 0..2 kept, the bad frame not written
    assert sampled_frames(stage, "/World/ball")["points"] == [0.0, 1.0, 2.0]


def test_append_resumes_and_replaces_later_frames(model, tmp_path):
    path = tmp_path / "resume.usdc"
    simulate(model, 5, fps=30, writer=UsdWriter(path, model, 30), progress=False)
    state = model.state()
    x = state.x.numpy()
    x[:, 1] += 1.0  # a recognisably different state
    state.x.assign(x)
    with UsdWriter(path, model, 30, append=True) as w:
        w.write_frame(3, state)
        w.write_frame(4, state)
    stage = open_fresh(path)
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 4
    pts = stage.GetPrimAtPath("/World/dough_block").GetAttribute("points")
    assert pts.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0]  # frame 5 of the first run is gone
    np.testing.assert_array_equal(np.array(pts.Get(4)), x[: model.bodies[0].count].astype(np.float32))
    assert np.array(pts.Get(2))[:, 1].max() < 0.5  # frames before the resume point are kept
    with pytest.raises(ValueError, match="fps"):
        UsdWriter(path, model, 24, append=True)
    with pytest.raises(FileNotFoundError):
        UsdWriter(tmp_path / "missing.usdc", model, 30, append=True)


def test_appending_to_a_file_with_no_frame_starts_it_at_the_first_frame_written(model, tmp_path):
    """A file whose writer stopped before its first frame holds none: appended to, it read as
    holding frame 0 (the stage's start and end time codes, 0 in a file of no frame), so the
    writer's first and last frame said 0 and the file's start time code stayed 0 before a
    first frame of 5; ``run --resume`` took it as holding frame 0."""
    path = tmp_path / "empty.usdc"
    UsdWriter(path, model, 30).close()
    with pytest.raises(ValueError, match="it holds no frames"):
        UsdFrames(str(path))
    with UsdWriter(path, model, 30, append=True) as w:
        assert (w.first_frame, w.last_frame) == (None, None)
        w.write_frame(5, model.state())
        w.write_frame(6, model.state())
        assert (w.first_frame, w.last_frame) == (5, 6)
    stage = open_fresh(path)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (5.0, 6.0)
    assert UsdFrames(str(path)).frames == [5, 6]
    # A file that holds frames 2..4 (start time code 0 left as a file written so): its own frames.
    with UsdWriter(path, model, 30) as w:
        for f in (2, 3, 4):
            w.write_frame(f, model.state())
    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload(force=True)
    layer.startTimeCode = 0.0
    layer.Save()
    with UsdWriter(path, model, 30, append=True) as w:
        assert (w.first_frame, w.last_frame) == (2, 4)


def test_a_writer_opened_for_another_model_is_named_not_the_state(model, tmp_path):
    """A writer of another scene made the run fail at its first frame, blaming the state's
    shape; it is refused by name before the run, and the file keeps nothing of it."""
    b = SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.2, 0.0), (0.2, 0.2, 0.2), Material.preset("dough"), name="dough_block")
    other = b.finalize()
    writer = UsdWriter(tmp_path / "other.usdc", other, 30)
    with pytest.raises(ValueError, match=r"writer is not allowed: it was opened for another model \(bodies "
                                         r"\[\('dough_block', 64\)\], this one \[\('dough block', 36\), \('ball', 27\)\]\)"):
        simulate(model, 2, fps=30, writer=writer, progress=False)
    assert writer.closed and writer.frames_written == 0


def test_writer_rejects_bad_arguments(model, tmp_path):
    with pytest.raises(ValueError, match="extension"):
        UsdWriter(tmp_path / "out.txt", model, 30)
    with pytest.raises(ValueError, match="fps"):
        UsdWriter(tmp_path / "out.usdc", model, 0)
    with pytest.raises(FileNotFoundError):
        UsdWriter(tmp_path / "no" / "out.usdc", model, 30)
    if os.path.isdir("/proc"):
        # A folder that takes no file is a failed write, as pxr's at the working copies was, not
        # a FileNotFoundError ('the input is missing') from the writer's lock file.
        with pytest.raises(OSError, match=r"^could not create /proc/\.x\.usdc\.lock: ") as refused:
            UsdWriter("/proc/x.usdc", model, 30)
        assert type(refused.value) is OSError
    with UsdWriter(tmp_path / "ok.usdc", model, 30) as w:
        with pytest.raises(ValueError, match="frame_index"):
            w.write_frame(-1, model.state())
    with pytest.raises(ValueError, match="closed"):
        w.write_frame(0, model.state())


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_killed_process_leaves_valid_file(tmp_path, model):
    """SIGKILL a writer at arbitrary moments: the file always opens with every finished frame.
    While it writes, a writer of the same file in another process is refused (the two shared
    the working copies beside it: the first failed with 'Unable to open .killed.usdc.wa.usdc',
    saying its file kept its frames, and the file was the second's); once it is killed, the
    file is free again."""
    path = tmp_path / "killed.usdc"
    child = textwrap.dedent(
        f"""
        import sys, warp as wp
        wp.config.log_level = wp.LOG_WARNING
        from warp_esph import Material, SceneBuilder
        from warp_esph.usd import UsdWriter
        b = SceneBuilder(spacing=0.01)
        b.add_box((0, 0.5, 0), (0.25, 0.25, 0.25), Material.preset("dough"), name="a")
        m = b.finalize()
        s = m.state()
        x0 = m.particle_x0.copy()
        with UsdWriter({str(path)!r}, m, 30) as w:
            for f in range(100000):
                s.x.assign(x0 + 0.001 * f)
                w.write_frame(f, s)
                print(f, flush=True)
        """
    )
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    rng = np.random.default_rng(7)
    for trial in range(2):
        proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True)
        try:
            first = proc.stdout.readline()
            assert first.strip().isdigit(), "the writer process did not start"
            with pytest.raises(ValueError, match=rf"^path = '{path}' is not allowed: another writer \(process "
                                                 rf"{proc.pid}\) is writing it; wait for it to finish, or write "
                                                 "another file"):
                UsdWriter(path, model, 30)
            time.sleep(float(rng.uniform(0.05, 0.4)))
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        printed = [int(line) for line in proc.stdout.read().split() if line.strip().isdigit()]
        done = printed[-1] if printed else int(first)
        stage = open_fresh(path)
        end = int(stage.GetEndTimeCode())
        assert end >= done
        pts = stage.GetPrimAtPath("/World/a").GetAttribute("points")
        assert pts.GetTimeSamples() == [float(f) for f in range(end + 1)]
        x_end = np.array(pts.Get(end))
        x_0 = np.array(pts.Get(0))
        np.testing.assert_allclose(x_end - x_0, 0.001 * end, atol=1e-5)
        del stage
    with UsdWriter(path, model, 30) as w:  # the killed writer's lock went with its process
        w.write_frame(0, model.state())
    assert sorted(os.listdir(tmp_path)) == ["killed.usdc"]


def test_resolve_timestep(model):
    stable = model.stable_dt()
    n, dt = resolve_timestep(model, 30)
    assert dt <= stable and n * dt == pytest.approx(1 / 30)
    assert n == 1 or (1 / 30) / (n - 1) > stable  # the largest step that fits a whole number of times
    assert resolve_timestep(model, 30, substeps=7) == (7, pytest.approx(1 / 210))
    assert resolve_timestep(model, 30, dt=1 / 300)[0] == 10
    assert resolve_timestep(model, 25, dt=0.004)[0] == 10
    with pytest.raises(ValueError, match="dt = 0.0007"):
        resolve_timestep(model, 30, dt=0.0007)
    with pytest.raises(ValueError, match="dt"):
        resolve_timestep(model, 30, dt=-1.0)
    with pytest.raises(ValueError, match="dt"):
        resolve_timestep(model, 30, dt=0.1)  # longer than a frame
    with pytest.raises(ValueError, match="substeps"):
        resolve_timestep(model, 30, substeps=2, dt=1 / 60)
    with pytest.raises(ValueError, match="fps"):
        resolve_timestep(model, 0)


def test_simulate_validates_and_does_not_touch_input_state(model):
    with pytest.raises(ValueError, match="frames"):
        simulate(model, 0, progress=False)
    with pytest.raises(ValueError, match="frames"):
        simulate(model, 2.5, progress=False)
    with pytest.raises(ValueError, match="fps"):
        simulate(model, 1, fps=-30, progress=False)
    with pytest.raises(ValueError, match="solver"):
        simulate(model, 1, progress=False, solver=object())
    start = model.state()
    x0 = start.x.numpy().copy()
    solver = Solver(model)
    final = simulate(model, 1, fps=300, substeps=3, progress=False, solver=solver, state=start)
    assert solver.step_count == 3
    np.testing.assert_array_equal(start.x.numpy(), x0)  # copied, not advanced
    assert final is not start and not np.array_equal(final.x.numpy(), x0)


@pytest.mark.parametrize("have_tqdm", [True, False])
def test_progress_bar_shows_frames_and_steps_per_second(model, capsys, monkeypatch, have_tqdm):
    if not have_tqdm:
        monkeypatch.setitem(sys.modules, "tqdm", None)  # the plain fallback bar
    simulate(model, 2, fps=30, progress=True)
    err = capsys.readouterr().err
    assert "2/2" in err and "steps/s" in err and f"{model.particle_count} particles" in err


def test_a_folder_where_the_file_goes_is_refused_by_name(model, tmp_path):
    """A folder named like the output met an IsADirectoryError at the first frame."""
    (tmp_path / "d.usda").mkdir()
    with pytest.raises(ValueError, match=r"path = .*d\.usda' is not allowed: it is a folder; a file is written there"):
        UsdWriter(tmp_path / "d.usda", model, 30.0)


def test_a_symbolic_link_where_the_file_goes_is_refused_as_every_command_refuses_it(model, tmp_path):
    """``UsdWriter(link)`` renamed its frames over the link: the link became a regular file
    and the file it linked to was left as it was, where every command refuses the link
    (``checks.output_place``). The writer refuses it too, by the same check, before it
    takes the file's lock or writes anything."""
    real = tmp_path / "real.usda"
    real.write_text("kept")
    link = tmp_path / "link.usda"
    link.symlink_to(real.name)
    before = sorted(os.listdir(tmp_path))
    for append in (False, True):
        with pytest.raises(ValueError) as e:
            UsdWriter(link, model, 30.0, append=append)
        assert str(e.value) == (f"path = {str(link)!r} is not allowed: it is a symbolic link (to 'real.usda'), not a "
                                "file; the output is written beside it and renamed over it, which would replace it: "
                                "give the path of the file it links to, or another name")
    assert link.is_symlink() and real.read_text() == "kept" and sorted(os.listdir(tmp_path)) == before


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_float64_run_reads_back_to_the_last_bit(tmp_path, dtype):
    """The schema's points and velocities are float: a float64 run's file rounded them to
    float32 (2e-9 m, measured), and a fit to that run's USD compared its float64 rollout
    with them. A float64 run also writes its own values (``warp_esph:points_float64``,
    ``velocities_float64``), which ``UsdFrames.arrays`` (fit targets, export) reads back
    bit for bit; its alpha and singular values primvars are double (they were float32, and
    the export wrote them so); a float32 run's file is as before."""
    import warp as wp  # noqa: PLC0415

    from warp_esph.export import frame_arrays_to_mesh  # noqa: PLC0415
    from warp_esph.render import UsdFrames  # noqa: PLC0415

    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.05, 0.0), (0.06, 0.06, 0.06), Material(mu=2e3, lam=3e3, yield_stress=40.0, flow_rate=20.0))
    b.add_ground()
    m = b.finalize(dtype=getattr(wp, dtype))
    path = tmp_path / "run.usdc"
    kept = {}
    with UsdWriter(path, m, fps=50.0) as w:
        simulate(m, 3, fps=50.0, writer=w, progress=False,
                 callback=lambda frame, s: kept.update({frame: (s.x.numpy().copy(), s.v.numpy().copy(),
                                                                s.alpha.numpy().copy(), s.F.numpy().copy())}))
    data = UsdFrames(str(path))
    rounded = []
    for frame, (x, v, alpha, F) in kept.items():
        a = data.arrays(frame)
        assert a["points"].dtype == x.dtype and a["velocities"].dtype == v.dtype
        np.testing.assert_array_equal(a["points"], x)
        np.testing.assert_array_equal(a["velocities"], v)
        # alpha and the singular values too (they were float32 primvars in a float64 run), and
        # the exported frame keeps them so.
        assert a["alpha"].dtype == a["singular_values"].dtype == x.dtype
        np.testing.assert_array_equal(a["alpha"], alpha)
        np.testing.assert_array_equal(a["singular_values"],
                                      np.linalg.svd(F.astype(np.float64), compute_uv=False).astype(x.dtype))
        mesh = frame_arrays_to_mesh(a, "vtu")
        assert mesh.point_data["alpha"].dtype == mesh.point_data["singular_values"].dtype == x.dtype
        rounded.append((a["singular_values"] != a["singular_values"].astype(np.float32)).any())
    # A float64 run's singular values differ from their float32 rounding: the comparison sees it.
    assert any(rounded) == (dtype == "float64")
    stage = open_fresh(path)
    prim = stage.GetPrimAtPath("/World/" + m.bodies[0].name)
    assert bool(prim.GetAttribute("warp_esph:points_float64")) == (dtype == "float64")
    assert len(kept) == 4  # frames 0..3
    if dtype == "float64":
        # A file whose early frames lack them (begun before they were written, then resumed):
        # those frames read their own float points, not the nearest double sample.
        layer = Sdf.Layer.FindOrOpen(str(path))
        edit_stage = Usd.Stage.Open(layer)
        edit = edit_stage.GetPrimAtPath("/World/" + m.bodies[0].name)
        for key in ("warp_esph:points_float64", "warp_esph:velocities_float64"):
            for frame in (0, 1):
                edit.GetAttribute(key).ClearAtTime(float(frame))
        layer.Save()
        data = UsdFrames(str(path))
        for frame in (0, 1):
            a = data.arrays(frame)
            assert a["points"].dtype == np.float32
            np.testing.assert_allclose(a["points"], kept[frame][0], atol=1e-6)
        np.testing.assert_array_equal(data.arrays(2)["points"], kept[2][0])


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_an_inverted_particles_singular_values_are_written_signed(tmp_path, dtype):
    """The primvar held numpy's singular values, all >= 0: a particle whose F is inverted
    (det F < 0) read back as one of the mirrored, uninverted shape. It holds the rotation-variant
    SVD's (docs/method.md §3), the smallest of det F's sign, as the export writes them."""
    import warp as wp  # noqa: PLC0415

    from warp_esph.export import frame_arrays_to_mesh  # noqa: PLC0415

    b = SceneBuilder(spacing=0.02)
    b.add_particles(np.array([[0.0, 0.1, 0.0], [0.02, 0.1, 0.0], [0.04, 0.1, 0.0]]), Material.preset("dough"))
    m = b.finalize(dtype=getattr(wp, dtype))
    # A rotation times diag(1.3, 0.9, -0.6) (inverted), its sound twin diag(1.3, 0.9, 0.6), and I.
    c, s_ = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    F = np.stack([R @ np.diag([1.3, 0.9, -0.6]), R @ np.diag([1.3, 0.9, 0.6]), np.eye(3)])
    state = m.state()
    state.F.assign(F.astype(m.types.np_dtype))
    path = tmp_path / "inv.usdc"
    with UsdWriter(path, m) as w:
        w.write_frame(0, state)
    a = UsdFrames(str(path)).arrays(0)
    want = np.array([[1.3, 0.9, -0.6], [1.3, 0.9, 0.6], [1.0, 1.0, 1.0]])
    np.testing.assert_allclose(a["singular_values"], want, rtol=1e-6)
    assert np.sign(np.linalg.det(F)).tolist() == np.sign(a["singular_values"].prod(axis=1)).tolist()
    np.testing.assert_array_equal(frame_arrays_to_mesh(a, "vtu").point_data["singular_values"], a["singular_values"])


def test_appending_with_a_model_of_the_other_precision_is_refused_naming_both(tmp_path):
    """A model of the other precision appended to a run's file wrote its frames in its own:
    a float64 model's double positions after a float32 file's (read back float32 up to the
    resume, float64 after), a float32 model's rounded ones in a file whose warp_esph:dtype
    says float64. It is refused before anything is written, naming both precisions."""
    import warp as wp  # noqa: PLC0415

    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.05, 0.0), (0.06, 0.06, 0.06), Material(mu=2e3, lam=3e3))
    models = {name: b.finalize(dtype=getattr(wp, name)) for name in ("float32", "float64")}
    for written, other in (("float32", "float64"), ("float64", "float32")):
        path = tmp_path / f"{written}.usdc"
        with UsdWriter(path, models[written], 50.0) as w:
            w.write_frame(0, models[written].state())
        before = path.read_bytes()
        with pytest.raises(ValueError, match=rf"^cannot append to .*{written}\.usdc: it holds a {written} run's frames "
                                             rf"\(warp_esph:dtype\) and the model is {other}; a file keeps one precision: "
                                             rf"finalize the model with dtype=wp\.{written} to continue it, or write a new file$"):
            UsdWriter(path, models[other], 50.0, append=True)
        # The file as it was, and no working copy left beside it.
        assert path.read_bytes() == before and not [f for f in os.listdir(tmp_path) if f.startswith(".")]
        # The model of the file's own precision still continues it.
        with UsdWriter(path, models[written], 50.0, append=True) as w:
            w.write_frame(1, models[written].state())
        assert open_fresh(path).GetEndTimeCode() == 1


def test_appending_with_a_model_without_a_body_the_file_holds_is_refused_naming_it(tmp_path):
    """A model of the file's first body alone continued a file of two: the second body's
    samples from the resume on were dropped and none written, so the file held it up to
    frame 1 only (rendered and exported without it, refused as a fit target) while its
    warp_esph:particle_count still said 16 for frames of 8. Refused before anything is
    written, naming the body; the model of the file's scene still continues it."""
    def scene(bodies):
        b = SceneBuilder(spacing=0.04)
        for name, x in (("a", 0.0), ("b", 0.5))[:bodies]:
            b.add_box((x, 0.1, 0.0), (0.08, 0.08, 0.08), Material.preset("dough"), name=name)
        return b.finalize()

    both, first = scene(2), scene(1)
    path = tmp_path / "two.usdc"
    with UsdWriter(path, both, 24.0) as w:
        for frame in range(3):
            w.write_frame(frame, both.state())
    before = path.read_bytes()
    with pytest.raises(ValueError) as e:
        UsdWriter(path, first, 24.0, append=True)
    assert str(e.value) == (f"cannot append to {path}: it holds body 'b' (8 particles, Points prim /World/b), which the "
                            "model has not; a file continues the scene that wrote it: append with that scene's model, "
                            "or write a new file")
    assert path.read_bytes() == before and not [f for f in os.listdir(tmp_path) if f.startswith(".")]
    with UsdWriter(path, both, 24.0, append=True) as w:
        w.write_frame(2, both.state())
        w.write_frame(3, both.state())
    stage = open_fresh(path)
    for name in ("a", "b"):
        assert stage.GetPrimAtPath(f"/World/{name}").GetAttribute("points").GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]


def test_a_foreign_files_surfaces_colliders_and_tools_are_read_in_metres_and_world_coordinates_as_its_particles(tmp_path):
    """Another program's copy of a run's file, in centimetres (metersPerUnit 0.01) under a
    /World moved 50 cm up and turned 90 degrees about y: its particles were read in metres and
    world coordinates, but its surfaces, colliders and tools in the file's own units and
    frame (100 x too large, and elsewhere). Every geometry is now read through the same
    transform."""
    import shutil

    from pxr import Gf

    from warp_esph.render import tool_mesh
    from warp_esph.usd import UsdFrames, quat_matrix

    b = SceneBuilder(spacing=0.04)
    b.add_box((0.0, 0.12, 0.0), (0.16, 0.12, 0.12), Material.preset("dough"), name="dough")
    b.add_ground()
    b.add_sphere_collider((0.0, -0.5, 1.0), 0.2)
    b.add_box_collider((1.0, -0.5, 0.0), (0.1, 0.2, 0.3))
    b.add_tool("box", half_extents=(0.05, 0.02, 0.03), position=(0.3, 0.6, 0.1), orientation=(0.0, 0.3826834, 0.0, 0.9238795))
    model = b.finalize()
    ours, theirs = tmp_path / "run.usda", tmp_path / "cm.usda"
    simulate(model, 1, fps=30, writer=UsdWriter(ours, model, 30, surface=True), progress=False)
    shutil.copy(ours, theirs)
    stage = Usd.Stage.Open(str(theirs))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    world = UsdGeom.Xformable(stage.GetPrimAtPath("/World"))
    world.AddTranslateOp().Set(Gf.Vec3d(0.0, 50.0, 0.0))
    world.AddRotateYOp().Set(90.0)
    stage.Save()
    A = 0.01 * np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # x_world = 0.01 x R_y(90) + (0, 0.5, 0)

    def moved(x):
        return np.asarray(x, dtype=np.float64) @ A + [0.0, 0.5, 0.0]

    run, cm = UsdFrames(ours), UsdFrames(theirs)
    np.testing.assert_allclose(cm.arrays(1)["points"], moved(run.arrays(1)["points"]), atol=1e-12)
    np.testing.assert_allclose(cm.surface(1, 0)[0], moved(run.surface(1, 0)[0]), atol=1e-7)
    ground, sphere, box = cm.colliders
    assert ground.normal == pytest.approx([0.0, 1.0, 0.0]) and ground.offset == pytest.approx(0.5)
    assert ground.center == pytest.approx(moved(run.colliders[0].center))
    assert sphere.center == pytest.approx(moved([0.0, -0.5, 1.0]), abs=1e-12) and sphere.size == pytest.approx([0.002] * 3)
    assert box.center == pytest.approx(moved([1.0, -0.5, 0.0]), abs=1e-12) and box.size == pytest.approx([0.003, 0.002, 0.001])
    shapes = []
    for data in (run, cm):
        p, q = data.tools[0].pose(1)
        shapes.append(tool_mesh(data.tools[0])[0] @ quat_matrix(q).T + p)
    np.testing.assert_allclose(shapes[1], moved(shapes[0]), atol=1e-9)


def test_a_foreign_plane_colliders_normal_and_offset_are_in_its_parents_frame_as_all_collider_data(tmp_path):
    """A copy of a run's file whose ground prim was given its own transform (moved 0.3 m up and
    tilted): the plane's normal and offset, custom data as the sphere's and box's centre, were
    moved by it too, though all collider data is in the prim's parent's frame (a run writes the
    plane prim without a transform; the sphere's own translate repeats its centre). The plane
    stays where its data puts it, and its quad is drawn on it."""
    import shutil

    from pxr import Gf

    from warp_esph.usd import UsdFrames

    b = SceneBuilder(spacing=0.04)
    b.add_box((0.0, 0.12, 0.0), (0.08, 0.08, 0.08), Material.preset("dough"), name="dough")
    b.add_ground(height=0.02)
    model = b.finalize()
    ours, theirs = tmp_path / "run.usda", tmp_path / "moved.usda"
    simulate(model, 1, fps=30, writer=UsdWriter(ours, model, 30), progress=False)
    shutil.copy(ours, theirs)
    stage = Usd.Stage.Open(str(theirs))
    ground = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Colliders/plane_0"))
    ground.AddTranslateOp().Set(Gf.Vec3d(0.0, 0.3, 0.0))
    ground.AddRotateXOp().Set(20.0)
    stage.Save()
    plane = UsdFrames(theirs).colliders[0]
    assert plane.normal == pytest.approx([0.0, 1.0, 0.0], abs=1e-12) and plane.offset == pytest.approx(0.02, abs=1e-12)
    assert float(plane.normal @ plane.center) == pytest.approx(0.02, abs=1e-9)


def test_velocities_under_a_time_sampled_rotation_carry_x_dA_dt():
    """A body turned 5 degrees a frame (24 fps) by its own time-sampled rotateY, its local
    points at rest: the velocities read are x dA/dt, the rate of the positions read, with the
    transform's rate over half a frame either side (within 1e-3 of the rotation's derivative)
    and one-sided at the first and last frame (the secant over half a frame)."""
    import math
    import tempfile

    from pxr import Gf, Vt

    from warp_esph.usd import UsdFrames

    p = np.random.default_rng(2).uniform(-10.0, 10.0, (5, 3))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "turning.usda")
        stage = Usd.Stage.CreateNew(path)
        stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
        UsdGeom.SetStageMetersPerUnit(stage, 0.01)
        stage.SetTimeCodesPerSecond(24)
        cloud = UsdGeom.Points.Define(stage, "/World/cloud")
        turn = cloud.AddRotateYOp()
        for f in range(4):
            cloud.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p.astype(np.float32)), float(f))
            cloud.GetVelocitiesAttr().Set(Vt.Vec3fArray([Gf.Vec3f(0.0, 0.0, 0.0)] * 5), float(f))
            turn.Set(5.0 * f, float(f))
        stage.Save()
        data = UsdFrames(path)
        arrays = [data.arrays(f) for f in range(4)]

    def turned(deg):  # x_world = 0.01 x R_y(deg)^T, row vectors
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        return 0.01 * p @ np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])

    omega = math.radians(5.0) * 24.0
    for f in (1, 2):
        c, s = math.cos(math.radians(5.0 * f)), math.sin(math.radians(5.0 * f))
        exact = 0.01 * omega * p @ np.array([[-s, 0.0, -c], [0.0, 0.0, 0.0], [c, 0.0, -s]])
        np.testing.assert_allclose(arrays[f]["points"], turned(5.0 * f), atol=1e-9)
        np.testing.assert_allclose(arrays[f]["velocities"], exact, rtol=0, atol=1e-3 * np.abs(exact).max())
    np.testing.assert_allclose(arrays[0]["velocities"], (turned(2.5) - turned(0.0)) * 48.0, atol=1e-9)
    np.testing.assert_allclose(arrays[3]["velocities"], (turned(15.0) - turned(12.5)) * 48.0, atol=1e-9)


def test_a_file_system_without_flock_is_written_unguarded_not_refused(model, tmp_path, monkeypatch):
    """Only a lock another writer holds refuses the file: a file system without flock (ENOLCK,
    some network mounts) must not read as 'another writer is writing it'."""
    import errno
    import fcntl

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with UsdWriter(tmp_path / "nfs.usdc", model, 30) as w:
        w.write_frame(0, model.state())
    assert sorted(os.listdir(tmp_path)) == ["nfs.usdc"]


def test_another_users_lock_file_left_by_a_killed_run_does_not_refuse_the_output(model, tmp_path, monkeypatch):
    """A killed run leaves its lock file; in a shared folder it is another user's (mode 0644),
    which this user cannot open for writing. The lock was refused as 'could not create
    .shared.usdc.lock: Permission denied', though nobody held it and the output is writable
    here: flock needs no write access, and the stale file is replaced by this writer's own
    (a writer refused meanwhile is told this process, not the killed one)."""
    lock = tmp_path / ".shared.usdc.lock"
    lock.write_text("4821")
    real_open = os.open

    def as_another_user(path, flags, *a, **k):  # the tests may run as root, who may open anything
        foreign = os.fspath(path) == str(lock) and lock.exists() and lock.read_text() == "4821"
        if foreign and flags & (os.O_RDWR | os.O_WRONLY):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real_open(path, flags, *a, **k)

    monkeypatch.setattr(os, "open", as_another_user)
    with UsdWriter(tmp_path / "shared.usdc", model, 30) as w:
        w.write_frame(0, model.state())
        with pytest.raises(ValueError, match=rf"another writer of this process \({os.getpid()}\) is writing it"):
            UsdWriter(tmp_path / "shared.usdc", model, 30)  # still held while it writes
    assert sorted(os.listdir(tmp_path)) == ["shared.usdc"]


def test_a_usd_file_records_every_frame_from_which_a_callback_switched_the_solver(tmp_path):
    """``fit="auto"`` resolves by the material values, so a callback that makes an elastic
    body plastic after frame 1 switches the rest-configuration model to the incremental one
    from frame 2: ``warp_esph:solver_frames`` says so. Before, the file recorded only the
    run's start (the rest model), for frames the incremental composition wrote. A resumed run
    rewrites the entries from its start frame on; one made elastic again after its body flowed
    keeps the incremental composition (``State.flowed``), with the elastic parameters' fit and
    control, and says so from its first frame."""
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.06, 0.0), (0.06, 0.06, 0.06), Material(mu=2e3, lam=3e3, density=1000.0))
    b.add_ground(friction=0.5)
    model = b.finalize()
    solver = Solver(model)

    def plastic(frame, state):
        if frame == 1:
            model.set_material(0, model.materials[0].replace(yield_stress=100.0, flow_rate=10.0))

    out = tmp_path / "run.usda"
    end = simulate(model, 3, solver=solver, writer=UsdWriter(str(out), model), progress=False, callback=plastic)
    data = open_fresh(out).GetRootLayer().customLayerData
    assert data["warp_esph:solver_frames"] == "0: rest curvature_corrected c=0.05; 2: incremental linear c=0"
    assert (data["warp_esph:resolved_fit"], data["warp_esph:rest_model"]) == ("curvature_corrected", True)
    # Elastic again from frame 3 on, appended: the body flowed, so it is not handed over to the
    # rest model.
    assert end.alpha.numpy().max() > 0.0
    model.set_material(0, model.materials[0].replace(yield_stress=float("inf"), flow_rate=0.0))
    simulate(model, 2, solver=solver, state=end, start_frame=3,
             writer=UsdWriter(str(out), model, append=True), progress=False)
    data = open_fresh(out).GetRootLayer().customLayerData
    assert data["warp_esph:solver_frames"] == (
        "0: rest curvature_corrected c=0.05; 2: incremental linear c=0; 3: incremental curvature_corrected c=0.05")
    assert (data["warp_esph:resolved_fit"], data["warp_esph:rest_model"]) == ("curvature_corrected", False)


def test_a_run_resumed_before_a_switch_by_the_solver_before_it_drops_the_later_entries(model, tmp_path):
    """``warp_esph:solver_frames`` drops an earlier run's entries at or after a resumed run's
    frames. A resume at frame 1 whose solver ran as the entry before it (frame 0's) returned
    early, keeping ``"2: incremental linear c=0"`` for frames the resumed run wrote with the
    rest model."""
    class Ran:  # what Solver.label says, without a model to switch
        def __init__(self, label):
            self.text = label

        def label(self):
            return self.text

    rest, incremental = "rest curvature_corrected c=0.05", "incremental linear c=0"
    writer = UsdWriter(tmp_path / "resumed.usda", model, 30)
    for frame in (-1, 1.5, True):  # int(frame) wrote "-1: ..." and took 1.5 for frame 1
        with pytest.raises(ValueError, match=rf"^frame = {re.escape(repr(frame))} is not allowed: must be an integer >= 0"):
            writer.record_solver(Ran(rest), frame)
    for frame, label in ((0, rest), (1, rest), (2, incremental)):
        writer.record_solver(Ran(label), frame)
    key = "warp_esph:solver_frames"
    assert writer._stages[0].GetRootLayer().customLayerData[key] == f"0: {rest}; 2: {incremental}"
    for frame in (1, 2, 3):  # resumed from frame 1, the rest model throughout
        writer.record_solver(Ran(rest), frame)
        assert writer._stages[0].GetRootLayer().customLayerData[key] == f"0: {rest}"
    writer.close()


def test_a_file_written_before_solver_frames_has_the_key_start_at_the_resume_frame(model, tmp_path):
    """A file written before ``warp_esph:solver_frames`` existed (frames, no key), appended
    to from frame 2: the key starts at frame 2, the earlier frames without an entry, as
    docs/cli.md says (not "0: ...", which would claim a solver for frames it never saw)."""
    class Ran:
        def label(self):
            return "incremental linear c=0"

    path = tmp_path / "old.usda"
    state = model.state()
    with UsdWriter(path, model, 30) as w:
        for frame in range(4):
            w.write_frame(frame, state)
    with UsdWriter(path, model, 30, append=True) as w:
        for frame in (2, 3):
            w.record_solver(Ran(), frame)
            w.write_frame(frame, state)
    assert open_fresh(path).GetRootLayer().customLayerData["warp_esph:solver_frames"] == "2: incremental linear c=0"


def test_a_writer_whose_record_solver_takes_the_solver_alone_is_told_it_at_the_start(model):
    """``simulate`` told a writer's ``record_solver(solver)`` the solver at the start; once it
    passed the frame too, such a writer failed at the first frame with a TypeError. It is
    told at the start only; one that takes the frame is told before each frame too, also
    where ``frame`` is keyword-only (bound positionally, that one was told at the start only)."""
    class Frames:
        def __init__(self):
            self.told, self.written = [], []

        def write_frame(self, frame, state):
            self.written.append(frame)

    class Alone(Frames):
        def record_solver(self, solver):
            self.told.append(solver.label())

    class Each(Frames):
        def record_solver(self, solver, frame=None):
            self.told.append(frame)

    class Keyword(Frames):
        def record_solver(self, solver, *, frame=None):
            self.told.append(frame)

    alone, each, keyword = Alone(), Each(), Keyword()
    for writer in (alone, each, keyword):
        simulate(model, 2, fps=30, writer=writer, progress=False)
    assert alone.written == each.written == keyword.written == [0, 1, 2]
    assert len(alone.told) == 1 and alone.told[0].startswith(("rest ", "incremental "))
    assert each.told == keyword.told == [None, 0, 1, 2]


def test_a_damaged_collider_whose_bad_value_holds_the_files_path_is_named_as_every_damage(tmp_path):
    """The reader let a ValueError out unchanged where its text held the file's path (meant for
    a message already naming the file, which nothing in the collider and tool readers raises):
    a plane offset holding that path as text failed as float()'s bare 'could not convert string
    to float', naming no damage. Every damage is now said the one way."""
    from warp_esph.usd import UsdFrames

    path = tmp_path / "damaged.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(30.0)
    UsdGeom.Points.Define(stage, "/World/blob").GetPointsAttr().Set([(0.0, 0.1, 0.0), (0.02, 0.1, 0.0)], Usd.TimeCode(0.0))
    plane = UsdGeom.Mesh.Define(stage, "/World/Colliders/plane_0")
    plane.GetPointsAttr().Set([(-1.0, 0.0, -1.0), (1.0, 0.0, -1.0), (1.0, 0.0, 1.0), (-1.0, 0.0, 1.0)])
    prim = plane.GetPrim()
    prim.SetCustomDataByKey("warp_esph:collider", "plane")
    prim.SetCustomDataByKey("warp_esph:normal", (0.0, 1.0, 0.0))
    prim.SetCustomDataByKey("warp_esph:offset", str(path))
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"^cannot read .*damaged\.usda: a collider or tool is damaged \(could not convert "):
        UsdFrames(path)


def test_each_bodys_material_is_recorded_whole_and_a_file_without_the_later_fields_is_read_and_appended(tmp_path):
    """Each body's prim records every field of its Material (``warp_esph:material:<field>``),
    the settings that change the forces among them (``pair_repulsion``, ``clamp_pressure``,
    ``pressure_force``), so that the file says what ran; a file written when fewer were
    recorded (those three keys removed) is still read and appended to."""
    import dataclasses

    mat = Material(density=1000.0, mu=1.0e3, lam=1.5e3, pressure_force="spiky", clamp_pressure=False, pair_repulsion=2.0)
    b = SceneBuilder(spacing=0.04)
    b.add_box((0.0, 0.12, 0.0), (0.16, 0.12, 0.12), mat, name="block")
    b.add_ground()
    m = b.finalize()
    path = tmp_path / "out.usda"
    simulate(m, 1, fps=30, writer=UsdWriter(path, m, 30), progress=False)
    stage = open_fresh(path)
    prim = stage.GetPrimAtPath("/World/block")
    recorded = dict(prim.GetCustomDataByKey("warp_esph:material"))
    assert recorded == {f.name: getattr(mat, f.name) for f in dataclasses.fields(mat)}
    assert recorded["pair_repulsion"] == 2.0 and recorded["clamp_pressure"] is False
    assert recorded["pressure_force"] == "spiky"
    # An older file: the three keys absent.
    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload(force=True)
    old = Usd.Stage.Open(layer)
    for key in ("pair_repulsion", "clamp_pressure", "pressure_force"):
        old.GetPrimAtPath("/World/block").ClearCustomDataByKey(f"warp_esph:material:{key}")
    layer.Save()
    assert "pair_repulsion" not in open_fresh(path).GetPrimAtPath("/World/block").GetCustomDataByKey("warp_esph:material")
    assert len(UsdFrames(str(path)).particles(1)["points"]) == m.particle_count
    with UsdWriter(path, m, 30, append=True) as w:
        w.write_frame(2, m.state())
    assert len(UsdFrames(str(path)).particles(2)["points"]) == m.particle_count


def test_colliders_moved_in_place_are_exported_where_the_kernels_run_them(tmp_path):
    """docs/errors.md moves a static collider by writing its arrays
    (``model.plane_offset.assign``); the export drew it from ``model.planes``, which only records
    the build: a ground raised to 0.05 m was exported at 0, a sphere and a box where they were
    built. Each is now exported as its arrays hold it (``Model.static_colliders``)."""
    b = SceneBuilder(spacing=0.04)
    b.add_box((0.0, 0.12, 0.0), (0.08, 0.08, 0.08), Material.preset("dough"))
    b.add_ground()
    b.add_sphere_collider((0.0, -0.5, 1.0), 0.2)
    b.add_box_collider((1.0, -0.5, 0.0), (0.1, 0.2, 0.3))
    model = b.finalize()
    model.plane_offset.assign(np.array([0.05], dtype=np.float32))
    model.sphere_radius.assign(np.array([0.25], dtype=np.float32))
    model.box_center.assign(np.array([(1.5, -0.5, 0.0)], dtype=np.float32))
    path = tmp_path / "moved.usda"
    writer = UsdWriter(path, model, 30)
    writer.write_frame(0, model.state())
    writer.close()
    ground, sphere, box = UsdFrames(path).colliders
    assert ground.offset == 0.05 and ground.normal == pytest.approx([0.0, 1.0, 0.0])
    assert sphere.size == pytest.approx([0.25] * 3, abs=0.0) and sphere.center == pytest.approx([0.0, -0.5, 1.0])
    assert box.center == pytest.approx([1.5, -0.5, 0.0], abs=0.0) and box.size == pytest.approx([0.1, 0.2, 0.3])
