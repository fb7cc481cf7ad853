"""The ``warp-esph`` command line, in-process through ``main`` and as a subprocess."""

import functools
import json
import os
import pathlib
import re
import shutil
import signal
import stat
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from run_files import box_on_ground, frames_in, open_fresh, refused_run
from warp_esph.sim import solver as solver_module
from warp_esph.cli import main
from warp_esph.scenes import SCENES, get_scene
from warp_esph.simulate import resolve_timestep

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY = ["--scale", "0.3", "--frames", "2", "--no-progress"]

GOOD_TOML = box_on_ground("tiny", 2, "soft", "dough", "1.5e4")


def log_frames(usd_path) -> dict[str, list[int]]:
    """The frames of each row name in the force log beside ``usd_path``, read from the CSV and
    checked against the JSON (the two must hold the same rows)."""
    import csv  # noqa: PLC0415
    import json  # noqa: PLC0415

    out = {}
    with open(f"{usd_path}_tools.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        out.setdefault(r["tool"], []).append(int(r["frame"]))
    with open(f"{usd_path}_tools.json") as fh:
        data = json.load(fh)["rows"]
    assert [(r["tool"], r["frame"]) for r in data] == [(r["tool"], int(r["frame"])) for r in rows]
    assert all(np.isfinite(r["force"]).all() and np.isfinite(r["torque"]).all() for r in data)
    return out


def assert_one_line_error(err: str, *needles: str):
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one stderr line, got: {err!r}"
    assert lines[0].startswith("warp-esph: error: "), lines[0]
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"


def test_run_default_scene_in_process(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", *TINY]) == 0
    out, err = capsys.readouterr()
    path = tmp_path / "dough_drop.usdc"  # default scene, default output name, current folder
    assert path.exists()
    assert str(path) in out and "3 frames" in out
    assert " particles, 1 body, 2 frames at 30 fps" in out, out  # the banner had said '1 bodies'
    for name in solver_module.GUARD_NAMES:
        assert f"{name}=" in out
    assert "warning" not in err and "Traceback" not in err
    assert frames_in(path) == [0.0, 1.0, 2.0]
    # The ground's reaction per frame beside the USD (a scene without tools).
    assert sorted(os.listdir(tmp_path)) == ["dough_drop.usdc", "dough_drop.usdc_tools.csv", "dough_drop.usdc_tools.json"]
    assert log_frames(tmp_path / "dough_drop.usdc") == {"plane0": [0, 1, 2]}


def test_a_count_of_one_is_said_in_the_singular(tmp_path, capsys):
    """The commands said '1 frames at 30 fps', 'wrote 1 .vtu files', '1 PNG files', '(1 frames)'
    and '(1 bodies as surfaces)' (checks.plural is the rule: '1 evaluations' read wrong)."""
    usd = tmp_path / "one.usdc"
    assert main(["run", "--scale", "0.3", "--frames", "1", "--no-progress", "--surface", "-o", str(usd)]) == 0
    assert ", 1 body, 1 frame at 30 fps, " in capsys.readouterr().out
    assert main(["export", str(usd), "-o", str(tmp_path / "vtu"), "--frames", "1"]) == 0
    assert capsys.readouterr().out.startswith(f"wrote 1 .vtu file and frames.pvd (open it in ParaView) to {tmp_path / 'vtu'}")
    small = ["--width", "40", "--height", "30", "--frames", "1"]
    assert main(["render", str(usd), "-o", str(tmp_path / "pictures"), *small]) == 0
    assert capsys.readouterr().out.startswith(f"wrote 1 PNG file in {tmp_path / 'pictures'}: 40x30, 64 particles (1 body as "
                                              "surfaces), ")
    assert main(["render", str(usd), "-o", str(tmp_path / "one.gif"), *small]) == 0
    assert capsys.readouterr().out.startswith(f"wrote {tmp_path / 'one.gif'} (1 frame): ")


def test_run_options_and_dt_warning(tmp_path, capsys):
    out_path = tmp_path / "star.usda"
    # 40 steps per frame at fps 10: above the stable step of this scene (2.3 x). Scale 0.5: at
    # TINY's 0.3 the 4 cm star is one particle layer, refused as under-resolved, and its
    # skipped fits let it run at 0.05 s (45 x) without diverging, as it does at 0.5.
    assert main(["run", "star", "-o", str(out_path), "--fps", "10", "--dt", "0.0025", *TINY, "--scale", "0.5"]) == 0
    out, err = capsys.readouterr()
    warnings = [line for line in err.splitlines() if line.startswith("warp-esph: warning:")]
    # The star's tips at scale 0.5 are too narrow for the fit: the run says so too (test_resolution.py).
    warnings = [line for line in warnings if "deformation fit was skipped" not in line]
    assert len(warnings) == 1 and "stability limit" in warnings[0], err
    assert "Traceback" not in err
    assert out_path.read_bytes().startswith(b"#usda")
    stage = open_fresh(out_path)
    assert stage.GetTimeCodesPerSecond() == 10 and stage.GetEndTimeCode() == 2


def test_scenes_lists_every_scene(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert len(lines) == len(SCENES)
    for name, line in zip(SCENES, lines):
        assert line.startswith(name) and len(line.split()) > 2
    assert "(default)" in lines[0]


def test_a_stable_step_too_short_for_a_frame_is_refused_with_the_run_s_options(tmp_path, capsys):
    """Frames of 10000 s at the stable step: the advice was Python's 'give dt or substeps', and
    'warp-esph run' has no substeps; it names the command's options."""
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(tmp_path / "t.usdc"), "--fps", "0.0001",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"warp-esph: error: {tmp_path / 's.toml'}: [scene] the stable step "), err
    assert err.endswith(" needs it: use softer materials, a larger spacing, a higher --fps, or give --dt\n"), err
    assert not (tmp_path / "t.usdc").exists()
    # Where the hourglass control's limit sets the step, its option is named, not a softer material.
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(tmp_path / "t.usdc"), "--fps", "0.0001", "--hourglass", "1000",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "; the hourglass control sets it (the hourglass control's limit at strength c = 1000, " in err
    assert err.endswith(": use a smaller --hourglass (or [solver] hourglass), a larger spacing, a higher --fps, or give "
                        "--dt\n"), err


def test_a_run_of_too_many_steps_is_refused_with_the_run_s_options(tmp_path, capsys):
    """More than 1e10 steps in all: the advice was Python's 'use fewer frames or a larger dt',
    naming no option; it names the command's (--frames, --dt where a dt is given, else --scale,
    whose larger spacing lengthens the stable step), and a scene file's frames by the file."""
    scene = tmp_path / "s.toml"
    output = ["-o", str(tmp_path / "t.usdc"), "--no-progress"]
    for frames, extra, said in (
            ("1000000000", ["--frames", "1000000000"], "--frames = 1000000000 is not allowed: at 11 steps per frame the run "
             "would take 1.1e+10 steps, more than 1e+10; give fewer --frames, or a smaller --scale (a larger spacing, whose "
             "stable step is longer)"),
            ("2", ["--frames", "1000000000", "--fps", "25", "--dt", "0.0001"], "--frames = 1000000000 is not allowed: at 400 steps per "
             "frame the run would take 4e+11 steps, more than 1e+10; give fewer --frames or a larger --dt"),
            ("1000000000", [], f"{scene}: [scene] frames = 1000000000 is not allowed: at 11 steps per frame the run would "
             "take 1.1e+10 steps, more than 1e+10; give fewer --frames, or a smaller --scale (a larger spacing, whose "
             "stable step is longer)")):
        scene.write_text(box_on_ground("tiny", frames, "soft", "dough", "1.5e4"))
        assert main(["run", str(scene), *output, *extra]) == 2
        err = capsys.readouterr().err
        assert err == f"warp-esph: error: {said}\n", err
        assert not (tmp_path / "t.usdc").exists()


def test_toml_scene_file_runs(tmp_path, capsys):
    scene = tmp_path / "tiny.toml"
    scene.write_text(GOOD_TOML)
    out_path = tmp_path / "tiny.usdc"
    assert main(["run", str(scene), "-o", str(out_path), "--no-progress"]) == 0
    assert frames_in(out_path, "/World/box0") == [0.0, 1.0, 2.0]


def test_solver_options_from_scene_file_and_cli(tmp_path, capsys):
    """``[solver]`` in the file runs the corrected fit; ``--solver-fit linear`` overrides it
    (the same frames as the file without ``[solver]``, whose default ``auto`` runs the linear
    fit for this dough); the run record keeps the choice."""
    from warp_esph.checkpoint import read_checkpoint

    falling = GOOD_TOML.replace('material = "soft"', 'material = "soft"\nvelocity = [0.0, -3.0, 0.0]')
    plain, chosen = tmp_path / "plain.toml", tmp_path / "chosen.toml"
    plain.write_text(falling)
    chosen.write_text('[solver]\nfit = "curvature_corrected"\ncontact = "instant"\n' + falling)

    def last_frame(scene, name, *extra):
        out = tmp_path / f"{name}.usdc"
        assert main(["run", str(scene), "-o", str(out), "--no-progress", "--checkpoint-every", "2", *extra]) == 0
        stage = open_fresh(out)
        x = np.array(stage.GetPrimAtPath("/World/box0").GetAttribute("points").Get(2.0))
        return x, read_checkpoint(str(out) + ".checkpoint.npz")[0]["run"]

    x_plain, run_plain = last_frame(plain, "plain")
    x_chosen, run_chosen = last_frame(chosen, "chosen")
    x_back, run_back = last_frame(chosen, "back", "--solver-fit", "linear", "--contact", "continuous")
    # The record keeps the choice as asked: "auto", which runs the linear fit for this dough
    # (a material that can flow), bit for bit as --solver-fit linear (below).
    assert (run_plain["fit"], run_plain["contact_ramp"]) == ("auto", 1.0)  # the continuous contact, the default
    assert (run_chosen["fit"], run_chosen["contact_ramp"]) == ("curvature_corrected", 0.0)
    assert (run_back["fit"], run_back["contact_ramp"]) == ("linear", 1.0)
    assert np.array_equal(x_back, x_plain)
    assert np.abs(x_chosen - x_plain).max() > 1e-4  # the impact bends the surface: the fits differ there
    capsys.readouterr()


def _falling_scenes(tmp_path, solver_table: str):
    """``GOOD_TOML``'s box falling at 3 m/s, as ``plain.toml`` and, with ``solver_table`` before
    it, ``chosen.toml``: ``(plain, chosen, text of plain)``."""
    falling = GOOD_TOML.replace('material = "soft"', 'material = "soft"\nvelocity = [0.0, -3.0, 0.0]')
    plain, chosen = tmp_path / "plain.toml", tmp_path / "chosen.toml"
    plain.write_text(falling)
    chosen.write_text(solver_table + falling)
    return plain, chosen, falling


def _box_frames(out):
    """The box's particle positions in the first five frames of the run written to ``out``."""
    stage = open_fresh(out)
    return [np.array(stage.GetPrimAtPath("/World/box0").GetAttribute("points").Get(float(t))) for t in range(5)]


def _run_four_frames(tmp_path, scene, name, *extra):
    """``warp-esph run SCENE`` for 4 frames (``extra`` after it) into ``tmp_path/name.usdc``."""
    out = tmp_path / f"{name}.usdc"
    assert main(["run", str(scene), "-o", str(out), "--no-progress", "--frames", "4", *extra]) == 0
    return out


def test_hourglass_from_scene_file_cli_and_resume(tmp_path, capsys):
    """``[solver] hourglass = 0.1`` runs the control (other frames than without it);
    ``--hourglass 0`` overrides it (the frames of the file without ``[solver]``); the run
    record keeps the value, and ``--resume`` keeps the run's value even when the scene file
    no longer has it: the resumed run writes the frames of the uninterrupted one."""
    from warp_esph.checkpoint import read_checkpoint

    plain, chosen, falling = _falling_scenes(tmp_path, "[solver]\nhourglass = 0.1\n")
    frames, run = _box_frames, functools.partial(_run_four_frames, tmp_path)

    x_plain = frames(run(plain, "plain"))
    x_chosen = frames(run(chosen, "chosen"))
    x_off = frames(run(chosen, "off", "--hourglass", "0"))
    x_flag = frames(run(plain, "flag", "--hourglass", "0.1"))
    assert all(np.array_equal(a, b) for a, b in zip(x_off, x_plain))
    assert all(np.array_equal(a, b) for a, b in zip(x_flag, x_chosen))
    assert np.abs(x_chosen[-1] - x_plain[-1]).max() > 1e-5
    part = run(chosen, "part", "--frames", "2", "--checkpoint-every", "2")  # the last --frames wins: 2
    ckpt = str(part) + ".checkpoint.npz"
    assert read_checkpoint(ckpt)[0]["run"]["hourglass"] == 0.1
    chosen.write_text(falling)  # the scene now says 0: the resumed run keeps its 0.1
    assert main(["run", "--resume", ckpt, "--frames", "4", "--no-progress"]) == 0
    assert all(np.array_equal(a, b) for a, b in zip(frames(part), x_chosen))
    capsys.readouterr()
    # What the checkpoint's run decides is refused beside --resume, not ignored.
    for extra, named in ((["--hourglass", "0"], "--hourglass = 0 is not allowed"), ([str(plain)], "SCENE = "), (["--dt", "0.007"], "--dt = 0.007")):
        assert main(["run", *extra, "--resume", ckpt, "--frames", "6", "--no-progress"]) == 2
        assert_one_line_error(capsys.readouterr().err, named, "is not allowed with --resume: the checkpoint's run decides it")


def test_hourglass_on_a_material_that_can_flow_is_warned_of_once(tmp_path, capsys):
    """``--hourglass 0.5`` on a dough box ran without a word, though the control pulls a flowed
    body back towards its rest shape (docs/physics.md, "Hourglass modes"); it warns once,
    naming the body, and runs. An elastic box with the control says nothing."""
    for preset, warned in (("dough", True), ("rubber", False)):
        scene = tmp_path / f"{preset}.toml"
        scene.write_text(box_on_ground("tiny", 2, "soft", preset, "1.5e4"))
        capsys.readouterr()
        assert main(["run", str(scene), "-o", str(tmp_path / f"{preset}.usdc"), "--hourglass", "0.5", "--no-progress"]) == 0
        err = capsys.readouterr().err
        lines = [line for line in err.splitlines() if "warning" in line]
        if warned:
            assert lines == ["warp-esph: warning: the hourglass control (strength c = 0.5) runs on bodies whose material "
                             "can flow plastically ('box0': a finite yield_stress and flow_rate > 0): it measures the "
                             "motion against the rest positions, so it pulls a flowed body back towards its rest shape "
                             "and holds its flow back; it is for elastic solids: leave it off (hourglass = 0, what "
                             "fit = 'auto' runs for them)"], err
        else:
            assert lines == [], err


def test_fit_weight_from_scene_file_cli_and_resume(tmp_path, capsys):
    """``[solver] fit_weight`` naming the weight that is not the default changes the frames of a
    deforming run; ``--fit-weight`` naming the default over it gives the frames of the file
    without it, bit for bit; the run record and the USD metadata keep the weight, ``--resume``
    keeps the run's, and refuses it given again."""
    from warp_esph.checkpoint import read_checkpoint
    from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS

    other = next(w for w in FIT_WEIGHTS if w != DEFAULT_FIT_WEIGHT)
    plain, chosen, falling = _falling_scenes(tmp_path, f'[solver]\nfit_weight = "{other}"\n')
    frames, run = _box_frames, functools.partial(_run_four_frames, tmp_path)

    x_plain = frames(run(plain, "plain"))
    chosen_out = run(chosen, "chosen")
    x_chosen = frames(chosen_out)
    assert open_fresh(chosen_out).GetRootLayer().customLayerData["warp_esph:fit_weight"] == other
    x_back = frames(run(chosen, "back", "--fit-weight", DEFAULT_FIT_WEIGHT))
    assert all(np.array_equal(a, b) for a, b in zip(x_back, x_plain))
    assert np.abs(x_chosen[-1] - x_plain[-1]).max() > 1e-6
    part = run(chosen, "part", "--frames", "2", "--checkpoint-every", "2")
    ckpt = str(part) + ".checkpoint.npz"
    assert read_checkpoint(ckpt)[0]["run"]["fit_weight"] == other
    chosen.write_text(falling)  # the scene now names no weight: the resumed run keeps its own
    assert main(["run", "--resume", ckpt, "--frames", "4", "--no-progress"]) == 0
    assert all(np.array_equal(a, b) for a, b in zip(frames(part), x_chosen))
    capsys.readouterr()
    assert main(["run", "--fit-weight", DEFAULT_FIT_WEIGHT, "--resume", ckpt, "--frames", "6", "--no-progress"]) == 2
    assert_one_line_error(capsys.readouterr().err, f"--fit-weight = '{DEFAULT_FIT_WEIGHT}'", "is not allowed with --resume")


def test_a_checkpoint_whose_run_predates_the_fit_weight_resumes_on_poly6(tmp_path, capsys):
    """A run record written before ``fit_weight`` existed has none, and its run was poly6's
    (then the only weight). Since the biweight became the default (2026-12-06) such a
    checkpoint resumed on the scene's weight, the biweight, whose fingerprint is another's:
    refused as "written for another scene", with ``--fit-weight`` refused beside ``--resume``,
    so it could not be resumed at all. It resumes on poly6: the frames of the uninterrupted
    poly6 run."""
    from warp_esph import checkpoint

    plain, chosen, falling = _falling_scenes(tmp_path, '[solver]\nfit_weight = "poly6"\n')
    x_whole = _box_frames(_run_four_frames(tmp_path, chosen, "whole"))
    part = _run_four_frames(tmp_path, chosen, "part", "--frames", "2", "--checkpoint-every", "2")
    ckpt = pathlib.Path(str(part) + ".checkpoint.npz")
    meta, arrays = checkpoint.read_checkpoint(ckpt)
    del meta["run"]["fit_weight"]  # as the run record was before the option
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    with open(ckpt, "wb") as f:
        np.savez(f, **arrays)
    chosen.write_text(falling)  # and its scene named no weight
    assert main(["run", "--resume", str(ckpt), "--frames", "4", "--no-progress"]) == 0, capsys.readouterr().err
    assert all(np.array_equal(a, b) for a, b in zip(_box_frames(part), x_whole))


RESTING_TOML = textwrap.dedent(
    """
    [scene]
    spacing = 0.02
    frames = 20
    fps = 50

    [materials.gel]
    E = 1.0e5
    nu = 0.3
    density = 1000.0
    viscosity = 2.0

    [[bodies]]
    shape = "box"
    name = "block"
    material = "gel"
    center = [0.2, 0.03, -0.1]
    size = [0.06, 0.06, 0.06]

    [[colliders]]
    type = "ground"
    height = 0.01
    """
)


def test_run_writes_the_static_colliders_reaction_rows_and_usd_attributes(tmp_path, capsys):
    """A 3 x 3 x 3 block whose bottom layer starts on the ground (y = 0.01), off the origin,
    for 0.4 s (float64): each frame's ``plane0`` row of ``<output>_tools.csv`` is the momentum
    balance over the frame, ``(P_k - P_(k-1)) / T - M g``, from the USD velocities; once the
    block has settled the rows carry its weight straight up, with the torque of the weight
    about the plane's reference point (0, 0.01, 0); the USD collider prim holds the same
    force as time-sampled attributes."""
    import csv  # noqa: PLC0415

    from warp_esph.scenes import load_scene_file  # noqa: PLC0415

    scene = tmp_path / "resting.toml"
    scene.write_text(RESTING_TOML)
    out = tmp_path / "rest.usdc"
    assert main(["run", str(scene), "-o", str(out), "--dtype", "float64", "--no-progress"]) == 0
    assert "reaction forces (static colliders)" in capsys.readouterr().out
    with open(f"{out}_tools.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["tool"] for r in rows] == ["plane0"] * 21 and [int(r["frame"]) for r in rows] == list(range(21))
    force = np.array([[float(r[k]) for k in ("fx", "fy", "fz")] for r in rows])
    torque = np.array([[float(r[k]) for k in ("tx", "ty", "tz")] for r in rows])
    np.testing.assert_array_equal([[float(r[k]) for k in ("px", "py", "pz")] for r in rows[:1]], [[0.0, 0.01, 0.0]])
    # A float64 run's CSV holds its values to the last bit, as its JSON does (9 digits rounded them).
    with open(f"{out}_tools.json") as fh:
        doc = json.load(fh)
    assert [float(r["time"]) for r in rows] == [r["time"] for r in doc["rows"]]
    np.testing.assert_array_equal(force, [r["force"] for r in doc["rows"]])

    model = load_scene_file(scene).builder.finalize()
    mass = model.particle_mass.numpy().astype(np.float64)
    M, g, T = mass.sum(), np.array(model.gravity), 1.0 / 50.0
    stage = open_fresh(out)
    points = stage.GetPrimAtPath("/World/block")
    P = np.array([(mass[:, None] * np.array(points.GetAttribute("velocities").Get(float(k)), dtype=np.float64)).sum(axis=0)
                  for k in range(21)])
    balance = (P[1:] - P[:-1]) / T - M * g
    print(f"weight {M * 9.81:.5f} N; frame 1 {force[1]}, balance {balance[0]}; late mean {force[11:].mean(axis=0)}")
    assert np.all(force[0] == 0.0)  # frame 0 has no preceding frame
    assert force[1, 1] > 0.5 * M * 9.81  # it is in contact from the start
    np.testing.assert_allclose(force[1:], balance, rtol=0.0, atol=1e-5 * M * 9.81)  # float32 velocities in the USD
    weight_up = np.array([0.0, M * 9.81, 0.0])
    late = force[11:].mean(axis=0)
    np.testing.assert_allclose(late, weight_up, atol=0.01 * M * 9.81)
    lever = np.array(points.GetAttribute("points").Get(20.0), dtype=np.float64).mean(axis=0) - [0.0, 0.01, 0.0]
    np.testing.assert_allclose(torque[11:].mean(axis=0), np.cross(lever, late), atol=1e-3 * M * 9.81 * np.linalg.norm(lever))
    prim = stage.GetPrimAtPath("/World/Colliders/plane_0")
    assert prim.GetCustomDataByKey("warp_esph:collider_name") == "plane0"
    attr = prim.GetAttribute("warp_esph:reaction_force")
    assert attr.GetTimeSamples() == [float(k) for k in range(21)]
    usd_late = np.array([attr.Get(float(k)) for k in range(11, 21)])  # the frame's last step, not the mean
    np.testing.assert_allclose(usd_late.mean(axis=0), weight_up, atol=0.05 * M * 9.81)


def test_resumed_run_keeps_and_continues_the_force_log(tmp_path, capsys):
    """A run stopped after frame 3 with a checkpoint at frame 2, then resumed to frame 6:
    the force log holds every frame once, bit for bit the uninterrupted run's (the rows the
    stopped run finished up to the checkpoint are kept, the later ones recomputed)."""
    scene = tmp_path / "resting.toml"
    scene.write_text(RESTING_TOML.replace("frames = 20", "frames = 6"))
    whole, part = tmp_path / "whole.usdc", tmp_path / "part.usdc"
    assert main(["run", str(scene), "-o", str(whole), "--no-progress"]) == 0
    assert main(["run", str(scene), "-o", str(part), "--no-progress", "--frames", "3", "--checkpoint-every", "2"]) == 0
    assert log_frames(part) == {"plane0": [0, 1, 2, 3]}
    capsys.readouterr()
    assert main(["run", "--resume", f"{part}.checkpoint.npz", "--frames", "6", "--no-progress"]) == 0
    # The file's frames, and those this run wrote (from the checkpoint's frame on).
    assert f"wrote {part}: frames 0..6 (2..6 by this run)," in capsys.readouterr().out
    assert log_frames(part) == {"plane0": list(range(7))}
    with open(f"{part}_tools.csv") as a, open(f"{whole}_tools.csv") as b:
        assert a.read() == b.read()
    capsys.readouterr()


def test_json_nested_too_deeply_is_refused_by_name(tmp_path):
    from warp_esph import checks

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(ValueError, match=r"--experiments .*deep\.json cannot be read: arrays or objects nested too deeply"):
        checks.json_file("--experiments", deep)


def test_an_experiments_or_camera_json_saved_with_a_byte_order_mark_is_read(tmp_path):
    """Windows' Notepad saves UTF-8 with a byte-order mark, which json refused: '--experiments
    e.json is not valid JSON: Unexpected UTF-8 BOM (decode using utf-8-sig)', advice for
    Python code, not for the file's author. It is read past, as the CSV targets' is; text
    in UTF-8 (a scene's name with an accent) is read as UTF-8 whatever the locale."""
    from warp_esph import checks

    doc = [{"scene": "pâte.toml", "target": "t.npz"}]
    path = tmp_path / "e.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(doc, ensure_ascii=False).encode("utf-8") + b"\r\n")
    assert checks.json_file("--experiments", path) == doc


def test_resuming_beside_a_damaged_force_log_refuses_before_it_loses_the_rows(tmp_path, capsys):
    """The force log of the run to resume is damaged: resuming would rewrite it with the
    resumed frames only. Refused by name before anything is written; the USD keeps its
    frames. Deleted, the log is not there to lose: the run resumes."""
    scene = tmp_path / "resting.toml"
    scene.write_text(RESTING_TOML.replace("frames = 20", "frames = 6"))
    part = tmp_path / "part.usdc"
    assert main(["run", str(scene), "-o", str(part), "--no-progress", "--frames", "3", "--checkpoint-every", "2"]) == 0
    log = tmp_path / "part.usdc_tools.json"
    log.write_text('{"rows": [')
    before = part.read_bytes()
    capsys.readouterr()
    assert main(["run", "--resume", f"{part}.checkpoint.npz", "--frames", "6", "--no-progress"]) == 2
    assert_one_line_error(capsys.readouterr().err, "part.usdc_tools.json", "cannot be read", "move it away")
    assert log.read_text() == '{"rows": [' and part.read_bytes() == before
    log.unlink()
    assert main(["run", "--resume", f"{part}.checkpoint.npz", "--frames", "6", "--no-progress"]) == 0
    assert log_frames(part) == {"plane0": list(range(2, 7))}


BAD_TOML = {
    "nested_too_deep": ("a = " + "[" * 3000 + "]" * 3000 + "\n" + GOOD_TOML, ["nested too deeply"]),
    "unknown_key": (GOOD_TOML.replace('shape = "box"', 'shape = "box"\ncolour = "red"'), ["'colour'", "[[bodies]] #1"]),
    "typo_key": (GOOD_TOML.replace("spacing = 0.05", "spaceing = 0.05"), ["'spaceing'", "[scene]", "did you mean 'spacing'"]),
    "typo_table": (GOOD_TOML.replace("[[colliders]]", "[[colliderz]]"), ["'colliderz'", "did you mean 'colliders'"]),
    "wrong_type": (GOOD_TOML.replace("frames = 2", 'frames = "two"'), ["'frames'", "[scene]", "integer"]),
    "wrong_vector": (GOOD_TOML.replace("size = [0.2, 0.15, 0.2]", "size = [0.2, 0.15]"), ["'size'", "3 numbers"]),
    "bad_value": (GOOD_TOML.replace("nu = 0.3", "nu = 0.7"), ["nu = 0.7", "[materials.soft]"]),
    # A softening of 2 mu or more (E = 15 kPa, nu = 0.3: mu = 5769 Pa) ran, its yield stress gone
    # at the first flow (tests/test_units.py, the softening test).
    "hardening_beyond_minus_two_mu": (GOOD_TOML.replace("nu = 0.3", "nu = 0.3\nhardening = -1e30"),
                                      ["[materials.soft]: hardening = -1e+30 is not allowed: must be > -2 mu = -11538.5"]),
    # mu = E / (2 (1 + nu)) = inf was refused as 'mu = inf', a key the file does not hold.
    "young_past_the_floats": (GOOD_TOML.replace("E = 1.5e4", "E = 1e308").replace("nu = 0.3", "nu = -0.9"),
                              ["[materials.soft]: E = 1e+308 and nu = -0.9 are not allowed together",
                               "mu = E / (2 (1 + nu)) = inf"]),
    # ... and E = 1e-320 as 'mu = 3.84383e-321 is not allowed in float32', a key it does not hold either.
    "young_below_the_floats": (GOOD_TOML.replace("E = 1.5e4", "E = 1e-320"),
                               ["[materials.soft]: E = 1e-320 and nu = 0.3 are not allowed together",
                                "mu = E / (2 (1 + nu)) = 3.84383e-321", "give a larger E"]),
    "bad_syntax": (GOOD_TOML.replace("frames = 2", "frames = = 2"), ["invalid TOML", "line"]),
    "bad_material": (GOOD_TOML.replace('material = "soft"', 'material = "sofft"'), ["'sofft'", "did you mean 'soft'"]),
    "bad_fit": ('[solver]\nfit = "quadratic"\n' + GOOD_TOML, ["fit = 'quadratic' in [solver]", "linear, curvature_corrected"]),
    "bad_hourglass": ("[solver]\nhourglass = -0.1\n" + GOOD_TOML, ["'hourglass' in [solver]", "-0.1", ">= 0"]),
    "bad_fit_weight": ('[solver]\nfit_weight = "gauss"\n' + GOOD_TOML, ["fit_weight = 'gauss' in [solver]", "poly6, biweight"]),
    # The name makes the default output file: '../../x' wrote x.usdc two folders up.
    "name_a_path": (GOOD_TOML.replace('name = "tiny"', 'name = "../../x"'), ["[scene] name = '../../x'", "a file name"]),
    "name_empty": (GOOD_TOML.replace('name = "tiny"', 'name = " "'), ["[scene] name = ' '", "not empty"]),
    # A newline in the name made the default output 'ti\nny.usdc' and split every one-line message
    # that names the scene; other control characters (a tab, DEL, ESC) went into it as well.
    "name_newline": (GOOD_TOML.replace('name = "tiny"', 'name = "ti\\nny"'),
                     ["[scene] name = 'ti\\nny' is not allowed", "no control characters"]),
    "name_escape": (GOOD_TOML.replace('name = "tiny"', 'name = "ti\\u001bny"'),
                    ["[scene] name = 'ti\\x1bny' is not allowed", "no control characters"]),
    # So did a newline (or NUL, ESC) in a body's, tool's, pinned set's or material's name and in
    # the description: they reach one-line messages, the force log's rows and the USD file.
    "body_name_newline": (GOOD_TOML.replace('shape = "box"', 'shape = "box"\nname = "a\\nb"'),
                          ["[[bodies]] #1 (shape 'box'): name = 'a\\nb' is not allowed", "one line of text"]),
    "tool_name_escape": (GOOD_TOML + '[[tools]]\nshape = "sphere"\nradius = 0.05\nposition = [2, 2, 2]\nname = "t\\u001b"\n',
                         ["[[tools]] #1 (shape 'sphere'): name = 't\\x1b' is not allowed", "one line of text"]),
    "pin_name_nul": (GOOD_TOML + '[[pins]]\nbody = "box0"\nname = "p\\u0000"\n',
                     ["[[pins]] #1: name = 'p\\x00' is not allowed", "one line of text"]),
    "material_name_newline": (GOOD_TOML + '[materials."a\\nb"]\npreset = "clay"\n',
                              ['[materials."a\\nb"] is not allowed', "one line of text"]),
    "description_newline": (GOOD_TOML.replace('name = "tiny"', 'name = "tiny"\ndescription = """two\nlines"""'),
                            ["[scene] description = 'two\\nlines' is not allowed", "one line of text"]),
    # A bidirectional control (U+202E, right-to-left override; U+2066-U+2069 isolates) or any
    # other invisible format character (Unicode Cf: a zero-width space, joiner) was taken and
    # printed: 'evil\u202etxt.exe' shows as 'evilexe.txt', a name spoofing another.
    "body_name_bidi": (GOOD_TOML.replace('shape = "box"', 'shape = "box"\nname = "evil\\u202etxt.exe"'),
                       ["[[bodies]] #1 (shape 'box'): name = 'evil\\u202etxt.exe' is not allowed",
                        "no invisible format characters"]),
    "tool_name_isolate": (GOOD_TOML + '[[tools]]\nshape = "sphere"\nradius = 0.05\nposition = [2, 2, 2]\nname = "t\\u2066"\n',
                          ["[[tools]] #1 (shape 'sphere'): name = 't\\u2066' is not allowed", "no invisible format characters"]),
    "pin_name_zero_width": (GOOD_TOML + '[[pins]]\nbody = "box0"\nname = "p\\u200b"\n',
                            ["[[pins]] #1: name = 'p\\u200b' is not allowed", "no invisible format characters"]),
    "material_name_bidi": (GOOD_TOML + '[materials."a\\u202Eb"]\npreset = "clay"\n',
                           ["[materials.\"a\\u202eb\"] is not allowed", "no invisible format characters"]),
    "scene_name_bidi": (GOOD_TOML.replace('name = "tiny"', 'name = "ti\\u202any"'),
                        ["[scene] name = 'ti\\u202any' is not allowed", "no invisible format characters"]),
    # JSON's escapes, which name the table, leave a line separator (U+2028) or a C1 control
    # (U+0085, a next-line) as they are: the table was named '[materials."a<U+2028>b"]', a
    # line break in the Python message, a space in the CLI's line.
    "material_name_line_separator": (GOOD_TOML + '[materials."a\\u2028b"]\npreset = "clay"\n',
                                     ['[materials."a\\u2028b"] is not allowed', "one line of text"]),
    "material_name_next_line": (GOOD_TOML + '[materials."a\\u0085b"]\npreset = "clay"\n',
                                ['[materials."a\\u0085b"] is not allowed', "one line of text"]),
    # Past U+FFFF, a tag character (Cf) was named '\ue0020', which TOML reads as U+E002 and a '0'.
    "material_name_tag": (GOOD_TOML + '[materials."a\\U000E0020b"]\npreset = "clay"\n',
                          ['[materials."a\\U000e0020b"] is not allowed', "no invisible format characters"]),
    "description_bidi": (GOOD_TOML.replace('name = "tiny"', 'name = "tiny"\ndescription = "a \\u202eb"'),
                         ["[scene] description = 'a \\u202eb' is not allowed", "no bidirectional embeddings, overrides"]),
    # A tool named like a body's floor (its pinned set, '<body>_floor') was refused as 'must be a
    # new non-empty string', naming no clash with a set the file never named.
    "tool_name_taken_by_floor": (GOOD_TOML.replace('shape = "box"', 'shape = "box"\nfloor_margin = 0.0')
                                 + '[[tools]]\nshape = "sphere"\nradius = 0.05\nposition = [2, 2, 2]\nname = "box0_floor"\n',
                                 ["[[tools]] #1 (shape 'sphere'): name = 'box0_floor' is not allowed: a pinned set of that "
                                  "name exists already; tools and pinned sets share one set of names"]),
    # A mesh path the file gives relative is read from the file's folder: its refusal named the
    # joined path alone, not the key, nor where a relative path is read from.
    "mesh_not_beside_the_file": (GOOD_TOML + '[[bodies]]\nshape = "mesh"\nmaterial = "dough"\nfile = "meshes/part.obj"\n',
                                 ["[[bodies]] #2 (shape 'mesh'): file = 'meshes/part.obj' is not allowed: there is no ",
                                  "mesh_not_beside_the_file.toml", "read from the scene file's folder", "not the working folder"]),
    "tool_mesh_home": (GOOD_TOML + '[[tools]]\nshape = "mesh"\nfile = "~/part.obj"\nposition = [2, 2, 2]\n',
                       ["[[tools]] #1 (shape 'mesh'): file = '~/part.obj' is not allowed", "'~' is not expanded"]),
    # Rows narrower than the solver's min_neighbors = 6: refused naming the file and table (the
    # Solver's refusal named neither).
    "max_neighbors_narrow": (GOOD_TOML.replace("frames = 2", "frames = 2\nmax_neighbors = 4"),
                             ["[scene]: max_neighbors = 4 is not allowed: must be at least 6"]),
    # Above the widest row: the range a file has (the builder's own said [1, 1024], though 1-5 are refused).
    "max_neighbors_wide": (GOOD_TOML.replace("frames = 2", "frames = 2\nmax_neighbors = 2000"),
                           ["[scene]: max_neighbors = 2000 is not allowed: must be an integer in [6, 1024]"]),
    # Below 1 the same range (the builder's own said 'an integer >= 1', though 1-5 are refused).
    "max_neighbors_zero": (GOOD_TOML.replace("frames = 2", "frames = 2\nmax_neighbors = 0"),
                           ["[scene]: max_neighbors = 0 is not allowed: must be an integer in [6, 1024]"]),
    # A dt that does not divide the frame is the file's: named with it (it was the bare message).
    "dt_not_dividing": (GOOD_TOML.replace("frames = 2", "frames = 2\nfps = 30\ndt = 0.007"),
                        ["[scene] dt = 0.007 is not allowed", "whole number of steps", "use e.g. dt = 0.00666667 or 0.00833333, or leave dt out"]),
}


def test_a_scene_description_keeps_its_joining_format_characters(tmp_path):
    """``[scene] description`` is free text, not a name: an emoji ZWJ sequence (U+200D) or a
    Persian word's zero-width non-joiner (U+200C) was refused with the names' invisible format
    characters, though the description is never a name. Taken as written; only the
    bidirectional controls, which reorder the text after them, are refused (BAD_TOML)."""
    from warp_esph.scenes import load_scene_file

    text = "drop test \U0001f469\u200d\U0001f52c, \u0645\u06cc\u200c\u062e\u0648\u0627\u0647\u0645"
    scene = tmp_path / "described.toml"
    scene.write_text(GOOD_TOML.replace('name = "tiny"', f'name = "tiny"\ndescription = "{text}"'), encoding="utf-8")
    assert load_scene_file(str(scene)).description == text


def test_a_scene_named_by_its_file_gets_a_one_line_name(tmp_path):
    """A scene file with no ``[scene] name`` is named by its file: 'ev\u202eil.toml' named it
    'ev\u202eil', unchecked where ``[scene] name`` refuses the same, and 'warp-esph run'
    printed it as it was ('ev<right-to-left override>il: 48 particles, ...' reordered the line)
    and wrote 'ev\u202eil.usdc'. As a mesh file's default name, it only labels: its control and
    invisible format characters become '_'."""
    from warp_esph.scenes import load_scene_file

    # Nor what a name may not hold, which a scene made in Python refuses (a backslash, blank).
    for stem, name in (("ev\u202eil", "ev_il"), ("ti\nny", "ti_ny"), ("a\\b", "a_b"), ("  ", "__")):
        scene = tmp_path / f"{stem}.toml"
        scene.write_text(GOOD_TOML.replace('name = "tiny"\n', ""))
        assert load_scene_file(str(scene)).name == name


@pytest.mark.parametrize("case", sorted(BAD_TOML))
def test_bad_scene_file_is_one_line_exit_2(tmp_path, capsys, case):
    text, needles = BAD_TOML[case]
    scene = tmp_path / f"{case}.toml"
    scene.write_text(text)
    assert_one_line_error(refused_run(capsys, scene, tmp_path / "x.usdc"), f"{case}.toml", *needles)
    assert not (tmp_path / "x.usdc").exists()


@pytest.mark.parametrize(
    "args, needles",
    [
        (["run", "no_such_scene"], ["'no_such_scene'", "dough_drop"]),
        (["run", "dough_drp"], ["did you mean 'dough_drop'"]),
        (["run", "--dt", "-1"], ["--dt", "-1"]),
        # The step's check named its parameter ('dt = 0.0007 ... leave dt out'), not the option;
        # its hint is the option as typed ('--dt = 0.000694444' was no command line).
        (["run", "--dt", "0.0007"], ["--dt = 0.0007", "whole number", "use e.g. --dt 0.000694444 or 0.00070922, or leave --dt out"]),
        (["run", "dough_drop", "--fps", "1e9"], ["--fps = 1000000000.0 is not allowed: must be at most"]),
        (["run", "--frames", "0"], ["--frames", "0"]),
        (["run", "--frames", "many"], ["--frames", "many"]),
        (["run", "--scale", "0"], ["--scale"]),
        (["run", "--fps", "-5"], ["--fps"]),
        (["run", "--dtype", "float16"], ["--dtype", "float16"]),
        (["run", "--device", "tpu"], ["--device", "tpu"]),
        (["run", "-o", "out.obj"], ["out.obj", "extension"]),
        (["run", "missing_scene.toml"], ["missing_scene.toml", "No such file"]),
        # A built-in scene's name with '.toml', no such file here: the scene is named bare.
        (["run", "dough_drop.toml"], ["'dough_drop.toml': No such file", "'dough_drop' is a built-in scene: give its name "
                                      "alone, 'dough_drop'"]),
        (["run", "-o", "/nonexistent_dir_xyz/out.usdc", "--scale", "0.3"], ["/nonexistent_dir_xyz"]),
        (["frobnicate"], ["frobnicate"]),
        (["run", "--solver-fit", "quadratic"], ["--solver-fit = 'quadratic'", "'linear', 'curvature_corrected'"]),
        (["run", "--contact", "soft"], ["--contact = 'soft'", "'instant', 'continuous'"]),
        (["run", "--hourglass", "-0.1"], ["--hourglass = -0.1 is not allowed", ">= 0"]),
        (["run", "--hourglass", "strong"], ["--hourglass = 'strong'", ">= 0"]),
        (["run", "--hourglass", "inf"], ["--hourglass = inf is not allowed", "finite number >= 0"]),
        (["fit", "dough_drop", "--target", "t.npz", "--hourglass", "-1"], ["--hourglass = -1 is not allowed", ">= 0"]),
        (["run", "--fit-weight", "gauss"], ["--fit-weight = 'gauss'", "'poly6', 'biweight'"]),
        # The checkpoint reader's parameter was named, not the option: "checkpoint = 'nope.npz'".
        (["run", "--resume", "nope.npz"], ["--resume = 'nope.npz' is not allowed: no such file"]),
        (["sweep", "dough_drop", "--param", "mu=1:2:linear:2", "--fit-weight", "cubic"], ["--fit-weight = 'cubic'"]),
        # fit's options are checked before its scene and targets are read (here neither exists):
        # --lr 0 and -0.1 used to run the whole L-BFGS fit and exit 0.
        (["fit", "nothing.toml", "--target", "t.npz", "--lr", "0"], ["--lr = 0.0 is not allowed: must be > 0"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--lr", "-0.1"], ["--lr = -0.1 is not allowed: must be > 0"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--lr", "nan"], ["--lr = nan is not allowed: must be a finite number"]),
        # Levenberg-Marquardt never reads a step size: --lr ran as if it had not been given.
        (["fit", "nothing.toml", "--target", "t.npz", "--optimizer", "gauss-newton", "--lr", "0.5"],
         ["--lr = 0.5 is not allowed with --optimizer gauss-newton", "leave --lr out, or give --optimizer lbfgs or adam"]),
        # Nor does it record a tape to checkpoint: --memory-limit and --checkpoint-every N ran as if
        # they had not been given.
        (["fit", "nothing.toml", "--target", "t.npz", "--optimizer", "gauss-newton", "--memory-limit", "512"],
         ["--memory-limit = 512.0 is not allowed with --optimizer gauss-newton: it sizes the checkpointing of",
          "records none", "leave --memory-limit out"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--optimizer", "gauss-newton", "--checkpoint-every", "10"],
         ["--checkpoint-every = 10 is not allowed with --optimizer gauss-newton: it sizes the checkpointing of",
          "records none", "leave --checkpoint-every out"]),
        # A first step at or below the step tolerance: named by the flag, before the scene is read
        # (it was refused after, naming lr).
        (["fit", "nothing.toml", "--target", "t.npz", "--lr", "1e-7"],
         ["--lr = 1e-07 is not allowed with xtol = 1e-06: must be > xtol (the first step of Adam and of L-BFGS moves "
          "by --lr, and a step below xtol counts as converged)"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--seed", "-1"], ["--seed = -1 is not allowed: must be an integer >= 0"]),
        # Named as fit()'s parameters (worlds = True, optimizer = 'gauss-newton'), after the scene was read.
        (["fit", "nothing.toml", "--target", "t.npz", "--optimizer", "gauss-newton", "--starts", "2", "--worlds"],
         ["--worlds is not allowed with --optimizer gauss-newton: its starts run one after the other",
          "leave --worlds out"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--bounds", "yield_stress=10:1"],
         ["--bounds yield_stress=10:1 is not allowed: need lo < hi"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--bounds", "yield_stress=nan:1"],
         ["--bounds yield_stress=nan:1 is not allowed: a bound must be a number, not NaN (an open end is -inf "
          "or inf)"]),
        # Named as typed ('1e3:1e2', not '1000:100'), and a parameter not fitted by its entry
        # (it was "--bounds for 'mu' are not allowed", neither typed nor a sentence).
        (["fit", "nothing.toml", "--target", "t.npz", "--bounds", "yield_stress=1e3:1e2"],
         ["--bounds yield_stress=1e3:1e2 is not allowed: need lo < hi"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--bounds", "mu=1e3:1e4"],
         ["--bounds mu=1e3:1e4 is not allowed: mu is not fitted (--params yield_stress,flow_rate); give bounds of a "
          "fitted parameter"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--starts", "0"], ["--starts = 0 is not allowed: must be an integer >= 1"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--sample-range", "0.5"], ["--sample-range = 0.5 is not allowed: must be > 1"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--checkpoint-every", "0"], ["--checkpoint-every = 0 is not allowed"]),
        # Options nothing reads in that fit: each was ignored.
        (["fit", "nothing.toml", "--target", "t.npz", "--sample-range", "8"],
         ["--sample-range = 8.0 is not allowed without --samples or --starts"]),
        # Nothing is drawn without jitter, samples or extra starts: --seed 3 ran as without it.
        (["fit", "nothing.toml", "--target", "t.npz", "--seed", "3"],
         ["--seed = 3 is not allowed without --jitter, --samples or --starts", "this fit draws nothing"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--noise", "1e-4", "--no-diagnostics"],
         ["--noise = 0.0001 is not allowed with --no-diagnostics"]),
        # Only the automatic checkpointing reads the limit: with a fixed segment it was ignored.
        (["fit", "nothing.toml", "--target", "t.npz", "--checkpoint-every", "50", "--memory-limit", "64"],
         ["--memory-limit = 64.0 is not allowed with --checkpoint-every = 50"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--params", "mu,mu"], ["names must be distinct"]),
        # The point-cloud loss's own check named its parameter: 'radius = 0.0'.
        (["fit", "nothing.toml", "--target", "t.npz", "--radius", "0"], ["--radius = 0.0 is not allowed: must be > 0"]),
        # Sizes that exhausted memory (the sample hypercube, the starts' worlds) or a jitter
        # that made the first loss non-finite:
        (["fit", "nothing.toml", "--target", "t.npz", "--samples", "99999999999"], ["--samples = 99999999999", "at most 10000"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--starts", "1000000"], ["--starts = 1000000", "[1, 1000]"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--jitter", "1e300"], ["--jitter = 1e+300", "[0.0, 0.5]"]),
        # An iteration count no fit reaches was taken, its estimate '~6643201749991729152.0 h'.
        (["fit", "nothing.toml", "--target", "t.npz", "--iterations", "99999999999999999999999"],
         ["--iterations = 99999999999999999999999 is not allowed: must be at most 100000"]),
        (["fit", "nothing.toml", "--target", "t.npz", "--iterations", "100001"], ["--iterations = 100001", "at most 100000"]),
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path, monkeypatch, capsys, args, needles):
    monkeypatch.chdir(tmp_path)
    assert main([*args, "--no-progress"] if args[0] == "run" else args) == 2
    out, err = capsys.readouterr()
    assert_one_line_error(err, *needles)
    assert list(tmp_path.iterdir()) == []  # nothing written


def _valued_options():
    """(command, option, what it must be) for every option of every command that takes a number
    or one of a list of names: a word neither is refused naming the option, the word and that."""
    import argparse

    from warp_esph.cli import _build_parser

    commands = next(a for a in _build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    for name, parser in commands.items():
        for action in parser._actions:
            if not action.option_strings or action.nargs not in (None, 1):
                continue
            if action.choices is not None:
                yield name, action.option_strings[-1], "must be one of " + ", ".join(map(repr, action.choices))
            elif action.type in (int, float):
                yield name, action.option_strings[-1], "must be an integer" if action.type is int else "must be a number"
            elif action.type is not None and action.type is not str:
                yield name, action.option_strings[-1], "must be"


@pytest.mark.parametrize("command, option, allowed", list(_valued_options()))
def test_a_word_for_a_number_or_a_name_is_one_line_naming_option_value_and_what_is_allowed(tmp_path, monkeypatch, capsys,
                                                                                         command, option, allowed):
    """argparse's own line ('argument --frames: invalid int value: 'many'', 'argument --device:
    invalid choice: ...') named the option and the word but not in the command's form, and said
    of a number only its Python type; --dt's own line was given twice ('argument --dt: --dt = ...')."""
    monkeypatch.chdir(tmp_path)
    head = {"run": [], "scenes": [], "fit": ["dough_drop", "--target", "t.npz"], "render": ["o.usdc"],
            "export": ["o.usdc"], "sweep": ["dough_drop", "--param", "mu=1:2"]}[command]
    assert main([command, *head, option, "many"]) == 2
    assert_one_line_error(capsys.readouterr().err, f"warp-esph: error: {option} = 'many' is not allowed: {allowed}")
    # A word of 5000 characters was written whole: a 5 kB line (the value is shortened).
    assert main([command, *head, option, "m" * 5000]) == 2
    line = capsys.readouterr().err
    assert_one_line_error(line, f"warp-esph: error: {option} = 'mmmm")
    assert f"... is not allowed: {allowed}" in line and len(line) < 400, line[:500]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("option, word, said", [
    ("--bounds", "m" * 5000, "--bounds 'mmm"), ("--param-scales", "m" * 5000, "--param-scales 'mmm"),
    ("--hourglass", "m" * 5000, "--hourglass = 'mmm"), ("--hourglass", "9" * 5000, "--hourglass = 999"),
])
def test_a_long_word_for_an_option_the_command_parses_itself_is_shortened(tmp_path, monkeypatch, capsys, option, word, said):
    """Found by a fuzz of the commands' options: these wrote a 5000-character word whole into
    their one line (the options argparse converts: the test above)."""
    monkeypatch.chdir(tmp_path)
    assert main(["fit", "dough_drop", "--target", "t.npz", option, word]) == 2
    line = capsys.readouterr().err
    assert_one_line_error(line, f"warp-esph: error: {said}", "... is not allowed: ")
    assert len(line) < 300, line[:500]
    assert list(tmp_path.iterdir()) == []


def test_a_rate_a_built_in_scene_s_own_step_does_not_fill_names_the_rate_and_the_options(tmp_path, monkeypatch, capsys):
    """A figure scene's own step (dt = 0.005 s at --scale 0.1) at --fps 30, or at the rate a fit's
    target was recorded at: the line named a bare 'dt = 0.005' that was typed nowhere and advised
    'leave dt out', which a built-in scene's step cannot be."""
    monkeypatch.chdir(tmp_path)
    steps = "a frame (1/fps = 0.0333333 s) must be a whole number of steps, but 1/fps / dt = 6.66667; give --dt 0.0047619 or 0.00555556 with it"
    assert main(["run", "fig1_non_newtonian", "--scale", "0.1", "--fps", "30", "--no-progress"]) == 2
    assert_one_line_error(capsys.readouterr().err, "--fps = 30 is not allowed with fig1_non_newtonian's dt = 0.005 s: "
                          + steps + ", or a rate the step fills (28.5714 or 33.3333 fps)")
    np.savez(tmp_path / "t.npz", positions=np.zeros((2, 3, 3)), fps=30.0)
    assert main(["fit", "fig1_non_newtonian", "--scale", "0.1", "--target", "t.npz", "--no-progress"]) == 2
    line = capsys.readouterr().err
    assert_one_line_error(line, "the 30 fps the target t.npz was recorded at is not allowed with the scene's dt = 0.005 s: " + steps)
    assert "a rate the step fills" not in line  # the target's rate is no choice
    assert main(["fit", "fig1_non_newtonian", "--scale", "0.1", "--target", "t.npz", "--fps", "30", "--no-progress"]) == 2
    assert_one_line_error(capsys.readouterr().err, "--fps = 30 is not allowed with the scene's dt = 0.005 s: " + steps)
    assert sorted(os.listdir(tmp_path)) == ["t.npz"]


@pytest.mark.parametrize("name", ["run.usdc", "run.USDA", "run.usd"])
def test_fit_refuses_a_usd_name_for_its_json_before_it_replaces_a_run_s_file(tmp_path, monkeypatch, capsys, dough_scene, name):
    """fit's -o is its JSON, where run's -o is its USD: `fit ... -o run.usdc` (the fitted run
    meant) replaced an earlier run's USD file with the fit's JSON, exit 0."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "guess.toml").write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    np.savez(tmp_path / "t.npz", positions=np.zeros((3, 64, 3)))
    (tmp_path / name).write_bytes(b"an earlier run's frames")
    assert main(["fit", "guess.toml", "--target", "t.npz", "-o", name, "--iterations", "1", "--no-progress"]) == 2
    assert_one_line_error(capsys.readouterr().err, f"--output = '{name}' is not allowed: it is the fit's JSON file",
                          "the fitted run's USD is fitted.usdc in --output-dir", "give a .json name")
    assert (tmp_path / name).read_bytes() == b"an earlier run's frames"
    assert sorted(os.listdir(tmp_path)) == sorted(["guess.toml", "t.npz", name])


def test_fit_seed_is_taken_where_something_is_drawn(tmp_path, monkeypatch, capsys):
    """--seed is refused only where nothing draws from it: with jitter, samples or extra
    starts it is read, and the fit goes on (here to its missing scene file)."""
    monkeypatch.chdir(tmp_path)
    for more in (["--jitter", "0.001"], ["--samples", "2"], ["--starts", "2"]):
        assert main(["fit", "nothing.toml", "--target", "t.npz", "--seed", "3", *more]) == 2
        err = capsys.readouterr().err
        assert_one_line_error(err, "nothing.toml")
        assert "--seed" not in err


def test_cuda_asked_for_where_there_is_none_is_one_line(tmp_path, capsys):
    """The reason is in the one line (it was Warp's warning line and then the error), the same
    from run and fit whenever Warp was started: it was Warp's driver note where the command
    started Warp and 'Warp finds no CUDA device on this machine' where Warp had started before
    (a second command of one process). On a machine with CUDA the run goes on."""
    import warp as wp

    from warp_esph.startup import cuda_absence

    if wp.is_cuda_available():
        pytest.skip("CUDA is available here: nothing to refuse (the CPU machines of CI run this check)")
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    said = (f"warp-esph: error: --device = 'cuda' is not allowed: Warp finds no CUDA device on this machine: {cuda_absence()} "
            "(use --device cpu)\n")
    assert cuda_absence() in ("this Warp was built without CUDA", "it could not find or load the NVIDIA CUDA driver")
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(tmp_path / "t.usdc"), "--device", "cuda", "--no-progress"]) == 2
    assert capsys.readouterr().err == said
    assert main(["fit", str(tmp_path / "s.toml"), "--target", str(tmp_path / "t.npz"), "--device", "cuda"]) == 2
    assert capsys.readouterr().err == said


def test_an_output_another_writer_is_writing_is_refused_and_left_to_it(tmp_path, capsys):
    """Two runs given one output shared the writer's working copies: the first failed mid-run
    with pxr's 'Unable to open .t.usdc.wa.usdc for writing', saying its file kept its frames,
    while the file was the second's. A run now refuses an output that another writer holds,
    before the run and before it touches that run's force log."""
    from warp_esph.scenes import load_scene
    from warp_esph.usd import UsdWriter

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    out = tmp_path / "t.usdc"
    model = load_scene(str(tmp_path / "s.toml")).builder.finalize()
    with UsdWriter(out, model, 30) as holder:
        holder.write_frame(0, model.state())
        (tmp_path / "t.usdc_tools.csv").write_text("the holder's log\n")
        assert main(["run", str(tmp_path / "s.toml"), "-o", str(out), "--no-progress"]) == 2
        # Held by this process here: its own writer, never finished by waiting, is named as such.
        assert capsys.readouterr().err == (f"warp-esph: error: --output = '{out}' is not allowed: another writer of this "
                                           f"process ({os.getpid()}) is writing it; close() that one first, or write "
                                           "another file\n")
        assert (tmp_path / "t.usdc_tools.csv").read_text() == "the holder's log\n"
        holder.write_frame(1, model.state())
    assert frames_in(out, "/World/box0") == [0.0, 1.0]
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(out), "--no-progress"]) == 0
    assert frames_in(out, "/World/box0") == [0.0, 1.0, 2.0]
    assert sorted(os.listdir(tmp_path)) == ["s.toml", "t.usdc", "t.usdc_tools.csv", "t.usdc_tools.json"]


@pytest.mark.parametrize("in_the_way, options, needle", [
    ("t.usdc_tools.csv", [], "the reaction log = "),
    ("t.usdc.checkpoint.npz", ["--checkpoint-every", "1"], "--checkpoint-every's checkpoint = "),
    ("t.usdc.png", ["--preview"], "--preview's picture = "),
])
def test_a_folder_where_run_writes_a_file_is_refused_before_the_run(tmp_path, capsys, in_the_way, options, needle):
    """Found only after the whole run before (the USD written, then a raw [Errno 21])."""
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    (tmp_path / in_the_way).mkdir()
    out = tmp_path / "t.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(out), "--no-progress", *options]) == 2
    assert_one_line_error(capsys.readouterr().err, needle, "is not allowed: it is a folder; a file is written there")
    assert not out.exists()  # nothing ran


def test_fit_refuses_its_output_places_before_fitting_and_names_a_damaged_experiments_file(tmp_path, capsys, monkeypatch):
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    run = tmp_path / "truth.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress", "--dtype", "float64"]) == 0
    # The experiments observe another recording: the command line's file at every frame,
    # observed again, is refused before any scene is read (they test the scenes' refusals).
    shutil.copy(run, tmp_path / "other.usdc")
    capsys.readouterr()
    fit = ["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "1"]
    (tmp_path / "fo" / "fitted.usdc").mkdir(parents=True)
    assert main([*fit, "--output-dir", str(tmp_path / "fo")]) == 2
    assert_one_line_error(capsys.readouterr().err, "--output-dir = ", "fitted.usdc in it is a folder")
    assert main([*fit, "-o", str(tmp_path / "no" / "dir" / "fit.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, "--output = ", "does not exist or is not a folder")
    # A named pipe (or a device: -o /dev/null, run as root) was replaced by a file of the fit's
    # JSON, which renames its file over the name, and the fit reported it written, exit 0.
    os.mkfifo(tmp_path / "pipe.json")
    assert main([*fit, "-o", str(tmp_path / "pipe.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, f"--output = '{tmp_path / 'pipe.json'}' is not allowed: it is a named "
                                                   "pipe, not a file; the output is written beside it and renamed over it")
    assert stat.S_ISFIFO(os.stat(tmp_path / "pipe.json").st_mode)
    # Options of another kind of target are refused, not ignored (both ran the fit and exited 0).
    assert main([*fit, "--radius", "0.01"]) == 2
    assert_one_line_error(capsys.readouterr().err, "--radius = 0.01 is not allowed: it is the search radius of point-cloud")
    assert main([*fit, "--target-tool", "ground"]) == 2
    assert_one_line_error(capsys.readouterr().err, "--target-tool = 'ground' is not allowed: it picks the tool of a force-curve")
    assert main([*fit, "--mesh-mode", "outside"]) == 2
    assert_one_line_error(capsys.readouterr().err, "--mesh-mode = 'outside' is not allowed: it is how mesh targets are compared")
    # A damaged --experiments file is named as itself, not as the --target.
    (tmp_path / "exp.json").write_bytes(b"\xda\x00\xff garbage")
    assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, f"--experiments {tmp_path / 'exp.json'} is not valid JSON")
    # A missing target is named with its experiment, as its other refusals are (it named none).
    (tmp_path / "exp.json").write_text(json.dumps([{"scene": "s.toml", "target": "missing.usdc"}]))
    assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, f"{tmp_path / 'exp.json'}: experiment #1: target file "
                                                   f"{tmp_path / 'missing.usdc'} does not exist")
    # An empty list, and one experiment's object not in a list, were both told to 'give a list of
    # experiments': each is said as what it is.
    for doc, words in (([], "it lists no experiments: give one or more objects with the keys scene and target"),
                       ({"scene": "s.toml", "target": "other.usdc"},
                        "it is one experiment's object, not a list of them: write it in brackets, [{...}]"),
                       # Under the key too: it was told to give {"experiments": [...]}, which it did, but for the brackets.
                       ({"experiments": {"scene": "s.toml", "target": "other.usdc"}},
                        "it is one experiment's object, not a list of them: write it in brackets, [{...}]")):
        (tmp_path / "exp.json").write_text(json.dumps(doc))
        assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
        assert_one_line_error(capsys.readouterr().err, f"--experiments {tmp_path / 'exp.json'} is not allowed: {words}")
    # A negative weight would maximise that experiment's loss.
    (tmp_path / "exp.json").write_text(json.dumps([{"scene": "s.toml", "target": "other.usdc", "weight": -1}]))
    assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, "experiment #1: weight = -1 is not allowed: must be > 0")
    # Frame numbers as a JSON list are one choice per target: the refusal says how one target's
    # frames are written (it said only 'given 2 times for 1 target files').
    (tmp_path / "exp.json").write_text(json.dumps([{"scene": "s.toml", "target": "other.usdc", "target_frames": [1, 2]}]))
    assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, "experiment #1: target_frames is given 2 times for 1 target files: ",
                          'a list is one choice per target: frames 1, 2 of one target are "1,2"')
    # A material index out of range, or true (read as a body named 'True'): named by experiment.
    for chosen, words in ((5, "experiment #1: material 5 is not allowed: indices are 0..0"),
                          (True, "experiment #1: material = True is not allowed: give a material index or a body name")):
        (tmp_path / "exp.json").write_text(json.dumps([{"scene": "s.toml", "target": "other.usdc", "material": chosen}]))
        assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
        assert_one_line_error(capsys.readouterr().err, words)
    # The scene file is named as the JSON wrote it, not by the path it resolves to beside the JSON
    # ('exp.json: experiment #1: /tmp/.../fast.toml: ...'); it is still read from there, and a
    # missing one says so (it said only 'nope.toml', as if looked for in the working folder).
    (tmp_path / "fast.toml").write_text(GOOD_TOML.replace("[[bodies]]", "[[bodies]]\nvelocity = [0.0, -1e3, 0.0]"))
    (tmp_path / "bad.toml").write_text(GOOD_TOML + "\n[scene]\n")
    # A path without '.toml' (a scene file all the same) was read relative to the working folder.
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "bad").write_text(GOOD_TOML + "\n[scene]\n")
    looked = f"(looked for relative to {tmp_path}, the folder of the --experiments file): No such file or directory"
    for scene, words in (("fast.toml", "fast.toml: [[bodies]] #1 (shape 'box'): initial velocity of body 'box0': a speed "
                                        "of 1e+03 m/s"),
                         ("bad.toml", "bad.toml: invalid TOML: "),
                         ("nope.toml", f"cannot read scene file 'nope.toml' {looked}"),
                         ("sub/nope.toml", f"cannot read scene file 'sub/nope.toml' {looked}"),
                         ("sub/bad", "sub/bad: invalid TOML: "),
                         ("sub/nope", f"cannot read scene file 'sub/nope' {looked}")):
        (tmp_path / "exp.json").write_text(json.dumps([{"scene": scene, "target": "other.usdc"}]))
        assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
        captured = capsys.readouterr()
        assert_one_line_error(captured.err, f"error: {tmp_path / 'exp.json'}: experiment #1: {words}")
        assert str(tmp_path / scene) not in captured.err and not captured.out, captured
    # A bare name that is neither a built-in scene nor a file beside the JSON was read from the
    # working folder, silently (exit 0); one beside the JSON is still read from there.
    (tmp_path / "cwd").mkdir()
    (tmp_path / "cwd" / "plain").write_text(GOOD_TOML)
    (tmp_path / "cwd" / "twice").write_text(GOOD_TOML)
    (tmp_path / "twice").write_text(GOOD_TOML + "\n[scene]\n")
    monkeypatch.chdir(tmp_path / "cwd")
    for scene, words in (("plain", ("scene = 'plain' is not allowed: unknown scene; the built-in scenes are ",
                                    f"scene file (relative to {tmp_path}, the folder of the --experiments file)")),
                         ("twice", ("twice: invalid TOML: ",))):
        (tmp_path / "exp.json").write_text(json.dumps([{"scene": scene, "target": "other.usdc"}]))
        assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
        assert_one_line_error(capsys.readouterr().err, f"error: {tmp_path / 'exp.json'}: experiment #1: {words[0]}", *words[1:])
    monkeypatch.chdir(tmp_path)
    # An absolute path is named as written, and was looked for nowhere else.
    (tmp_path / "exp.json").write_text(json.dumps([{"scene": str(tmp_path / "nope.toml"), "target": "other.usdc"}]))
    assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, f"experiment #1: cannot read scene file '{tmp_path / 'nope.toml'}': No such file or directory")
    assert "relative to" not in err, err
    # The command's own --material is named as the option typed (it said "material 'nobody'").
    for chosen, words in (("nobody", "error: --material 'nobody' is not allowed: give a material index, a body name (box0) "
                                     "or a material name of the scene file (soft)"),
                          ("5", "error: --material 5 is not allowed: indices are 0..0")):
        assert main([*fit, "--material", chosen]) == 2
        assert_one_line_error(capsys.readouterr().err, words)
    # A key given twice kept the last value without a word (TOML refuses it).
    (tmp_path / "exp.json").write_text('[{"scene": "s.toml", "target": "other.usdc", "weight": 1, "weight": 2}]')
    assert main([*fit, "--experiments", str(tmp_path / "exp.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, "exp.json is not allowed: the key 'weight' appears twice in one object")
    assert not (tmp_path / "fit_tiny").exists()


@pytest.mark.parametrize("error", [
    json.JSONDecodeError("Expecting value", "{", 1),
    UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"),
    pytest.param("scale", id="ScaleRefused")])
def test_an_experiment_s_refusal_of_a_class_of_several_arguments_is_one_line_naming_it(tmp_path, capsys, monkeypatch, error):
    """An --experiments file's refusal is said with its experiment ('exp.json: experiment #1:
    ...'), raised again as ``type(e)(text)``: an error whose class takes more than a message
    (json's decode error, a UnicodeDecodeError, the package's ``scenes.ScaleRefused``) made that
    a TypeError traceback in place of the one line. The experiment's loading is replaced by one
    that raises it: no reader of the package is known to let one out now."""
    from warp_esph import calibrate
    from warp_esph.scenes import ScaleRefused

    if error == "scale":
        error = ScaleRefused(0.5, "for its thin cubes", "at least 1")
    np.save(tmp_path / "t.npy", np.zeros((2, 3)))
    (tmp_path / "exp.json").write_text(json.dumps([{"scene": "rubber_bounce", "target": "t.npy"}]))
    real = calibrate._experiment

    def load(spec, args, where, *rest, **how):
        if where:
            raise error
        return real(spec, args, where, *rest, **how)

    monkeypatch.setattr(calibrate, "_experiment", load)
    assert main(["fit", "rubber_bounce", "--target", str(tmp_path / "t.npy"), "--experiments", str(tmp_path / "exp.json"),
                 "--no-progress", "--iterations", "1", "-o", str(tmp_path / "fit.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, f"{tmp_path / 'exp.json'}: experiment #1: {error}")
    assert not (tmp_path / "fit.json").exists()


def test_an_experiment_s_scene_is_named_as_the_json_wrote_it_where_its_resolved_path_is_shown_by_its_ends(tmp_path, capsys):
    """An --experiments file's scene named relative to it is named as the JSON wrote it, also
    where the path it resolves to is over checks.PATH_SHOWN_WHOLE characters: the refusal shows
    that path by its ends, which the rewrite (a match of the whole path) missed, naming a cut
    path the user never gave."""
    from warp_esph.checks import PATH_SHOWN_WHOLE

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    run = tmp_path / "truth.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress", "--dtype", "float64"]) == 0
    # The experiments observe another recording: the command line's file at every frame,
    # observed again, is refused before any scene is read (they test the scenes' refusals).
    shutil.copy(run, tmp_path / "other.usdc")
    capsys.readouterr()
    sub = "sub" + "d" * 100
    (tmp_path / sub).mkdir()
    (tmp_path / sub / "fast.toml").write_text(GOOD_TOML.replace("[[bodies]]", "[[bodies]]\nvelocity = [0.0, -1e3, 0.0]"))
    (tmp_path / sub / "bad.toml").write_text(GOOD_TOML + "\n[scene]\n")
    looked = f"(looked for relative to {tmp_path}, the folder of the --experiments file): No such file or directory"
    for scene, words in ((f"{sub}/fast.toml", f"{sub}/fast.toml: [[bodies]] #1 (shape 'box'): initial velocity of body 'box0'"),
                         (f"{sub}/bad.toml", f"{sub}/bad.toml: invalid TOML: "),
                         (f"{sub}/nope.toml", f"cannot read scene file '{sub}/nope.toml' {looked}")):
        assert len(str(tmp_path / scene)) > PATH_SHOWN_WHOLE >= len(scene)
        (tmp_path / "exp.json").write_text(json.dumps([{"scene": scene, "target": "other.usdc"}]))
        assert main(["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "1",
                     "--experiments", str(tmp_path / "exp.json")]) == 2
        captured = capsys.readouterr()
        assert_one_line_error(captured.err, f"error: {tmp_path / 'exp.json'}: experiment #1: {words}")
        assert not captured.out, captured


def test_a_refusal_of_targets_of_two_rates_shows_a_long_path_by_its_ends(tmp_path, capsys):
    """The targets' rates read from their files are named by the path shown by its ends
    (checks.shown_path) where it is over checks.PATH_SHOWN_WHOLE characters: the first
    target's was named whole beside the other's, shortened, a path with spaces whole even on
    the command line."""
    from warp_esph.checks import PATH_SHOWN_WHOLE, shown_path
    from warp_esph.fit import save_target

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    folder = tmp_path / ("a long folder " + "d" * PATH_SHOWN_WHOLE)
    folder.mkdir()
    for name, fps in (("a.npz", 30.0), ("b.npz", 60.0)):
        save_target(folder / name, np.zeros((2, 4, 3), np.float32), frames=[1, 2], fps=fps)
    assert main(["fit", str(tmp_path / "s.toml"), "--target", str(folder / "a.npz"), "--target", str(folder / "b.npz"),
                 "--no-progress", "--iterations", "1", "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, f"target {shown_path(folder / 'b.npz', False)} is not allowed beside the target "
                               f"{shown_path(folder / 'a.npz', False)}: it was recorded at 60 fps")
    assert str(folder) not in err


def test_an_output_folder_holding_a_fit_input_is_refused_naming_long_paths_by_their_ends(tmp_path, capsys):
    """The refusal of an --output-dir that holds the target as a file the fit writes names the
    folder and the target, over checks.PATH_SHOWN_WHOLE characters, by their ends
    (checks.shown_path): both were named whole, a path with spaces whole on the command line."""
    from warp_esph.checks import PATH_SHOWN_WHOLE, shown_path

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    folder = tmp_path / ("a long folder " + "d" * PATH_SHOWN_WHOLE)
    folder.mkdir()
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(folder / "fitted.usdc"), "--no-progress", "--dtype", "float64"]) == 0
    capsys.readouterr()
    measured = (folder / "fitted.usdc").read_bytes()
    assert main(["fit", str(tmp_path / "s.toml"), "--target", str(folder / "fitted.usdc"), "--no-progress",
                 "--iterations", "1", "--output-dir", str(folder)]) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, f"--output-dir {shown_path(folder, False)}: fitted.usdc = {shown_path(folder / 'fitted.usdc')} is "
                               f"not allowed: it is --target {shown_path(folder / 'fitted.usdc')} of this fit")
    assert str(folder) not in err
    assert (folder / "fitted.usdc").read_bytes() == measured


@pytest.mark.parametrize("scene", ["nope.toml", "nosuch"])
def test_an_experiment_s_scene_looked_for_in_a_long_folder_names_the_folder_by_its_ends(tmp_path, capsys, scene):
    """An --experiments file's scene that is not there (a file, or a name neither built in nor
    beside the JSON) is refused naming the folder it was looked for in, the JSON's: one over
    checks.PATH_SHOWN_WHOLE characters by its ends (checks.shown_path), as the JSON itself is
    named; it was named whole, a path with spaces whole on the command line."""
    from warp_esph.checks import PATH_SHOWN_WHOLE, shown_path

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    run = tmp_path / "truth.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress", "--dtype", "float64"]) == 0
    # The experiments observe another recording: the command line's file at every frame,
    # observed again, is refused before any scene is read (they test the scenes' refusals).
    shutil.copy(run, tmp_path / "other.usdc")
    capsys.readouterr()
    folder = tmp_path / ("a long folder " + "d" * PATH_SHOWN_WHOLE)
    folder.mkdir()
    (folder / "exp.json").write_text(json.dumps([{"scene": scene, "target": str(tmp_path / "other.usdc")}]))
    assert main(["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "1",
                 "--experiments", str(folder / "exp.json")]) == 2
    captured = capsys.readouterr()
    assert_one_line_error(captured.err, f"error: {shown_path(folder / 'exp.json', False)}: experiment #1: ",
                          f"relative to {shown_path(folder, False)}, the folder of the --experiments file")
    assert str(folder) not in captured.err
    assert not captured.out, captured


@pytest.mark.parametrize("where", ["plots", "fitted run"])
def test_a_ctrl_c_while_fit_writes_its_results_says_which_files_are_whole(tmp_path, monkeypatch, capsys, where):
    """A Ctrl-C after the fit (and its diagnostics) had finished, while its pictures or its
    fitted run were written: the line said 'interrupted' alone, and a fitted.usdc cut short
    stayed beside fit.json as if it were the fitted run."""
    from warp_esph import calibrate

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    run = tmp_path / "truth.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress", "--dtype", "float64"]) == 0
    if where == "plots":
        def interrupted(*a, **k):
            raise KeyboardInterrupt

        monkeypatch.setattr(calibrate, "_plots", interrupted)
    else:
        simulate_module = sys.modules["warp_esph.simulate"]  # the package's name is the function
        real = simulate_module.simulate

        def interrupted(model, frames, **kw):
            return real(model, frames, callback=lambda f, s: (_ for _ in ()).throw(KeyboardInterrupt) if f == 1 else None,
                        **kw)

        monkeypatch.setattr(simulate_module, "simulate", interrupted)
    out = tmp_path / "fit"
    capsys.readouterr()
    assert main(["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "0",
                 "--no-diagnostics", "--output-dir", str(out)]) == 130
    err = capsys.readouterr().err.splitlines()
    kept = f"{out}/fit.json, {out}/history.csv" + (f", {out}/loss.png, {out}/params.png" if where != "plots" else "")
    assert err[-2:] == [f"warp-esph fit: interrupted while writing the fit's results (printed above): wrote {kept}; the "
                        "other files are not written", "warp-esph: interrupted"]
    assert sorted(os.listdir(out)) == sorted(os.path.basename(f) for f in kept.split(", "))


def test_a_usd_output_named_in_bytes_that_are_not_utf8_is_refused_before_the_work(tmp_path, capsys):
    """USD takes file names as UTF-8: run -o b'\\xfe.usdc' failed at the writer's first save with
    a bare "'utf-8' codec can't encode ..." naming no option; fit --output-dir b'\\xfa' ran the
    whole fit, wrote four files, then failed the same way at fitted.usdc, exit 2."""
    from warp_esph.usd import UsdWriter

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    odd = os.fsdecode(b"\xfe")  # a name Linux holds, which Python keeps as a surrogate escape
    out = tmp_path / f"{odd}.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(out), "--no-progress"]) == 2
    assert_one_line_error(capsys.readouterr().err, f"--output = {str(out)!r} is not allowed: USD names its files in UTF-8")
    assert os.listdir(tmp_path) == ["s.toml"]  # no lock, no working copy
    run = tmp_path / "truth.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress"]) == 0
    capsys.readouterr()
    fit = ["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "1", "--no-diagnostics"]
    assert main([*fit, "--output-dir", str(tmp_path / odd)]) == 2
    assert_one_line_error(capsys.readouterr().err, f"--output-dir = {str(tmp_path / odd)!r} is not allowed: USD names")
    assert not (tmp_path / odd).exists()  # refused before the fit
    from warp_esph.scenes import load_scene_file

    model = load_scene_file(tmp_path / "s.toml").builder.finalize()
    with pytest.raises(ValueError, match=r"^path = '.*' is not allowed: USD names its files in UTF-8 text"):
        UsdWriter(out, model)


def test_a_usd_input_named_in_bytes_that_are_not_utf8_is_refused_naming_what_is_allowed(tmp_path, capsys):
    """USD takes file names as UTF-8: render, export and fit --target of b'\\xfb.usdc' exited 2
    with "cannot read '\\udcfb.usdc': 'utf-8' codec can't encode ..." (fit's adding 'a damaged
    or foreign file?'), which said neither what was wrong with the file nor what is allowed."""
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    odd = tmp_path / (os.fsdecode(b"\xfb") + ".usdc")  # a name Linux holds, which Python keeps as a surrogate escape
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(tmp_path / "run.usdc"), "--no-progress"]) == 0
    os.rename(tmp_path / "run.usdc", odd)
    capsys.readouterr()
    for command in (["render", str(odd), "-o", str(tmp_path / "x.png")], ["export", str(odd), "-o", str(tmp_path / "e")],
                    ["fit", str(tmp_path / "s.toml"), "--target", str(odd), "--no-progress", "--iterations", "0",
                     "--no-diagnostics", "--output-dir", str(tmp_path / "f")]):
        assert main(command) == 2, command
        err = capsys.readouterr().err
        assert_one_line_error(err, f"{str(odd)!r}", "USD names its files in UTF-8 text", "give a path of UTF-8 text")
        assert "codec" not in err and "damaged" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["s.toml", odd.name, "run.usdc_tools.csv",
                                                                 "run.usdc_tools.json"])  # nothing written


def test_fit_refuses_an_empty_path_instead_of_dropping_it(tmp_path, capsys, monkeypatch):
    """'' (an unset shell variable) was taken as not given: --experiments '' and --cameras ''
    ran the fit without them and exited 0, --output-dir '' and -o '' wrote to the defaults."""
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    run = tmp_path / "truth.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress"]) == 0
    capsys.readouterr()
    monkeypatch.chdir(tmp_path)
    fit = ["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "0", "--no-usd",
           "--no-diagnostics"]
    for flag in ("--experiments", "--cameras", "--output-dir", "-o"):
        assert main([*fit, *(["--output-dir", str(tmp_path / "o")] if flag != "--output-dir" else []), flag, ""]) == 2
        shown = "--output" if flag == "-o" else flag
        assert_one_line_error(capsys.readouterr().err, f"{shown} = '' is not allowed: must be a path (not empty")
    (tmp_path / "exp.json").write_text(json.dumps([{"scene": "s.toml", "target": "truth.usdc", "cameras": ""}]))
    assert main([*fit, "--output-dir", str(tmp_path / "o"), "--experiments", str(tmp_path / "exp.json")]) == 2
    assert_one_line_error(capsys.readouterr().err, "experiment #1: cameras = '' is not allowed: must be the path of a camera file")
    assert not (tmp_path / "o").exists() and not (tmp_path / "fit_tiny").exists()


@pytest.mark.parametrize("argv, said", [
    (["render", ""], "cannot read '': the path is empty; give the path of a warp-esph USD file"),
    (["export", ""], "cannot read '': the path is empty; give the path of a warp-esph USD file"),
    (["run", "--resume", ""], "--resume = '' is not allowed: must be a path (not empty, no NUL character)"),
    (["fit", "dough_drop", "--target", "", "--scale", "0.3"], "--target = '' is not allowed: must be a path (not empty, no NUL character)"),
])
def test_an_empty_input_path_is_named_as_typed(argv, said, tmp_path, monkeypatch, capsys):
    """'' (an unset shell variable) for an input was said as nothing, or as a path nobody typed:
    'cannot read : no such file' (render, export), 'target file does not exist' (fit), and
    --resume read it as the working folder, "--resume = '.' is not allowed: it cannot be read (Is
    a directory)". Each names '' and what is allowed."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"warp-esph: error: {said}"]
    assert os.listdir(tmp_path) == []
    if argv[0] == "fit":  # the Python API's reader, as the command's check names its option
        from warp_esph.fit import load_target

        with pytest.raises(ValueError, match=r"^path = '' is not allowed: must be the path of a target file$"):
            load_target("")
    if argv[0] == "run":  # the checkpoint readers name their own parameter, as --resume names the option
        import warp_esph as we
        from warp_esph.checkpoint import load_state, read_checkpoint

        b = we.SceneBuilder(spacing=0.05)
        b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"))
        model = b.finalize()
        for read in (read_checkpoint, lambda p: load_state(p, model)):
            with pytest.raises(ValueError, match=r"^path = '' is not allowed: must be a path \(not empty, no NUL character\)$"):
                read("")


def _fail_after(monkeypatch, steps: int, action):
    """Make Solver.step call ``action(state_out)`` once ``steps`` steps have run."""
    original = solver_module.Solver.step
    calls = {"n": 0}

    def step(self, state_in, state_out, dt):
        original(self, state_in, state_out, dt)
        calls["n"] += 1
        if calls["n"] == steps:
            action(state_out)

    monkeypatch.setattr(solver_module.Solver, "step", step)


def _steps_per_frame(scale=0.3) -> int:
    scene = get_scene("dough_drop", scale)
    return resolve_timestep(scene.builder.finalize(), scene.fps)[0]


def test_keyboard_interrupt_keeps_finished_frames(tmp_path, monkeypatch, capsys):
    def interrupt(state):
        raise KeyboardInterrupt

    n = _steps_per_frame()
    _fail_after(monkeypatch, 2 * n + 1, interrupt)  # inside frame 3
    out_path = tmp_path / "stopped.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress"]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "Traceback" not in err
    assert frames_in(out_path) == [0.0, 1.0, 2.0]
    assert sorted(os.listdir(tmp_path)) == ["stopped.usdc", "stopped.usdc_tools.csv", "stopped.usdc_tools.json"]
    assert log_frames(out_path) == {"plane0": [0, 1, 2]}  # the finished frames, as in the USD


def test_an_interrupt_between_the_writers_start_and_the_first_frame_leaves_no_working_copy(tmp_path, monkeypatch, capsys):
    """Ctrl-C after the writer has made its working copies but before the run's frame loop (the
    earlier run's force log being retired) left the two hidden copies beside the output, each as
    large as the file."""
    real_isfile = os.path.isfile

    def isfile(path):
        if str(path).endswith("_tools.csv") and any(n.startswith(".") for n in os.listdir(tmp_path)):
            raise KeyboardInterrupt
        return real_isfile(path)

    monkeypatch.setattr(os.path, "isfile", isfile)
    out_path = tmp_path / "early.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "2", "--no-progress"]) == 130
    err = capsys.readouterr().err
    assert err == "warp-esph: interrupted\n"
    assert sorted(os.listdir(tmp_path)) == ["early.usdc"]  # no .early.usdc.wa.usdc, .early.usdc.wb.usdc
    assert frames_in(out_path) == []


def test_sigterm_mid_run_says_terminated_and_exits_143(tmp_path, monkeypatch, capsys):
    """SIGTERM after start-up exited 143 but its line said 'interrupted', as for Ctrl-C (before
    start-up it said 'terminated')."""
    n = _steps_per_frame()
    _fail_after(monkeypatch, 2 * n + 1, lambda state: os.kill(os.getpid(), signal.SIGTERM))  # inside frame 3
    out_path = tmp_path / "stopped.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress"]) == 143
    assert capsys.readouterr().err == f"warp-esph: terminated: {out_path} keeps the 3 frames finished\n"
    assert frames_in(out_path) == [0.0, 1.0, 2.0]


@pytest.fixture
def sigint_as_in_a_terminal():
    """SIGINT handled as in a terminal: a runner started in the background (``nohup ... &``, some
    CI services) starts its processes ignoring it, and the command keeps ignoring a signal it
    started ignoring, so a Ctrl-C these tests send themselves would never arrive."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_ctrl_c_while_the_force_log_is_written_at_the_end_keeps_the_whole_log(tmp_path, monkeypatch, capsys, sigint_as_in_a_terminal):
    """The force log of a run without checkpoints is written once, at its end: a Ctrl-C inside
    that write (a second one, or one as the run ended) lost the whole log, its USD complete.
    The write now finishes first; the run still does not report success."""
    from warp_esph import tools

    real = tools.ReactionLog.write

    def interrupted(self, stem):
        os.kill(os.getpid(), signal.SIGINT)
        return real(self, stem)

    monkeypatch.setattr(tools.ReactionLog, "write", interrupted)
    out_path = tmp_path / "late.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "3", "--no-progress"]) == 130
    assert capsys.readouterr().err == f"warp-esph: interrupted: {out_path} keeps the 4 frames finished\n"
    assert frames_in(out_path) == [0.0, 1.0, 2.0, 3.0]
    assert log_frames(out_path) == {"plane0": [0, 1, 2, 3]}


def test_a_ctrl_c_while_the_force_log_is_written_at_a_checkpoint_waits_for_the_log(tmp_path, monkeypatch, capsys,
                                                                                   sigint_as_in_a_terminal):
    """The force log is rewritten at every checkpoint; a Ctrl-C just after a working file of
    that write was opened, before its ``with`` block, left the file object to the garbage
    collector ('warning: unclosed file <.a.usdc_tools.json.PID.tmp>'). The log write and the
    checkpoint it belongs to now finish first; then the run stops there."""
    from warp_esph import tools
    from warp_esph.checkpoint import read_checkpoint

    sent = []

    def open_interrupted(*args, **kwargs):
        fh = open(*args, **kwargs)
        if not sent:
            sent.append(args[0])
            os.kill(os.getpid(), signal.SIGINT)  # acted on before the caller's with block
        return fh

    monkeypatch.setattr(tools, "open", open_interrupted, raising=False)
    out_path = tmp_path / "c.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "6", "--checkpoint-every", "2",
                 "--no-progress"]) == 130
    assert capsys.readouterr().err == f"warp-esph: interrupted: {out_path} keeps the 3 frames finished\n"
    assert frames_in(out_path) == [0.0, 1.0, 2.0]
    assert log_frames(out_path) == {"plane0": [0, 1, 2]}
    assert read_checkpoint(str(out_path) + ".checkpoint.npz")[0]["frame"] == 2
    assert sorted(os.listdir(tmp_path)) == ["c.usdc", "c.usdc.checkpoint.npz", "c.usdc_tools.csv", "c.usdc_tools.json"]


def test_a_ctrl_c_in_a_finalizer_or_a_second_one_is_no_traceback_and_no_success(tmp_path, monkeypatch, capsys,
                                                                               sigint_as_in_a_terminal):
    """A Ctrl-C that lands in a finalizer (``__del__``, which Python runs between any two
    steps) was printed as 'Exception ignored in ... Traceback ... KeyboardInterrupt' and
    dropped: the run went on and exited 0; then it was only recorded, and the run went on to
    its last frame before saying so. It now stops the run at the next frame's end. A second
    Ctrl-C while the first unwound cut the writer's cleanup short: it is recorded."""
    from warp_esph import usd as usd_module

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)

    n = _steps_per_frame()
    _fail_after(monkeypatch, n + 1, lambda state: Finalized())  # inside frame 2
    out_path = tmp_path / "late.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress"]) == 130
    assert capsys.readouterr().err == f"warp-esph: interrupted: {out_path} keeps the 3 frames finished\n"
    assert frames_in(out_path) == [0.0, 1.0, 2.0]

    def interrupt(state):
        raise KeyboardInterrupt

    real_close = usd_module.UsdWriter.close

    def close_interrupted(self):
        os.kill(os.getpid(), signal.SIGINT)  # the second Ctrl-C, as the first is handled
        real_close(self)

    _fail_after(monkeypatch, 2 * n + 1, interrupt)  # inside frame 3
    monkeypatch.setattr(usd_module.UsdWriter, "close", close_interrupted)
    out_path = tmp_path / "twice.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress"]) == 130
    assert capsys.readouterr().err == f"warp-esph: interrupted: {out_path} keeps the 3 frames finished\n"
    assert frames_in(out_path) == [0.0, 1.0, 2.0]
    assert not [name for name in os.listdir(tmp_path) if name.startswith(".")]


