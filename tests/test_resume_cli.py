"""The CLI's checkpoint/resume and signal handling: a resumed run writes the same file
as an uninterrupted one; SIGINT and SIGTERM leave every finished frame readable."""

import json
import os
import re
import signal
import shutil
import subprocess
import sys
import time

import numpy as np
from pxr import Usd, UsdGeom

from warp_esph.checkpoint import read_checkpoint
from warp_esph.cli import main

ARGS = ["run", "three_cylinders", "--scale", "0.35", "--no-progress"]


def _points(path):
    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Points):
            attr = UsdGeom.Points(prim).GetPointsAttr()
            out[str(prim.GetPath())] = {t: np.array(attr.Get(t)) for t in attr.GetTimeSamples()}
    return out


def _time_samples(path):
    """Every time-sampled attribute value of the file, ``{(prim, attribute, time): value}``."""
    stage = Usd.Stage.Open(str(path))
    return {(str(prim.GetPath()), attr.GetName(), t): np.array(attr.Get(t))
            for prim in stage.Traverse() for attr in prim.GetAttributes() for t in attr.GetTimeSamples()}


def test_resume_writes_what_the_uninterrupted_run_writes(tmp_path, capsys):
    """A run stopped after frame 6 (its last checkpoint) and resumed to frame 8 writes
    the same file, bit for bit, as a run of 8 frames: every time sample of every attribute,
    the ground's reaction at the resume frame too (a checkpoint carries the reactions of the
    step that produced its state, ``State.STEP_REPORTS``; they were written as zero there)."""
    full = tmp_path / "full.usdc"
    assert main(ARGS + ["--frames", "8", "-o", str(full)]) == 0
    part = tmp_path / "part.usdc"
    assert main(ARGS + ["--frames", "6", "-o", str(part), "--checkpoint-every", "2"]) == 0
    ckpt = tmp_path / "part.usdc.checkpoint.npz"
    assert read_checkpoint(ckpt)[0]["frame"] == 6
    assert main(["run", "--resume", str(ckpt), "--frames", "8", "--no-progress"]) == 0
    assert read_checkpoint(ckpt)[0]["frame"] == 8
    a, b = _points(full), _points(part)
    assert a.keys() == b.keys()
    for prim in a:
        assert sorted(a[prim]) == sorted(b[prim]) == list(range(9))
        for t in a[prim]:
            np.testing.assert_array_equal(a[prim][t], b[prim][t])
    sa, sb = _time_samples(full), _time_samples(part)
    assert sa.keys() == sb.keys()
    ground = [k for k in sa if k[1] == "warp_esph:reaction_force" and k[2] == 6.0]
    assert ground and all(np.abs(sa[k]).max() > 0.0 for k in ground)  # landed by the resume frame
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key], err_msg=str(key))
    assert main(["run", "--resume", str(ckpt), "--no-progress"]) == 2  # nothing left to run
    # --frames at or below the checkpoint's frame: the message names --frames and the frame.
    assert main(["run", "--resume", str(ckpt), "--frames", "7", "--no-progress"]) == 2
    assert "--frames = 7 is not allowed with --resume" in capsys.readouterr().err
    # The checkpoint's run decides the precision and the surfaces too (both were ignored).
    for extra, needle in ((["--dtype", "float64"], "--dtype = 'float64' is not allowed with --resume"),
                          (["--surface"], "--surface = True is not allowed with --resume")):
        assert main(["run", "--resume", str(ckpt), "--frames", "9", "--no-progress", *extra]) == 2
        assert needle in capsys.readouterr().err
    # The file rewritten by a shorter run (frames 0..2) under a copy of the checkpoint of frame 8
    # (the run removes the one beside its output): resuming would leave frames 3..7 unwritten (it
    # wrote 0..2 and 8..9 and exited 0); refused, the file and its force log untouched.
    kept = tmp_path / "kept.npz"
    kept.write_bytes(ckpt.read_bytes())
    assert main(ARGS + ["--frames", "2", "-o", str(part)]) == 0
    before = _time_samples(part)
    log = (tmp_path / "part.usdc_tools.json").read_bytes()
    capsys.readouterr()
    assert main(["run", "--resume", str(kept), "--frames", "9", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another run (run id '" in err[0], err  # the file (and its force log) name their run
    # A checkpoint and file written before runs were named have no run id: the frames it would
    # leave unwritten are what refuses it.
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(part))
    layer.Reload(force=True)
    layer.customLayerData = {k: v for k, v in dict(layer.customLayerData).items() if k != "warp_esph:run_id"}
    layer.Save()
    doc = json.loads((tmp_path / "part.usdc_tools.json").read_text())
    del doc["run_id"]
    (tmp_path / "part.usdc_tools.json").write_text(json.dumps(doc))
    log = (tmp_path / "part.usdc_tools.json").read_bytes()
    before = _time_samples(part)
    with np.load(kept) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(arrays["meta"].tobytes())
    del meta["run"]["run_id"]
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(kept, **arrays)
    assert main(["run", "--resume", str(kept), "--frames", "9", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds frames 0..2" in err[0] and "frames 3..7 unwritten" in err[0], err
    after = _time_samples(part)
    assert before.keys() == after.keys() and (tmp_path / "part.usdc_tools.json").read_bytes() == log


def test_resume_of_a_bad_checkpoint_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"junk")
    assert main(["run", "--resume", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.npz" in err[0] and "Traceback" not in err[0]


def _interrupt(tmp_path, sig, expected_status):
    out = tmp_path / "run.usdc"
    proc = subprocess.Popen(
        [sys.executable, "-m", "warp_esph", "run", "dough_drop", "--scale", "0.5", "--frames", "400", "-o", str(out), "--no-progress"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ.copy(),
        # As in a terminal: a pytest-xdist worker ignores SIGINT and its children inherit
        # that, and the CLI rightly keeps an inherited ignore (as `nohup` asks).
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.time() + 120
    while time.time() < deadline and not (out.exists() and len(_points(out).get("/World/dough", {})) >= 3):
        time.sleep(0.3)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == expected_status, err
    assert "Traceback" not in err
    frames = _points(out)["/World/dough"]
    assert len(frames) >= 3 and sorted(frames) == list(range(len(frames)))
    return frames


def test_sigint_leaves_every_finished_frame(tmp_path):
    _interrupt(tmp_path, signal.SIGINT, 130)


def test_sigterm_leaves_every_finished_frame(tmp_path):
    _interrupt(tmp_path, signal.SIGTERM, 143)


def test_fit_subcommand_is_wired_and_reports_bad_input(tmp_path, capsys):
    assert main(["fit", "dough_drop", "--target", str(tmp_path / "nope.npz"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.npz" in err[0]


def test_a_new_run_over_an_output_retires_the_earlier_runs_force_log_and_checkpoint(tmp_path, capsys):
    """A run writes a.usdc with checkpoints; a new run (another dt) writes a.usdc again. The
    first run's checkpoint resumed onto the second run's file: its frames 0..5, then the first
    run's state from frame 6 on, exit 0. The new run removes the old force log once it has
    replaced the file it belongs to; the checkpoint stays (it resumes its own run where that
    run's file is put back) and is refused on the new run's frames, by the run ids, or where
    the checkpoint names no run (written before run ids) by the file's naming one."""
    out = tmp_path / "a.usdc"
    ckpt = tmp_path / "a.usdc.checkpoint.npz"
    tiny = ["run", "dough_drop", "--scale", "0.3", "--no-progress", "-o", str(out)]
    assert main(tiny + ["--frames", "6", "--checkpoint-every", "2"]) == 0
    first = tmp_path / "first.usdc"
    shutil.copyfile(out, first)
    for ext in ("csv", "json"):
        shutil.copyfile(tmp_path / f"a.usdc_tools.{ext}", tmp_path / f"first_tools.{ext}")
    assert ckpt.exists()
    assert main(tiny + ["--frames", "8", "--dt", "0.000505051"]) == 0
    assert ckpt.exists()
    before = _time_samples(out)
    log = (tmp_path / "a.usdc_tools.json").read_bytes()
    capsys.readouterr()
    assert main(["run", "--resume", str(ckpt), "--frames", "10", "--no-progress"]) == 2
    assert "another run (run id '" in capsys.readouterr().err  # the file's, or its force log's
    with np.load(ckpt) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(arrays["meta"].tobytes())
    del meta["run"]["run_id"]
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    legacy = tmp_path / "legacy.npz"
    np.savez(legacy, **arrays)
    assert main(["run", "--resume", str(legacy), "--frames", "10", "--no-progress"]) == 2
    assert "another run (run id '" in capsys.readouterr().err
    after = _time_samples(out)
    assert before.keys() == after.keys() and all(np.array_equal(before[k], after[k]) for k in before)
    assert (tmp_path / "a.usdc_tools.json").read_bytes() == log
    # The earlier run's file put back: the force log beside it is the later run's, whose rows
    # were taken as the earlier run's (exit 0); refused. With its own log back, it resumes.
    shutil.copyfile(first, out)
    capsys.readouterr()
    assert main(["run", "--resume", str(ckpt), "--frames", "8", "--no-progress"]) == 2
    assert "a.usdc_tools.json belongs to another run (run id '" in capsys.readouterr().err
    for ext in ("csv", "json"):
        shutil.copyfile(tmp_path / f"first_tools.{ext}", tmp_path / f"a.usdc_tools.{ext}")
    assert main(["run", "--resume", str(ckpt), "--frames", "8", "--no-progress"]) == 0
    rows = json.loads((tmp_path / "a.usdc_tools.json").read_text())["rows"]
    first_rows = json.loads((tmp_path / "first_tools.json").read_text())["rows"]
    assert [r for r in rows if r["frame"] <= 4] == [r for r in first_rows if r["frame"] <= 4]


def test_a_checkpoint_resumes_onto_its_own_runs_frames_only(tmp_path, capsys):
    """A copy of a run's checkpoint, resumed after another run (another dt) rewrote the output,
    spliced the first run's state after the second run's frames, exit 0: a new run names itself
    in its file and its checkpoints (``run_id``), and a resume onto another run's file is refused."""
    out = tmp_path / "a.usdc"
    keep = tmp_path / "keep.npz"
    tiny = ["run", "dough_drop", "--scale", "0.3", "--no-progress", "-o", str(out)]
    assert main(tiny + ["--frames", "6", "--checkpoint-every", "2"]) == 0
    shutil.copyfile(tmp_path / "a.usdc.checkpoint.npz", keep)
    assert main(tiny + ["--frames", "8", "--dt", "0.000505051"]) == 0
    before = _time_samples(out)
    capsys.readouterr()
    assert main(["run", "--resume", str(keep), "--frames", "10", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "another run (run id '" in err, err
    after = _time_samples(out)
    assert before.keys() == after.keys() and all(np.array_equal(before[k], after[k]) for k in before)
    # Its own run's file resumes.
    assert main(tiny + ["--frames", "6", "--checkpoint-every", "2"]) == 0
    capsys.readouterr()
    assert main(["run", "--resume", str(tmp_path / "a.usdc.checkpoint.npz"), "--frames", "8", "--no-progress"]) == 0
    assert re.search(r"\d+ frames at .* \(resumed at frame (\d+), the run 8 frames\)", capsys.readouterr().out)


def test_a_killed_run_resumes_with_its_force_log_whole(tmp_path, capsys):
    """SIGKILL (out of memory, a preempted job) after a few checkpoints, then --resume: the
    force log holds every frame, bit for bit the uninterrupted run's. It was written only at the
    end: the killed run left none, and the resumed one kept only its own frames (exit 0)."""
    out = tmp_path / "k.usdc"
    ckpt = tmp_path / "k.usdc.checkpoint.npz"
    proc = subprocess.Popen(
        [sys.executable, "-m", "warp_esph", "run", "dough_drop", "--scale", "0.3", "--frames", "2000", "-o", str(out),
         "--checkpoint-every", "2", "--no-progress"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=os.environ.copy())
    deadline = time.time() + 120
    while time.time() < deadline and not (ckpt.exists() and read_checkpoint(ckpt)[0]["frame"] >= 4):
        time.sleep(0.1)
    proc.kill()
    proc.communicate(timeout=60)
    frame = read_checkpoint(ckpt)[0]["frame"]
    assert frame >= 4
    assert main(["run", "--resume", str(ckpt), "--frames", str(frame + 2), "--no-progress"]) == 0
    whole = tmp_path / "whole.usdc"
    assert main(["run", "dough_drop", "--scale", "0.3", "--frames", str(frame + 2), "-o", str(whole), "--no-progress"]) == 0
    capsys.readouterr()
    with open(f"{out}_tools.csv") as fh:
        csv = fh.read()
    assert [int(line.split(",")[0]) for line in csv.splitlines()[1:]] == list(range(frame + 3))
    with open(f"{whole}_tools.csv") as fh:
        assert csv == fh.read()


def test_a_resume_onto_a_file_that_holds_no_frame_is_refused_naming_the_frames_it_would_leave(tmp_path, capsys):
    """A file of no frame (its samples gone: a writer stopped before its first frame, or an
    output replaced) read as holding frame 0, so a resume at frame 1 onto it wrote frames 1..2
    and exited 0 with frame 0 never written; it is refused, as a file short of frames is."""
    from warp_esph.usd import UsdWriter

    out = tmp_path / "a.usdc"
    tiny = ["run", "dough_drop", "--scale", "0.3", "--no-progress", "-o", str(out)]
    assert main(tiny + ["--frames", "1", "--checkpoint-every", "1"]) == 0
    ckpt = tmp_path / "a.usdc.checkpoint.npz"
    assert read_checkpoint(ckpt)[0]["frame"] == 1
    stage = Usd.Stage.Open(str(out))
    UsdWriter._drop_frames_from(stage, 0)
    stage.GetRootLayer().Save()
    before = _time_samples(out)
    assert not before
    capsys.readouterr()
    assert main(["run", "--resume", str(ckpt), "--frames", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the file holds no frames" in err[0] and "frames 0..0 unwritten" in err[0], err
    assert not _time_samples(out)


_PRESS = """
[scene]
name = "press"
spacing = 0.05
gravity = [0.0, 0.0, 0.0]
frames = 21
fps = 30

[[bodies]]
shape = "box"
name = "block"
material = "rubber"
center = [0.0, 0.1, 0.0]
size = [0.2, 0.2, 0.2]

[[colliders]]
type = "ground"
friction = 0.0

[[tools]]
shape = "box"
name = "plate"
half_extents = [0.2, 0.025, 0.2]
keyframe_times = [0.0, 0.3, 1.0]
keyframe_positions = [[0.0, 0.225, 0.0], [0.0, 0.131, 0.0], [0.35, 0.131, 0.0]]
"""


def test_resume_counts_the_tools_work_before_the_checkpoint(tmp_path, capsys):
    """A rubber block a keyframed plate presses 47 % and slides off, checkpointed at frame 14
    and resumed: the checkpoint did not keep the plate's work, so the resumed run's blow-up
    bound read the height the plate can have given in its place (none: no gravity) and exited
    3 at frame 20 in the block's spring-back (36.1 J against 34.3 J), where the uninterrupted
    run exits 0. The checkpoint keeps the work, and the resumed run counts it."""
    scene = tmp_path / "press.toml"
    scene.write_text(_PRESS)
    out = tmp_path / "press.usdc"
    assert main(["run", str(scene), "-o", str(out), "--frames", "14", "--checkpoint-every", "14", "--no-progress"]) == 0
    ckpt = tmp_path / "press.usdc.checkpoint.npz"
    assert read_checkpoint(ckpt)[0]["tool_work"] > 10.0  # J: the plate's press
    capsys.readouterr()
    assert main(["run", "--resume", str(ckpt), "--frames", "21", "--no-progress"]) == 0, capsys.readouterr().err
    assert sorted(_points(out)["/World/block"]) == list(range(22))


def test_a_resume_of_a_checkpoint_whose_fingerprint_version_is_no_version_is_one_line(tmp_path, capsys):
    """``run --resume`` of a checkpoint whose ``fingerprint_version`` was edited to 3.5 prints
    one line naming the field, its value and what is allowed, and exits 2; written 3.0 it is
    version 3, which this scene's checkpoints resume as (the same fingerprint). Seen failing
    with ``checkpoint.read_fingerprint_version`` taking 3.5 as 3 (resumed, exit 0)."""
    ckpt = tmp_path / "a.usdc.checkpoint.npz"
    assert main(["run", "dough_drop", "--scale", "0.3", "--no-progress", "-o", str(tmp_path / "a.usdc"), "--frames", "1",
                 "--checkpoint-every", "1"]) == 0
    with np.load(ckpt) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(arrays["meta"].tobytes())

    def resume(label) -> int:
        arrays["meta"] = np.frombuffer(json.dumps({**meta, "fingerprint_version": label}).encode(), dtype=np.uint8)
        np.savez(ckpt, **arrays)
        capsys.readouterr()
        return main(["run", "--resume", str(ckpt), "--frames", "2", "--no-progress"])

    assert resume(3.5) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("a.usdc.checkpoint.npz' is not allowed: its metadata has fingerprint_version "
                                             "= 3.5 (must be an integer from 1 to 4, the versions this warp_esph reads)"), err
    assert resume(3.0) == 0