def test_a_resume_stopped_before_its_first_frame_leaves_the_force_log_as_the_file(tmp_path, monkeypatch, capsys):
    """A run stopped in frame 7 keeps frames 0..6 and their log rows; its resume (from the
    checkpoint of frame 4) stopped before publishing a frame left the USD as it was, but cut
    the log back to frames 0..4: the rows of frames 5 and 6 were lost, their frames kept."""
    from warp_esph import usd as usd_module

    def interrupt(state):
        raise KeyboardInterrupt

    n = _steps_per_frame()
    _fail_after(monkeypatch, 6 * n + 1, interrupt)  # inside frame 7
    out_path = tmp_path / "r.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--checkpoint-every", "4",
                 "--no-progress"]) == 130
    assert frames_in(out_path) == [float(f) for f in range(7)] and log_frames(out_path) == {"plane0": list(range(7))}
    before = (tmp_path / "r.usdc_tools.json").read_bytes()
    monkeypatch.setattr(usd_module.UsdWriter, "write_frame", lambda self, frame, state: interrupt(state))
    capsys.readouterr()
    assert main(["run", "--resume", f"{out_path}.checkpoint.npz", "--no-progress"]) == 130
    assert capsys.readouterr().err == f"warp-esph: interrupted: {out_path} keeps frames 0..6 finished\n"
    assert frames_in(out_path) == [float(f) for f in range(7)]
    assert (tmp_path / "r.usdc_tools.json").read_bytes() == before


def test_a_resume_finds_its_output_and_scene_file_in_a_moved_folder(tmp_path, monkeypatch, capsys):
    """A checkpoint records the output's and the scene file's absolute paths: the resume of a
    run whose folder was moved since said 'cannot append to /old/folder/m.usdc: no such file'.
    Where the recorded file is gone, the one of its name beside the checkpoint is used; the
    output beside the checkpoint is used even where the recorded one is still there (a copy)."""
    from warp_esph.scenes import load_scene

    def interrupt(state):
        raise KeyboardInterrupt

    old, new = tmp_path / "old", tmp_path / "new"
    old.mkdir()
    (old / "s.toml").write_text(GOOD_TOML)
    scene = load_scene(str(old / "s.toml"))
    n = resolve_timestep(scene.builder.finalize(), scene.fps)[0]
    _fail_after(monkeypatch, 2 * n + 1, interrupt)  # inside frame 3
    monkeypatch.chdir(old)
    assert main(["run", "s.toml", "-o", "m.usdc", "--frames", "4", "--checkpoint-every", "2", "--no-progress"]) == 130
    monkeypatch.undo()
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    # A copy, the original still there: the resume appended to the original's file and
    # rewrote its checkpoint and force log, the copy left as it was.
    copy = tmp_path / "copy"
    shutil.copytree(old, copy)
    before = {name: (old / name).read_bytes() for name in os.listdir(old)}
    assert main(["run", "--resume", str(copy / "m.usdc.checkpoint.npz"), "--no-progress"]) == 0, capsys.readouterr().err
    assert f"-> {copy / 'm.usdc'} (resumed at frame 2" in capsys.readouterr().out
    assert frames_in(copy / "m.usdc", prim="/World/box0") == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert {name: (old / name).read_bytes() for name in os.listdir(old)} == before
    shutil.rmtree(copy)
    os.rename(old, new)
    assert main(["run", "--resume", str(new / "m.usdc.checkpoint.npz"), "--no-progress"]) == 0, capsys.readouterr().err
    assert f"-> {new / 'm.usdc'} (resumed at frame 2" in capsys.readouterr().out
    assert frames_in(new / "m.usdc", prim="/World/box0") == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert sorted(os.listdir(tmp_path)) == ["new"]


def test_full_disk_exit_4_keeps_published_frames(tmp_path, monkeypatch, capsys):
    """A write error mid-run (here: ENOSPC when frame 3 is published) keeps frames 0-2."""
    import errno

    from warp_esph import usd as usd_module

    real_replace, calls = os.replace, []

    def replace(src, dst):
        calls.append(dst)
        if len(calls) == 5:  # the empty file at the start, then frames 0, 1, 2 were published
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        real_replace(src, dst)

    monkeypatch.setattr(usd_module.os, "replace", replace)
    out_path = tmp_path / "full.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress"]) == 4
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "No space left on device" in err and "keeps the 3 frames" in err and str(out_path) in err
    assert frames_in(out_path) == [0.0, 1.0, 2.0]
    # No working copies left behind; the force log holds the published frames.
    assert sorted(os.listdir(tmp_path)) == ["full.usdc", "full.usdc_tools.csv", "full.usdc_tools.json"]
    assert log_frames(out_path) == {"plane0": [0, 1, 2]}


def test_a_file_size_limit_reached_by_the_usd_save_is_exit_4_not_a_damaged_input(tmp_path, capsys):
    """A real full disk: the limit on file size (RLIMIT_FSIZE; Python ignores SIGXFSZ, so the
    write fails with EFBIG) is met inside pxr's save, which raises its own error. That was
    taken for a damaged input file: exit 2, `cannot read ... (a damaged or foreign file?)`."""
    import resource

    args = ["run", "dough_drop", "--scale", "0.6", "--frames", "30", "--no-progress"]
    assert main([*args[:-2], "1", "--no-progress", "-o", str(tmp_path / "warm.usdc")]) == 0  # kernels in the cache
    limit = 100 * 1024  # frames 0..2 of 729 particles fit, frame 3 does not

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out_path = tmp_path / "full.usdc"
    p = subprocess.run([sys.executable, "-m", "warp_esph", *args, "-o", str(out_path)], env=env, capture_output=True,
                       text=True, timeout=120, preexec_fn=small_files)
    assert p.returncode == 4, p.stderr
    assert_one_line_error(p.stderr, f"cannot write {out_path}", "File too large", "keeps the")
    assert "cannot read" not in p.stderr
    kept = frames_in(out_path)
    assert kept and kept == [float(k) for k in range(len(kept))]
    assert log_frames(out_path) == {"plane0": list(range(len(kept)))}
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".")]  # no working copies left


def test_a_full_disk_at_the_runs_first_save_is_exit_4(tmp_path, monkeypatch, capsys):
    """The writer saves its empty stage at once: a full disk there raised out of the run
    before its failure handling, exit 2 as bad input."""
    import errno

    from warp_esph import usd as usd_module

    def full(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(usd_module.UsdWriter, "_save_and_publish", full)
    out = tmp_path / "b.usdc"
    assert main(["run", "dough_drop", "--scale", "0.3", "--frames", "2", "--no-progress", "-o", str(out)]) == 4
    assert_one_line_error(capsys.readouterr().err, f"cannot write {out}", "No space left on device",
                          "(no frame of this run was written)")


def test_a_full_disk_when_the_writer_creates_its_layers_is_exit_4_not_a_damaged_input(tmp_path, monkeypatch, capsys):
    """pxr writes a new layer as it creates it: a full disk there raised pxr's own error, which
    the command took for a damaged input (exit 2, 'cannot read ... (a damaged or foreign
    file?)', naming the output)."""
    from pxr import Sdf, Tf

    def full(*args, **kwargs):
        raise Tf.ErrorException("Error occurred writing file: No space left on device")

    monkeypatch.setattr(Sdf.Layer, "CreateNew", staticmethod(full))
    out = tmp_path / "b.usdc"
    assert main(["run", "dough_drop", "--scale", "0.3", "--frames", "2", "--no-progress", "-o", str(out)]) == 4
    assert_one_line_error(capsys.readouterr().err, f"cannot write {out}", "No space left on device",
                          "(no frame of this run was written)")
    assert os.listdir(tmp_path) == []


def test_a_checkpoint_that_cannot_be_written_is_named_not_the_usd(tmp_path, monkeypatch, capsys):
    """The disk fills while the checkpoint of frame 4 is saved: the one line names the
    checkpoint and what it still holds (it named the USD, which was written)."""
    import errno

    from warp_esph import checkpoint as checkpoint_module

    real_save = checkpoint_module.save_state

    def save_state(path, model, state, **kwargs):
        if kwargs["frame"] == 4:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_save(path, model, state, **kwargs)

    monkeypatch.setattr(checkpoint_module, "save_state", save_state)
    out_path = tmp_path / "c.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--checkpoint-every", "2",
                 "--no-progress"]) == 4
    assert_one_line_error(capsys.readouterr().err, f"cannot write the checkpoint {out_path}.checkpoint.npz",
                          "No space left on device", "it keeps frame 2", f"{out_path} keeps the 5 frames")
    assert frames_in(out_path) == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_a_checkpoint_that_cannot_be_written_where_none_is_left_does_not_say_it_keeps_one(tmp_path, monkeypatch, capsys):
    """A resume from a copy of the checkpoint (none beside the output) whose first save fails
    said 'it keeps frame 2' of a checkpoint file that was not there."""
    import errno
    import shutil

    from warp_esph import checkpoint as checkpoint_module

    out_path = tmp_path / "c.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "2", "--checkpoint-every", "2",
                 "--no-progress"]) == 0
    copy = tmp_path / "copy.npz"
    shutil.move(f"{out_path}.checkpoint.npz", copy)

    def full(path, model, state, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoint_module, "save_state", full)
    capsys.readouterr()
    assert main(["run", "--resume", str(copy), "--frames", "4", "--no-progress"]) == 4
    assert_one_line_error(capsys.readouterr().err, f"cannot write the checkpoint {out_path}.checkpoint.npz",
                          "(no checkpoint of this run is left there;", f"{out_path} keeps frames 0..4 finished")


def test_a_signal_held_while_a_checkpoint_fails_to_write_is_reported(tmp_path, monkeypatch, capsys):
    """A SIGTERM held while a --checkpoint-every checkpoint was written, whose write then
    failed (a full disk), was dropped: the run exited 4 as a plain failed write. The signal
    wins (143), the one line saying both, as a sweep's tables do."""
    import errno

    from warp_esph import checkpoint as checkpoint_module

    def terminated_then_full(path, model, state, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)  # held: the checkpoint is being written
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoint_module, "save_state", terminated_then_full)
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    out_path = tmp_path / "m.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(out_path), "--frames", "4", "--checkpoint-every", "2",
                 "--no-progress"]) == 143
    err = capsys.readouterr().err
    assert err.splitlines() == [f"warp-esph: terminated: cannot write the checkpoint {out_path}.checkpoint.npz: No space "
                                f"left on device (no checkpoint of this run is left there; {out_path} keeps the 3 frames "
                                "finished)"], err


def _fill_the_disk_at_the_last_force_log_write(monkeypatch, terminate=False):
    """The force log's write after the run's frames are all written fails as on a full disk
    (its earlier writes, at checkpoints, succeed); with ``terminate`` a SIGTERM comes while
    it is written, so the run holds it."""
    import builtins
    import errno

    from warp_esph import tools as tools_module
    from warp_esph import usd as usd_module

    ended, real_close = [], usd_module.UsdWriter.close

    def close(self):
        ended.append(True)  # the run's frames are all written: the log's last write comes next
        real_close(self)

    def open_(path, mode="r", *args, **kwargs):
        if ended and "_tools.json" in str(path) and "w" in mode:
            if terminate:
                os.kill(os.getpid(), signal.SIGTERM)  # held: the log is being written
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return builtins.open(path, mode, *args, **kwargs)

    monkeypatch.setattr(usd_module.UsdWriter, "close", close)
    monkeypatch.setattr(tools_module, "open", open_, raising=False)


def test_a_signal_held_while_the_last_force_log_write_fails_is_reported(tmp_path, monkeypatch, capsys):
    """A SIGTERM held while the force log's last write ran, which then failed, was dropped: the
    finished run exited 4. The signal wins (143), the one line naming the log."""
    _fill_the_disk_at_the_last_force_log_write(monkeypatch, terminate=True)
    out_path = tmp_path / "g.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "2", "--no-progress"]) == 143
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"warp-esph: terminated: cannot write the force log {out_path}_tools.csv, "
                                         f".json: No space left on device (it is left as it was; {out_path} keeps the 3 "
                                         "frames finished)"], captured.err
    assert "wrote" not in captured.out


def test_a_stopped_run_whose_writer_fails_to_close_still_exits_as_stopped(tmp_path, monkeypatch, capsys):
    """A run stopped by a SIGTERM whose writer then failed to close (its working copies not
    removed: a full disk, a folder made read-only) left with the close's OSError and exited 4,
    the signal dropped. The stop wins (143), its one line naming the failure."""
    import errno

    from warp_esph import usd as usd_module

    def close(self):
        os.kill(os.getpid(), signal.SIGTERM)  # the run's end: raised, or held inside the stop's close
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(usd_module.UsdWriter, "close", close)
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    out_path = tmp_path / "c.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(out_path), "--frames", "2", "--no-progress"]) == 143
    err = capsys.readouterr().err
    assert err.splitlines() == [f"warp-esph: terminated: cannot finish {out_path}: No space left on device (its working "
                                f"copies may be left beside it; it keeps the 3 frames finished)"], err
    # Unstopped, the same close is a failed write (it was exit 2, '[Errno 28] No space left on device').
    monkeypatch.setattr(usd_module.UsdWriter, "close", lambda self: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device")))
    out_path = tmp_path / "d.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(out_path), "--frames", "2", "--no-progress"]) == 4
    err = capsys.readouterr().err
    assert err.splitlines() == [f"warp-esph: error: cannot write {out_path}: No space left on device (it keeps the 3 frames "
                                "finished)"], err


@pytest.mark.parametrize("extra", [["--preview"], ["--export", "ply"]])
def test_a_full_disk_under_the_preview_or_export_of_a_finished_run_is_exit_4(tmp_path, monkeypatch, capsys, extra):
    """The run is whole; its picture or export files could not be written: exit 2, 'bad input',
    with the bare '[Errno 28] No space left on device', naming no file."""
    import errno

    import meshio
    from PIL import Image

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Image.Image, "save", full)
    monkeypatch.setattr(meshio, "write", full)
    out_path = tmp_path / "p.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "2", "--no-progress", *extra]) == 4
    if extra == ["--preview"]:
        needles = (f"--preview: cannot write {out_path}.png: No space left on device; {out_path} holds the whole run",)
    else:
        needles = (f"--export ply: cannot write {out_path}_ply/frame_00000.ply: No space left on device (0 of the 3 frames",
                   f"{out_path} holds the whole run")
    assert_one_line_error(capsys.readouterr().err, *needles)
    assert frames_in(out_path) == [0.0, 1.0, 2.0]


def test_a_force_log_that_cannot_be_written_is_exit_4_and_keeps_its_last_whole_version(tmp_path, monkeypatch, capsys):
    """The disk fills as the force log is written at the end of a finished run: one line naming
    the log, exit 4 (it was exit 2, 'bad input', naming no file), and the log as its last
    checkpoint wrote it, whole, the CSV and the JSON agreeing (it was cut where the disk filled)."""
    _fill_the_disk_at_the_last_force_log_write(monkeypatch)
    out_path = tmp_path / "g.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "5", "--checkpoint-every", "2",
                 "--no-progress"]) == 4
    captured = capsys.readouterr()
    assert_one_line_error(captured.err, f"cannot write the force log {out_path}_tools.csv, .json",
                          "No space left on device", f"{out_path} keeps the 6 frames")
    assert "wrote" not in captured.out
    assert frames_in(out_path) == [float(k) for k in range(6)]
    assert log_frames(out_path) == {"plane0": [0, 1, 2, 3, 4]}
    assert sorted(os.listdir(tmp_path)) == ["g.usdc", "g.usdc.checkpoint.npz", "g.usdc_tools.csv", "g.usdc_tools.json"]


def test_diverged_run_exit_3_keeps_frames(tmp_path, monkeypatch, capsys):
    def poison(state):
        x = state.x.numpy()
        x[5] = np.inf
        state.x.assign(x)

    n = _steps_per_frame()
    _fail_after(monkeypatch, n + 1, poison)  # inside frame 2: found after step 2 n
    out_path = tmp_path / "diverged.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert_one_line_error(err, f"step {2 * n}", "particle", "'dough'", "keeps the 2 frames")
    assert frames_in(out_path) == [0.0, 1.0]
    assert log_frames(out_path) == {"plane0": [0, 1]}


def _raise_interrupt(state):
    raise KeyboardInterrupt


def _poison(state):
    x = state.x.numpy()
    x[5] = np.inf
    state.x.assign(x)


@pytest.mark.parametrize("stop, status", [(_raise_interrupt, 130), (_poison, 3)], ids=["interrupted", "diverged"])
def test_a_run_that_stops_early_exports_its_finished_frames_and_no_earlier_run_s(tmp_path, monkeypatch, capsys, stop, status):
    """``run --export ply --preview`` that was interrupted or diverged wrote no frame file: its
    finished frames were in the USD alone, and the folder kept an earlier run's frames (of
    another length) and ``.png`` beside the new file, as if they were this run's. Now the
    finished frames are exported as the file holds them, and nothing of the earlier run's
    export or picture is left."""
    import meshio

    out_path = tmp_path / "e.usdc"
    folder = tmp_path / "e.usdc_ply"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "4", "--no-progress", "--export", "ply"]) == 0
    assert len(os.listdir(folder)) == 5
    (tmp_path / "e.usdc.png").write_bytes(b"an earlier run's picture")
    capsys.readouterr()
    n = _steps_per_frame()
    _fail_after(monkeypatch, 2 * n + 1, stop)  # inside frame 3 (a poisoned step is found as frame 3 ends)
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress", "--export", "ply",
                 "--preview"]) == status
    captured = capsys.readouterr()
    assert "wrote" not in captured.out and "Traceback" not in captured.err
    frames = frames_in(out_path)
    assert frames and frames == [float(k) for k in range(len(frames))]
    assert sorted(os.listdir(folder)) == [f"frame_{k:05d}.ply" for k in range(len(frames))]
    stage = open_fresh(out_path)
    points = stage.GetPrimAtPath("/World/dough").GetAttribute("points")
    for k in range(len(frames)):
        np.testing.assert_array_equal(meshio.read(folder / f"frame_{k:05d}.ply").points, np.asarray(points.Get(k), dtype=np.float64))
    assert not (tmp_path / "e.usdc.png").exists()


@pytest.mark.parametrize("error", [RuntimeError, ValueError, TypeError])
def test_an_unexpected_error_in_the_writer_mid_run_is_one_line_saying_what_the_file_keeps(tmp_path, monkeypatch, capsys, error):
    """An exception of no kind the run expects, raised by the writer (or the solver) once frames
    are written: a RuntimeError or TypeError left as a traceback (exit 1) that said nothing of
    the file; a ValueError was called bad input (exit 2), also silent on the file, and the
    run's --export frames were not written."""
    import meshio

    from warp_esph.usd import UsdWriter

    write_frame = UsdWriter.write_frame

    def failing(self, frame, state):
        if frame == 3:
            raise error("the writer broke")
        write_frame(self, frame, state)

    monkeypatch.setattr(UsdWriter, "write_frame", failing)
    out_path = tmp_path / "broken.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "6", "--no-progress", "--export", "ply"]) == 1
    captured = capsys.readouterr()
    assert "wrote" not in captured.out
    assert_one_line_error(captured.err, "the run stopped in frame 3", f"{error.__name__}: the writer broke",
                          f"{out_path} keeps the 3 frames finished")
    assert frames_in(out_path) == [0.0, 1.0, 2.0]
    assert sorted(os.listdir(tmp_path / "broken.usdc_ply")) == [f"frame_{k:05d}.ply" for k in range(3)]
    assert len(meshio.read(tmp_path / "broken.usdc_ply" / "frame_00002.ply").points) > 0
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # no working copy or lock left


def test_a_resumed_run_s_export_holds_the_frames_of_its_file_and_no_more(tmp_path, capsys):
    """A run resumed from its checkpoint at frame 8 to frame 9 rewrote its file to 10 frames,
    and its export folder kept the earlier run's frame 10 beside them."""
    out_path = tmp_path / "r.usdc"
    common = ["--no-progress", "--export", "ply"]
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--checkpoint-every", "4", *common]) == 0
    assert main(["run", "--resume", f"{out_path}.checkpoint.npz", "--frames", "9", *common]) == 0
    capsys.readouterr()
    assert frames_in(out_path) == [float(k) for k in range(10)]
    assert sorted(os.listdir(tmp_path / "r.usdc_ply")) == [f"frame_{k:05d}.ply" for k in range(10)]


def test_an_export_that_fails_after_a_run_stopped_keeps_the_run_s_status(tmp_path, monkeypatch, capsys):
    """The frames of an interrupted run are exported after its line; an export that could not
    read the file (removed meanwhile) replaced the stop's 130 with 2, 'bad input'."""
    import warp_esph.export as export_module

    def unreadable(path, *args, **kwargs):
        raise ValueError(f"cannot read {path}: no such file")

    monkeypatch.setattr(export_module, "export_frames", unreadable)
    _fail_after(monkeypatch, 2 * _steps_per_frame() + 1, _raise_interrupt)
    out_path = tmp_path / "gone.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress", "--export", "ply"]) == 130
    lines = capsys.readouterr().err.splitlines()
    assert lines == [f"warp-esph: interrupted: {out_path} keeps the 3 frames finished",
                     f"warp-esph: error: --export ply: cannot read {out_path}: no such file; {out_path} keeps the 3 frames finished"]


def test_a_run_the_neighbour_search_stops_exits_3_naming_step_and_frame(tmp_path, monkeypatch, capsys):
    """A step the neighbour search stops (``NeighborOverflow``: a body crushed together, or a
    blow-up) left ``run`` as a traceback, the step, frame and time said nowhere. It is one line
    now, as a divergence's, naming them and what the file keeps, exit 3."""
    from warp_esph.sim.neighbors import NeighborOverflow  # noqa: PLC0415

    def overflow(state):
        raise NeighborOverflow("a particle has 5000 particles within h s + skin = 0.04 s + 0.006: more than 4096; "
                               "the body has collapsed (reduce dt)", particles=[7], need=5000)

    n = _steps_per_frame()
    _fail_after(monkeypatch, n + 2, overflow)  # the second step of frame 2
    out_path = tmp_path / "collapsed.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "10", "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert_one_line_error(err, f"stopped in step {n + 2} (frame 2, t = ", "more than 4096; the body has collapsed",
                          "(particle 7 of body 'dough'", "keeps the 2 frames")
    assert frames_in(out_path) == [0.0, 1.0]


def _run_subprocess(*args, cwd):
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def test_a_reader_that_leaves_is_not_bad_input_and_leaves_no_traceback(tmp_path):
    """``warp-esph scenes | head -1``: the reader closed the pipe before the listing was
    written. Not exit 2 (bad input) with 'Broken pipe', not a traceback from the flush at
    exit: 141, as a shell reports a writer stopped by SIGPIPE, and nothing on stderr."""
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def reader_gone(*args):
        """Run ``python -m warp_esph ARGS`` with a standard output whose reader is gone before
        it starts: its exit status and stderr. (Closed after the start, the reader raced the
        child: one slower to close than the child to write its short listing into the pipe's
        buffer saw it exit 0.)"""
        read_end, write_end = os.pipe()
        os.close(read_end)
        try:
            # As a context manager: the stderr pipe read here is closed with it (left open, unclosed).
            with subprocess.Popen([sys.executable, "-m", "warp_esph", *args], cwd=tmp_path, env=env, stdout=write_end,
                                  stderr=subprocess.PIPE, text=True) as p:
                os.close(write_end)
                write_end = None
                err = p.stderr.read()
                return p.wait(timeout=120), err
        finally:
            if write_end is not None:
                os.close(write_end)

    status, err = reader_gone("scenes")
    assert status == 141 and err == "", (status, err)
    # A run whose reader left: not a write failure of its output file (exit 4).
    status, err = reader_gone("run", "three_cylinders", "-o", "c.usdc", *TINY)
    assert status == 141 and "Traceback" not in err and "cannot write" not in err, (status, err)


_SMALL_RUN = ["run", "three_cylinders", "-o", "c.usdc", "--scale", "0.3", "--frames", "2", "--no-progress"]


def _console_run_in_a_child(tmp_path, prelude: str, env=None, argv=_SMALL_RUN):
    """``console_main`` running ``warp-esph argv`` (a small three_cylinders run) in a child
    Python after ``prelude`` (which may set up what sends it signals), its SIGINT handled as in
    a terminal: a runner started in the background starts its children ignoring it."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = REPO + os.pathsep + os.environ.get("PYTHONPATH", "")
    code = textwrap.dedent(prelude) + textwrap.dedent(f"""
        from warp_esph.cli import console_main
        sys.argv = {["warp-esph", *argv]!r}
        sys.exit(console_main())
    """)
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def test_a_signal_as_the_process_ends_does_not_kill_it_by_the_default_action(tmp_path):
    """Python's shutdown resets the signal handlers to the default action before it tears
    the modules down: a Ctrl-C there (here sent by an object of ``__main__`` as it is torn
    down) killed a finished run by SIGINT (-2, no line). The command now ends with its own
    status once its work is done, so no shutdown follows it."""
    p = _console_run_in_a_child(tmp_path, """
        import os, signal, sys
        class Probe:
            def __del__(self):
                os.kill(os.getpid(), signal.SIGINT)
        probe = Probe()
    """)
    assert p.returncode == 0, (p.returncode, p.stderr)
    assert "wrote" in p.stdout and "guard counts" in p.stdout  # the streams flushed before the end
    assert p.stderr == "", p.stderr


_SECOND_CTRL_C = """
    import os, signal, sys
    from warp_esph import cli, usd
    real_write, real_kept = usd.UsdWriter.write_frame, cli._kept
    def write_frame(self, frame, state):
        if frame == 3:
            os.kill(os.getpid(), signal.SIGINT)  # the first: raised, the run stops
        return real_write(self, frame, state)
    def kept(writer, start_frame):
        os.kill(os.getpid(), signal.SIGINT)  # the second, as the command says what its file keeps
        open("went-on", "w").close()
        return real_kept(writer, start_frame)
    usd.UsdWriter.write_frame, cli._kept = write_frame, kept
"""


def test_a_second_ctrl_c_after_the_first_was_raised_ends_the_command_at_once_its_force_log_whole(tmp_path):
    """After the first Ctrl-C was raised every further one was ignored until the command
    ended: a fit writing its pictures or a sweep waiting on its workers could be ended only
    by SIGKILL. A further one outside a write that must finish now ends the process at once
    (its one line, 130); the output keeps its finished frames, whole. Here the second comes
    as the interrupted run says what its file keeps, and the command would go on after it.

    The force log of a run without checkpoints was written only in the run's last cleanup
    step: a second Ctrl-C while the 'interrupted ... keeps N frames' line was built ended the
    process with the USD whole and no log. The log is now written (a further signal waiting
    for it) before that line: it holds the rows of the frames the USD keeps. (One child for
    both: each was a run of its own, through the same two signals at the same points, the
    first of three_cylinders, whose force log this default scene's plane also has.)"""
    p = _console_run_in_a_child(tmp_path, _SECOND_CTRL_C,
                                argv=["run", "-o", "d.usdc", "--scale", "0.3", "--frames", "10", "--no-progress"])
    assert p.returncode == 130, (p.returncode, p.stderr)
    assert p.stderr == "warp-esph: interrupted\n", p.stderr
    assert not (tmp_path / "went-on").exists()
    assert frames_in(tmp_path / "d.usdc") == [0.0, 1.0, 2.0]
    # Its force log is written before that line (a second Ctrl-C there lost it).
    assert sorted(os.listdir(tmp_path)) == ["d.usdc", "d.usdc_tools.csv", "d.usdc_tools.json"]
    assert log_frames(tmp_path / "d.usdc") == {"plane0": [0, 1, 2]}  # the finished frames, as in the USD


def test_a_signal_while_the_exit_functions_run_leaves_the_command_s_status(tmp_path):
    """The handler was disarmed before the exit functions ran (``_leave``): a Ctrl-C there
    made a finished run exit 130 'interrupted'. It is now recorded, and the process ends with
    the command's own status. Native output held in the C library's buffer for a redirected
    stdout (as Warp's and pxr's notes are) is flushed before the end, not lost."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # the C library's buffer as by default
    p = _console_run_in_a_child(tmp_path, """
        import atexit, ctypes, os, signal, sys
        atexit.register(lambda: os.kill(os.getpid(), signal.SIGINT))
        atexit.register(lambda: ctypes.CDLL(None).printf(b"a native line\\n"))  # the last native output
    """, env)
    assert p.returncode == 0, (p.returncode, p.stderr)
    assert "wrote" in p.stdout and p.stderr == "", p.stderr
    assert "a native line" in p.stdout


def test_a_run_whose_standard_error_reader_left_goes_on_without_its_progress_bar(tmp_path):
    """``warp-esph run ... 2> >(head -c 1)``: the progress bar's write met a closed pipe
    (BrokenPipeError), and the run ended with exit 1 after two frames, its traceback written
    to nobody. The bar now stops drawing and the run finishes its frames, exit 0. (Here the
    pipe's reader is gone before the run starts: every write to stderr fails.)"""
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        p = subprocess.run([sys.executable, "-m", "warp_esph", "run", "dough_drop", "--scale", "0.3", "--frames", "4",
                            "-o", "e.usdc"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=write_end, text=True,
                           timeout=120)
    finally:
        os.close(write_end)
    assert p.returncode == 0, p.stdout
    assert f"wrote {tmp_path / 'e.usdc'}: 5 frames" in p.stdout
    assert frames_in(tmp_path / "e.usdc") == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_an_absurd_scale_is_refused_naming_scale_not_the_body(tmp_path, capsys):
    """``--scale 1e-300`` divides the spacing into 5e+298 m: the scene's checks blamed the
    body ('it is smaller than the spacing 5e+298') or its centre (--scale 1e300), as if the
    scene file were wrong. Where the scene builds at --scale 1, the refusal names --scale."""
    path = tmp_path / "s.toml"
    path.write_text(GOOD_TOML)
    for scene, scale, why in ((str(path), "1e-300", "smaller than the spacing 5e+298"),
                              # the spacing it divides into, 5e-302 m, is one no precision builds
                              (str(path), "1e300", "spacing = 5e-302 is not allowed: must be at least 4.4e-35"),
                              ("dough_drop", "1e-300", "body 'dough' has no particles")):
        assert main(["run", scene, "--scale", scale, "--frames", "1", "--no-progress", "-o", str(tmp_path / "x.usdc")]) == 2
        assert_one_line_error(capsys.readouterr().err, f"--scale = {float(scale):g} is not allowed for {scene}: it builds at "
                              "--scale 1", why, "give a --scale nearer 1")
    assert not (tmp_path / "x.usdc").exists()
    # A scene file wrong at any scale keeps its own error, not one blaming --scale.
    path.write_text(GOOD_TOML.replace("size = [0.2, 0.15, 0.2]", "size = [0.2, -0.15, 0.2]"))
    assert main(["run", str(path), "--scale", "0.5", "--frames", "1", "--no-progress", "-o", str(tmp_path / "x.usdc")]) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, "size")
    assert "--scale" not in err


def test_a_too_fast_body_of_a_scene_file_is_named_by_its_table(tmp_path, capsys):
    """A body too fast for the step said '[[bodies]] initial velocity ...' without its table's
    number, unlike the file's other refusals ('[[bodies]] #2 (shape 'box'): ...')."""
    path = tmp_path / "fast.toml"
    second = GOOD_TOML.split("[[bodies]]")[1].split("[[colliders]]")[0]
    second = second.replace("center = [0.0, 0.15, 0.0]", "center = [0.6, 0.15, 0.0]\nvelocity = [1e6, 0.0, 0.0]")
    path.write_text(GOOD_TOML.replace("[[colliders]]", "[[bodies]]" + second + "[[colliders]]"))
    for dt in ([], ["--dt", "auto"]):
        assert main(["run", str(path), "--frames", "1", "--no-progress", "-o", str(tmp_path / "f.usdc"), *dt]) == 2
        assert_one_line_error(capsys.readouterr().err,
                              f"{path}: [[bodies]] #2 (shape 'box'): initial velocity of body 'box1'", "1e+06 m/s")


def test_run_refusing_a_start_the_step_cannot_follow_names_its_own_options(tmp_path, capsys):
    """A start faster than a spacing a step, and an adaptive step too short for the material,
    were refused by 'warp-esph run' with a Python caller's advice ('a smaller dt, or the
    adaptive step'; 'a higher fps'): the command names --dt, --dt auto and --fps, as Python
    names dt=, dt='auto' and fps=."""
    from warp_esph.scenes import load_scene  # noqa: PLC0415
    from warp_esph.simulate import check_start_speed, simulate  # noqa: PLC0415

    path = tmp_path / "fast.toml"
    path.write_text(GOOD_TOML.replace("center = [0.0, 0.15, 0.0]", "center = [0.0, 0.15, 0.0]\nvelocity = [1e6, 0.0, 0.0]"))
    out = tmp_path / "f.usdc"
    assert main(["run", str(path), "--frames", "1", "--no-progress", "-o", str(out), "--dt", "1e-3", "--fps", "50"]) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, f"{path}: [[bodies]] #1 (shape 'box'): initial velocity of body 'box0': a speed of 1e+06 m/s")
    assert err.rstrip().endswith("so at most 50 m/s; give a smaller velocity (or angular_velocity), a smaller --dt, "
                                 "or --dt auto (the adaptive step)"), err
    model = load_scene(str(path)).builder.finalize()
    with pytest.raises(ValueError, match=r"so at most 50 m/s; give a smaller velocity \(or angular_velocity\), a smaller "
                                         r"dt=, or dt='auto' \(the adaptive step\)$"):
        check_start_speed(model, model.state(), 50.0, 1e-3)
    # A frame of 100 s: the gravity it adds (981 m/s) takes the adaptive step below 1e-4 s, though
    # the stable step (3 ms) is 3.2e4 steps a frame. It was called 'its stable step, 1.52e-05 s'
    # and a softer material advised, which leaves gravity's term as it is.
    path.write_text(GOOD_TOML)
    assert main(["run", str(path), "--frames", "1", "--no-progress", "-o", str(out), "--dt", "auto", "--fps", "0.01"]) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, f"{path}: the adaptive step is not allowed for this model at 0.01 fps: its step C dx / (c_P "
                               "+ v_max + |g| / fps) = 1.52e-05 s (c_P = 4.75 m/s, v_max = 0 m/s, |g| / fps = 981 m/s, at "
                               "spacing 0.05 m; the stable step is 0.00316 s), would take 6.57e+06 steps a frame")
    assert err.rstrip().endswith("; use a higher --fps (gravity adds up to |g| / fps to a speed within a frame) or a larger "
                                 "spacing"), err
    model = load_scene(str(path)).builder.finalize()
    with pytest.raises(ValueError, match=r"; use a higher fps= \(gravity adds up to \|g\| / fps to a speed within a frame\) "
                                         r"or a larger spacing$"):
        simulate(model, 1, fps=0.01, dt="auto", progress=False)
    assert not out.exists()


def test_subprocess_bad_input(tmp_path):
    # (A run started as ``python -m warp_esph.cli`` that succeeds: the child of
    # test_a_process_started_with_its_standard_error_closed_runs.)
    # A scene-file error after Warp has started: still exactly one line (no native Warp notes).
    (tmp_path / "typo.toml").write_text(GOOD_TOML.replace("center = [0.0, 0.15, 0.0]", "centre = [0.0, 0.15, 0.0]"))
    bad = _run_subprocess("warp_esph", "run", "typo.toml", "--no-progress", cwd=tmp_path)
    assert bad.returncode == 2
    assert_one_line_error(bad.stderr, "'centre'", "did you mean 'center'")


def test_init_warp_holds_back_only_the_native_cuda_note(capfd, monkeypatch, tmp_path):
    """``we.init_warp()`` (the notebooks' and the CLI's start): a Python process starting Warp
    this way writes nothing on stderr on a CPU machine, where a bare ``wp.init()`` writes
    Warp's native CUDA-driver note; other native output still reaches stderr. The same child
    then runs a 2-frame ``run`` through ``cli.main``: a successful run writes nothing on
    stderr either (no traceback, no warning)."""
    from warp_esph.startup import _native_notes

    notes = _native_notes(lambda: os.write(2, b"native note A\nWarp CUDA warning: no driver\n"))
    assert notes == ["native note A", "Warp CUDA warning: no driver"]
    os.write(2, b"after\n")  # fd 2 is back where it was
    assert capfd.readouterr().err == "after\n"

    code = ("import warp as wp, warp_esph as we; print(len(we.init_warp())); print(wp.get_device())\n"
            "from warp_esph.cli import main\n"
            "print('rc', main(['run', 'dough_drop', '--scale', '0.3', '--frames', '2', '-o', 'q.usdc', '--no-progress']))")
    quiet = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert quiet.returncode == 0, quiet.stderr
    assert "CUDA" not in quiet.stderr and "Warp" not in quiet.stderr and "Warp" not in quiet.stdout
    assert quiet.stderr == "" and "rc 0" in quiet.stdout and (tmp_path / "q.usdc").stat().st_size > 0, quiet.stderr
    bare = subprocess.run([sys.executable, "-c", "import warp as wp; wp.config.log_level = wp.LOG_WARNING; wp.init()"],
                          capture_output=True, text=True, timeout=120)
    held = int(quiet.stdout.split()[0])
    # Whatever a bare start prints natively is what init_warp held back (none on a GPU machine).
    assert held == len([line for line in bare.stderr.splitlines() if line.strip()])
    # Of the notes a start prints, only the CUDA-driver one is held back: the rest are echoed.
    # (In this process, as if Warp had not started: its start replaced by one printing two notes.)
    import warp as wp
    from warp._src import context

    from warp_esph import startup

    with monkeypatch.context() as m:
        m.setattr(context, "runtime", None)
        m.setattr(wp.config, "log_level", wp.config.log_level)
        m.setattr(startup, "_native_notes", lambda init: ["native note A", "Warp CUDA warning: no driver"])
        assert len(startup.init_warp()) == 2
    assert capfd.readouterr().err == "native note A\n"


def test_init_warp_refuses_a_device_a_log_level_or_echo_it_cannot_take():
    """``init_warp(log_level="debug")`` ended in Python's 'invalid literal for int()', naming no
    parameter; ``log_level=2.5`` was taken as 2, ``device="gpu"`` (a name no Warp device has)
    and ``echo="no"`` (echoed) without a word. Each is refused naming it, before the log level
    is touched; Warp's own device names still serve."""
    import warp as wp

    from warp_esph.startup import init_warp

    level = wp.config.log_level
    for kw, said in (({"log_level": "debug"}, r"log_level = 'debug' is not allowed: must be an integer, e.g. wp\.LOG_WARNING"),
                     ({"log_level": 2.5}, r"log_level = 2\.5 is not allowed: must be an integer"),
                     ({"log_level": True}, r"log_level = True is not allowed: must be an integer"),
                     ({"device": "gpu"}, r"device = 'gpu' is not allowed: must be None, 'cpu', 'cuda' or 'cuda:N'"),
                     ({"device": 0}, r"device = 0 is not allowed: must be None, 'cpu', 'cuda' or 'cuda:N'"),
                     ({"echo": "no"}, r"echo = 'no' is not allowed: must be True or False")):
        with pytest.raises(ValueError, match=f"^{said}"):
            init_warp(**kw)
        assert wp.config.log_level == level
    for device in (None, "cpu", "cuda", "cuda:1"):
        assert init_warp(device, log_level=level, echo=False) == []  # Warp has started: nothing held back


def test_init_warp_takes_a_warp_device():
    """A Warp ``Device`` (``model.device``, ``wp.get_device()``, what ``finalize(device=...)``
    takes) is a device Warp has, yet ``init_warp(wp.get_device("cpu"))`` was refused as
    "device = 'cpu' is not allowed: must be None, 'cpu', 'cuda' or 'cuda:N'", naming a value it
    allows."""
    import warp as wp

    from warp_esph.startup import init_warp

    level = wp.config.log_level
    assert init_warp(wp.get_device("cpu"), log_level=level, echo=False) == []  # Warp has started: nothing held back


def test_a_process_started_with_its_standard_error_closed_runs(tmp_path, monkeypatch):
    """Started with descriptor 2 closed (2>&-), Python leaves sys.stderr None: Warp's start
    (``sys.stderr.flush()``) and then the progress bar raised AttributeError, exit 1, and the
    run never ran."""
    from warp_esph import usd
    from warp_esph.startup import _native_notes

    monkeypatch.setattr(sys, "stderr", None)
    assert _native_notes(lambda: None) == []
    with usd._native_stderr() as notes:
        pass
    assert notes == []
    monkeypatch.undo()
    # Started as ``python -m warp_esph.cli`` (the module's own entry; ``-m warp_esph`` is the
    # child of test_a_run_whose_standard_error_reader_left_goes_on_without_its_progress_bar),
    # a scene of three bodies, each of which is written.
    out = tmp_path / "quiet.usdc"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run([sys.executable, "-m", "warp_esph.cli", "run", "three_cylinders", "--scale", "0.3", "--frames",
                           "2", "-o", str(out)], stdout=subprocess.PIPE, text=True, timeout=300, env=env, cwd=tmp_path,
                          preexec_fn=lambda: os.close(2))
    assert done.returncode == 0, done.stdout
    assert f"wrote {out}: 3 frames" in done.stdout
    stage = open_fresh(out)
    for name in ("elastic", "plastic", "very_plastic"):
        assert stage.GetPrimAtPath(f"/World/{name}").GetAttribute("points").GetTimeSamples() == [0.0, 1.0, 2.0]


def test_a_run_with_the_adaptive_step_resumes_bit_for_bit(tmp_path, capsys):
    """``--dt auto`` records its dt as "auto" and its checkpoints' step as -1 (the step count
    is no function of the frame): the resume refused both ("dt = 'auto' is not allowed: must
    be a number"), so no adaptive run could be resumed."""
    from warp_esph.usd import UsdFrames

    args = ["run", "dough_drop", "--scale", "0.3", "--dt", "auto", "--no-progress"]
    assert main([*args, "--frames", "3", "-o", str(tmp_path / "whole.usdc")]) == 0
    assert main([*args, "--frames", "2", "--checkpoint-every", "1", "-o", str(tmp_path / "part.usdc")]) == 0
    assert main(["run", "--resume", str(tmp_path / "part.usdc.checkpoint.npz"), "--frames", "3", "--no-progress"]) == 0
    part, whole = UsdFrames(tmp_path / "part.usdc"), UsdFrames(tmp_path / "whole.usdc")
    for k in range(4):
        np.testing.assert_array_equal(part.arrays(k)["points"], whole.arrays(k)["points"])
    capsys.readouterr()


def test_a_failed_run_whose_file_is_gone_does_not_say_it_keeps_frames(tmp_path):
    """The output folder removed during a run: the failure said the file 'keeps the 3 frames
    finished' of a file that no longer existed."""
    import types

    from warp_esph.cli import _kept

    path = tmp_path / "gone" / "b.usdc"
    writer = types.SimpleNamespace(path=str(path), frames_written=3, last_frame=2)
    assert _kept(writer, 0) == "nothing: the file is gone"
    path.parent.mkdir()
    path.write_bytes(b"")
    assert _kept(types.SimpleNamespace(path=str(path), frames_written=0, last_frame=None), 0) == "no frame: none was finished"
    assert _kept(writer, 0) == "the 3 frames finished" and _kept(writer, 1) == "frames 0..2 finished"


def _unsimulated_usd(tmp_path, frames=3):
    """The tiny box scene (``GOOD_TOML``) written as ``frames`` frames of its start, without
    running it: a USD file render, export and a fit read as a run's."""
    from warp_esph.scenes import load_scaled_scene  # noqa: PLC0415
    from warp_esph.usd import UsdWriter  # noqa: PLC0415

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    model = load_scaled_scene(str(tmp_path / "s.toml"), 1.0).builder.finalize(dtype="float64")
    state = model.state(requires_grad=False)
    path = tmp_path / "a.usdc"
    with UsdWriter(path, model, 30.0) as writer:
        for f in range(frames):
            writer.write_frame(f, state)
    return path


def test_every_command_refuses_an_output_whose_parent_folder_is_missing(tmp_path, capsys):
    """A folder output is created, but not its missing parents: export, sweep and render into a
    folder built the whole tree ('/nonexist/q/sw') while run and render into a file refused it."""
    usd = _unsimulated_usd(tmp_path)
    missing = tmp_path / "nonexist"
    commands = {
        "run": ["run", str(tmp_path / "s.toml"), "-o", str(missing / "x.usdc"), "--no-progress"],
        "render file": ["render", str(usd), "-o", str(missing / "x.png")],
        "render folder": ["render", str(usd), "-o", str(missing / "x")],
        "export": ["export", str(usd), "-o", str(missing / "x")],
        "sweep": ["sweep", str(tmp_path / "s.toml"), "--param", "yield_stress=100", "--workers", "1", "--no-progress",
                  "-o", str(missing / "q" / "sw")],
        "fit": ["fit", str(tmp_path / "s.toml"), "--target", str(usd), "--no-progress", "--iterations", "1",
                "--output-dir", str(missing / "f")],
    }
    for name, argv in commands.items():
        assert main(argv) == 2, name
        err = capsys.readouterr().err
        option = "--output-dir" if name == "fit" else "--output"
        parent = missing / "q" if name == "sweep" else missing
        assert_one_line_error(err, f"{option} = ", f"its folder {str(parent)!r} does not exist")
        assert not missing.exists(), name
    # The folder itself is still created where its parent is there.
    assert main(["export", str(usd), "-o", str(tmp_path / "frames")]) == 0
    assert sorted(os.listdir(tmp_path / "frames"))[:1] == ["frame_00000.vtu"]
    capsys.readouterr()


def test_every_command_refuses_a_folder_output_given_with_a_slash_where_a_file_is(tmp_path, capsys):
    """``-o taken/`` where ``taken`` is a file passed the check (a path with a trailing slash
    does not exist where its stem is a file): render and export said '[Errno 17] File exists:
    'taken/'', a sweep ran every sample and a fit the whole fit before the same error, exit 4
    and their results lost. Each is now refused before any work, as ``-o taken`` is."""
    usd = _unsimulated_usd(tmp_path)
    taken = tmp_path / "taken"
    taken.write_text("mine")
    for slash in ("/", "//"):
        where = str(taken) + slash
        commands = {
            "render": ["render", str(usd), "-o", where],
            "export": ["export", str(usd), "-o", where],
            "sweep": ["sweep", str(tmp_path / "s.toml"), "--param", "yield_stress=100", "--workers", "1",
                      "--no-progress", "-o", where],
            "fit": ["fit", str(tmp_path / "s.toml"), "--target", str(usd), "--no-progress", "--iterations", "1",
                    "--output-dir", where],
        }
        for name, argv in commands.items():
            assert main(argv) == 2, name
            option = "--output-dir" if name == "fit" else "--output"
            assert_one_line_error(capsys.readouterr().err, f"{option} = {where!r} is not allowed: it is a file; "
                                  "a folder is written there")
            assert taken.read_text() == "mine"
    from warp_esph.sweep import SweepTable, write_outputs  # noqa: PLC0415

    with pytest.raises(ValueError, match=r"^folder = .*taken/' is not allowed: it is a file; the sweep's tables"):
        write_outputs(SweepTable([], [], []), str(taken) + "/")


def test_run_given_a_usd_file_or_a_checkpoint_says_what_it_is_and_which_command_reads_it(tmp_path, capsys):
    """``run out.usdc`` (a run's output given where the scene goes) said 'invalid TOML: not
    UTF-8 text (byte 16)', ``run out.usda`` 'invalid TOML: Invalid statement (at line 1, column
    1)' and ``run out.usdc.checkpoint.npz`` likewise, naming neither what the file is nor the
    command that reads it (``render`` says it of a scene file the other way round)."""
    usd = _unsimulated_usd(tmp_path)
    text = tmp_path / "a.usda"
    text.write_text('#usda 1.0\n(\n    upAxis = "Y"\n)\n')
    checkpoint = tmp_path / "a.usdc.checkpoint.npz"
    np.savez(checkpoint, x=np.zeros(3))
    before = {p: p.read_bytes() for p in (usd, text, checkpoint)}
    for given, said in ((usd, "it is a USD file, a run's output: 'warp-esph render' draws it, 'warp-esph export' exports it, "
                              "'warp-esph fit SCENE --target' fits to it; a scene file is TOML (docs/scene_format.md)"),
                        (text, "it is a USD file, a run's output"),
                        (checkpoint, "it is a .npz file, a checkpoint's or a fit target's: 'warp-esph run --resume' resumes a "
                                     "checkpoint; a scene file is TOML (docs/scene_format.md)")):
        assert main(["run", str(given), "--no-progress"]) == 2
        assert_one_line_error(capsys.readouterr().err, f"{given.name}: invalid TOML: ", said)
    assert {p: p.read_bytes() for p in before} == before


def test_a_kernel_cache_folder_warp_cannot_make_is_one_line_naming_warp_cache_path(tmp_path):
    """``WARP_CACHE_PATH`` naming a file, or a folder whose parent is missing, was one line
    naming neither the variable nor what is allowed (``warp-esph: error: [Errno 20] Not a
    directory: '.../cache/1.19.0'``), and ``init_warp()`` Warp's ``NotADirectoryError``
    traceback from inside ``wp.init``. Each now names the variable, its value and what it
    must be, before any scene is read."""
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    a_file = tmp_path / "cache"
    a_file.write_text("")
    for given in (a_file, a_file / "sub"):
        env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""), WARP_CACHE_PATH=str(given))
        said = (f"WARP_CACHE_PATH = {str(given)!r} is not allowed: Warp keeps its compiled kernels in a folder there, "
                "and cannot make ")
        p = subprocess.run([sys.executable, "-m", "warp_esph", "run", "s.toml", "--no-progress"], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 2, p.stderr
        assert_one_line_error(p.stderr, said, "give a folder that is there or can be made, or unset WARP_CACHE_PATH")
        assert not (tmp_path / "tiny.usdc").exists()
        p = subprocess.run([sys.executable, "-c", "import warp_esph as we\ntry:\n    we.init_warp()\n"
                            "except ValueError as e:\n    print(e)"], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=120)
        assert p.returncode == 0 and p.stdout.startswith(said) and "Traceback" not in p.stderr, p.stderr
    assert a_file.read_text() == ""


def test_the_iteration_cap_is_the_one_the_help_and_the_docs_give(capsys):
    from warp_esph.fit import MAX_ITERATIONS, check_options  # noqa: PLC0415

    assert check_options(params="mu", iterations=MAX_ITERATIONS)["iterations"] == MAX_ITERATIONS
    with pytest.raises(ValueError, match=rf"^iterations = {MAX_ITERATIONS + 1} is not allowed: must be at most {MAX_ITERATIONS} "):
        check_options(params="mu", iterations=MAX_ITERATIONS + 1)
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    assert f"at most {MAX_ITERATIONS})" in " ".join(capsys.readouterr().out.split())
    with open(os.path.join(REPO, "docs", "cli.md")) as fh:
        assert f"at most\n  {MAX_ITERATIONS}:" in fh.read()


def test_a_frame_or_swept_value_named_twice_is_refused_naming_the_option_and_the_value(tmp_path, capsys):
    """A sheet drew ``--frames 1,1`` twice, a fit's USD target weighed a repeated frame twice,
    and a sweep ran ``yield_stress=1,1`` as two identical samples. A GIF may still repeat a
    frame (it holds it), which ``tests/test_render.py`` checks."""
    usd = _unsimulated_usd(tmp_path)
    (tmp_path / "s.toml").write_text(GOOD_TOML)
    cases = [
        (["render", str(usd), "-o", str(tmp_path / "sheet.png"), "--frames", "1,1"],
         "--frames = '1,1' is not allowed: it names frame 1 twice; name each frame once"),
        (["render", str(usd), "-o", str(tmp_path / "pics"), "--frames", "last,2"], "--frames = 'last,2' is not allowed: it names frame 2 twice"),
        (["export", str(usd), "-o", str(tmp_path / "vtu"), "--frames", "0:2,1"], "--frames = '0:2,1' is not allowed: it names frame 1 twice"),
        (["fit", str(tmp_path / "s.toml"), "--target", str(usd), "--target-frames", "1,2,1", "--no-progress", "--iterations", "1",
          "--output-dir", str(tmp_path / "fit")], "--target-frames = '1,2,1' is not allowed: it names frame 1 twice"),
        (["sweep", str(tmp_path / "s.toml"), "--param", "yield_stress=1,1", "--workers", "1", "--no-progress", "-o",
          str(tmp_path / "sw")], "--param yield_stress: value 1.0 is not allowed twice: each value is a sample; give it once"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        assert_one_line_error(capsys.readouterr().err, message)
    assert sorted(os.listdir(tmp_path)) == ["a.usdc", "s.toml"]  # nothing drawn, written or run
def test_a_fitted_run_another_writer_is_writing_is_refused_naming_the_folder_and_the_files_written(tmp_path, capsys):
    """A fit whose fitted.usdc another writer holds (a second fit into the same folder): the
    line named the library's parameter ('path = 'fit/fitted.usdc' is not allowed') and nothing
    of the files the finished fit had written before it."""
    from warp_esph.scenes import load_scene
    from warp_esph.usd import UsdWriter

    (tmp_path / "s.toml").write_text(GOOD_TOML)
    run = tmp_path / "truth.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress", "--dtype", "float64"]) == 0
    out = tmp_path / "fit"
    out.mkdir()
    model = load_scene(str(tmp_path / "s.toml")).builder.finalize()
    capsys.readouterr()
    with UsdWriter(out / "fitted.usdc", model, 30):
        assert main(["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "0",
                     "--no-diagnostics", "--output-dir", str(out)]) == 2
    kept = ", ".join(f"{out}/{name}" for name in ("fit.json", "history.csv", "loss.png", "params.png"))
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"warp-esph: error: --output-dir = '{out}' is not allowed: another writer of this process ({os.getpid()}) is "
        f"writing {out}/fitted.usdc; close() that one first, or write another file (the fit's results are printed above; wrote "
        f"{kept} before it)")
    assert sorted(os.listdir(out)) == ["fit.json", "history.csv", "loss.png", "params.png"]


@pytest.mark.parametrize("command", ["run", "sweep", "fit"])
def test_the_solver_fit_help_names_the_rest_configuration_model(command, capsys):
    """``--solver-fit auto`` runs the rest-configuration model for purely elastic scenes
    (``Model.auto_runs_rest``), as docs/cli.md says; the help named only the incremental
    curvature-corrected fit."""
    with pytest.raises(SystemExit):
        main([command, "--help"])
    # Without the white space, which the help's wrapping moves (and puts after a hyphen).
    text = "".join(capsys.readouterr().out.split())
    auto = text[text.rindex("--solver-fitNAME"):]
    for said in ("auto (where no material can flow and all use the variational force, the rest-configuration model",
                 "tools allowed; in a scene with floor images or a ghost floor the incremental curvature_corrected fit"):
        assert "".join(said.split()) in auto


def test_the_run_record_and_the_usd_file_say_which_model_auto_ran(tmp_path, capsys):
    """``fit = "auto"`` resolves by the materials: the dough (it can flow) runs the linear
    incremental fit, the same dough with ``flow_rate = 0`` the rest-configuration model with
    the corrected fit and the control. The checkpoint's run record and the USD file's custom
    data say which, beside the requested ``"auto"`` (before, only ``"auto"`` was recorded, in
    the run record alone)."""
    from warp_esph.checkpoint import read_checkpoint

    elastic = GOOD_TOML.replace("nu = 0.3", "nu = 0.3\nflow_rate = 0.0")
    want = {"dough": ("linear", 0.0, False), "elastic": ("curvature_corrected", 0.05, True)}
    for name, text in (("dough", GOOD_TOML), ("elastic", elastic)):
        scene, out = tmp_path / f"{name}.toml", tmp_path / f"{name}.usdc"
        scene.write_text(text)
        assert main(["run", str(scene), "-o", str(out), "--no-progress", "--checkpoint-every", "2"]) == 0
        run = read_checkpoint(str(out) + ".checkpoint.npz")[0]["run"]
        assert run["fit"] == "auto"
        assert (run["resolved_fit"], run["resolved_hourglass"], run["rest_model"]) == want[name]
        data = open_fresh(out).GetRootLayer().customLayerData
        assert data["warp_esph:fit"] == "auto"
        assert (data["warp_esph:resolved_fit"], data["warp_esph:hourglass"], data["warp_esph:rest_model"]) == want[name]
    capsys.readouterr()


@pytest.mark.parametrize("argv, shown", [
    (["run", "--scale", "1e400"], "--scale = 1e400 is not allowed: must be a finite number (it overflows a float)"),
    (["run", "--fps=-1E+999"], "--fps = -1E+999 is not allowed: must be a finite number (it overflows a float)"),
    (["run", "--dt", "2e308"], "--dt = 2e308 is not allowed: must be a finite number (it overflows a float)"),
    (["run", "--scale", "1e-400"], "--scale = 1e-400 is not allowed: it is not 0, but no float holds this number: "
                                   "it reads as 0.0 (the smallest float above 0 is 5e-324)"),
    (["sweep", "dough_drop", "--param", "yield_stress=1:10:lin:2", "--duration", "1e400"],
     "--duration = 1e400 is not allowed: must be a finite number (it overflows a float)"),
])
def test_a_number_no_float_holds_is_echoed_as_typed(argv, shown, capsys):
    """'--scale 1e400' was refused as '--scale = inf', a value nobody typed (and '1e-400' as
    '0.0'); the overflow is said too."""
    assert main(argv) == 2
    assert_one_line_error(capsys.readouterr().err, shown)


UNDERFLOW = "is not allowed: it is not 0, but no float holds this number: it reads as 0.0 (the smallest float above 0 is 5e-324)"


@pytest.mark.parametrize("argv, shown", [
    (["run", "--hourglass", "1e-400"], f"--hourglass = 1e-400 {UNDERFLOW}; --hourglass 0 is off (no hourglass control): give 0 for that"),
    (["fit", "dough_drop", "--target", "t.npz", "--hourglass", "1e-400"], "--hourglass = 1e-400 "),
    (["render", "o.usdc", "--azimuth", "1e-400"], f"--azimuth = 1e-400 {UNDERFLOW}"),
    (["render", "o.usdc", "--elevation=-1e-400"], f"--elevation = -1e-400 {UNDERFLOW}"),
    (["fit", "dough_drop", "--target", "t.npz", "--jitter", "1e-400"],
     f"--jitter = 1e-400 {UNDERFLOW}; --jitter 0 is off (the lattice as written): give 0 for that"),
    (["fit", "dough_drop", "--target", "t.npz", "--cloud-offset", "1e-400"], f"--cloud-offset = 1e-400 {UNDERFLOW}"),
    (["run", "--dt", "1e-400"], f"--dt = 1e-400 {UNDERFLOW}"),
    (["fit", "dough_drop", "--target", "t.npz", "--params", "lam", "--bounds", "lam=1e-400:10"],
     "--bounds 'lam=1e-400:10' is not allowed: 1e-400: it is not 0, but no float holds this number: it reads as 0.0"),
    (["fit", "dough_drop", "--target", "t.npz", "--params", "mu", "--bounds", "mu=1:1e400"],
     "--bounds 'mu=1:1e400' is not allowed: 1e400: no float holds this number: it reads as inf (the largest float is "
     "1.798e+308); write inf or -inf for an open end"),
    (["sweep", "dough_drop", "--param", "lam=1e-400:10:lin:2"], f"--param 'lam=1e-400:10:lin:2': LO = 1e-400 {UNDERFLOW}"),
    (["sweep", "dough_drop", "--param", "lam=1e-400,2"], f"--param 'lam=1e-400,2': value = 1e-400 {UNDERFLOW}"),
])
def test_a_number_typed_that_reads_as_0_or_as_an_open_end_is_refused(argv, shown, tmp_path, monkeypatch, capsys):
    """Found by a fuzz of the commands' options: '--hourglass 1e-400' ran with the control off,
    '--azimuth 1e-400' drew at 0, '--bounds mu=1:1e400' was an open end and a swept 1e-400 a 0:
    a number typed that is not 0 but reads as 0.0 (or as inf where inf is a choice) is refused."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert_one_line_error(capsys.readouterr().err, shown)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("line, shown", [
    ("[solver]\nhourglass = 1e-400\n",
     f"key 'hourglass' in [solver]: 1e-400 {UNDERFLOW}; hourglass = 0 is off (no hourglass control): write 0 for that"),
    ("[materials.soft]\npreset = 'dough'\nyield_stress = 1e400\n",
     "key 'yield_stress' in [materials.soft]: 1e400 is not allowed: no float holds this number: it reads as inf (the "
     "largest float is 1.798e+308); write inf where inf is meant"),
    ("[scene]\ngravity = [0.0, -9.81, 1e-400]\n", f"key 'gravity' in [scene]: 1e-400 {UNDERFLOW}"),
])
def test_a_number_no_float_holds_in_a_scene_file_is_refused(line, shown, tmp_path, capsys):
    """TOML reads 1e-400 as 0.0 (a [solver] hourglass of 1e-400 ran with the control off) and
    1e400 as inf (a yield stress that never yields): refused, naming the key."""
    body = "\n[[bodies]]\nshape = 'box'\nmaterial = 'soft'\ncenter = [0.0, 0.2, 0.0]\nsize = [0.2, 0.2, 0.2]\n"
    scene = tmp_path / "s.toml"
    scene.write_text(line + ("" if "materials" in line else "[materials.soft]\npreset = 'dough'\n") + body)
    assert_one_line_error(refused_run(capsys, scene, tmp_path / "x.usdc"), "s.toml: " + shown)
    assert sorted(os.listdir(tmp_path)) == ["s.toml"]


def test_the_advice_for_a_0_that_is_off_comes_from_one_table(tmp_path, monkeypatch, capsys):
    """The command line's --hourglass and a scene file's [solver] hourglass said what 0 turns
    off from two copies of the same words (cli.ZERO_IS_OFF and an inline advice in the scene
    file's checks): both now read checks.ZERO_IS_OFF."""
    from warp_esph import checks

    monkeypatch.setitem(checks.ZERO_IS_OFF, "hourglass", "off (the table's words)")
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--hourglass", "1e-400", "-o", "x.usdc"]) == 2
    assert_one_line_error(capsys.readouterr().err, "; --hourglass 0 is off (the table's words): give 0 for that")
    scene = tmp_path / "s.toml"
    scene.write_text("[solver]\nhourglass = 1e-400\n[materials.soft]\npreset = 'dough'\n[[bodies]]\nshape = 'box'\n"
                     "material = 'soft'\ncenter = [0.0, 0.2, 0.0]\nsize = [0.2, 0.2, 0.2]\n")
    assert_one_line_error(refused_run(capsys, scene, tmp_path / "x.usdc"),
                          "; hourglass = 0 is off (the table's words): write 0 for that")
    assert sorted(os.listdir(tmp_path)) == ["s.toml"]


@pytest.mark.parametrize("case", ["run -o", "a scene file's mesh file", "its relative mesh file", "fit --target",
                                  "run --resume", "render's file"])
def test_a_long_path_in_a_refusal_is_shown_by_its_ends(case, tmp_path, monkeypatch, capsys):
    """A 5000-character path (-o, a scene file's mesh file, a fit's target) was written whole in
    its refusal, a 5 kB line: a long path is shown by its first and last 40 characters, so that
    the line stays short and still names the file."""
    long = str(tmp_path / ("d" * 2500) / ("e" * 2500))  # its folders do not exist
    monkeypatch.chdir(tmp_path)
    scene = tmp_path / "s.toml"
    body = "[materials.soft]\npreset = 'dough'\n[[bodies]]\nshape = 'mesh'\nmaterial = 'soft'\nfile = '{}'\n"
    if case == "run -o":
        argv, name = ["run", "--frames", "1", "-o", long + "/out.usdc"], "out.usdc"
    elif case == "a scene file's mesh file":
        scene.write_text(body.format(long + "/bunny.obj"))
        argv, name = ["run", str(scene), "-o", "x.usdc"], "bunny.obj"
    elif case == "its relative mesh file":
        scene.write_text(body.format("d" * 2500 + "/bunny.obj"))
        argv, name = ["run", str(scene), "-o", "x.usdc"], "bunny.obj"
    elif case == "fit --target":
        argv, name = ["fit", "dough_drop", "--target", long + "/t.npz", "--no-progress"], "t.npz"
    elif case == "run --resume":
        argv, name = ["run", "--resume", long + "/r.npz"], "r.npz"
    else:
        argv, name = ["render", long + "/o.usdc", "-o", "x.png"], "o.usdc"
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert_one_line_error(err, f"/{name}")
    assert len(err.strip()) < 400, err[:500]
    assert re.search(r"'?(/tmp|d)\S*\.\.\.[de]+/" + re.escape(name), err), err  # the start, '...', the end


@pytest.mark.parametrize("kind", ["a folder", "a name too long"])
def test_resume_from_a_path_the_system_cannot_open_says_why(kind, tmp_path, capsys):
    """Found by a fuzz of the commands' path options: 'run --resume <folder>' said 'not a readable
    warp_esph checkpoint (IsADirectoryError)', and a name past the file system's limit '(OSError)'."""
    path = tmp_path if kind == "a folder" else tmp_path / ("n" * 300 + ".npz")
    assert main(["run", "--resume", str(path)]) == 2
    why = "Is a directory" if kind == "a folder" else "File name too long"
    assert_one_line_error(capsys.readouterr().err, f"is not allowed: it cannot be read ({why})")


@pytest.mark.parametrize("argv", [["fit", "dough_drop", "--target=~/t.npz"], ["run", "--output=~/o.usdc"],
                                  ["run", "~/s.toml"], ["render", "~/o.usdc"]])
def test_a_path_starting_with_a_tilde_that_names_nothing_says_it_is_not_expanded(argv, tmp_path, monkeypatch, capsys):
    """Found by a fuzz of the commands' path options: the shell leaves '~' as written after
    '--target=' (or quoted), and 'target file ~/t.npz does not exist' did not say why, where a
    scene file's mesh file said it."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert_one_line_error(capsys.readouterr().err, "'~' is not expanded")
    assert os.listdir(tmp_path) == []


def test_shown_path_keeps_a_short_path_whole_and_a_long_one_s_ends():
    from warp_esph.checks import shown_path

    assert repr(shown_path("a/b.usdc")) == "'a/b.usdc'" and f"{shown_path('a/b.usdc', quote=False)}" == "a/b.usdc"
    copied = "/x" + "y" * 140 + "/name.usdc"  # a path of a deep folder, to copy from the line: whole
    assert f"{shown_path(copied, quote=False)}" == copied
    long = "/x" + "y" * 5000 + "/name.usdc"
    assert f"{shown_path(long)}" == repr(long)[:40] + "..." + repr(long)[-40:]
    assert str(shown_path(pathlib.Path(long), quote=False)).endswith("yyy/name.usdc")
    assert repr(shown_path(None)) == "None"


@pytest.mark.parametrize("argv", [["render", "{}", "-o", "x.png"], ["run", "--frames", "1", "-o", "{}"]])
def test_a_path_of_160_characters_is_shown_whole(argv, tmp_path, monkeypatch, capsys):
    """A path of exactly PATH_SHOWN_WHOLE characters is one a refusal shows whole: its quotes
    (shown_path's repr) or the ':' after it (the commands' one-line messages) had counted in its
    length, and it was cut to its ends."""
    from warp_esph.checks import PATH_SHOWN_WHOLE

    monkeypatch.chdir(tmp_path)
    folder = str(tmp_path / "absent") + "/"  # nothing there: render cannot read it, run cannot write in it
    path = folder + "p" * (PATH_SHOWN_WHOLE - len(folder) - 5) + ".usdc"
    assert len(path) == PATH_SHOWN_WHOLE
    assert main([a.format(path) for a in argv]) == 2
    assert_one_line_error(capsys.readouterr().err, path)


def test_a_number_read_as_typed_computes_as_its_float():
    import pickle

    from warp_esph.checks import read_number

    assert type(read_number("1.5")) is float and read_number("inf") == float("inf")
    big = read_number("1e400")
    assert big == float("inf") and repr(big) == "1e400" and f"{big:g}" == "1e400"
    assert pickle.loads(pickle.dumps(big)) == big and repr(pickle.loads(pickle.dumps(big))) == "1e400"
    assert read_number(" 1e-400 ") == 0.0 and repr(read_number("1e-400")) == "1e-400"
    assert type(read_number("0e5")) is float


@pytest.mark.parametrize("error", [ValueError, TypeError])
def test_an_unexpected_error_in_the_last_force_log_write_is_one_line_exit_1(tmp_path, monkeypatch, capsys, error):
    """An error of no kind expected (a bug in the log's writer, not a full disk) as the force
    log was written at the end of a finished run: a ValueError was exit 2, 'bad input', and the
    others a traceback, neither naming the log nor what the run's file keeps. Now one line, as
    run says such an error, exit 1; the log as its last checkpoint wrote it."""
    from warp_esph import tools as tools_module
    from warp_esph import usd as usd_module

    ended, real_close, real_write = [], usd_module.UsdWriter.close, tools_module.ReactionLog.write

    def close(self):
        ended.append(True)  # the run's frames are all written: the log's last write comes next
        real_close(self)

    def write(self, stem):
        if ended:
            raise error("the log broke")
        return real_write(self, stem)

    monkeypatch.setattr(usd_module.UsdWriter, "close", close)
    monkeypatch.setattr(tools_module.ReactionLog, "write", write)
    out_path = tmp_path / "g.usdc"
    assert main(["run", "-o", str(out_path), "--scale", "0.3", "--frames", "5", "--checkpoint-every", "2",
                 "--no-progress"]) == 1
    captured = capsys.readouterr()
    assert_one_line_error(captured.err, f"cannot write the force log {out_path}_tools.csv, .json: {error.__name__}: the log "
                                        "broke (raised at test_cli.py:", f"it is left as it was; {out_path} keeps the 6 frames")
    assert "wrote" not in captured.out
    assert frames_in(out_path) == [float(k) for k in range(6)]
    assert log_frames(out_path) == {"plane0": [0, 1, 2, 3, 4]}


@pytest.mark.parametrize("extra, said", [
    # A frame of inf s: 'would take inf steps', and with --dt the advice 'use --dt >= inf s'.
    (["--fps", "5e-324"], "--fps = 5e-324 is not allowed: it is too small to step"),
    (["--fps", "5e-324", "--dt", "1e-3"], "--fps = 5e-324 is not allowed: it is too small to step"),
    # argparse took these for options ('expected one argument'), where '--dt -1' was read as -1.
    (["--fps", "-inf"], "--fps = -inf is not allowed: must be a finite number"),
    (["--dt", "-1e-3"], "--dt = -0.001 is not allowed: must be > 0"),
    (["--scale", "-.5"], "--scale = -0.5 is not allowed: must be > 0"),
    (["--dt", "-1"], "--dt = -1.0 is not allowed: must be > 0"),
])
def test_run_refuses_a_frame_too_long_and_negative_words_as_the_values_they_are(tmp_path, capsys, extra, said):
    err = refused_run(capsys, "star", tmp_path / "o.usdc", "--frames", "1", *extra)
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines == [f"warp-esph: error: {lines[0].split('error: ', 1)[1]}"] and said in lines[0], err


def test_sweep_refuses_a_frame_too_long_to_step_as_run_does(tmp_path, capsys):
    """The sweep's own check of --fps (before any sample) is run's: 5e-324 had passed it and
    each sample then named Python's 'fps'."""
    assert main(["sweep", "star", "--param", "star.mu=1e3,1e4", "--frames", "1", "--workers", "1", "-o",
                 str(tmp_path / "sw"), "--fps", "5e-324"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("warp-esph: error: --fps = 5e-324 is not allowed: it is too small to step"), err


def test_a_kernel_cache_folder_set_in_warp_s_config_is_refused_by_that_name(tmp_path):
    """``wp.config.kernel_cache_dir``, Warp's own way to place its cache, is taken over
    ``WARP_CACHE_PATH``; set to a folder Warp cannot make, ``init_warp()`` blamed the variable
    (``WARP_CACHE_PATH = '/a/good/folder' is not allowed ... or unset WARP_CACHE_PATH``) or, unset,
    advised setting it, which changed nothing. It names the setting that was given."""
    import warp as wp  # noqa: PLC0415

    a_file = tmp_path / "cache"
    a_file.write_text("")
    good = tmp_path / "good"
    for env in (dict(os.environ, WARP_CACHE_PATH=str(good)), {k: v for k, v in os.environ.items() if k != "WARP_CACHE_PATH"}):
        env["PYTHONPATH"] = REPO + os.pathsep + os.environ.get("PYTHONPATH", "")
        p = subprocess.run([sys.executable, "-c", "import warp as wp\nimport warp_esph as we\n"
                            f"wp.config.kernel_cache_dir = {str(a_file / 'k')!r}\ntry:\n    we.init_warp()\n"
                            "except ValueError as e:\n    print(e)"], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=120)
        said = (f"wp.config.kernel_cache_dir = {str(a_file / 'k')!r} is not allowed: Warp keeps its compiled kernels in a "
                f"folder there (before WARP_CACHE_PATH), and cannot make {str(a_file / 'k' / wp.config.version)!r} (Not a "
                "directory); give a folder that is there or can be made, or leave it None\n")
        assert p.returncode == 0 and p.stdout == said and "Traceback" not in p.stderr, (p.stdout, p.stderr)
    assert a_file.read_text() == "" and not good.exists()
    # Mended as the refusal says, init_warp() again in the same process starts Warp there: the
    # failed start had left Warp's setting at the folder it could not make, taken over the
    # variable ('wp.config.kernel_cache_dir = .../cache/1.19.0 is not allowed').
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""), WARP_CACHE_PATH=str(a_file))
    p = subprocess.run([sys.executable, "-c", "import os\nimport warp as wp\nimport warp_esph as we\ntry:\n    we.init_warp()\n"
                        "except ValueError as e:\n    print(e)\n"
                        f"os.environ['WARP_CACHE_PATH'] = {str(good)!r}\nwe.init_warp()\nprint(wp.config.kernel_cache_dir)"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    refused, started = p.stdout.splitlines()
    assert refused.startswith(f"WARP_CACHE_PATH = {str(a_file)!r} is not allowed")
    assert started == str(good / wp.config.version) and (good / wp.config.version).is_dir()
