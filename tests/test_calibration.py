"""Calibration a researcher can trust: the fit command on a previous run's USD, joint fits
of several experiments, silhouette targets, and diagnostics that say when the data do not
determine a parameter (warp_esph.calibrate, fit, diagnostics, silhouette).

Scenes are tiny (64-125 particles, tens of steps) so the file runs in CI; gradients are
checked in float64 against central differences.
"""

import dataclasses
import json
import math
import os
import pathlib
import re
import shutil
import signal
import warnings

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.cli import EXIT_NOT_CONVERGED
from warp_esph.diagnostics import LARGE_STRAIN_ALPHA, diagnose
from warp_esph.fit import Experiment, choose_checkpointing, fit, latin_hypercube, memory_estimate
from warp_esph.losses import PositionLoss
from warp_esph.rollout import FRAME_BUFFERS, Rollout, _RolloutMemory, state_nbytes
from warp_esph.silhouette import PinholeCamera, SilhouetteLoss, load_cameras, load_masks, soft_silhouette
from run_files import run_script

pxr = pytest.importorskip("pxr")


def test_cli_fit_offers_every_optimizer_fit_runs():
    """``warp-esph fit --optimizer`` kept its own copy of fit's names, which a new optimiser
    would have left behind: it takes each of ``fit.OPTIMIZERS`` and no other."""
    import argparse

    from warp_esph.calibrate import add_calibration_arguments
    from warp_esph.fit import OPTIMIZERS

    parser = argparse.ArgumentParser()
    add_calibration_arguments(parser)
    assert next(a for a in parser._actions if a.dest == "optimizer").choices == OPTIMIZERS
    assert [parser.parse_args(["--optimizer", o]).optimizer for o in OPTIMIZERS] == list(OPTIMIZERS)


def test_cli_fit_refuses_a_tool_faster_than_a_spacing_a_step_before_the_fit(tmp_path, capsys, dough_scene):
    """A tool whose keyframes move it 50 spacings a step was fitted to (the rollouts do not
    check speeds), and only fitted.usdc's run refused it, after the fit, naming a Python
    caller's 'a smaller dt=' (exit 2, the fit's files written). It is refused before the fit
    now, as 'warp-esph run' refuses it, naming fit's --dt; a body started too fast likewise."""
    from warp_esph.cli import main

    tool = ('\n[[tools]]\nshape = "box"\nname = "fast"\nhalf_extents = [0.02, 0.02, 0.02]\nkeyframe_times = [0.0, 0.001]\n'
            'keyframe_positions = [[1.0, 0.5, 0.0], [1.5, 0.5, 0.0]]\n')
    guess = tmp_path / "guess.toml"
    scene = dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2)
    np.save(tmp_path / "t.npy", np.zeros((3, 64, 3)))
    out = tmp_path / "cal"
    capsys.readouterr()
    argv = ["fit", str(guess), "--target", str(tmp_path / "t.npy"), "--iterations", "1", "--output-dir", str(out), "--no-progress"]
    for text, start, end in (
            (scene + tool, "tool 'fast': its Keyframes motion moves its points at up to 500 m/s",
             "so at most 10.2 m/s; give a slower motion or a smaller --dt"),
            (scene.replace("velocity = [0.0, -1.0, 0.0]", "velocity = [0.0, -100.0, 0.0]"),
             "[[bodies]] #1 (shape 'box'): initial velocity of body 'dough': a speed of 100 m/s",
             "; give a smaller velocity (or angular_velocity) or a smaller --dt")):
        assert text != scene  # the replaced start speed is in the scene
        guess.write_text(text)
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {guess}: {start}"), err
        assert err[0].endswith(end), err
        assert not out.exists()


def _fit_mu_from_three_starts(tmp_path, capsys, dough_scene, *options):
    """``warp-esph fit`` of the dough's mu from three starts (no iterations) to a zero target;
    returns the scene file, the output folder, the exit status and stderr."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    np.save(tmp_path / "t.npy", np.zeros((3, 64, 3)))
    out = tmp_path / "cal"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(tmp_path / "t.npy"), "--params", "mu", "--starts", "3", *options,
                   "--iterations", "0", "--no-diagnostics", "--no-usd", "--no-progress", "--output-dir", str(out)])
    return guess, out, status, capsys.readouterr().err


def test_cli_fit_with_starts_steps_at_the_stiffest_starts_stable_step(tmp_path, capsys, dough_scene):
    """``--starts 3`` fitting mu: the steps per frame were chosen from the guess's stable
    step (34 a frame), past the stable step of the start at 3.7 x mu, which warned and could
    blow up. Where the command chooses the step (no --dt, none in the scene) it is now the
    stiffest start's, rounded to fill a frame (48 a frame), for every start."""
    from warp_esph.scenes import load_scene

    guess, out, status, err = _fit_mu_from_three_starts(tmp_path, capsys, dough_scene)
    assert status == 0
    assert "warning" not in err, err
    doc = json.loads((out / "fit.json").read_text())
    mus = [h["params"]["mu"][0] for h in doc["history"]]
    assert len(mus) == 3 and max(mus) > 3.0 * 2000.0

    def stable(mu):  # the pressure stiffness tied to mu, as the fit ties it
        model = load_scene(str(guess)).builder.finalize(requires_grad=True)
        model.set_material(0, model.materials[0].replace(mu=mu, pressure_stiffness=None))
        return model.stable_dt()

    least = min(stable(mu) for mu in mus)
    substeps = math.ceil((1.0 / 30.0) / least)
    assert substeps == 24 and (1.0 / 30.0) / stable(2000.0) < 17
    assert f"dt = {1.0 / 30.0 / substeps:.4g} s: each evaluation runs {2 * substeps} steps" in err
    assert doc["dt"] == pytest.approx(1.0 / 30.0 / substeps, rel=1e-12, abs=0.0)
    # The help says so: it said 'else the stable step', read as the guess's.
    from warp_esph.cli import main

    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert ("else the stable step, rounded to fill a frame; with --samples or --starts K > 1, that of the stiffest point "
            "they start from, the guess included, for every start)") in text


def test_cli_fit_starts_whose_stable_step_overruns_the_steps_per_frame_are_refused_by_their_options(tmp_path, capsys,
                                                                                                 dough_scene):
    """A start drawn at 1e15 Pa (--sample-range 1e12) needs 2.2e6 steps a frame: the refusal
    blamed the scene's 'stiffest material (p-wave speed 3 m/s)' and advised softer materials,
    which the guess already is; it now names the starts and their options."""
    _, out, status, err = _fit_mu_from_three_starts(tmp_path, capsys, dough_scene,
                                                    "--sample-range", "1e12", "--bounds", "mu=1:1e16")
    assert status == 2
    assert err.count("\n") == 1, err
    assert "--starts 3 starts from" in err and "more than 1e+06" in err and "--sample-range (now 1e+12)" in err, err
    assert "p-wave" not in err and not out.exists()


def test_cli_fit_refuses_a_target_coordinate_past_what_the_loss_can_square(tmp_path, capsys, dough_scene):
    """A target position of 1e300 (inf in float32, and its square inf in float64) ran the
    fit's first rollout and stopped it with exit 3, 'the loss or its gradient is not finite
    at the initial guess'. It is refused first (exit 2), in one line naming the file, the
    value, where it is and the bound of the model's precision."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    target = np.zeros((3, 64, 3))
    target[2, 5, 1] = 1e300
    np.save(tmp_path / "t.npy", target)
    out = tmp_path / "cal"
    for dtype, bound, largest in (("float32", "1.8e+18", "3.4e+38"), ("float64", "1.3e+153", "1.8e+308")):
        capsys.readouterr()
        assert main(["fit", str(guess), "--target", str(tmp_path / "t.npy"), "--dtype", dtype, "--iterations", "1",
                     "--no-progress", "--output-dir", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"warp-esph: error: target {tmp_path / 't.npy'} is not allowed: it holds the coordinate 1e+300 "
                       f"(frame 2, particle 5), past what the {dtype} loss can square (at most {bound} m; the {dtype} max "
                       f"is {largest}): give positions in metres, of this scene"], err
        assert not out.exists()


def test_a_target_coordinate_past_the_bound_in_one_bodys_target_names_that_body():
    """With ``--target-body``, the target's particles are that body's, numbered from 0
    within it: the message said 'particle 1', which read as the scene's particle 1 (the
    first body's). It says 'particle 1 of body 'ball'' now."""
    from warp_esph.fit import Target

    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.05, 0.0), (0.04, 0.04, 0.04), we.Material(mu=2e3, lam=3e3), name="block")
    b.add_box((0.2, 0.05, 0.0), (0.04, 0.04, 0.04), we.Material(mu=2e3, lam=3e3), name="ball")
    model = b.finalize(dtype=wp.float32)
    data = np.zeros((2, 8, 3))
    data[1, 1, 2] = 1e300
    with pytest.raises(ValueError) as e:
        Target("positions", data, [0, 1], None, "run.usdc", body="ball").loss(model, {0: 0, 1: 10})
    assert str(e.value) == ("target run.usdc is not allowed: it holds the coordinate 1e+300 (frame 1, particle 1 of body "
                            "'ball'), past what the float32 loss can square (at most 1.8e+18 m; the float32 max is "
                            "3.4e+38): give positions in metres, of this scene")


def test_python_fit_refuses_a_tool_or_a_start_faster_than_a_spacing_a_step_before_any_rollout():
    """``fit`` itself took them, as the command line's once did: a box pressing at two
    spacings a step drove the block 0.25 m through the ground, and the fit fitted to that.
    Refused at set-up now, naming the experiment, the tool or body and fit's ``dt=``."""
    from warp_esph import tools

    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    b.add_ground()
    b.add_tool("box", half_extents=(0.3, 0.05, 0.3), name="plate", motion=tools.Velocity((0.0, -100.0, 0.0), position=(0.0, 0.3, 0.0)))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    target = PositionLoss(model.particle_x0[None], frames=[2])
    seen = []
    with pytest.raises(ValueError, match=r"^the experiment: tool 'plate': its Velocity motion moves its points at up to 100 m/s "
                                         r".* at dt = 0\.001 s: a step may carry a tool at most one spacing \(0\.05 m\), so at "
                                         r"most 50 m/s; give a slower motion or a smaller dt=$"):
        fit(model, target, ["mu"], steps=2, dt=1e-3, iterations=1, progress=False, callback=lambda *a: seen.append(a))
    assert seen == []  # no evaluation ran
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.1, 0.1), we.Material.preset("dough"), name="d")
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    with pytest.raises(ValueError, match=r"^the experiment: initial velocity of body 'd': a speed of 60 m/s \(particle 0\) is "
                                         r"not allowed at dt = 0\.001 s: .* so at most 50 m/s; give a smaller velocity \(or "
                                         r"angular_velocity, or v0\) or a smaller dt=$"):
        fit(model, target, ["mu"], steps=2, dt=1e-3, iterations=1, progress=False, initial={"v0": (0.0, 60.0, 0.0)})
    fit(model, target, ["mu"], steps=2, dt=1e-3, iterations=1, progress=False, diagnostics=False,
        initial={"v0": (0.0, 40.0, 0.0)})


def test_cli_fit_names_its_own_options_when_the_rollout_cannot_fit_in_memory(tmp_path, capsys, dough_scene, monkeypatch):
    """The rollout's memory refusal reached the command as the fit's Python one: 'steps = 170
    is not allowed with checkpoint_every = None', naming no option of the command and giving
    the segment --checkpoint-every auto had chosen as if typed. It names what set the run's
    length, the command's --checkpoint-every as given, and the command's options to change;
    an experiment of an --experiments file is named as its other refusals are."""
    from warp_esph import builder
    from warp_esph.cli import main
    from warp_esph.rollout import _RolloutMemory
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=10))
    np.save(tmp_path / "t.npy", np.zeros((11, 64, 3)))
    out = tmp_path / "cal"
    errors_md = (pathlib.Path(__file__).parents[1] / "docs" / "errors.md").read_text()
    # The command's model and its rollout of 170 steps, 10 frames observed: one world's and two's.
    model = load_scene(str(guess)).builder.finalize(dtype=wp.float64, requires_grad=True)
    one = _RolloutMemory(model, 170, frames=10)
    two = _RolloutMemory(builder.replicate_worlds(model, 2), 170, frames=10)
    least = one.least()
    gib = one.need(least)[0] / 2**30
    monkeypatch.setattr(builder, "_device_memory", lambda dev: 2 * 10**6)  # not even the least
    assert one.need(least)[0] > 2 * 10**6
    argv = ["fit", str(guess), "--target", str(tmp_path / "t.npy"), "--iterations", "1", "--output-dir", str(out), "--no-progress"]
    capsys.readouterr()
    plan = r" on cpu: at 17 steps a frame \(dt = 0\.001961 s at 30 fps\) the fit's rollout takes 170 steps, and "
    need = r"the rollout would need about 0\.0\d+ GiB, more than the 0\.00186 GiB available; "
    for extra, said in (([], r"the targets' last frame, 10, is not allowed with --checkpoint-every auto" + plan
                          + rf"even at its least memory, a checkpoint every {least} steps, " + need
                          + r"fit fewer frames \(--frames, --target-frames\)"),
                        (["--frames", "10", "--checkpoint-every", "100"],
                         r"--frames = 10 is not allowed with --checkpoint-every 100" + plan + need
                         + rf"fit fewer frames \(--frames, --target-frames\) \(with --checkpoint-every {least}, the least, "
                           rf"it would need about {re.escape(f'{gib:.3g}')} GiB\)")):
        assert main(argv + extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and re.fullmatch("warp-esph: error: " + said, err[0]), err
        if not extra:  # docs/errors.md shows this one whole (it showed sqrt(steps) = 13 as the least)
            assert f"`{err[0].removeprefix('warp-esph: error: ')}`" in errors_md
    # Room for the least, not for segments of 100.
    device = 2 * one.need(least)[0]
    assert one.need(100)[0] > device
    monkeypatch.setattr(builder, "_device_memory", lambda dev: device)
    assert main(argv + ["--checkpoint-every", "100"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    fix = (f"; give --checkpoint-every auto (the default: it chooses a segment that fits) or {least} (the least memory, about "
           f"{gib:.3g} GiB), or fit fewer frames (--frames, --target-frames)")
    assert len(err) == 1 and err[0].endswith(fix), err
    assert re.search(r"`\.\.\.; give --checkpoint-every auto \(the default: it chooses a segment that fits\) or \d+ \(the "
                     r"least memory, about [\d.]+ GiB\), or fit fewer frames \(--frames, --target-frames\)`", errors_md)
    # Room for one world's rollout at the least, not for two worlds' (--starts 2 --worlds).
    device = (one.need(least)[0] + two.need(two.least())[0]) // 2
    assert one.need(least)[0] < device < two.need(two.least())[0]
    monkeypatch.setattr(builder, "_device_memory", lambda dev: device)
    assert main(argv + ["--starts", "2", "--worlds"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warp-esph: error: the targets' last frame, 10, is not allowed with "
                                               "--checkpoint-every auto and --worlds (2 copies of the scene) on cpu: "), err
    assert err[0].endswith("; fit fewer frames (--frames, --target-frames), or fewer --starts, or leave out --worlds (the "
                           "starts one after another)"), err
    # The command's own experiment fits (auto chooses a segment that does), the file's longer one not.
    longer = _RolloutMemory(model, 200 * 17, frames=200)
    device = 2 * one.need(least)[0]
    assert longer.need(longer.least())[0] > device
    monkeypatch.setattr(builder, "_device_memory", lambda dev: device)
    # A copy of the target: the same file as the command line's would be refused as counted twice.
    np.save(tmp_path / "t2.npy", np.zeros((11, 64, 3)))
    (tmp_path / "e.json").write_text(json.dumps([{"scene": "guess.toml", "target": "t2.npy", "frames": 200}]))
    assert main(argv + ["--experiments", str(tmp_path / "e.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {tmp_path / 'e.json'}: experiment #1: frames = 200 is "
                                               "not allowed with --checkpoint-every auto on cpu"), err
    assert err[0].endswith("; fit fewer frames (the experiment's frames, target_frames)"), err
    assert not out.exists()
    # A Gauss-Newton fit records no tape: on the memory that refused the taped fit its rollout
    # (its untaped states) is taken and the fit runs.
    assert _RolloutMemory(model, 170, frames=10, taped=False).need(None)[0] < 3.5e6 < one.need(least)[0]
    monkeypatch.setattr(builder, "_device_memory", lambda dev: 3.5e6)
    assert main(argv[:4] + ["--iterations", "0", "--output-dir", str(out), "--no-progress", "--optimizer", "gauss-newton",
                            "--no-diagnostics"]) == 0
    err = capsys.readouterr().err
    assert "170 steps of 0.001961 s; no tape (Gauss-Newton runs forward only)" in err, err
    import types

    from warp_esph.calibrate import _memory_refusal
    from warp_esph.rollout import RolloutMemoryError

    # Where even the two states do not fit, the refusal says so in the command's words, not as a
    # checkpointed tape's ('--checkpoint-every auto ... even at its least memory, a checkpoint').
    e = RolloutMemoryError("", reason="the rollout would need about 0.5 GiB, more than the 0.25 GiB available", device="cpu",
                           steps=170, segment=None, least=170, least_gib=0.5, least_fits=False, taped=False)
    exp = types.SimpleNamespace(frames_source="the targets' last frame, 10,", substeps=17, dt=0.001961, fps=30.0)
    assert _memory_refusal(e, exp, "", "auto") == (
        "the targets' last frame, 10, is not allowed with --optimizer gauss-newton on cpu: at 17 steps a frame (dt = "
        "0.001961 s at 30 fps) the fit's rollout takes 170 steps, and even untaped (as every run of a Gauss-Newton fit "
        "is) the rollout would need about 0.5 GiB, more than the 0.25 GiB available; fit fewer frames (--frames, --target-frames)")


def test_cli_fits_two_parameters_to_a_usd_run(tmp_path, capsys, dough_scene):
    """``warp-esph run`` a dough block dropped on the ground (64 particles, 102 steps), then
    ``warp-esph fit`` a copy that starts 2x off in yield stress and flow rate, with the
    run's USD (one body, frames 2, 4, 6) as the target. From the 2x guess alone L-BFGS
    now converges to the truth too (100.00008, 10.0000006 in 19 evaluations, measured at
    a44659e; docs/cli.md, Fit); an earlier build stopped there in a valley at yield_stress
    217, flow_rate 10.8 (loss 4.9e-8, reported as not converged), which the sampled first
    stage (``--samples``) guards against by starting the descent in the right one.

    With the default pressure force (energy_spiky) there is a second valley near the truth:
    from the best of 4, 6 or 10 samples L-BFGS converges at yield_stress 111.7, flow_rate
    10.10 (loss 8.0e-10, 7.5e-5 of the initial; 1.4e-18 at the truth; a minimum along each
    parameter at +-1e-4, and the loss rises smoothly from it towards the truth, 8.4e-10 a
    quarter of the way, before it falls: measured), also with ``--starts 2`` from 6
    samples; from the best of 8 or 12 it reaches the truth (100.00003, 10.0000; loss
    1.3e-18). So 8 samples, the number docs/fitting.md's silhouette fit uses."""
    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    out = tmp_path / "calibration"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(run), "--target-body", "dough", "--target-frames", "2,4,6",
                   "--iterations", "30", "--samples", "8", "--output-dir", str(out), "--no-progress", "--no-usd",
                   "--noise", "1e-4"])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    doc = json.loads((out / "fit.json").read_text())
    assert doc["optimizer"] == "lbfgs"  # the default for two values
    # The truth, not the valley at 111.7 / 10.10 (loss 7.5e-5 of the initial).
    assert doc["params"]["yield_stress"][0] == pytest.approx(100.0, rel=1e-3)
    assert doc["params"]["flow_rate"][0] == pytest.approx(10.0, rel=1e-3)
    assert doc["loss"] < 1e-9 * doc["initial_loss"]
    # The command says how the fit ended, and before it, what it will cost.
    assert doc["stopped"] in ("converged", "stalled", "iterations")
    assert f"fit {doc['termination']}" in captured.out
    assert "MiB of Warp arrays" in captured.err and "one evaluation (forward + backward) took" in captured.err
    assert "diagnostics" in captured.out and doc["diagnostics"]["labels"] == ["yield_stress", "flow_rate"]
    # History as CSV (one row per evaluation) and the plots, in the chosen folder only.
    rows = (out / "history.csv").read_text().strip().splitlines()
    assert len(rows) == len(doc["history"]) + 1 and rows[0].startswith("evaluation,stage,loss,yield_stress,flow_rate")
    assert (out / "loss.png").stat().st_size > 0 and (out / "params.png").stat().st_size > 0
    # (the run's force log of its ground beside its USD)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration", "guess.toml", "run.usdc", "run.usdc_tools.csv",
                                                          "run.usdc_tools.json", "truth.toml"]


def test_cli_fits_yield_stress_to_masks_from_calibrated_cameras(tmp_path, capsys, dough_scene):
    """End to end from the command line with ``--cameras``: a dough block dropped on the
    ground (64 particles) seen by two calibrated cameras (front and side, intrinsics ``K``
    and extrinsics ``R, t`` in a JSON file), binary masks of the true run at frames 2, 4, 6,
    and ``warp-esph fit`` from 4x the true yield stress. The masks are binary, so the
    loss's minimum need not be at the truth; it lies in a flat bottom that the fit must
    reach, and the diagnostics must say the masks do not determine the yield stress.
    Measured with the contact's touchdown share: the loss 0.026319 at 400 Pa, 0.025514 at
    150, 0.025449 at 100, 0.025427 at 50, 0.025435 at 25 (the minimum near 50 Pa, 0.09 %
    below the truth's loss); the fit 400 -> 49.7 Pa in 8 iterations, loss 0.966 of the
    initial. With the share's first form the minimum was near the truth (400 -> 93.3 Pa);
    earlier, on the spiky pressure force, 400 -> 122 Pa in 9 evaluations.

    The splat opacity is 0.9: with 0.5 a body a few particles thick never reaches O = 1
    inside, and the loss fell monotonically towards ever lower yield stresses (a softer,
    wider body covers more of each mask), the fit moving away from the truth."""
    from warp_esph.cli import main
    from warp_esph.render import UsdFrames

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    guess.write_text(dough_scene(yield_stress=400.0, flow_rate=10.0))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    down = np.diag([1.0, -1.0, -1.0])  # looking along -z, image y down
    side = [[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]]  # looking along -x
    cams = [PinholeCamera(64, 40, 200.0, 200.0, 31.5, 19.5, R, [0.0, 0.03, 0.5], name) for name, R in (("front", down), ("side", side))]
    radius, opacity = 0.01, 0.9
    data = UsdFrames(str(run))
    masks = {}
    for f in (2, 4, 6):
        x = data.arrays(f)["points"].astype(np.float64)
        for c in cams:
            masks[f"{c.name}_{f}"] = (soft_silhouette(x, c, radius, opacity) > 0.5).astype(np.uint8)
            assert 0.3 < masks[f"{c.name}_{f}"].mean() < 0.7  # each camera sees the body and its outline
    np.savez(tmp_path / "masks.npz", **masks)
    doc = {"cameras": [{"name": c.name, "width": c.width, "height": c.height, "K": [[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]],
                        "R": c.R.tolist(), "t": c.t.tolist()} for c in cams], "radius": radius, "opacity": opacity}
    (tmp_path / "cameras.json").write_text(json.dumps(doc))
    out = tmp_path / "fit"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(tmp_path / "masks.npz"), "--cameras", str(tmp_path / "cameras.json"),
                   "--params", "yield_stress", "--iterations", "8", "--output-dir", str(out), "--no-progress", "--no-usd",
                   "--dtype", "float64"])
    captured = capsys.readouterr()
    # In the flat bottom, not converged (the masks do not determine it): the results written, exit 5.
    assert status == EXIT_NOT_CONVERGED, captured.err
    assert "to silhouettes from" in captured.err
    result = json.loads((out / "fit.json").read_text())
    fitted = result["params"]["yield_stress"][0]
    assert 25.0 < fitted < 150.0, fitted  # into the flat bottom (loss within 0.35 % of its minimum)
    assert result["loss"] < 0.98 * result["initial_loss"]
    rows = (out / "history.csv").read_text().strip().splitlines()
    assert rows[0].startswith("evaluation,stage,loss,yield_stress") and len(rows) == len(result["history"]) + 1
    assert (out / "loss.png").stat().st_size > 0 and (out / "params.png").stat().st_size > 0
    # Silhouettes alone barely see the yield stress (a factor 1.5 changes the chi-square by
    # 0.03 here): wherever the fit stopped, the diagnostics must not call it determined.
    assert result["diagnostics"]["labels"] == ["yield_stress"]
    assert result["diagnostics"]["undetermined"] == ["yield_stress"]
    assert min(result["diagnostics"]["range_rise"][0]) < 1.0
    assert any("factor 1.5 changes the chi-square by only" in w for w in result["diagnostics"]["warnings"])


@pytest.mark.parametrize("yield_stress, flagged, fit_weight", [(1.0, True, "poly6"), (1.0, True, "biweight"), (300.0, False, None)],
                         ids=["1Pa-poly6", "1Pa-biweight", "300Pa-default"])
def test_diagnostics_flag_an_unobservable_yield_stress(yield_stress, flagged, fit_weight, dropped_cube):
    """With a yield stress far below the stresses of the impact, the flow rule's
    ``(|s| - Y) / |s|`` hardly depends on it: the diagnostics must say the data do not
    determine it, for that reason (and still fix the flow rate to 1 %). At a yield stress
    the stresses are comparable to, the data depend on it a quarter as much as on the flow
    rate and fix it to 3 %.

    Measured with the default pressure force (energy_spiky) and the contact's touchdown
    share: at 1 Pa, the yield stress 955 % (sensitivity 0.81e-3 of the flow rate's), the
    flow rate 0.77 %; at 300 Pa, 2.5 % and 0.64 % (sensitivity 420 against 1629). Either
    way the two are correlated (|r| = 0.995), so the diagnostics also flag the pair as a
    combination: at 1 Pa the flow rate is flagged for that alone, at 300 Pa both are. (With
    the share's first form |r| was 0.980 at 300 Pa and below 0.95 at 1 Pa; measured |r| at
    100, 150, 200, 250, 400, 500 Pa then: 0.956, 0.669, 0.943, 0.983, 0.987, 0.988: the drop
    mostly fixes a combination of yield stress and flow rate once Y is within reach of its
    stresses.)

    With the biweight fit weight (measured): at 1 Pa the yield stress 574 % (sensitivity
    0.68e-3 of the flow rate's), the flow rate 0.39 %; at 300 Pa 1.86 % and 0.35 %
    (sensitivity 272 against 1446); |r| = 0.980 at both: the same verdicts. The 1 Pa drop
    runs with each weight by name, so that the bias note's way through ``diagnose`` (said for
    poly6, not for the biweight) is checked whichever weight is the default; 300 Pa with the
    default."""
    model = dropped_cube(yield_stress, 10.0, fit_weight=fit_weight)
    dt = model.stable_dt()
    steps = 100
    frames = [35, 70, 100]
    truth = Rollout(model, steps, dt, frames=frames)
    target = truth.forward()
    past = round(100 * np.mean(truth.final_state().alpha.numpy() > LARGE_STRAIN_ALPHA))  # % of particles
    d = diagnose(model, PositionLoss(target, frames=frames), ["yield_stress", "flow_rate"], steps=steps, dt=dt, noise=1e-3)
    assert d.method == "gauss-newton" and d.labels == ["yield_stress", "flow_rate"]
    assert d.relative_error[1] < 0.01
    if flagged:
        assert "yield_stress" in d.undetermined, d.summary()
        # Sensitivity ratio measured 0.85e-3 with the paper's 30-wide rows and the earlier
        # contact law, 0.81e-3 to 1.1e-3 with the wide rows and the continuous contact
        # (docs/method.md §1): three orders below the flow rate's either way.
        assert d.relative_error[0] > 0.25 and d.sensitivity[0] < 2e-3 * d.sensitivity[1]
        assert any(w.startswith("yield_stress is not determined by the data: the data barely depend on it")
                   for w in d.warnings), d.warnings
        # The flow rate, determined on its own, is flagged for the correlation alone if at all.
        assert all("correlated" in w and "standard error" not in w for w in d.warnings if w.startswith("flow_rate")), d.warnings
    else:
        assert d.relative_error[0] < 0.03 and d.sensitivity[0] > 0.1 * d.sensitivity[1], d.summary()
        # Flagged for their correlation alone (energy_spiky, above), not for either's error.
        assert abs(d.correlation[0, 1]) > 0.95 and d.undetermined == ["yield_stress", "flow_rate"], d.summary()
        assert len(d.warnings) == 2 and all("correlated" in w for w in d.warnings), d.warnings
    assert np.allclose(d.correlation, d.correlation.T) and np.allclose(np.diag(d.correlation), 1.0)
    # The 5-across cube flattens on impact: measured 20 % (1 Pa) and 14 % (300 Pa) of its
    # particles end past alpha = 0.65 with the poly6 fit weight, 20 % and 17 % with the
    # biweight. Past it the poly6 packing has rearranged, so with poly6 the diagnostics name
    # the model's bias too (apart from what the data determine); the biweight's packing holds
    # its flow stress there (large_strain_bias), so the same flow draws no note.
    share = {("poly6", True): 20, ("poly6", False): 14, ("biweight", True): 20, ("biweight", False): 17}[model.fit_weight, flagged]
    assert past == share
    if model.fit_weight == "poly6":
        assert len(d.bias) == 1 and d.bias[0].startswith(f"{share} % of the particles end past a plastic strain of 0.65"), d.bias
        assert "WARNING (model): " + d.bias[0] in d.summary() and d.to_dict()["bias"] == d.bias
    else:
        assert d.bias == [] and "WARNING (model)" not in d.summary() and d.to_dict()["bias"] == []


def test_the_large_strain_bias_is_said_for_the_poly6_weight_past_its_measured_strain():
    """``large_strain_bias``: more than a tenth of the particles of materials that can flow
    past alpha = 0.65 (the median alpha where the uniaxial flow stress falls, 8 and 12
    across) with the poly6 fit weight; not with the biweight, whose packing holds 0.83-0.95
    of the Bingham stress. An elastic body's particles (a floor, alpha 0 for ever) do not
    dilute the share."""
    from types import SimpleNamespace

    from warp_esph.diagnostics import large_strain_bias

    def model(weight, n, elastic=0):
        array = SimpleNamespace  # what the function reads: .numpy() of the parameter arrays
        return SimpleNamespace(fit_weight=weight, particle_material_np=np.r_[np.zeros(n, int), np.ones(elastic, int)],
                               yield_stress=array(numpy=lambda: np.array([10.0, np.inf])),
                               flow_rate=array(numpy=lambda: np.array([50.0, 50.0])))

    alpha = np.r_[np.full(85, 0.3), np.full(15, 0.9)]
    said = large_strain_bias(model("poly6", 100), alpha, "experiment 1: ")
    assert said.startswith("experiment 1: 15 % of the particles end past a plastic strain of 0.65") and "biweight" in said
    # Where the weight is chosen, in each of the three ways: it had said "fit with
    # fit_weight='biweight'", a keyword fit() does not take and no option of warp-esph fit.
    assert "SceneBuilder(fit_weight='biweight'), [solver] fit_weight = \"biweight\" or --fit-weight biweight" in said
    assert large_strain_bias(model("biweight", 100), alpha) is None
    assert large_strain_bias(model("poly6", 100), np.r_[np.full(91, 0.3), np.full(9, 0.9)]) is None
    assert large_strain_bias(model("poly6", 10), np.full(10, 0.65)) is None  # at the threshold, not past it
    # 15 of 100 flowing particles past it, beside 200 elastic floor particles: still 15 %.
    floor = large_strain_bias(model("poly6", 100, elastic=200), np.r_[alpha, np.zeros(200)])
    assert floor is not None and floor.startswith("15 % of the particles")


def _stretch(rate, seconds, noise_seed, factor=1.0):
    """64-125 particles stretched at a uniform rate (no gravity, no ground): one stress level.
    The paper's elastic force, as when the numbers in docs/fitting.md were measured (with
    the variational force one stretch alone already fixes the yield stress to 6 %)."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), we.Material(mu=2e3, lam=3e3, density=1000.0, yield_stress=100.0,
                                                            flow_rate=10.0, elastic_force="paper"))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    model.particle_v0 = rate * model.particle_x0 * np.array([1.0, -0.5, -0.5])
    dt = model.stable_dt()
    steps = int(seconds / dt)
    frames = [steps // 3, 2 * steps // 3, steps]
    target = Rollout(model, steps, dt, frames=frames).forward()
    target = target + np.random.default_rng(noise_seed).normal(scale=1e-4, size=target.shape)
    if factor != 1.0:
        m = model.materials[0]
        model.set_material(0, dataclasses.replace(m, yield_stress=factor * m.yield_stress, flow_rate=factor * m.flow_rate))
    return Experiment(model, PositionLoss(target, frames=frames), steps=steps, dt=dt, noise=1e-4)


def test_joint_fit_recovers_what_neither_experiment_determines():
    """A slow and a fast stretch of one material: each alone fixes only a combination of
    yield stress and flow rate (the rate of flow at its own stress level), so its
    diagnostics flag both; together they determine both, and a joint fit from 2x off
    recovers them from targets with 0.1 mm noise."""
    params = ["yield_stress", "flow_rate"]
    slow, fast = _stretch(4.0, 0.1, 1), _stretch(30.0, 0.04, 2)
    for e in (slow, fast):
        d = fit([e], None, params, iterations=0, progress=False).diagnostics
        assert d.undetermined == params, d.summary()
        assert abs(d.correlation[0, 1]) > 0.95
    slow, fast = _stretch(4.0, 0.1, 1, factor=2.0), _stretch(30.0, 0.04, 2, factor=2.0)
    result = fit([slow, fast], None, params, iterations=30, optimizer="lbfgs", progress=False)
    d = result.diagnostics
    assert d.undetermined == [], d.summary()
    assert abs(d.correlation[0, 1]) < 0.9
    assert result.params["yield_stress"][0] == pytest.approx(100.0, rel=0.10)
    assert result.params["flow_rate"][0] == pytest.approx(10.0, rel=0.10)
    # Each experiment's model is left holding the shared fitted material.
    for m in result.models:
        assert m.materials[0].yield_stress == result.params["yield_stress"][0]
    # The fit reaches the noise floor: residuals of 0.1 mm per coordinate, as put in.
    assert result.stopped == "converged"
    assert d.residual_rms == pytest.approx([1e-4, 1e-4], rel=0.2)


def test_gauss_newton_fits_the_joint_experiments_from_forward_runs():
    """optimizer="gauss-newton" (Levenberg-Marquardt on the residual vectors, Jacobian by
    forward differences): the joint stretch fit from 2x off reaches the noise floor from
    forward runs only, its history's loss is the sum of squared weighted residuals (the
    loss itself), and a loss without residuals is refused before any run."""
    params = ["yield_stress", "flow_rate"]
    slow, fast = _stretch(4.0, 0.1, 1, factor=2.0), _stretch(30.0, 0.04, 2, factor=2.0)
    result = fit([slow, fast], None, params, iterations=30, optimizer="gauss-newton", xtol=1e-4, progress=False)
    assert result.stopped == "converged", result.termination
    assert result.params["yield_stress"][0] == pytest.approx(100.0, rel=0.10)
    assert result.params["flow_rate"][0] == pytest.approx(10.0, rel=0.10)
    assert result.diagnostics.residual_rms == pytest.approx([1e-4, 1e-4], rel=0.2)
    assert all(h["grad"] is None for h in result.history)  # no backward pass
    # The residual vector is the loss: the same value from fit's loss evaluation.
    again = fit([slow, fast], None, params, iterations=0, diagnostics=False, progress=False)
    assert again.loss == pytest.approx(result.loss, rel=1e-9, abs=0.0)

    class NoResiduals(PositionLoss):
        residuals = property(lambda self: (_ for _ in ()).throw(AttributeError("residuals")))

    e = _stretch(4.0, 0.1, 1)
    e.target = NoResiduals(np.zeros((1, e.model.particle_count, 3)), frames=[e.steps])
    with pytest.raises(ValueError, match="optimizer = 'gauss-newton' is not allowed: .* has no residual vector"):
        fit([e], None, params, iterations=5, optimizer="gauss-newton", progress=False)


def _cameras():
    front = PinholeCamera(32, 24, 60.0, 60.0, 15.5, 11.5, np.diag([1.0, -1.0, -1.0]), [0.0, 0.05, 0.5], "front")
    side = PinholeCamera(24, 24, 50.0, 50.0, 11.5, 11.5, [[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]],
                         [0.0, 0.05, 0.5], "side")
    return [front, side]


def test_silhouette_loss_and_gradient_match_reference_and_central_differences():
    rng = np.random.default_rng(0)
    X = rng.normal(scale=0.03, size=(40, 3)) + np.array([0.0, 0.05, 0.0])
    cams = _cameras()
    masks = [(soft_silhouette(X + np.array([0.01, -0.005, 0.0]), c, 0.01) > 0.3).astype(float) for c in cams]
    assert all(0.1 < m.mean() < 0.5 for m in masks)  # both views see the body, not all of the image
    loss = SilhouetteLoss({5: masks}, cams, radius=0.01)
    value, grads = loss.value_and_grad({5: wp.array(X, dtype=wp.vec3d)})
    reference = np.mean([np.mean((soft_silhouette(X, c, 0.01) - m) ** 2) for c, m in zip(cams, masks)])
    assert value == pytest.approx(reference, rel=1e-12, abs=0.0)
    g = grads[5].numpy()
    h = 1e-6
    for i in range(0, 40, 3):
        for d in range(3):
            xp, xm = X.copy(), X.copy()
            xp[i, d] += h
            xm[i, d] -= h
            fd = (loss.value({5: wp.array(xp, dtype=wp.vec3d)}) - loss.value({5: wp.array(xm, dtype=wp.vec3d)})) / (2 * h)
            assert g[i, d] == pytest.approx(fd, rel=1e-5, abs=1e-9)
    # The residual vector is what the diagnostics use: sum r^2 = residual_scale * value.
    r = loss.residuals({5: X})
    assert np.sum(r**2) == pytest.approx(loss.residual_scale() * value, rel=1e-12)


def test_a_silhouette_loss_with_every_camera_facing_away_says_so():
    """Cameras facing away from the body see no particle: the silhouettes are empty whatever the
    parameters, the gradient 0, and a fit stopped 'flat' blaming the yield stress. The loss
    now names the cameras (``out_of_reach``); a camera that sees the body has nothing to say."""
    rng = np.random.default_rng(0)
    X = rng.normal(scale=0.03, size=(40, 3)) + np.array([0.0, 0.05, 0.0])
    cams = _cameras()
    masks = [(soft_silhouette(X, c, 0.01) > 0.3).astype(float) for c in cams]
    # The same cameras moved to the far side, still looking the same way: the body is behind them.
    away = [PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.R, np.asarray(c.t) * [1.0, 1.0, -1.0], c.name)
            for c in cams]
    loss = SilhouetteLoss({5: masks}, away, radius=0.01)
    _, grads = loss.value_and_grad({5: wp.array(X, dtype=wp.vec3d)})
    assert not grads[5].numpy().any()
    assert loss.out_of_reach() == ("no particle is in view of any camera in any frame (cameras facing away from the "
                                   "body, or placed in other units than metres?)")
    seen = SilhouetteLoss({5: masks}, cams, radius=0.01)
    seen.value({5: wp.array(X, dtype=wp.vec3d)})
    assert seen.out_of_reach() is None


def test_a_silhouette_target_that_constrains_nothing_is_refused(tmp_path):
    """Masks all ones in every view (every pixel inside) and splats that cover every pixel of
    a view by a radius larger than the particles' spacing (0.1 m: splats of 11 pixels and
    more in a 32 x 24 image) ask only that the particles fill the view, whatever the body's
    shape: refused, the masks by their file (or camera and step), the radius at the camera's
    first evaluation, naming the camera file it came from."""
    rng = np.random.default_rng(0)
    X = rng.normal(scale=0.03, size=(40, 3)) + np.array([0.0, 0.05, 0.0])
    cams = _cameras()
    masks = [(soft_silhouette(X, c, 0.01) > 0.3).astype(float) for c in cams]
    np.save(tmp_path / "grey.npy", np.full((24, 32), 200.0))
    with pytest.raises(ValueError, match=r"^mask \S*grey\.npy is not allowed: every pixel is inside \(nonzero, or > 0\.5 of "
                                         r"its maximum\), so it shows no outline of the body and constrains nothing"):
        load_masks(tmp_path / "grey.npy", cams[:1], 3)
    np.savez(tmp_path / "full.npz", front_3=np.ones((24, 32)), side_3=np.ones((24, 24)))
    with pytest.raises(ValueError, match=r"^mask \S*full\.npz is not allowed: every pixel of its 2 masks is inside"):
        load_masks(tmp_path / "full.npz", cams)
    with pytest.raises(ValueError, match=r"^mask of camera 'front' at step 5 is not allowed: every pixel is 1 \(inside\), as "
                                         r"in every other view and step, so the masks show no outline"):
        SilhouetteLoss({5: [np.ones((24, 32)), np.ones((24, 24))]}, cams, radius=0.01)
    x = {5: wp.array(X, dtype=wp.vec3d)}
    with pytest.raises(ValueError, match=r"^radius = 0\.1 is not allowed with camera 'front': at step 5 the particles' splats "
                                         r"\(standard deviation 11\.1 pixels and more\) cover every pixel of its 32 x 24 "
                                         r"image, so the silhouette shows no outline and constrains nothing; the radius is in "
                                         r"metres, about half a particle spacing, and the particles lie about 0\.0\d+ m apart$"):
        SilhouetteLoss({5: masks}, cams, radius=0.1).value(x)
    doc = {"cameras": [{"name": c.name, "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx,
                        "cy": c.cy, "R": c.R.tolist(), "t": c.t.tolist()} for c in cams], "radius": 0.1}
    (tmp_path / "cams.json").write_text(json.dumps(doc))
    np.savez(tmp_path / "m.npz", front_1=masks[0], side_1=masks[1])
    from warp_esph.silhouette import load_silhouette_target

    with pytest.raises(ValueError, match=r"^camera file \S*cams\.json: radius = 0\.1 is not allowed with camera 'front': "):
        load_silhouette_target(tmp_path / "cams.json", tmp_path / "m.npz", None, 1, 5).value(x)
    with pytest.raises(ValueError, match=r"^camera file \S*cams\.json: radius = 0\.1 is not allowed with camera 'front': "):
        SilhouetteLoss({5: masks}, tmp_path / "cams.json", radius=0.1).value(x)
    assert 0.0 < SilhouetteLoss({5: masks}, cams, radius=0.03).value(x) < 0.5  # splats of 3-4 pixels leave an outline


def test_a_view_the_body_fills_with_splats_of_the_right_size_is_a_silhouette_like_any_other(tmp_path):
    """A camera close enough that the body fills its view sees all ones, and the body's splats
    (radius half the spacing) cover its image: a fair observation beside another camera that
    shows the outline. Both were refused (the mask as constraining nothing, the radius as too
    large); they are taken, and the loss still falls towards the true position."""
    g = np.arange(-0.05, 0.0501, 0.02)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)  # 216 particles, spacing 0.02
    close = PinholeCamera(16, 12, 40.0, 40.0, 7.5, 5.5, np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.15], "close")
    far = PinholeCamera(24, 24, 50.0, 50.0, 11.5, 11.5, [[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]],
                        [0.0, 0.0, 0.5], "far")
    masks = [(soft_silhouette(X, c, 0.01) > 0.5).astype(float) for c in (close, far)]
    assert masks[0].all() and 0.1 < masks[1].mean() < 0.5
    np.savez(tmp_path / "m.npz", close_2=masks[0], far_2=masks[1])
    assert load_masks(tmp_path / "m.npz", [close, far])[2][0].all()
    loss = SilhouetteLoss({5: masks}, [close, far], radius=0.01)
    shifted = loss.value({5: wp.array(X + [0.0, 0.03, 0.0], dtype=wp.vec3d)})
    assert loss.value({5: wp.array(X, dtype=wp.vec3d)}) < 0.2 * shifted  # measured 0.0078 and 0.072


def test_silhouette_gradient_through_a_rollout():
    """d(silhouette loss)/d(mu) through 4 steps of a stretched block, tape vs central differences."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.05, 0.0), (0.06, 0.06, 0.06), we.Material(mu=1e3, lam=1.5e3, density=1000.0))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    model.particle_v0 = 20.0 * (model.particle_x0 - [0.0, 0.05, 0.0]) * np.array([1.0, -0.5, 0.0])
    r = Rollout(model, 4, 1e-3, frames=[4])
    x = r.forward()[0]
    cams = _cameras()
    masks = [(soft_silhouette(x * 1.05, c, 0.01) > 0.3).astype(float) for c in cams]
    loss = SilhouetteLoss({4: masks}, cams, radius=0.01)
    _, grads = r.value_and_grad(loss)
    mu = r.get_parameters()["mu"][0]
    vals = []
    for s in (1, -1):
        r.set_parameters({"mu": [mu * (1 + s * 1e-5)]})
        r.forward()
        vals.append(loss.value(dict(zip(r.frames, r.frame_positions))))
    fd = (vals[0] - vals[1]) / (2e-5 * mu)
    assert abs(fd) > 0
    assert grads["mu"][0] == pytest.approx(fd, rel=1e-4, abs=0.0)


@pytest.mark.parametrize("fit_weight, yield_stress, flow_rate", [("poly6", 512.6, 13.28), ("biweight", 566.1, 13.31)],
                         ids=["poly6", "biweight"])
def test_silhouette_only_diagnostics_flag_the_yield_stress(fit_weight, yield_stress, flow_rate, dropped_cube):
    """Silhouettes alone do not determine the yield stress of the drop (docs/fitting.md,
    "Silhouettes"). Two 48 x 48 cameras (front, top), masks of the true run (Y = 100 Pa,
    flow rate 10/s) at steps 50 and 100. The diagnostics are taken where the fit of
    docs/fitting.md ends with each fit weight (energy_spiky pressure force, continuous contact;
    L-BFGS from 2x, 8 samples first, 30 iterations, measured), the truth's masks made with
    the same weight:
    - poly6: at its iteration cap, Y = 512.6 Pa (+413 %), flow rate 13.28/s (+33 %), loss
      0.008670 from 0.01236. There the standard errors are 31 % and 9.2 % (|r| = 0.879; 34.8 %
      and 12.5 % when measured): Y is flagged, the flow rate is not. (The same fit now converges
      at 505.98 Pa, 12.39/s: 25.7 % and 15.5 %, |r| = 0.959, the flow rate flagged for the
      correlation alone.)
    - biweight: at its iteration cap, Y = 566.1 Pa, 13.31/s, loss 0.008656 from 0.013426:
      38 % and 15.8 %, |r| = 0.959: Y flagged, the flow rate for the correlation alone.
    At poly6's 512.6 Pa the biweight's drop reads Y to 1.59 % (flow rate 0.70 %): there, at
    506-519 Pa, its rebounding cube sheds particles whose landings hinge on Y (a 0.2 % change
    moves 13-31 particles by more than 1 mm at step 100, up to 12 mm; poly6's at most 0.2 mm),
    a steep loss the curvature at that point reads as information, while a factor 1.5 in Y
    raises the chi-square by 13.7 and 21.6 only (docs/physics.md, "The switch list worked
    through"). (Under the instant contact law the poly6 fit ended at 294.8 Pa, 10.80/s, where a
    factor 1.5 in Y did not raise the chi-square: the command-line test above checks that
    warning.)"""
    front = PinholeCamera(48, 48, 80.0, 80.0, 23.5, 23.5, np.diag([1.0, -1.0, -1.0]), [0.0, 0.05, 0.5], "front")
    top = PinholeCamera(48, 48, 80.0, 80.0, 23.5, 23.5, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]],
                        [0.0, 0.0, 0.5], "top")
    cams = [front, top]
    model = dropped_cube(100.0, 10.0, fit_weight=fit_weight)
    dt, steps, frames = model.stable_dt(), 100, [50, 100]
    xs = Rollout(model, steps, dt, frames=frames).forward()
    masks = {f: [(soft_silhouette(np.asarray(x, dtype=np.float64), c, 0.01, 0.5) > 0.5).astype(float) for c in cams]
             for f, x in zip(frames, xs)}
    d = diagnose(dropped_cube(yield_stress, flow_rate, fit_weight=fit_weight), SilhouetteLoss(masks, cams, radius=0.01, opacity=0.5),
                 ["yield_stress", "flow_rate"], steps=steps, dt=dt)
    assert d.relative_error[0] > 0.25 > d.relative_error[1], d.summary()
    # The flow rate, determined on its own, is flagged for the correlation alone if at all.
    assert d.undetermined == (["yield_stress"] if fit_weight == "poly6" else ["yield_stress", "flow_rate"]), d.summary()
    assert all("correlated" in w and "standard error" not in w for w in d.warnings if w.startswith("flow_rate")), d.warnings
    # One observation per splat area: pi (2 * 0.01 m * 80 px / ~0.45 m)^2 ~ 40 pixels.
    assert 2 * 2 * 48 * 48 / 60 < d.observations < 2 * 2 * 48 * 48 / 20


def test_camera_file_and_masks(tmp_path):
    cams = _cameras()
    doc = {"cameras": [{"name": c.name, "width": c.width, "height": c.height, "K": [[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]],
                        "R": c.R.tolist(), "t": c.t.tolist()} for c in cams], "radius": 0.01}
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(doc))
    loaded, options = load_cameras(path)
    assert [c.name for c in loaded] == ["front", "side"] and options == {"radius": 0.01}
    assert loaded[0].fx == 60.0 and np.array_equal(loaded[1].R, cams[1].R)
    front = np.pad(np.ones((12, 16)), ((6, 6), (8, 8)))  # the body in the middle of the view
    np.savez(tmp_path / "masks.npz", front_3=front, side_3=np.zeros((24, 24)))
    masks = load_masks(tmp_path / "masks.npz", loaded)
    assert list(masks) == [3] and masks[3][0].shape == (24, 32)
    from warp_esph.silhouette import load_silhouette_target

    loss = load_silhouette_target(path, tmp_path / "masks.npz", None, frames=6, substeps=10)
    assert loss.frames == (30,) and loss.radius == 0.01 and [c.name for c in loss.cameras] == ["front", "side"]
    # A misspelt key was ignored; a radius that is no number was a float() error naming nothing;
    # a mask image given two frames was an int() error (an .npz, which it called an image too,
    # now has its frames chosen).
    for change, message in (({"cameras": [dict(doc["cameras"][0], fov=60)]}, "camera 'front': key 'fov' is not allowed"),
                            ({"bar": 2}, "key 'bar' is not allowed: the keys are cameras, radius, opacity"),
                            ({"radius": "x"}, "radius = 'x' is not allowed: must be a number")):
        path.write_text(json.dumps(dict(doc, **change)))
        with pytest.raises(ValueError, match=message):
            load_cameras(path)
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"--target-frames = '2,3' is not allowed: frame 2 is not in the file .*; the mask "
                                         r"file \S*masks\.npz holds frames 3$"):
        load_silhouette_target(path, tmp_path / "masks.npz", "2,3", frames=6, substeps=10)
    # A mask frame named twice is refused as every frame selection refuses it (it was taken once).
    with pytest.raises(ValueError, match=r"^--target-frames = '3,-1' is not allowed: it names frame 3 twice; name each frame "
                                         r"once; the mask file \S*masks\.npz holds frames 3$"):
        load_silhouette_target(path, tmp_path / "masks.npz", "3,-1", frames=6, substeps=10)
    np.save(tmp_path / "front.npy", np.ones((24, 32)))
    with pytest.raises(ValueError, match="--target-frames = '2,3' is not allowed with the mask image"):
        load_silhouette_target(path, tmp_path / "front.npy", "2,3", frames=6, substeps=10)
    doc["cameras"][0]["R"] = [[2, 0, 0], [0, 1, 0], [0, 0, 1]]
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="not a rotation"):
        load_cameras(path)
    with pytest.raises(ValueError, match="shape"):
        SilhouetteLoss({1: [np.ones((5, 5)), np.ones((24, 24))]}, cams, radius=0.01)


def test_termination_memory_and_global_stage(dropped_cube):
    """The fit says it hit the iteration cap; the memory estimate is the rollout's own;
    the automatic checkpointing fits a limit; the Latin hypercube stratifies every axis."""
    model = dropped_cube(100.0, 10.0)
    dt = model.stable_dt()
    r = Rollout(model, 20, dt, frames=[10, 20])
    target = r.forward()
    r.forward()
    taped = r.memory_bytes()["taped_states"]
    assert taped == 21 * state_nbytes(model.state(requires_grad=True))
    # Besides the rollout's own arrays, the loss's (its target, copy and gradient, the gradient
    # handed back: FRAME_BUFFERS - 1 positions' worth a frame) and 4 kB of small arrays.
    loss_side = 2 * (FRAME_BUFFERS - 1) * model.particle_count * 3 * 8 + 4096
    assert memory_estimate(model, 20, None, frames=2) == r.memory_bytes()["total"] + loss_side
    memory = _RolloutMemory(model, 400)
    limit = sum(memory.need(40)) + 1
    s = choose_checkpointing(model, 400, limit)
    assert s is not None and 20 <= s < 400 and sum(memory.need(s)) <= limit
    assert choose_checkpointing(model, 400, 10 * memory_estimate(model, 400, None)) is None

    u = latin_hypercube(7, 3, np.random.default_rng(0))
    for d in range(3):
        assert sorted(np.floor(u[:, d] * 7).astype(int)) == list(range(7))

    guess = dropped_cube(200.0, 20.0)
    messages = []
    result = fit(guess, PositionLoss(target, frames=[10, 20]), ["yield_stress", "flow_rate"], steps=20, dt=dt,
                 iterations=2, optimizer="lbfgs", progress=False, samples=4, seed=1, diagnostics=False,
                 log=messages.append)
    assert result.stopped == "iterations" and not result.converged and "iteration cap" in result.termination
    stages = [h["stage"] for h in result.history]
    assert stages[:5] == ["sample"] * 5 and stages[5:] == ["descent"] * 3
    # The descent starts from the best of the guess and the samples.
    assert result.history[5]["loss"] == min(h["loss"] for h in result.history[:5])
    assert result.initial_loss == result.history[0]["loss"]  # the guess
    assert any("global stage" in m for m in messages) and any("MiB" in m for m in messages)
    assert math.isfinite(result.loss) and result.loss <= result.history[5]["loss"]


def test_targets_from_data(tmp_path):
    """A run's USD read for one body and chosen frames; a point cloud (.npy of another
    size, .ply) and a mesh at a chosen frame."""
    from warp_esph.fit import load_target
    from warp_esph.losses import ChamferLoss, MeshLoss
    from warp_esph.simulate import simulate
    from warp_esph.usd import UsdWriter

    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.1, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name="block")
    b.add_sphere((0.2, 0.1, 0.0), 0.03, we.Material.preset("rubber"), name="ball")
    b.add_ground()
    model = b.finalize(dtype=wp.float64)
    path = tmp_path / "run.usdc"
    with UsdWriter(path, model, 30.0) as writer:
        simulate(model, 3, fps=30.0, writer=writer, progress=False)
    t = load_target(path, body="ball", frames="1,3")
    ball = model.bodies[1]
    assert t.kind == "positions" and t.frames == [1, 3] and t.fps == 30.0 and t.data.shape == (2, ball.count, 3)
    loss = t.loss(model, {1: 10, 3: 30})
    assert isinstance(loss, PositionLoss) and loss.frames == (10, 30)
    assert np.array_equal(loss.particles, np.arange(ball.start, ball.start + ball.count))
    assert load_target(path).frames == [1, 2, 3]  # default: every frame after the first
    with pytest.raises(ValueError, match="holds bodies block, ball"):
        load_target(path, body="cube")

    cloud = np.random.default_rng(0).normal(size=(50, 3))
    np.save(tmp_path / "cloud.npy", cloud)
    t = load_target(tmp_path / "cloud.npy")
    t.frames = [2]
    loss = t.loss(model, {2: 20})
    assert isinstance(loss, ChamferLoss) and loss.frames == (20,) and len(loss.targets[20]) == 50

    import meshio

    meshio.write(tmp_path / "cloud.ply", meshio.Mesh(cloud, []))
    assert load_target(tmp_path / "cloud.ply").kind == "points"
    tri = meshio.Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), [("triangle", np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32))])
    meshio.write(tmp_path / "shape.ply", tri)
    t = load_target(tmp_path / "shape.ply")
    assert t.kind == "mesh" and isinstance(t.loss(model, {3: 30}), MeshLoss)


def test_target_body_is_the_same_body_in_the_file_and_the_loss(tmp_path):
    """Bodies 'a b' and 'a_b' have the prims a_b and a_b_1: --target-body a_b read the prim a_b
    (body 'a b') from the file and compared it with body 'a_b''s particles; a name the prim
    cleaned ('pâte', 'a b') was refused."""
    from warp_esph.fit import load_target
    from warp_esph.usd import UsdWriter

    b = we.SceneBuilder(spacing=0.02)
    for k, name in enumerate(("a b", "a_b", "pâte")):
        b.add_box((0.3 * k, 0.1, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"), name=name)
    model = b.finalize()
    state = model.state()
    path = tmp_path / "run.usdc"
    with UsdWriter(path, model, 30.0) as writer:
        writer.write_frame(0, state)
        writer.write_frame(1, state)
    for name, body in (("a_b", 1), ("a b", 0), ("a_b_1", 1), ("pâte", 2)):
        t = load_target(path, body=name)
        mine = model.bodies[body]
        assert t.body == mine.name and np.array_equal(t.particles(model), np.arange(mine.start, mine.start + mine.count))
        assert np.allclose(t.data[0], model.particle_x0[mine.start: mine.start + mine.count], atol=1e-6)
    with pytest.raises(ValueError, match="holds bodies a b, a_b, pâte"):
        load_target(path, body="cube")


def test_a_run_target_read_whole_must_hold_the_scenes_bodies_in_order(tmp_path):
    """A run's USD read without --target-body is compared with the scene particle by
    particle: a scene listing the run's bodies in another order (same total) compared one
    body's run with another's, without a word. The bodies are now matched by name and
    count, in order (the prim names of a file without body names count too)."""
    from warp_esph.fit import load_target
    from warp_esph.usd import UsdWriter

    def model(names, sizes=(0.06, 0.06)):
        b = we.SceneBuilder(spacing=0.02)
        for k, (name, size) in enumerate(zip(names, sizes)):
            b.add_box((0.3 * k, 0.1, 0.0), (size, 0.06, 0.06), we.Material.preset("dough"), name=name)
        return b.finalize()

    run = model(["a b", "c"])
    state = run.state()
    path = tmp_path / "run.usdc"
    with UsdWriter(path, run, 30.0) as writer:
        writer.write_frame(0, state)
        writer.write_frame(1, state)
    t = load_target(path)
    assert t.bodies == [("a b", 27), ("c", 27)]
    t.loss(model(["a b", "c"]), {1: 10})  # the scene the run was made with
    for names, sizes in ((["c", "a b"], (0.06, 0.06)), (["a b", "c"], (0.04, 0.08)), (["c", "d"], (0.06, 0.06)),
                         (["e", "a b"], (0.06, 0.06))):
        with pytest.raises(ValueError, match=r"run\.usdc is not allowed: it holds the bodies a b \(27 particles\), c \(27 "
                                             r"particles\) in that order, the scene .*; particles are compared in order: use the scene the run "
                                             r"was made with, or observe one body of the run \(--target-body NAME; "
                                             r"load_target\(path, body=NAME\) in Python\)"):
            load_target(path).loss(model(names, sizes), {1: 10})
    # A scene that renamed its bodies (a guess scene of its own) is matched by the counts.
    for names in (["sample", "other"], ["a b", "d"]):
        load_target(path).loss(model(names), {1: 10})


def test_cli_joint_experiments_file(tmp_path, dough_scene):
    """``--experiments`` adds experiments to a fit: the joint loss is the weighted sum of theirs."""
    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    assert main(["run", str(truth), "-o", str(tmp_path / "run.usdc"), "--frames", "2", "--dtype", "float64",
                 "--no-progress"]) == 0
    common = ["--iterations", "0", "--no-progress", "--no-usd", "--no-diagnostics"]
    losses = []
    for frames in ("2", "1"):
        out = tmp_path / f"alone_{frames}"
        assert main(["fit", str(guess), "--target", str(tmp_path / "run.usdc"), "--target-frames", frames,
                     "--output-dir", str(out), *common]) == 0
        losses.append(json.loads((out / "fit.json").read_text())["initial_loss"])
    (tmp_path / "exps.json").write_text(json.dumps([{"scene": "guess.toml", "target": "run.usdc", "target_frames": "1",
                                                     "weight": 2.0}]))
    out = tmp_path / "joint"
    assert main(["fit", str(guess), "--target", str(tmp_path / "run.usdc"), "--target-frames", "2",
                 "--experiments", str(tmp_path / "exps.json"), "--output-dir", str(out), *common]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert len(doc["experiments"]) == 2 and doc["experiments"][1]["weight"] == 2.0
    assert doc["initial_loss"] == pytest.approx(losses[0] + 2.0 * losses[1], rel=1e-12, abs=0.0)
    assert losses[0] > 0 and losses[1] > 0
    (tmp_path / "bad.json").write_text(json.dumps([{"scene": "guess.toml", "targte": "run.usdc"}]))
    assert main(["fit", str(guess), "--target", str(tmp_path / "run.usdc"), "--experiments", str(tmp_path / "bad.json"),
                 "--output-dir", str(out), *common]) == 2


def test_experiments_observing_one_body_of_one_file_at_one_frame_are_refused(tmp_path, capsys, monkeypatch,
                                                                              two_materials_scene):
    """Two experiments fitting the same body of one run's USD at a frame both choose counted
    its observations twice without a word, where one experiment giving the file twice is
    refused; the file's other body, or another frame, is another observation and passes.
    The frames here are known from the command line and the file (chosen, or the frames a
    run's USD stores): the refusal comes before any scene is built or kernel launched (it
    came after every experiment's scene was built and its checks had run)."""
    import warp

    from warp_esph import fit as fit_module
    from warp_esph import scenes
    from warp_esph.cli import main

    scene, run, exps = tmp_path / "two.toml", tmp_path / "run.usdc", tmp_path / "e.json"
    scene.write_text(two_materials_scene)
    assert main(["run", str(scene), "-o", str(run), "--frames", "2", "--no-progress"]) == 0

    def stand_in(experiments, *args, **kwargs):
        raise ValueError(f"stopped by the test before the first evaluation of {len(experiments)} experiments")

    monkeypatch.setattr(fit_module, "fit", stand_in)
    # A target without a body observes every body of the file: body 'a' too (fitted twice
    # without a word while the check compared the body's names, None against 'a'). A hard
    # link is the file too (another real path: it passed).
    os.link(run, tmp_path / "again.usdc")
    def built(*args, **kwargs):
        raise AssertionError("built or launched before the refusal")

    # frames None: the experiment chooses none, and observes every frame the file stores.
    for mine, body, frames, refused, name in (("a", "a", "2", True, "run"), ("a", "b", "2", False, "run"),
                                              ("a", "a", "1", False, "run"), ("a", None, "2", True, "run"),
                                              (None, "b", "2", True, "run"), (None, "b", "1", False, "run"),
                                              ("a", "a", "2", True, "again"), ("a", "a", None, True, "run")):
        exps.write_text(json.dumps([{"scene": "two.toml", "target": f"{name}.usdc",
                                     **({} if frames is None else {"target_frames": frames}),
                                     **({} if body is None else {"target_body": body})}]))
        capsys.readouterr()
        with monkeypatch.context() as m:
            if refused:
                m.setattr(scenes, "load_scaled_scene", built)
                m.setattr(warp, "launch", built)
            assert main(["fit", str(scene), "--target", str(run), *([] if mine is None else ["--target-body", mine]),
                         "--target-frames", "2", "--experiments", str(exps), "--no-progress", "--no-usd",
                         "--output-dir", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        if refused:
            assert err == (f"warp-esph: error: {exps}: experiment #1: target = '{tmp_path / name}.usdc' (body '{mine or body}') is not allowed at "
                           "frame 2: the command line's --target observes the same file alike there, so its observations "
                           "would count twice, and the diagnostics' standard errors shrink by 1/sqrt(2); give it in one "
                           "experiment (two experiments may share a file for different bodies or tools)\n"), err
        else:
            assert err.endswith("stopped by the test before the first evaluation of 2 experiments\n"), err


def test_experiments_observing_one_file_at_the_last_frame_their_scenes_set_are_refused_once_the_frames_are_known(
        tmp_path, capsys, monkeypatch, dough_scene):
    """A positions file without frame numbers, no frames chosen, is observed at the run's last
    frame, which the scene (or the experiment's ``frames``) sets: two experiments observing it
    at the same last frame are refused once the scenes are built (the early pass cannot know
    it); at other last frames it passes (to the fit, stood in for here)."""
    from warp_esph import fit as fit_module
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    scene, exps = tmp_path / "guess.toml", tmp_path / "e.json"
    scene.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    np.save(tmp_path / "x.npy", load_scene(str(scene)).builder.finalize().particle_x0)

    def stand_in(experiments, *args, **kwargs):
        raise ValueError(f"stopped by the test with {len(experiments)} experiments")

    monkeypatch.setattr(fit_module, "fit", stand_in)
    for frames, refused in ((None, True), (1, False)):
        exps.write_text(json.dumps([{"scene": "guess.toml", "target": "x.npy", **({} if frames is None else {"frames": frames})}]))
        capsys.readouterr()
        assert main(["fit", str(scene), "--target", str(tmp_path / "x.npy"), "--experiments", str(exps), "--params", "yield_stress",
                     "--no-progress", "--no-usd", "--output-dir", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        if refused:
            assert err.endswith(f"{exps}: experiment #1: target = '{tmp_path / 'x.npy'}' is not allowed at frame 2: the command "
                                "line's --target observes the same file there, so its observations would count twice, and "
                                "the diagnostics' standard errors shrink by 1/sqrt(2); give it in one experiment (two "
                                "experiments may share a file for different bodies or tools)\n"), err
        else:
            assert err.endswith("stopped by the test with 2 experiments\n"), err


def test_fit_json_records_each_experiments_solver_settings(tmp_path, dough_scene):
    """A joint fit's ``solver_initial`` and ``solver`` in fit.json recorded the first scene's
    solver settings for every experiment: an ``--experiments`` scene of its own ``[solver]
    hourglass`` was said to run the first's strength. Where the experiments differ, the key
    is a list, one per experiment (the others, alike, one value)."""
    from warp_esph.cli import main

    truth, other = tmp_path / "truth.toml", tmp_path / "other.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    other.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0) + "\n[solver]\nhourglass = 0.1\n")
    assert main(["run", str(truth), "-o", str(tmp_path / "run.usdc"), "--frames", "2", "--dtype", "float64",
                 "--no-progress"]) == 0
    # Frame 1 of the file here, frame 2 there: the same frame in both would count twice (refused).
    (tmp_path / "exps.json").write_text(json.dumps([{"scene": "other.toml", "target": "run.usdc", "target_frames": "1"}]))
    out = tmp_path / "joint"
    assert main(["fit", str(truth), "--target", str(tmp_path / "run.usdc"), "--target-frames", "2", "--params", "mu",
                 "--experiments", str(tmp_path / "exps.json"), "--output-dir", str(out), "--iterations", "0",
                 "--no-progress", "--no-usd", "--no-diagnostics"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    for record in (doc["solver_initial"], doc["solver"]):
        assert record["hourglass"] == [None, 0.1] and record["resolved_hourglass"] == [0.0, 0.1], record
        assert (record["fit"], record["resolved_fit"], record["rest_model"]) == ("auto", "linear", False), record


@pytest.mark.parametrize("options", [["--solver-fit", "curvature_corrected", "--contact", "continuous"],
                                     ["--hourglass", "0.1"]], ids=["fit_contact", "hourglass"])
def test_cli_fit_takes_the_solver_options(tmp_path, capsys, options, dough_scene):
    """``fit --solver-fit/--contact/--hourglass`` reach the fit's solver: the initial loss
    against a run of the same scene with those options is 0 with them (the same forward run;
    up to the float32 rounding of the USD target) and not without; a bad name is one line,
    exit 2."""
    from warp_esph.cli import main

    truth = tmp_path / "truth.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    assert main(["run", str(truth), "-o", str(tmp_path / "run.usdc"), "--frames", "2", "--dtype", "float64",
                 "--no-progress", *options]) == 0
    common = ["--iterations", "0", "--no-progress", "--no-usd", "--no-diagnostics", "--target-frames", "2"]
    losses = []
    for name, extra in (("same", options), ("default", [])):
        out = tmp_path / name
        assert main(["fit", str(truth), "--target", str(tmp_path / "run.usdc"), "--output-dir", str(out), *common, *extra]) == 0
        losses.append(json.loads((out / "fit.json").read_text())["initial_loss"])
    assert losses[0] < 1e-9 * losses[1]
    capsys.readouterr()
    assert main(["fit", str(truth), "--target", str(tmp_path / "run.usdc"), "--solver-fit", "quad", *common]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--solver-fit = 'quad'" in err[0] and "'curvature_corrected'" in err[0]


def test_chamfer_residuals_match_the_loss():
    """The residual vector the diagnostics use has ``sum r^2 = residual_scale * value``,
    with clouds of different sizes and points beyond the radius."""
    from warp_esph.losses import ChamferLoss

    rng = np.random.default_rng(2)
    x = rng.normal(scale=0.05, size=(60, 3))
    y = np.concatenate([x[:40] + rng.normal(scale=0.005, size=(40, 3)), rng.normal(scale=0.05, size=(30, 3)) + 0.3])
    loss = ChamferLoss(y, radius=0.03, frames=[4])
    value = loss.value({4: wp.array(x, dtype=wp.vec3d)})
    assert sum(loss.unmatched[4]) > 0  # some points on both sides find nothing within the radius
    r = loss.residuals({4: x})
    assert np.sum(r**2) == pytest.approx(loss.residual_scale() * value, rel=1e-10)


@pytest.mark.parametrize("mode", ["surface", "outside"])
def test_mesh_residuals_match_the_loss(mode):
    """Point-to-plane residuals of a mesh target: ``sum r^2 = residual_scale * value`` at
    the point they are taken, some particles inside the mesh, some beyond ``max_dist``."""
    from warp_esph.losses import MeshLoss

    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]) * 0.1
    tris = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    x = np.random.default_rng(3).uniform(-0.05, 0.15, size=(80, 3))
    x[:3] += 2.0  # far away: nothing within max_dist
    loss = MeshLoss((verts, tris), frames=[2], mode=mode, max_dist=0.5)
    value = loss.value({2: wp.array(x, dtype=wp.vec3d)})
    r = loss.residuals({2: x})
    assert loss.unmatched[2] == 3
    assert np.sum(r**2) == pytest.approx(loss.residual_scale() * value, rel=1e-10)


def _dough_guess_and_target(tmp_path, dough_scene):
    """A dough scene at twice the true yield stress and flow rate, and a 3-frame float64 run of
    the truth to fit it to: the set-up of the interrupted-fit tests."""
    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--frames", "3", "--dtype", "float64", "--no-progress"]) == 0
    return guess, run


def test_a_positions_file_whose_frames_count_from_a_later_start_is_said_in_the_plan(tmp_path, capsys, dough_scene):
    """A lab's .npz whose stored frames count from a camera's counter (its entry of the start
    stored as frame 2) was fitted that many frames late without a word: the plan line is said
    for files without frame numbers only. Its first frame holding the scene's start, after
    frame 0, is now said; the same positions numbered from 0, or from 1 without the start,
    draw no such line."""
    from warp_esph.cli import main
    from warp_esph.fit import load_target

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    x = np.asarray(load_target(run, frames="all").data)  # frames 0..3, entry 0 the start

    def plan(name, positions, frames):
        np.savez(tmp_path / name, positions=positions, frames=frames, fps=30.0)
        capsys.readouterr()
        status = main(["fit", str(guess), "--target", str(tmp_path / name), "--iterations", "0", "--no-diagnostics",
                       "--no-progress", "--no-usd", "--output-dir", str(tmp_path / f"out_{name}")])
        err = capsys.readouterr().err
        assert status == 0, err
        return [line for line in err.splitlines() if "first stored frame" in line]

    said = plan("counted.npz", x, [2, 3, 4, 5])
    assert len(said) == 1 and "its first stored frame, 2, lies 0 spacings RMS from the scene's initial positions" in said[0]
    assert "renumber them from 0" in said[0]
    assert plan("from_zero.npz", x, [0, 1, 2, 3]) == []
    assert plan("from_one.npz", x[1:], [1, 2, 3]) == []


def test_a_body_resting_at_its_start_over_its_first_stored_frames_is_not_said_to_be_numbered_late():
    """A body at rest at its start over its first stored frames (a press that has not reached
    it by frame 5) holds the start at frame 3 and 4 alike, as the scene's own start does: it was
    told its frames counted from a later start. Said only where the motion starts at the first
    stored frame, the next one already off the start; the same motion with only the first
    stored frame at rest is still said."""
    import types

    from warp_esph.calibrate import _scene_run, _start_frame_later

    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.03, 0.0), (0.06, 0.06, 0.06), we.Material.preset("dough"))
    b.add_ground()
    model = b.finalize()
    start = np.asarray(model.particle_x0, dtype=np.float64)

    def pressed(share):  # the box pressed down to (1 - share) of its height, its base held
        x = start.copy()
        x[:, 1] = start[:, 1].min() + (1.0 - share) * (start[:, 1] - start[:, 1].min())
        return x

    def said(positions, frames):
        # The scene's own run judges a rest over several stored frames: this box settles onto
        # its ground by half a spacing and stays, so a rest over frames 3 and 4 is no lateness.
        return _start_frame_later("lab.npz", types.SimpleNamespace(frames=frames, data=np.stack(positions)), model,
                                  _scene_run(model, 31, 1.0 / 930.0))

    settled = _scene_run(model, 31, 1.0 / 930.0)(4)
    assert settled is not None and 0.3 < np.sqrt(np.mean(np.sum((settled - start) ** 2, axis=1))) / 0.02 < 1.0
    presses = [pressed(0.1), pressed(0.2), pressed(0.3)]
    assert said([start, start, *presses], [3, 4, 5, 6, 7]) is None  # at rest at frames 3 and 4, pressed from 5
    assert said([start], [4]) is None  # a lone frame at rest
    late = said([start, *presses], [3, 4, 5, 6])  # pressed from the frame after the first
    assert late is not None and "its first stored frame, 3, lies 0 spacings RMS" in late, late
    assert said([start, *presses], [0, 1, 2, 3]) is None  # numbered from 0


def test_a_late_counter_over_frames_at_rest_or_in_one_frame_is_said_by_the_scene_s_own_run(tmp_path, capsys,
                                                                                           dough_scene):
    """The dough block is dropped at 1 m/s: its scene leaves its start at once. A lab file
    holding the start at its stored frames 2 and 3 (moving from 4), or storing that one frame
    alone as frame 2, counts its frames from a later start; neither was said, since only a
    start followed at once by motion was. The scene's own run, already a spacing and more off
    its start by then, now says so."""
    from warp_esph.cli import main
    from warp_esph.fit import load_target

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    x = np.asarray(load_target(run, frames="all").data)  # frames 0..3, entry 0 the start

    def plan(name, positions, frames):
        np.savez(tmp_path / name, positions=positions, frames=frames, fps=30.0)
        capsys.readouterr()
        status = main(["fit", str(guess), "--target", str(tmp_path / name), "--iterations", "0", "--no-diagnostics",
                       "--no-progress", "--no-usd", "--frames", "5", "--output-dir", str(tmp_path / f"out_{name}")])
        err = capsys.readouterr().err
        assert status == 0, err
        return [line for line in err.splitlines() if "initial positions" in line]

    rested = plan("rested.npz", np.stack([x[0], x[0], x[1], x[2]]), [2, 3, 4, 5])
    assert len(rested) == 1 and "its stored frames 2 to 3 lie within 0.05 spacings RMS" in rested[0], rested
    assert "by frame 3" in rested[0] and "renumber them from 0" in rested[0]
    lone = plan("lone.npz", x[:1], [2])
    assert len(lone) == 1 and "its one stored frame, 2, lies within" in lone[0] and "by frame 2" in lone[0], lone


def _interrupt_evaluation(monkeypatch, n):
    """A Ctrl-C (KeyboardInterrupt) in the fit's ``n``-th evaluation."""
    from warp_esph import fit as fit_module

    calls, original = [], fit_module._Problem.value_and_grad

    def interrupted(self, z, losses=None):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt
        return original(self, z, losses)

    monkeypatch.setattr(fit_module._Problem, "value_and_grad", interrupted)


def _summary_with_range_rises(rises, gradient=(0.0, 0.0)):
    """The diagnostics' summary of a made two-parameter fit (log space, well curved at the
    optimum), given the range check's chi-square changes ``rises`` (per parameter: down, up)
    and the chi-square's gradient there (per unit of log value)."""
    from types import SimpleNamespace

    from warp_esph.diagnostics import _summarise

    names = ["mu", "yield_stress"]
    prob = SimpleNamespace(labels=names, params=names, k=1, spaces=dict.fromkeys(names, "log"), scales={},
                           from_z=lambda z: {"mu": np.exp(z[:1]), "yield_stress": np.exp(z[1:])})
    return _summarise(prob, np.log([1e3, 100.0]), np.diag([1e4, 1e4]), np.array(gradient), [0.1], [0.1], 100, 4, 1e-3,
                      max_relative_error=0.5, min_sensitivity=1e-3, max_correlation=0.99, rises=np.array(rises))


def test_a_range_check_that_finds_a_lower_chi_square_says_the_fit_stopped_short():
    """Moving a value alone by the range factor rose the chi-square by less than 1 either
    way: the data cannot tell the values apart. Lowered it by more than 1: the data do tell
    them apart; the fit stopped short of the minimum, which is what the warning must say."""
    # Still sloping down (the chi-square's slope and curvature put a fall of 2.5e3 within reach).
    short = _summary_with_range_rises([[50.0, 60.0], [-31.6, 40.0]], gradient=(0.0, 1e4))
    assert short.undetermined == []
    assert any(w.startswith("yield_stress is not at the data's best value") and "lowers the chi-square by 31.6" in w
               and "the fit stopped short of the minimum" in w for w in short.warnings), short.warnings
    flat = _summary_with_range_rises([[50.0, 60.0], [-0.2, 0.5]])
    assert flat.undetermined == ["yield_stress"]
    assert any("changes the chi-square by only -0.2" in w for w in flat.warnings), flat.warnings
    assert not any("best value" in w for w in flat.warnings)
    assert _summary_with_range_rises([[50.0, 60.0], [2.0, 3.0]]).warnings == []


def test_a_range_check_that_finds_a_lower_chi_square_beyond_a_local_minimum_says_so():
    """A fit that converged (no slope, curved) where the chi-square is yet lower at a factor
    1.5 away sits in a local minimum of the loss: an L-BFGS fit of a 1 cm landing's yield
    stress from 600 Pa converged at 599.4 Pa, the loss's minimum at 300 Pa, 1.5 x down lower
    by a chi-square of 293, and the warning said it stopped short and asked for more
    iterations, which only repeat the same point. It must name the local minimum, the side
    that is lower and a way past it (a start there, or the global stage)."""
    local = _summary_with_range_rises([[50.0, 60.0], [-293.0, 40.0]], gradient=(0.0, 0.2))
    said = [w for w in local.warnings if w.startswith("yield_stress is not at the data's best value")]
    assert len(said) == 1, local.warnings
    assert "lowers the chi-square by 293" in said[0] and "local minimum" in said[0], said[0]
    assert "at 66.67 (1/1.5 x)" in said[0] and "samples" in said[0], said[0]
    assert "more iterations do not leave" in said[0] and "stopped short" not in said[0], said[0]
    upper = _summary_with_range_rises([[50.0, 60.0], [40.0, -5.0]])
    said = [w for w in upper.warnings if w.startswith("yield_stress is not at the data's best value")]
    assert len(said) == 1 and "at 150 (1.5 x)" in said[0] and "local minimum" in said[0], upper.warnings


def test_a_target_whose_fps_is_not_one_number_is_refused_by_name(tmp_path):
    """An array of frame rates in a .npz target ended in a numpy TypeError traceback."""
    from warp_esph.fit import load_target

    path = tmp_path / "t.npz"
    np.savez(path, positions=np.zeros((2, 4, 3)), fps=np.array([30.0, 60.0]))
    with pytest.raises(ValueError, match=r"t\.npz is not allowed: its 'fps' must be one number, not an array of shape \(2,\)"):
        load_target(path)
    np.savez(path, positions=np.zeros((2, 4, 3)), fps=np.array(30.0))
    load_target(path)


def test_load_target_s_body_and_tool_refusals_name_the_python_arguments_and_an_experiment_its_keys(tmp_path, capsys):
    """load_target(body=, tool=) is refused naming body and tool, as its frames are named
    frames (the command passes its own names): it named --target-body and --target-tool, which
    an --experiments file's target_body and target_tool were refused as too."""
    import json

    from run_files import box_on_ground
    from warp_esph.cli import main
    from warp_esph.fit import load_target

    (tmp_path / "s.toml").write_text(box_on_ground("tiny", 2, "soft", "dough", "1.5e4"))
    run = tmp_path / "run.usdc"
    assert main(["run", str(tmp_path / "s.toml"), "-o", str(run), "--no-progress", "--dtype", "float64"]) == 0
    npz = tmp_path / "t.npz"
    np.savez(npz, positions=np.zeros((2, 4, 3)))
    log = tmp_path / "two_tools.csv"
    log.write_text("frame,time,tool,fx,fy,fz\n1,0.1,a,0,0,1\n1,0.1,b,0,0,1\n")
    for call, words in ((lambda: load_target(run, body="nosuch"), "body = 'nosuch' is not allowed: "),
                        (lambda: load_target(npz, body="dough"), "body = 'dough' is not allowed with the target "),
                        (lambda: load_target(log), "tool is required: "),
                        (lambda: load_target(log, tool="c"), "tool = 'c' is not allowed: ")):
        with pytest.raises(ValueError) as e:
            call()
        assert str(e.value).startswith(words), str(e.value)
    capsys.readouterr()
    for key, target, words in (("target_body", "run.usdc", "target_body = 'nosuch' is not allowed: "),
                               ("target_tool", "two_tools.csv", "target_tool = 'nosuch' is not allowed: ")):
        (tmp_path / "exp.json").write_text(json.dumps([{"scene": "s.toml", "target": target, key: "nosuch"}]))
        assert main(["fit", str(tmp_path / "s.toml"), "--target", str(run), "--no-progress", "--iterations", "1",
                     "--experiments", str(tmp_path / "exp.json")]) == 2
        err = capsys.readouterr().err
        assert f"exp.json: experiment #1: {words}" in err, err
        assert "--target-" not in err, err


def test_a_target_body_or_a_force_log_the_target_cannot_serve_is_refused_by_name(tmp_path):
    """``--target-body`` with a target that holds no bodies was ignored (every position was
    the target); a reaction-force log that lost a column was read as a point cloud and
    refused as one."""
    from warp_esph.fit import load_target

    npz = tmp_path / "t.npz"
    np.savez(npz, positions=np.zeros((2, 4, 3)))
    with pytest.raises(ValueError, match=r"^body = 'dough' is not allowed with the target .*t\.npz: only the USD"):
        load_target(npz, body="dough")
    log = tmp_path / "run_tools.csv"
    log.write_text("frame,time,tool,fx,fz\n1,0.1,plane0,0.0,0.0\n")
    with pytest.raises(ValueError, match=r"run_tools\.csv is not allowed: a reaction-force log needs the columns .*; it lacks fy"):
        load_target(log)


@pytest.mark.parametrize("positions", [(1, 60, 3), (60, 3), (2, 60, 3)])
def test_a_target_of_another_particle_count_is_told_so_before_its_frames(tmp_path, capsys, dough_scene, positions):
    """An .npz of one frame and no 'frames' holds frame 0 only: (1, 60, 3) positions for the
    64-particle scene were refused as 'the targets hold only frame 0', never told the count
    was wrong, while (60, 3) got the count; each is now refused for its count first."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    np.savez(tmp_path / "t.npz", positions=np.zeros(positions))
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(tmp_path / "t.npz"), "--no-progress",
                 "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "t.npz has 60 particles per frame, the scene 64: use the scene" in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("dt, message", [("0", "--dt = 0.0 is not allowed: must be > 0"),
                                         ("0.0007", "--dt = 0.0007 is not allowed: a frame (1/fps = 0.0333333 s) must be")])
def test_fit_dt_is_refused_by_the_option(tmp_path, capsys, dough_scene, dt, message):
    """The step's check named its parameter, 'dt = 0.0', which the command does not have."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    np.savez(tmp_path / "t.npz", positions=np.zeros((64, 3)))
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(tmp_path / "t.npz"), "--dt", dt, "--no-progress",
                 "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"warp-esph: error: {message}"), err


def test_fit_a_scene_files_dt_that_does_not_fill_its_frame_is_named_by_the_file_and_table(tmp_path, capsys, dough_scene):
    """A scene file's own ``dt`` that does not divide its own frame was refused by ``fit`` as a
    bare 'dt = 0.0007 is not allowed', a name typed nowhere, where ``run`` names the file and its
    table; an experiment's scene file so too, after the experiment."""
    from warp_esph.cli import main

    good = tmp_path / "good.toml"
    good.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    bad = tmp_path / "bad.toml"
    bad.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0).replace("fps = 30", "fps = 30\ndt = 0.0007"))
    np.savez(tmp_path / "t.npz", positions=np.zeros((64, 3)))
    np.savez(tmp_path / "u.npz", positions=np.ones((64, 3)))
    experiments = tmp_path / "exp.json"
    experiments.write_text(json.dumps([{"scene": "bad.toml", "target": "u.npz"}]))
    said = "[scene] dt = 0.0007 is not allowed: a frame (1/fps = 0.0333333 s) must be a whole number of steps"
    for scene, extra, prefix in ((bad, [], f"{bad}: "), (good, ["--experiments", str(experiments)],
                                                          f"{experiments}: experiment #1: bad.toml: ")):
        capsys.readouterr()
        assert main(["fit", str(scene), "--target", str(tmp_path / "t.npz"), "--no-progress", "--output-dir",
                     str(tmp_path / "out"), *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(f"warp-esph: error: {prefix}{said}"), err


def test_a_stable_step_too_short_for_a_frame_is_refused_with_the_fit_s_options(tmp_path, capsys, dough_scene):
    """Frames of 10000 s at the stable step: the advice was Python's 'give dt or substeps', and
    'warp-esph fit' has no substeps; it names the command's options."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    np.savez(tmp_path / "t.npz", positions=np.zeros((64, 3)))
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(tmp_path / "t.npz"), "--fps", "0.0001", "--no-progress",
                 "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("warp-esph: error: the stable step "), err
    assert err.endswith(" needs it: use softer materials, a larger spacing, a higher --fps, or give --dt\n"), err
    # Where the hourglass control's limit sets the step, its option is named, not a softer material.
    assert main(["fit", str(guess), "--target", str(tmp_path / "t.npz"), "--fps", "0.0001", "--hourglass", "1000",
                 "--no-progress", "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "; the hourglass control sets it (the hourglass control's limit at strength c = 1000, " in err
    assert err.endswith(": use a smaller --hourglass (or the scene's [solver] hourglass), a larger spacing, a higher --fps, "
                        "or give --dt\n"), err


def test_fit_frames_beyond_a_rollout_are_refused_by_the_option(tmp_path, capsys, dough_scene):
    """A frame count whose steps no rollout can take was refused as 'steps = ...', an
    option the command does not have."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    np.savez(tmp_path / "t.npz", positions=np.zeros((64, 3)))
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(tmp_path / "t.npz"), "--frames", "2147483647", "--no-progress",
                 "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--frames = 2147483647 is not allowed" in err, err


def test_target_body_picks_the_run_usd_and_leaves_a_force_log_beside_it_alone(tmp_path, capsys, dough_scene):
    """``--target-body`` with a run's USD and its force log as two targets: the body is the
    USD's; the log takes none (it was refused, as if the body had been meant for it). With a
    force log alone it is refused by name."""
    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2))
    guess.write_text(dough_scene(yield_stress=120.0, flow_rate=12.0, frames=2))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--no-progress"]) == 0
    common = ["--iterations", "1", "--no-progress", "--no-usd", "--output-dir", str(tmp_path / "fit")]
    assert main(["fit", str(guess), "--target", str(run), "--target", f"{run}_tools.csv", "--target-tool", "plane0",
                 "--target-body", "dough", *common]) == EXIT_NOT_CONVERGED  # one iteration: the cap, results written
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", f"{run}_tools.csv", "--target-body", "dough", *common]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--target-body = 'dough' is not allowed: it picks a body of a run's USD target" in err, err


def test_cli_fit_refuses_what_would_lose_data_or_mistime_the_targets(tmp_path, capsys, dough_scene):
    """From a fuzz of the command: each of these exited 0 (or with a traceback), and each is
    now one line and exit 2, before the fit, with every input file left as it was.

    - ``-o`` onto the target run, the scene file, or ``--output-dir`` holding the target as
      ``fitted.usdc``: replaced by the fit's JSON or run;
    - ``--fps`` other than the rate the run's USD recorded: frame k fitted at k / fps against
      a frame recorded at k / 30 s;
    - a ``.npz`` whose frames are not whole (1.5 read as frame 1) or whose one frame holds
      another number of particles (fitted as a point cloud), complex positions;
    - ``--target-frames`` with -1 (a KeyError traceback), or only frame 0 (blamed --frames);
    - an experiments entry whose scene is not a name (a TypeError traceback);
    - ``--worlds`` without starts, ``--starts`` beyond the samples, one parameter bounded
      twice, a nameless bound: options the fit would ignore, or silently overrule."""
    from warp_esph.cli import main
    from warp_esph.usd import UsdFrames

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    frames = UsdFrames(str(run))
    x = np.stack([frames.particles(k)["points"] for k in range(1, 4)])
    np.savez(tmp_path / "float_frames.npz", positions=x, frames=np.array([1.5, 2.0, 3.0]))
    np.savez(tmp_path / "one_short.npz", positions=x[2:, :-4], frames=[3])
    np.savez(tmp_path / "complex.npz", positions=x.astype(complex), frames=[1, 2, 3])
    np.savez(tmp_path / "good.npz", positions=x, frames=[1, 2, 3])
    (tmp_path / "exps.json").write_text(json.dumps([{"scene": 3, "target": "run.usdc"}]))
    # An entry's frames keys were refused as the command's options (--frames, --target-frames),
    # which the command line never gave.
    for name, entry in (("frames0.json", {"frames": 0}), ("tframes0.json", {"target_frames": "0"}),
                        ("tbody.json", {"target": "good.npz", "target_body": "x"})):
        # Another recording: run.usdc at every frame, observed again, is refused before any scene.
        (tmp_path / name).write_text(json.dumps([{"scene": "guess.toml", "target": "other.usdc", **entry}]))
    shutil.copy(run, tmp_path / "other.usdc")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "fitted.usdc").write_bytes(run.read_bytes())
    before = {p: p.read_bytes() for p in (run, guess, tmp_path / "out" / "fitted.usdc")}
    common = ["--iterations", "1", "--no-progress", "--no-diagnostics", "--no-usd", "--output-dir", str(tmp_path / "o")]
    cases = [
        (["--target", str(run), "-o", str(run)], "run.usdc' is not allowed: it is --target"),
        (["--target", str(run), "-o", str(guess)], "guess.toml' is not allowed: it is the scene"),
        (["--target", str(tmp_path / "out" / "fitted.usdc"), "--iterations", "1", "--no-progress", "--no-diagnostics",
          "--output-dir", str(tmp_path / "out")], "fitted.usdc = .* is not allowed: it is --target"),
        (["--target", str(run), "--fps", "60"], "run.usdc was recorded at 30 fps; leave --fps out or give 30"),
        (["--target", str(tmp_path / "float_frames.npz")], "its 'frames' must be whole frame indices, not [1.5, 2.0, 3.0]"),
        (["--target", str(tmp_path / "one_short.npz")], "has 60 particles per frame, the scene 64"),
        (["--target", str(tmp_path / "complex.npz")], "its positions must be real numbers, not complex128 values"),
        (["--target", str(tmp_path / "good.npz"), "--target-frames=-5,2,3"],
         "--target-frames = '-5' is not allowed: it counts back past the first frame"),
        (["--target", str(run), "--target-frames", "0"], "--target-frames = '0' is not allowed: the targets hold only frame 0"),
        (["--target", str(run), "--experiments", str(tmp_path / "exps.json")],
         "experiment #1: scene = 3 is not allowed: must be a scene name or a .toml path"),
        (["--target", str(run), "--experiments", str(tmp_path / "frames0.json")],
         "experiment #1: frames = 0 is not allowed: must be an integer >= 1"),
        (["--target", str(run), "--experiments", str(tmp_path / "tframes0.json")],
         "experiment #1: target_frames = '0' is not allowed: the targets hold only frame 0"),
        (["--target", str(run), "--experiments", str(tmp_path / "tbody.json")],
         "experiment #1: target_body = 'x' is not allowed: it picks a body of a run's USD target"),
        (["--target", str(run), "--worlds"], "--worlds is not allowed with --starts = 1"),
        (["--target", str(run), "--starts", "3", "--samples", "1"], "--starts = 3 is not allowed with --samples = 1"),
        (["--target", str(run), "--bounds", "yield_stress=1:2", "--bounds", "yield_stress=3:4"],
         "yield_stress already has bounds 1:2"),
        (["--target", str(run), "--bounds", "=1:2"], "--bounds '=1:2' is not allowed: use NAME=LO:HI"),
    ]
    import re

    for extra, message in cases:
        capsys.readouterr()
        args = ["fit", str(guess), *extra] + ([] if "--output-dir" in extra else common)
        status = main(args)
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert status == 2 and len(err) == 1 and err[0].startswith("warp-esph: error: "), (extra, err)
        assert re.search(message if ".*" in message else re.escape(message), err[0]), (extra, err)
    assert all(p.read_bytes() == data for p, data in before.items())
    assert not (tmp_path / "o").exists()


def test_a_target_frame_range_outside_an_npz_s_frames_is_refused_before_any_kernel(tmp_path, capsys, dough_scene,
                                                                                      monkeypatch):
    """--target-frames 0:6 of an .npz storing frames 2, 4, 6 was cut at frame 2 without a word
    (as 2:10 was at 6 before its end was checked), and the Python API's load_target ignored
    frames= for an .npz: both refuse a range starting before (or ending after) the stored
    frames, naming them, before any kernel is launched."""
    from warp_esph.cli import main
    from warp_esph.fit import load_target

    def no_kernel(*args, **kwargs):
        raise AssertionError("a kernel was launched before the refusal")

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.zeros((3, 64, 3)), frames=[2, 4, 6], fps=30.0)
    monkeypatch.setattr(wp, "launch", no_kernel)
    held = f"it holds 3 frames, 2..6; the target {target} holds frames 2, 4, 6"
    for spec, said in (("0:6", f"'0:6' starts before the file's first frame, 2: {held.replace('; the', '; start the range at 2 or leave its start out; the')}"),
                       ("4:10", f"'4:10' runs past the file's last frame, 6: {held.replace('; the', '; end the range at 6 or leave its end out; the')}")):
        assert main(["fit", str(guess), "--target", str(target), "--target-frames", spec, "--params", "yield_stress",
                     "--iterations", "0", "--no-progress", "--output-dir", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"warp-esph: error: --target-frames = '{spec}' is not allowed: {said} (-N counts frame numbers back "
                       "from the last)"]
        with pytest.raises(ValueError, match=re.escape(f"frames = '{spec}' is not allowed: {said}")):
            load_target(target, frames=spec)
    assert not (tmp_path / "out").exists()
    assert load_target(target, frames="4:").frames == [4, 6] and load_target(target, frames=[6, 2]).frames == [6, 2]
    np.save(tmp_path / "plain.npy", np.zeros((3, 64, 3)))
    with pytest.raises(ValueError, match=r"^frames = '0:1' is not allowed with the target .*plain\.npy: it chooses among "
                                         r"the frames a file stores, and this one stores none"):
        load_target(tmp_path / "plain.npy", frames="0:1")


@pytest.mark.parametrize("given, said", [(0, "target_frames = 0 is not allowed: the targets hold only frame 0"),
                                         ([], "target_frames = [] is not allowed: it chooses no frame")])
def test_an_experiment_s_target_frames_of_0_or_none_is_not_dropped(given, said, tmp_path, capsys, dough_scene):
    """An --experiments file's "target_frames": 0 (frame 0) or [] read as not given: the
    experiment fitted every frame of its target, 0, 1 and 2, exit 0."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.zeros((3, 64, 3)), frames=[0, 1, 2], fps=30.0)
    experiments = tmp_path / "e.json"
    experiments.write_text(json.dumps([{"scene": str(guess), "target": str(target), "target_frames": given}]))
    assert main(["fit", str(guess), "--target", str(target), "--target-frames", "2", "--experiments", str(experiments),
                 "--params", "yield_stress", "--iterations", "0", "--no-progress", "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {experiments}: experiment #1: {said}"), err
    assert not (tmp_path / "out").exists()


def test_an_experiment_s_target_frame_range_outside_its_npz_is_refused_before_any_scene_s_kernel(tmp_path, capsys,
                                                                                                    dough_scene, monkeypatch):
    """The refusal of a target frame choice is made before any scene is built for every
    experiment, not only the first: an --experiments file's experiment whose target_frames
    start before its .npz's stored frames was refused after the command line's experiment had
    built its scene, launching kernels."""
    from warp_esph.cli import main

    def no_kernel(*args, **kwargs):
        raise AssertionError("a kernel was launched before the refusal")

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    good, bad = tmp_path / "good.npz", tmp_path / "bad.npz"
    np.savez(good, positions=np.zeros((3, 64, 3)), frames=[2, 4, 6], fps=30.0)
    np.savez(bad, positions=np.zeros((3, 64, 3)), frames=[2, 4, 6], fps=30.0)
    experiments = tmp_path / "e.json"
    experiments.write_text(json.dumps([{"scene": str(guess), "target": str(bad), "target_frames": "0:6"}]))
    monkeypatch.setattr(wp, "launch", no_kernel)
    assert main(["fit", str(guess), "--target", str(good), "--target-frames", "2:6", "--experiments", str(experiments),
                 "--params", "yield_stress", "--iterations", "0", "--no-progress", "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {experiments}: experiment #1: target_frames = '0:6' is not "
                                               "allowed: '0:6' starts before the file's first frame, 2"), err
    assert not (tmp_path / "out").exists()


def test_target_frames_choose_among_the_frames_an_npz_stores(tmp_path, capsys, dough_scene, monkeypatch):
    """An .npz that stores its 'frames' had them renumbered by --target-frames: frames 2, 4, 6
    given '1,2,3' fitted frame 2's positions at frame 1 (and so on), exit 0, while '2,6'
    was refused for its count. --target-frames now chooses among the stored frames, as it
    does for a run's USD, and names the ones the file does not hold. The ten fits' plots are
    not drawn (fit.json is what is read; the plots are the tests' above)."""
    from warp_esph import calibrate
    from warp_esph.cli import main

    monkeypatch.setattr(calibrate, "_plots", lambda *args: None)

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    rng = np.random.default_rng(0)
    from warp_esph.scenes import load_scene

    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + rng.normal(0, 0.01, x0.shape) for _ in range(3)]), frames=[2, 4, 6], fps=30.0)
    common = ["--params", "yield_stress", "--iterations", "0", "--no-progress", "--no-usd", "--no-diagnostics"]

    def loss(frames, name):
        assert main(["fit", str(guess), "--target", str(target), *(["--target-frames", frames] if frames else []),
                     "--output-dir", str(tmp_path / name), *common]) == 0
        return json.loads((tmp_path / name / "fit.json").read_text())["initial_loss"]

    every = loss(None, "all")  # each fit's one evaluation is a rollout: read once, compared twice
    assert loss("6,2,4", "shuffled") == pytest.approx(every, rel=1e-12, abs=0.0)
    assert loss("2,6", "two") != pytest.approx(loss("4", "one"), rel=1e-3)
    # The run USD's selections choose among the stored frames too.
    six = loss("6", "six")
    assert loss("last", "last") == pytest.approx(six, rel=1e-12, abs=0.0)
    assert loss("4:6", "slice") == pytest.approx(loss("4,6", "pair"), rel=1e-12, abs=0.0)
    assert loss("all", "every") == pytest.approx(every, rel=1e-12, abs=0.0)
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(target), "--target-frames", "1,2,3", "--output-dir",
                 str(tmp_path / "bad"), *common]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("--target-frames = '1,2,3' is not allowed: the target " + str(target)
                            + " holds frames 2, 4, 6 (its 'frames'), not 1, 3"), err
    assert not (tmp_path / "bad").exists()
    # A frame named twice would weigh twice in the loss ('last,6' named frame 6 once here,
    # while a run's USD target fitted it twice): refused, as of a run's USD.
    assert main(["fit", str(guess), "--target", str(target), "--target-frames", "last,6", "--output-dir",
                 str(tmp_path / "bad"), *common]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("--target-frames = 'last,6' is not allowed: it names frame 6 twice; name each frame once"), err
    # Stored out of order: 'last' is still the largest frame.
    np.savez(target, positions=np.load(target)["positions"][[2, 0, 1]], frames=[6, 2, 4], fps=30.0)
    assert loss("last", "last_shuffled") == pytest.approx(six, rel=1e-12, abs=0.0)


def test_an_interrupted_fit_keeps_its_evaluations_and_the_best_so_far(tmp_path, capsys, dough_scene, monkeypatch):
    """Ctrl-C during ``warp-esph fit`` kept nothing (no fit.json, no history): the command
    now writes the evaluations so far and the best of them (``stopped`` "interrupted"),
    then exits 130 as an interrupted run does. Here the third evaluation is interrupted."""
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    _interrupt_evaluation(monkeypatch, 3)
    out = tmp_path / "fit"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(run), "--iterations", "10", "--optimizer", "adam", "--lr", "0.2",
                   "--no-progress", "--no-usd", "--output-dir", str(out)])
    err = capsys.readouterr().err
    assert status == 130, err
    doc = json.loads((out / "fit.json").read_text())
    assert doc["stopped"] == "interrupted" and len(doc["history"]) == 2
    assert doc["loss"] == min(h["loss"] for h in doc["history"]) < doc["initial_loss"]
    assert len((out / "history.csv").read_text().strip().splitlines()) == 3
    assert "interrupted after 2 evaluations of the descent; wrote the best so far" in err
    assert doc["interrupted"] == "the fit"


def test_a_fit_interrupted_in_its_first_evaluation_says_nothing_is_written(tmp_path, capsys, dough_scene, monkeypatch):
    """Ctrl-C in the first evaluation: no loss to keep, and the line said 'interrupted' alone,
    not that no file was written."""
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    _interrupt_evaluation(monkeypatch, 1)
    out = tmp_path / "fit"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(run), "--iterations", "10", "--no-progress", "--no-usd",
                   "--output-dir", str(out)])
    err = capsys.readouterr().err
    assert status == 130, err
    assert err.splitlines()[-1] == ("warp-esph: interrupted: no evaluation had finished with a finite loss, so there is "
                                    "no best point to keep: nothing is written"), err
    assert not out.exists() or list(out.iterdir()) == []


def test_an_interrupted_fit_counts_its_evaluations_as_its_summary_line_does(tmp_path, capsys, dough_scene, monkeypatch):
    """With a global stage, the interrupt's line 'interrupted after N evaluations' counted its
    samples and the descent's under one word, where the summary line of a finished fit says
    which are which. It says so too now: 3 of the global stage (the guess and 2 samples), and
    the descent's first evaluation; its second is interrupted."""
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    _interrupt_evaluation(monkeypatch, 2)  # the descent's second: the global stage reads the loss alone
    out = tmp_path / "fit"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(run), "--iterations", "10", "--optimizer", "adam", "--lr", "0.2",
                   "--samples", "2", "--no-progress", "--no-usd", "--output-dir", str(out)])
    err = capsys.readouterr().err
    assert status == 130, err
    doc = json.loads((out / "fit.json").read_text())
    assert (doc["sample_evaluations"], doc["evaluations"], len(doc["history"])) == (3, 1, 4), doc["history"]
    assert ("interrupted after 4 evaluations: 3 of the global stage (loss only: the guess and 2 samples), 1 of the "
            "descent; wrote the best so far") in err, err


def test_an_interrupted_fit_whose_files_cannot_be_written_still_exits_130(tmp_path, capsys, dough_scene, monkeypatch):
    """Ctrl-C during ``warp-esph fit`` writes the evaluations so far; where that write failed
    (a full disk) its error reached the command's handler as bad input: exit 2 with the bare
    '[Errno 28] No space left on device', the Ctrl-C dropped. It exits 130, the one line naming
    the file and what was written before it."""
    import errno

    from warp_esph import calibrate as calibrate_module
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    def full(result, folder, meta=None, json_path=None, written=None):
        if written is not None:
            written.append(os.path.join(folder, "fit.json"))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), os.path.join(folder, "history.csv"))

    _interrupt_evaluation(monkeypatch, 2)
    monkeypatch.setattr(calibrate_module, "write_outputs", full)
    out = tmp_path / "fit"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(run), "--iterations", "10", "--optimizer", "adam", "--lr", "0.2",
                   "--no-progress", "--no-usd", "--output-dir", str(out)])
    err = capsys.readouterr().err
    assert status == 130, err
    assert err.splitlines()[-1] == (f"warp-esph: interrupted: cannot write {out / 'history.csv'}: No space left on device "
                                    f"(the evaluations so far are kept only in {out / 'fit.json'}, written before it)"), err


def test_a_second_signal_while_a_stopped_fit_writes_the_best_so_far_waits_for_it(tmp_path, dough_scene):
    """A stopped fit writes the evaluations so far; a second signal there (a second Ctrl-C, or
    ``timeout``, which signals the command and then its process group) ended the process at
    once: no fit.json, the best so far lost. Run as the console script, the only place a
    second signal ends the process."""
    import textwrap

    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    np.savez(tmp_path / "t.npz", positions=np.stack([x0 + np.random.default_rng(2).normal(0, 0.005, x0.shape)]),
             frames=[2])
    script = tmp_path / "twice.py"
    script.write_text(textwrap.dedent("""
        import os, signal, sys
        import warp_esph.calibrate as c
        import warp_esph.fit as f
        from warp_esph.cli import console_main

        calls, real_value, real_write = [], f._Problem.value_and_grad, c.write_outputs

        def value_and_grad(self, z, losses=None):
            calls.append(1)
            if len(calls) == 3:
                os.kill(os.getpid(), signal.SIGTERM)  # the first signal, in the third evaluation
            return real_value(self, z, losses)

        def write(result, folder, meta=None, *args, **kwargs):
            if meta and meta.get("interrupted"):
                os.kill(os.getpid(), signal.SIGTERM)  # the second, as the stopped fit writes its files
            return real_write(result, folder, meta, *args, **kwargs)

        f._Problem.value_and_grad, c.write_outputs = value_and_grad, write
        sys.argv = ["warp-esph", "fit", "guess.toml", "--target", "t.npz", "--params", "yield_stress",
                    "--iterations", "10", "--optimizer", "adam", "--no-progress", "--no-usd", "--no-diagnostics",
                    "--output-dir", "out"]
        console_main()
    """))
    done = run_script(script, tmp_path, timeout=300)
    assert done.returncode == 143, done.stderr
    assert done.stderr.splitlines()[-1] == "warp-esph: terminated", done.stderr
    assert "terminated after 2 evaluations of the descent; wrote the best so far" in done.stderr, done.stderr
    doc = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert doc["stopped"] == "interrupted" and doc["interrupted"] == "the fit" and len(doc["history"]) == 2
    assert sorted(os.listdir(tmp_path / "out")) == ["fit.json", "history.csv", "loss.png", "params.png"]


def test_a_ctrl_c_in_a_finalizer_stops_a_fit_after_that_evaluation(tmp_path, capsys, dough_scene, monkeypatch):
    """A Ctrl-C that landed in a finalizer (``__del__``) could not be raised there: it was
    recorded and the fit ran all its iterations before the command said 'interrupted'. It
    now stops the fit once the evaluation it landed in is recorded, the best so far kept."""
    import os
    import signal

    from warp_esph import fit as fit_module
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)

    calls = []
    original = fit_module._Problem.value_and_grad

    def finalizer_in_the_second(self, z, losses=None):
        calls.append(1)
        if len(calls) == 2:
            Finalized()
        return original(self, z, losses)

    monkeypatch.setattr(fit_module._Problem, "value_and_grad", finalizer_in_the_second)
    # As in a terminal: a runner started in the background starts ignoring SIGINT.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        out = tmp_path / "fit"
        capsys.readouterr()
        status = main(["fit", str(guess), "--target", str(run), "--iterations", "10", "--optimizer", "adam", "--lr",
                       "0.2", "--no-progress", "--no-usd", "--no-diagnostics", "--output-dir", str(out)])
    finally:
        signal.signal(signal.SIGINT, previous)
    err = capsys.readouterr().err
    assert status == 130, err
    doc = json.loads((out / "fit.json").read_text())
    assert doc["stopped"] == "interrupted" and len(doc["history"]) == 2
    assert "interrupted after 2 evaluations of the descent; wrote the best so far" in err


def test_a_fit_whose_results_cannot_be_written_prints_them_and_exits_4(tmp_path, capsys, dough_scene, monkeypatch):
    """A full disk under the fit's files lost the finished fit: its values were printed only
    after every file was written, the error was the bare '[Errno 28] No space left on device'
    (exit 2, as bad input), and the plot being written stayed as an empty loss.png (fit.json
    as fit.json.tmp). Now the values come first, each file is whole or absent, and the one
    line names the file and those written before it, exit 4."""
    import errno

    from matplotlib.figure import Figure

    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--frames", "2", "--dtype", "float64", "--no-progress"]) == 0
    real = Figure.savefig

    def full(self, fname, *args, **kwargs):
        with open(fname, "wb") as f:
            f.write(b"\x89PNG")  # a few bytes, then the disk is full
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Figure, "savefig", full)
    out = tmp_path / "fit"
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(run), "--iterations", "0", "--no-progress", "--no-diagnostics",
                 "--output-dir", str(out)]) == 4
    printed = capsys.readouterr()
    assert "fit " in printed.out and "yield_stress = 200" in printed.out
    errors = [line for line in printed.err.splitlines() if not line.startswith("warp-esph fit: ")]
    assert errors == [f"warp-esph: error: cannot write {out / 'loss.png'}: No space left on device (the fit's results "
                      f"are printed above; wrote {out / 'fit.json'}, {out / 'history.csv'} before it)"]
    assert sorted(os.listdir(out)) == ["fit.json", "history.csv"]
    monkeypatch.setattr(Figure, "savefig", real)


def test_a_fit_interrupted_in_its_diagnostics_says_so_in_fit_json(tmp_path, capsys, dough_scene, monkeypatch):
    """Ctrl-C in the diagnostics kept the finished fit, but its fit.json (stopped as the fit
    ended, diagnostics null) read as a complete run with --no-diagnostics, and the log called
    it the best so far. fit.json now says where the run was interrupted."""
    from warp_esph import diagnostics
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    from warp_esph.scenes import load_scene

    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + np.random.default_rng(2).normal(0, 0.005, x0.shape)]), frames=[2])

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(diagnostics, "diagnose_problem", interrupted)
    out = tmp_path / "fit"
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(target), "--params", "yield_stress", "--iterations", "1",
                 "--no-progress", "--no-usd", "--output-dir", str(out)]) == 130
    err = capsys.readouterr().err
    doc = json.loads((out / "fit.json").read_text())
    assert doc["interrupted"] == "the diagnostics" and doc["diagnostics"] is None and doc["stopped"] == "iterations"
    assert "interrupted during the diagnostics: wrote the finished fit (iterations, loss" in err


def test_an_earlier_fits_run_does_not_stay_beside_a_new_fits_results(tmp_path, capsys, dough_scene, monkeypatch):
    """A fit into a folder holding an earlier fit rewrote fit.json, history.csv and the plots
    but left the earlier fitted.usdc when it wrote none (--no-usd, Ctrl-C): the folder then
    showed another fit's run as this one's. It is removed before this fit's results go there."""
    from warp_esph import fit as fit_module
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    rng = np.random.default_rng(1)
    from warp_esph.scenes import load_scene

    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + rng.normal(0, 0.005, x0.shape)]), frames=[2])
    out = tmp_path / "fit"
    common = ["fit", str(guess), "--target", str(target), "--params", "yield_stress", "--no-progress",
              "--no-diagnostics", "--output-dir", str(out)]
    out.mkdir()
    (out / "fitted.usdc").write_bytes(b"an earlier fit's run")
    assert main([*common, "--iterations", "0", "--no-usd"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["fit.json", "history.csv", "loss.png", "params.png"]

    (out / "fitted.usdc").write_bytes(b"an earlier fit's run")
    original = fit_module._Problem.value_and_grad
    _interrupt_evaluation(monkeypatch, 2)
    capsys.readouterr()
    assert main([*common, "--iterations", "5", "--optimizer", "adam"]) == 130
    assert json.loads((out / "fit.json").read_text())["stopped"] == "interrupted"
    assert not (out / "fitted.usdc").exists()
    # A target read from there is the fit's input: refused, with --no-usd too (it was removed).
    monkeypatch.setattr(fit_module._Problem, "value_and_grad", original)
    assert main(["run", str(guess), "-o", str(out / "fitted.usdc"), "--no-progress"]) == 0
    capsys.readouterr()
    assert main([*common[:3], str(out / "fitted.usdc"), *common[4:], "--iterations", "0", "--no-usd"]) == 2
    assert "is --target" in capsys.readouterr().err and (out / "fitted.usdc").exists()
    # A folder of that name is no fit's run: left alone, and no reason to refuse --no-usd.
    other = tmp_path / "other"
    (other / "fitted.usdc").mkdir(parents=True)
    assert main([*common[:-1], str(other), "--iterations", "0", "--no-usd"]) == 0
    assert (other / "fitted.usdc").is_dir()


def test_an_earlier_fits_json_does_not_stay_beside_a_fit_written_with_o_elsewhere(tmp_path, capsys, dough_scene):
    """``fit --output-dir D`` and then ``fit --output-dir D -o elsewhere.json``: the second fit
    rewrote D's history.csv and plots and left the first fit's D/fit.json beside them, read
    as the result of the history it does not belong to. It is removed now, as an earlier
    fitted.usdc is; an input of that name there is refused instead."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    from warp_esph.scenes import load_scene

    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + np.random.default_rng(1).normal(0, 0.005, x0.shape)]), frames=[2])
    out = tmp_path / "fit"
    common = ["fit", str(guess), "--target", str(target), "--params", "yield_stress", "--no-progress", "--no-usd",
              "--no-diagnostics", "--output-dir", str(out)]
    assert main([*common, "--iterations", "0"]) == 0
    assert json.loads((out / "fit.json").read_text())["iterations"] == 0
    elsewhere = tmp_path / "elsewhere.json"
    assert main([*common, "--iterations", "2", "-o", str(elsewhere)]) == EXIT_NOT_CONVERGED  # the cap, results written
    assert sorted(p.name for p in out.iterdir()) == ["history.csv", "loss.png", "params.png"]
    assert json.loads(elsewhere.read_text())["iterations"] == 2
    # -o naming the folder's own fit.json writes it there, as without -o.
    assert main([*common, "--iterations", "1", "-o", str(out / "fit.json")]) == EXIT_NOT_CONVERGED
    assert json.loads((out / "fit.json").read_text())["iterations"] == 1
    # An experiments file of that name in the folder is an input: refused, not removed.
    # A copy of the target: the command line's own file would be refused as counted twice first.
    shutil.copyfile(target, tmp_path / "t2.npz")
    (out / "fit.json").write_text(json.dumps([{"scene": str(guess), "target": str(tmp_path / "t2.npz")}]))
    before = (out / "fit.json").read_text()
    capsys.readouterr()
    assert main([*common, "--iterations", "0", "-o", str(elsewhere), "--experiments", str(out / "fit.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fit.json = " in err and "it is --experiments" in err, err
    assert (out / "fit.json").read_text() == before


def test_cli_fit_at_a_guess_that_blows_up_is_one_line_and_exit_3(tmp_path, capsys, dough_scene):
    """A guess 1e5 x stiffer at a dt 40 x its stable step: its rollout blows up while
    staying finite (it had been fitted, exit 0), or its loss is not finite (a
    FloatingPointError traceback, exit 1). Either is one line and exit 3, as a run that
    diverges."""
    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    guess.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0).replace("mu = 2000.0", "mu = 2.0e8"))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--no-progress"]) == 0
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(run), "--params", "yield_stress", "--iterations", "2",
                   "--dt", str(1.0 / 3000.0), "--output-dir", str(tmp_path / "out"), "--no-progress", "--no-usd"])
    err = capsys.readouterr().err
    assert status == 3, err
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and last.startswith("warp-esph: error: the rollout at the initial guess diverged: "), err


def test_losses_diagnostics_and_cameras_refuse_what_they_dropped_or_misread(tmp_path, dropped_cube):
    """From a fuzz of the losses, diagnostics and camera files: each of these crashed, was
    silently wrong or read a value otherwise than given."""
    from warp_esph import losses as L  # noqa: PLC0415

    x = np.random.default_rng(0).normal(size=(4, 3))
    # A particle index past int32 wrapped: 2**31 crashed the process, 2**32 + 1 read particle 1.
    for big in ([2**31], np.array([0, 2**32 + 1])):
        with pytest.raises(ValueError, match="particles is not allowed: index .* is beyond any model's particles"):
            L.ChamferLoss(x, 0.1, frames=[1], particles=big)
    # A particle listed twice in a SlumpLoss got half the gradient, the second copy's share
    # overwritten; a repeat is refused now, as by every loss; a mask of the wrong length was used.
    with pytest.raises(ValueError, match=r"^particles = \[1, 1\] is not allowed: particle 1 is listed 2 times"):
        L.SlumpLoss(0.05, 0.03, 1, spacing=0.01, particles=[1, 1])
    with pytest.raises(ValueError, match="particles is a boolean mask of 2 entries, the positions 4"):
        L.SlumpLoss(0.05, 0.03, 1, spacing=0.01, particles=np.array([True, False])).value_and_grad({1: x})
    with pytest.raises(ValueError, match="center = 'ab' is not allowed"):
        L.SlumpLoss(0.05, 0.03, 1, spacing=0.01, center="ab")
    with pytest.raises(ValueError, match="tau = 5e-324 is not allowed"):
        L.SlumpLoss(0.05, 0.03, 1, spacing=0.01, tau=5e-324)
    # Steps and frames are whole numbers (2.7 was step 2, frame 1.5 replaced frame 1), noise
    # a number whose square is finite, targets and positions real.
    with pytest.raises(ValueError, match="frame 2.7 is not allowed"):
        L.ReactionForceLoss(np.zeros((1, 3)), 0, [2.7])
    with pytest.raises(ValueError, match="positions for frame 1.5 are not allowed"):
        L.PositionLoss(x, frames=[1])({1: x, 1.5: x})
    with pytest.raises(ValueError, match="positions of frame 1 with shape \\(4, 2\\) are not allowed"):
        L.PositionLoss(x, frames=[1])({1: x[:, :2]})
    with pytest.raises(ValueError, match="targets .* complex"), warnings.catch_warnings():
        warnings.simplefilter("error")  # refused before numpy drops the imaginary part with a warning
        L.PositionLoss(x + 0j, frames=[1])
    for bad in (1e-200, 1e200):
        with pytest.raises(ValueError, match="noise = .* is not allowed: must be in"):
            L.SlumpLoss(0.05, 0.03, 1, spacing=0.01, noise=bad)
    with pytest.raises(ValueError, match="max_dist = 1e\\+200 is not allowed"):
        L.MeshLoss((np.eye(3), np.array([[0, 1, 2]])), frames=[1], max_dist=1e200)
    # A fit's difference step (0/0 at 1e-17, a NaN Fisher matrix reported as a conclusion), a
    # diagnose of a WorldLoss (None without a word).
    model = dropped_cube(100.0, 10.0)
    target = {5: model.particle_x0.copy()}
    for step in (1e-17, 14.0):
        with pytest.raises(ValueError, match="fd_step = .* is not allowed: must be in \\[1e-08, 1"):
            diagnose(model, PositionLoss(target, frames=[5]), ["yield_stress"], step=step, steps=5)
    worlds = we.builder.replicate_worlds(model, 2)
    with pytest.raises(ValueError, match="a WorldLoss has no diagnostics"):
        diagnose(worlds, L.WorldLoss(worlds, PositionLoss(target, frames=[5])), ["yield_stress"], steps=5)
    # Cameras: a skew or a bottom row K ignored, K beside fx, a reflection, a width of 16.9.
    base = {"name": "c", "width": 32, "height": 24, "K": [[60.0, 0.0, 16.0], [0.0, 60.0, 12.0], [0.0, 0.0, 1.0]],
            "R": np.eye(3).tolist(), "t": [0.0, 0.0, 1.0]}
    assert PinholeCamera.from_dict(base).fx == 60.0
    for change, words in (({"K": [[60.0, 1.0, 16.0], [0.0, 60.0, 12.0], [0.0, 0.0, 1.0]]}, "no skew"),
                          ({"fx": 50.0}, "K and fx are not allowed together"),
                          ({"R": np.diag([1.0, 1.0, -1.0]).tolist()}, "it is not a rotation"),
                          ({"width": 16.9}, "width = 16.9 is not allowed"),
                          ({"K": "abc"}, "K = 'abc' is not allowed")):
        with pytest.raises(ValueError, match=words):
            PinholeCamera.from_dict({**base, **change})
    cam = PinholeCamera.from_dict(base)
    mask = np.zeros((24, 32))
    assert list(SilhouetteLoss({2: [mask]}, cam, 0.01).frames) == [2]  # one camera, not a list of them
    with pytest.raises(ValueError, match="masks are given for steps \\[2\\] but frames = \\[7\\]"):
        SilhouetteLoss({2: [mask]}, [cam], 0.01, frames=[7])
    np.savez(tmp_path / "twice.npz", c_1=mask, c_01=mask)
    with pytest.raises(ValueError, match="camera 'c' already has a mask for frame 1"):
        load_masks(tmp_path / "twice.npz", [cam])


def test_second_review_of_the_losses_round(tmp_path, dropped_cube):
    """A fit of a scaled WorldLoss ran its diagnostics and lost the fit to their error; a
    linear value at 0 with any finite error read as determined; a NaN F stopped simulate in
    numpy's SVD; ReactionForceLoss refused a range of steps; cameras of whole-number floats,
    of a calibration tool's round-off or given as any iterable were refused; ragged targets
    got numpy's message."""
    import types  # noqa: PLC0415

    from warp_esph import losses as L  # noqa: PLC0415
    from warp_esph.diagnostics import _summarise  # noqa: PLC0415
    from warp_esph.simulate import SimulationError, simulate  # noqa: PLC0415

    model = dropped_cube(100.0, 10.0)
    worlds = we.builder.replicate_worlds(model, 2)
    target = {5: model.particle_x0.copy()}
    result = fit(worlds, 2.0 * L.WorldLoss(worlds, PositionLoss(target, frames=[5])), ["yield_stress"], steps=5,
                 dt=model.stable_dt(), iterations=1, progress=False)
    assert result.diagnostics is None
    # viscosity 0 with a standard error of 1e4 Pa s: undetermined (its own scale, 1)
    prob = types.SimpleNamespace(params=["viscosity"], k=1, labels=["viscosity"], spaces={"viscosity": "linear"},
                                 scales={"viscosity": 1.0}, from_z=lambda z: {"viscosity": np.array([0.0])})
    loose = _summarise(prob, np.zeros(1), np.array([[1e-8]]), np.zeros(1), [1e-3], [1e-3], 100, 3, 1e-3, 0.25, 1e-3,
                       0.95, None)
    tight = _summarise(prob, np.zeros(1), np.array([[1e2]]), np.zeros(1), [1e-3], [1e-3], 100, 3, 1e-3, 0.25, 1e-3,
                       0.95, None)
    assert loose.undetermined == ["viscosity"] and tight.undetermined == []
    state = model.state()
    F = state.F.numpy()
    F[0, 0, 0] = np.nan
    state.F.assign(F)
    with pytest.raises(SimulationError):
        simulate(model, 1, state=state, progress=False)
    assert L.ReactionForceLoss(np.zeros((3, 3)), 0, range(10, 31, 10)).frames == (10, 20, 30)
    cam = {"name": "c", "width": 32.0, "height": 24, "K": [[60.0, 1e-13, 16.0], [0.0, 60.0, 12.0], [0.0, 0.0, 1.0 + 2e-16]],
           "R": np.eye(3).tolist(), "t": [0.0, 0.0, 1.0]}
    c = PinholeCamera.from_dict(cam)
    assert c.width == 32 and list(SilhouetteLoss({2: [np.zeros((24, 32))]}, {"c": c}.values(), 0.01).frames) == [2]
    with pytest.raises(ValueError, match="masks are given for steps \\[2\\] but frames = \\[7\\]"):
        SilhouetteLoss({2: [np.zeros((24, 32))]}, [c], 0.01, frames=7)
    with pytest.raises(ValueError, match="targets is not allowed: give an array"):
        PositionLoss([[0.0, 0.0, 0.0], [0.0, 0.0]], frames=[1, 2])


def test_a_target_without_frame_numbers_says_which_frames_it_is_read_as(tmp_path, capsys, dough_scene):
    """A .npy (or an .npz without 'frames') that leaves out frame 0 was read one frame early,
    silently: its first entry as frame 0, which is not fitted, every later one a frame before
    its time, exit 0. The plan now says which frames the entries are read as and how far the
    one read as frame 0 lies from the scene's start, and ``--target-frames A:B`` names them."""
    from warp_esph.cli import main

    scene = tmp_path / "truth.toml"
    scene.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=3))
    run = tmp_path / "run.usdc"
    assert main(["run", str(scene), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    from warp_esph.fit import load_target

    whole = load_target(run, frames="all")
    assert whole.frames == [0, 1, 2, 3]
    np.save(tmp_path / "from1.npy", whole.data[1:])
    np.save(tmp_path / "all.npy", whole.data)

    def fit_to(*target):
        out = tmp_path / "fit"
        capsys.readouterr()
        assert main(["fit", str(scene), "--target", *target, "--iterations", "0", "--no-diagnostics", "--no-usd",
                     "--no-progress", "--output-dir", str(out)]) == 0
        return capsys.readouterr().err, json.loads((out / "fit.json").read_text())

    err, doc = fit_to(str(tmp_path / "from1.npy"))
    assert "from1.npy: a .npy holds no frame numbers; its 3 entries are read as frames 0 to 2, entry 0 as frame 0" in err, err
    lies = re.search(r"\(it lies ([0-9.e+-]+) spacings RMS from the scene's initial positions\)", err)
    assert lies and float(lies.group(1)) > 1.0, err  # a frame later, at 1 m/s: 3.3 cm, 1.7 spacings
    assert "name them with --target-frames (e.g. 1:3 for frames 1 to 3)" in err, err
    assert doc["target_frames"] == [[0, 1, 2]] and doc["initial_loss"] > 1e-5
    err, doc = fit_to(str(tmp_path / "all.npy"))
    assert "(it lies 0 spacings RMS from the scene's initial positions)" in err, err
    # Named, the same entries are the run's frames 1 to 3: the truth's own run matches them.
    err, doc = fit_to(str(tmp_path / "from1.npy"), "--target-frames", "1:3")
    assert "its 3 entries are read as frames 1, 2, 3 (--target-frames)" in err, err
    assert doc["target_frames"] == [[1, 2, 3]] and doc["initial_loss"] < 1e-20
    capsys.readouterr()
    assert main(["fit", str(scene), "--target", str(tmp_path / "from1.npy"), "--target-frames", "1,1,2",
                 "--no-progress", "--output-dir", str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--target-frames = '1,1,2' is not allowed: it names a frame twice" in err, err
    # A range is counted before it is listed: 0:10**12 would fill the memory first.
    assert main(["fit", str(scene), "--target", str(tmp_path / "from1.npy"), "--target-frames", f"0:{10**12}",
                 "--no-progress", "--output-dir", str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "it names more than 1000000 frames" in err, err


def test_targets_that_record_different_rates_are_refused(tmp_path, capsys, dough_scene):
    """Two targets recording 30 and 60 fps: the first one's rate was taken for both, and the
    second was fitted at other times than it was recorded, exit 0."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0))
    for name, rate in (("a", 30.0), ("b", 60.0)):
        np.savez(tmp_path / f"{name}.npz", positions=np.zeros((2, 64, 3)), frames=[1, 2], fps=rate)
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(tmp_path / "a.npz"), "--target", str(tmp_path / "b.npz"),
                 "--no-progress", "--output-dir", str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"target {tmp_path / 'b.npz'} is not allowed beside the target {tmp_path / 'a.npz'}: " \
                                   "it was recorded at 60 fps, the other at 30 fps" in err, err
    assert not (tmp_path / "fit").exists()


def test_a_point_cloud_that_repeats_points_counts_each_once(tmp_path, capsys, dough_scene):
    """A cloud listing its points twice weighed them twice: the diagnostics counted 192
    observations for 128 and gave standard errors sqrt(1.5) smaller, as if measured more
    often. Exactly repeated points are now counted once, with a warning naming the file."""
    from warp_esph.cli import main
    from warp_esph.losses import ChamferLoss

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2))
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    from warp_esph.fit import load_target

    cloud = load_target(run, frames="last").data[0]
    np.savetxt(tmp_path / "once.xyz", cloud)
    np.savetxt(tmp_path / "twice.xyz", np.concatenate([cloud, cloud[::-1]]))
    docs = {}
    for name in ("once", "twice"):
        capsys.readouterr()
        assert main(["fit", str(guess), "--target", str(tmp_path / f"{name}.xyz"), "--iterations", "0", "--noise", "1e-3",
                     "--no-usd", "--no-progress", "--output-dir", str(tmp_path / name)]) == 0
        docs[name] = (json.loads((tmp_path / name / "fit.json").read_text())["diagnostics"], capsys.readouterr().err)
    (once, quiet), (twice, said) = docs["once"], docs["twice"]
    assert "warning" not in quiet, quiet
    assert f"warp-esph: warning: target {tmp_path / 'twice.xyz'}: 64 of its 128 points repeat an earlier point exactly; " \
           "each point is counted once (64 points)" in said, said
    assert twice["observations"] == once["observations"] == 128
    assert twice["standard_error"] == pytest.approx(once["standard_error"], rel=1e-9)
    # Given to the loss directly, the same: one observation per distinct point.
    with pytest.warns(UserWarning, match=r"targets at step 5: 3 of its 5 points repeat an earlier point exactly"):
        loss = ChamferLoss(np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [1, 0, 0], [1, 0, 0]], float), radius=0.1, frames=[5])
    assert loss.targets[5].tolist() == [[0, 0, 0], [1, 0, 0]]


def _foreign_points_usd(path, samples, rate=None, meters=1.0):
    """A USD file of another program: one ``UsdGeom.Points`` prim ``/World/cloud`` with
    ``samples`` ``{time code: (n, 3) positions}``, ``timeCodesPerSecond`` = ``rate`` and
    ``metersPerUnit`` = ``meters`` (None: not authored)."""
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    if meters is not None:
        UsdGeom.SetStageMetersPerUnit(stage, meters)
    if rate is not None:
        stage.SetTimeCodesPerSecond(rate)
    points = UsdGeom.Points.Define(stage, "/World/cloud").GetPointsAttr()
    for t, p in samples.items():
        points.Set(Vt.Vec3fArray.FromNumpy(np.asarray(p, dtype=np.float32)), float(t))
    stage.Save()
    return str(path)


def test_a_long_target_path_is_shown_by_its_ends_through_the_python_api(tmp_path):
    """A target's or force log's path over checks.PATH_SHOWN_WHOLE characters is named by its
    ends (checks.shown_path) in the refusals of the Python API too: the force log's reader,
    ReactionForceLoss.from_csv and these load_target refusals named it whole (the CLI's
    long_words_cut shortens a word, not a path with spaces in it)."""
    import types

    from pxr import Usd, UsdGeom, Vt

    from warp_esph.checks import PATH_SHOWN_WHOLE, shown_path
    from warp_esph.fit import Target, _partial_refused, load_target, save_target
    from warp_esph.losses import ReactionForceLoss, read_tools_csv

    folder = tmp_path / ("a long folder " + "d" * PATH_SHOWN_WHOLE)
    folder.mkdir()
    log = folder / "press_tools.csv"
    log.write_text("frame,time,tool,fx,fy,fz\n1,0.1,press,0,1,0\n")
    (folder / "rowless_tools.csv").write_text("frame,time,tool,fx,fy,fz\n")
    (folder / "lab.csv").write_text("time,fx\n0,1\n")
    save_target(folder / "stored.npz", np.zeros((2, 4, 3), np.float32), frames=[2, 4])
    points = _foreign_points_usd(folder / "points.usda", {0: np.zeros((4, 3)), 1: np.zeros((4, 3))})
    nested = str(folder / "nested.usda")
    stage = Usd.Stage.CreateNew(nested)
    UsdGeom.Xform.Define(stage, "/World/group")
    UsdGeom.Points.Define(stage, "/World/group/cloud").GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.zeros((4, 3), np.float32)), 1.0)
    stage.Save()
    far = Target("positions", np.full((1, 2, 3), 1e30, np.float32), [1], None, str(folder / "far.npz"))
    for call, path in (
        (lambda: read_tools_csv(folder / "absent_tools.csv"), folder / "absent_tools.csv"),
        (lambda: read_tools_csv(folder / "rowless_tools.csv"), folder / "rowless_tools.csv"),
        (lambda: ReactionForceLoss.from_csv(log, "nope", {1: 10}), log),
        (lambda: ReactionForceLoss.from_csv(log, "press", {2: 20}, frames=[2]), log),
        (lambda: ReactionForceLoss.from_csv(log, "press", {}), log),
        (lambda: load_target(log, tool="nope"), log),
        (lambda: load_target(folder / "stored.npz", frames="3"), folder / "stored.npz"),
        (lambda: load_target(folder / "stored.npz", frames="x"), folder / "stored.npz"),
        (lambda: load_target(folder / "lab.csv"), folder / "lab.csv"),
        (lambda: load_target(nested), nested),
        (lambda: load_target(points, body="nope"), points),
        (lambda: far._check_range(types.SimpleNamespace(scalar=np.float32)), far.path),
    ):
        with pytest.raises((ValueError, FileNotFoundError)) as e:
            call()
        assert str(shown_path(path, False)) in str(e.value) and str(path) not in str(e.value), str(e.value)
    said = _partial_refused(str(log), "mesh")
    assert str(shown_path(log, False)) in said and str(log) not in said


def test_the_fit_plan_s_lines_show_a_long_target_path_by_its_ends():
    """The plan's readings of a target (its frames read without numbers, a force column all
    zero, a start stored late) name a path over checks.PATH_SHOWN_WHOLE characters by its ends
    (checks.shown_path), as the refusals do: they named it whole."""
    import types

    from warp_esph.calibrate import _frame_reading, _start_frame_later, _zero_force_columns
    from warp_esph.checks import PATH_SHOWN_WHOLE, shown_path

    path = "/data/a long folder " + "d" * PATH_SHOWN_WHOLE + "/target.npz"
    ns = types.SimpleNamespace
    model = ns(particle_x0=np.zeros((4, 3)), spacing=0.01)
    still, moved = np.zeros((4, 3)), np.full((4, 3), 0.1)
    lines = [
        _frame_reading(path, ns(data=np.zeros((2, 4, 3)), frames=[1, 2]), True, model),
        _frame_reading(path, ns(data=np.zeros((1, 4, 3)), frames=[5]), False, model),
        _frame_reading(path, ns(data=np.stack([still, moved]), frames=[0, 1]), False, model),
        _zero_force_columns(path, ns(targets=np.zeros((2, 3)), components="xyz", tool="press"), False),
        _zero_force_columns(path, ns(targets=np.array([[0.0, 1.0, 0.0]] * 2), components="xyz", tool="press"), False),
        _start_frame_later(path, ns(frames=[3, 5], data=np.stack([still, moved])), model),
        _start_frame_later(path, ns(frames=[3], data=still[None]), model, run=lambda frame: moved),
    ]
    for line in lines:
        assert line is not None and str(shown_path(path, False)) in line and path not in line, line


def test_a_long_camera_mask_usd_or_resumed_force_log_path_is_shown_by_its_ends(tmp_path):
    """A camera file's radius or opacity, a mask's shape, a file not USD and the force log of a
    run to resume are refused naming a path over checks.PATH_SHOWN_WHOLE characters by its
    ends (checks.shown_path), as every other refusal does: they named it whole."""
    import types

    from warp_esph.checks import PATH_SHOWN_WHOLE, shown_path
    from warp_esph.silhouette import load_cameras, load_masks
    from warp_esph.tools import ReactionLog
    from warp_esph.usd import UsdFrames

    folder = tmp_path / ("a long folder " + "d" * PATH_SHOWN_WHOLE)
    folder.mkdir()
    camera = {"name": "front", "width": 8, "height": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5,
              "R": np.eye(3).tolist(), "t": [0.0, 0.0, 1.0]}
    for key, value in (("radius", -1.0), ("opacity", 1.0)):
        (folder / f"{key}.json").write_text(json.dumps({"cameras": [camera], key: value}))
    np.savez(folder / "masks.npz", front_1=np.zeros((2, 6, 8)))
    (folder / "scene.toml").write_text("")
    (folder / "damaged_tools.json").write_text("{")
    (folder / "other_tools.json").write_text(json.dumps({"run_id": "other", "rows": []}))
    cameras = [PinholeCamera(8, 6, 10.0, 10.0, 3.5, 2.5, np.eye(3), [0.0, 0.0, 1.0], "front")]
    log = types.SimpleNamespace(run_id="mine", rows=[], _kept=None)
    for call, path in (
        (lambda: load_cameras(folder / "radius.json"), folder / "radius.json"),
        (lambda: load_cameras(folder / "opacity.json"), folder / "opacity.json"),
        (lambda: load_masks(folder / "masks.npz", cameras), folder / "masks.npz"),
        (lambda: UsdFrames(folder / "scene.toml"), folder / "scene.toml"),
        (lambda: ReactionLog.resume(log, str(folder / "damaged"), 3), folder / "damaged_tools.json"),
        (lambda: ReactionLog.resume(log, str(folder / "other"), 3), folder / "other_tools.json"),
    ):
        with pytest.raises(ValueError) as e:
            call()
        shown = (str(shown_path(path, False)), str(shown_path(path)))  # as written, or quoted
        assert any(form in str(e.value) for form in shown) and str(path) not in str(e.value), str(e.value)
    with pytest.warns(UserWarning, match="of the run to resume is not there") as caught:
        ReactionLog.resume(log, str(folder / "absent"), 3)
    said = str(caught[0].message)
    assert str(shown_path(folder / "absent_tools.json", False)) in said and str(folder) not in said


def test_a_nan_position_in_a_usd_target_is_a_missing_marker_as_in_an_npz(tmp_path):
    """NaN in an .npz target is a missing marker, left out of the loss; the same NaN in a USD
    target (another program's points, an occluded marker) was refused as 'must be finite'."""
    from warp_esph.fit import load_target, save_target

    p = np.random.default_rng(1).uniform(0.0, 0.1, (3, 8, 3)) + np.array([0.0, 0.01, 0.02])[:, None, None]
    p[2, 6] = np.nan  # marker 6 not seen at frame 2
    p[1, 3, 1] = np.nan  # one coordinate lost: the marker is missing there too
    p = p.astype(np.float32)
    usd = load_target(_foreign_points_usd(tmp_path / "gap.usda", dict(enumerate(p)), rate=30))
    save_target(tmp_path / "gap.npz", p, frames=[0, 1, 2], fps=30)
    npz = load_target(tmp_path / "gap.npz")
    assert usd.frames == [1, 2] and usd.fps == npz.fps == 30.0
    assert npz.frames == [0, 1, 2]
    np.testing.assert_array_equal(np.asarray(usd.data), np.asarray(npz.data)[1:])  # NaN where the .npz has it
    assert np.isnan(np.asarray(usd.data)[1, 6]).all() and np.isfinite(np.asarray(usd.data)[1, :6]).all()
    assert [usd.frames[k] for k in usd._fitted_frames()] == [npz.frames[k] for k in npz._fitted_frames()] == [1, 2]


def test_a_foreign_usd_target_is_read_by_its_frames_and_rate_or_refused_by_name(tmp_path):
    """Another program's USD of particles: a particle count that changes from frame to frame
    (or an empty sample) failed in numpy, 'all input arrays must have the same shape', naming
    no file; an infinite position was refused later as 'targets at step 34'; samples at negative
    time codes ended in a KeyError traceback in the fit command; a file that authors no
    rate was read at USD's fallback of 24 fps as if recorded so, which overrode the scene's
    rate and refused --fps 30 as 'recorded at 24 fps'."""
    from warp_esph.fit import load_target

    p = np.random.default_rng(0).uniform(0.0, 0.1, (8, 3))
    for name, samples, message in (
        ("fewer", {0: p, 1: p, 2: p[:5]}, r"body 'cloud' has 8 particles at frame 1 and 5 at frame 2; a run's particles "
                                          r"are the same in every frame"),
        ("empty", {0: p, 1: p, 2: p[:0]}, r"body 'cloud' has 8 particles at frame 1 and 0 at frame 2"),
        ("inf", {0: p, 1: p, 2: np.where(np.arange(8)[:, None] == 6, np.inf, p)},
         r"at frame 2, 1 of its 8 positions are infinite \(first: particle 6, \[inf, inf, inf\]\); a missing one \(an "
         r"occluded marker\) is NaN"),
        ("negative", {-2: p, -1: p, 0: p}, r"its points have time samples at negative time codes \(-2, -1\); a warp-esph "
                                           r"output has one per frame, at time code = frame index >= 0"),
    ):
        path = _foreign_points_usd(tmp_path / f"{name}.usda", samples, rate=30)
        with pytest.raises(ValueError, match=re.escape(path) + r".*" + message):
            load_target(path)
    # The same body chosen whole: read, at the file's own rate where it authors one, else
    # none (the scene's or --fps), not USD's fallback.
    ok = {0: p, 1: p + 0.01, 2: p + 0.02}
    t = load_target(_foreign_points_usd(tmp_path / "rate.usda", ok, rate=25))
    assert t.frames == [1, 2] and t.fps == 25.0 and t.bodies == [("cloud", 8)]
    np.testing.assert_allclose(t.data[1], (p + 0.02).astype(np.float32))
    t = load_target(_foreign_points_usd(tmp_path / "norate.usda", ok))
    assert t.frames == [1, 2] and t.fps is None
    # A body whose samples stop (or skip a frame) was read there as USD answers between samples,
    # held or interpolated: standing still, or on a straight line, which nothing measured.
    from pxr import Usd, UsdGeom, Vt

    stops = str(tmp_path / "stops.usda")
    stage = Usd.Stage.Open(_foreign_points_usd(stops, ok, rate=30))
    late = UsdGeom.Points.Define(stage, "/World/late").GetPointsAttr()
    for f in (0, 2):
        late.Set(Vt.Vec3fArray.FromNumpy(p.astype(np.float32) + f), float(f))
    stage.Save()
    with pytest.raises(ValueError, match=re.escape(stops) + r" is not allowed: body 'late' has no sample at frame 1 \(the "
                                         r"file's frames are those of any body\); a run's file holds every body at every frame"):
        load_target(stops)
    assert load_target(stops, body="cloud").data.shape == (2, 8, 3)  # the body observed alone has every frame
    assert load_target(stops, body="cloud", frames="2,0").frames == [2, 0]  # frames in any order


def test_an_image_mask_is_read_by_its_alpha_or_palette_colours_and_must_be_its_cameras_size(tmp_path):
    """An RGBA cut-out (the silhouette in the alpha channel, its colour one value) was read by
    its colours alone: all inside for white, empty for black; a palette image by its palette
    indices, which inverted a mask whose palette put white first; a mask of another size
    than its camera was refused later as 'the mask at step 34', naming no file."""
    from PIL import Image

    cam = PinholeCamera(8, 6, 10.0, 10.0, 3.5, 2.5, np.eye(3), [0.0, 0.0, 1.0], "front")
    inside = np.zeros((6, 8), dtype=np.uint8)
    inside[2:4, 3:6] = 1
    images = {}
    for colour in (0, 255):  # black or white everywhere, the silhouette opaque on a transparent ground
        rgba = np.full((6, 8, 4), colour, dtype=np.uint8)
        rgba[..., 3] = 255 * inside
        images[f"cutout_{colour}"] = Image.fromarray(rgba, "RGBA")
    palette = Image.fromarray(1 - inside, "P")  # index 0 (white) inside, index 1 (black) outside
    palette.putpalette([255, 255, 255, 0, 0, 0] + [0] * 762)
    images["palette"] = palette
    opaque = np.zeros((6, 8, 4), dtype=np.uint8)  # an alpha of one value: read by the colours, as before
    opaque[..., :3] = 255 * inside[..., None]
    opaque[..., 3] = 255
    images["opaque"] = Image.fromarray(opaque, "RGBA")
    images["grey"] = Image.fromarray(200 * inside)
    for name, image in images.items():
        image.save(tmp_path / f"{name}.png")
        np.testing.assert_array_equal(load_masks(tmp_path / f"{name}.png", [cam], 2)[2][0], inside, err_msg=name)
    Image.fromarray(np.zeros((12, 16), dtype=np.uint8)).save(tmp_path / "large.png")
    with pytest.raises(ValueError, match=r"^mask \S*large\.png with shape \(12, 16\) is not allowed: camera 'front' is "
                                         r"6 x 8 \(height x width\)$"):
        load_masks(tmp_path / "large.png", [cam], 2)
    np.savez(tmp_path / "m.npz", front_2=np.ones((3, 3)))
    with pytest.raises(ValueError, match=r"^mask \S*m\.npz:front_2 with shape \(3, 3\) is not allowed: camera 'front'"):
        load_masks(tmp_path / "m.npz", [cam])


def test_a_foreign_usd_targets_frames_and_points_are_named_as_the_command_gives_them(tmp_path, capsys, dough_scene):
    """Through ``warp-esph fit``: a USD sample at time code 1e12 was refused as '--frames =
    1000000000000', which was not given; a --target-frames the file does not hold as
    'frames = ...', which names no option; and particles another program wrote elsewhere
    than directly under /World (nested in a group, a PointInstancer) as 'mesh ... is not a
    closed triangle mesh', which they never were."""
    from pxr import Usd, UsdGeom, Vt

    from warp_esph.cli import main

    scene = tmp_path / "guess.toml"
    scene.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=3))
    p = np.random.default_rng(0).uniform(0.0, 0.1, (64, 3))
    far = _foreign_points_usd(tmp_path / "far.usda", {0: p, 1e12: p}, rate=30)
    three = _foreign_points_usd(tmp_path / "three.usda", {0: p, 1: p, 2: p}, rate=30)
    nested = str(tmp_path / "nested.usda")
    stage = Usd.Stage.CreateNew(nested)
    UsdGeom.Xform.Define(stage, "/World/group")
    UsdGeom.Points.Define(stage, "/World/group/cloud").GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p.astype(np.float32)), 1.0)
    UsdGeom.PointInstancer.Define(stage, "/World/copies")
    stage.Save()
    for target, extra, message in (
        (far, [], "the targets' last frame, 1000000000000, is not allowed: the fit runs to it, and a run has at most "
                  "2147483647 frames"),
        (three, ["--target-frames", "5"], "--target-frames = '5' is not allowed: frame 5 is not in the file (it holds 0..2)"),
        (nested, [], f"target {nested} is not allowed: it has no mesh, and its points (/World/group/cloud, /World/copies) are "
                     "not where a run's particles are read from: UsdGeom.Points prims directly under /World"),
    ):
        capsys.readouterr()
        assert main(["fit", str(scene), "--target", target, "--no-usd", "--no-progress",
                     "--output-dir", str(tmp_path / "out"), *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"warp-esph: error: {message}") and len(err.strip().splitlines()) == 1, err


def test_the_frames_of_npz_masks_are_chosen_and_a_mask_sequence_image_or_bad_opacity_is_refused(tmp_path):
    """``--target-frames`` with an ``.npz`` of masks was ignored: every frame of the file was
    fitted whatever it chose; a GIF or multi-page TIFF of masks was read as its first image
    alone; a camera file's opacity of 1 was refused by SilhouetteLoss, naming no file."""
    from PIL import Image

    from warp_esph.silhouette import load_silhouette_target

    cam = {"name": "front", "width": 8, "height": 6, "fx": 10.0, "fy": 10.0, "cx": 3.5, "cy": 2.5,
           "R": np.eye(3).tolist(), "t": [0.0, 0.0, 1.0]}
    (tmp_path / "cams.json").write_text(json.dumps({"cameras": [cam], "radius": 0.01}))
    body = np.pad(np.ones((2, 4)), ((2, 2), (2, 2)))
    np.savez(tmp_path / "m.npz", front_2=np.zeros((6, 8)), front_3=body, front_5=np.zeros((6, 8)))
    loss = load_silhouette_target(tmp_path / "cams.json", tmp_path / "m.npz", "3", 6, 10)
    assert loss.frames == (30,) and np.array_equal(loss.masks[30][0], body)
    assert load_silhouette_target(tmp_path / "cams.json", tmp_path / "m.npz", "2,last", 6, 10).frames == (20, 50)
    assert load_silhouette_target(tmp_path / "cams.json", tmp_path / "m.npz", None, 6, 10).frames == (20, 30, 50)
    with pytest.raises(ValueError, match=r"^--target-frames = '4' is not allowed: frame 4 is not in the file .*; the mask "
                                         r"file \S*m\.npz holds frames 2, 3, 5$"):
        load_silhouette_target(tmp_path / "cams.json", tmp_path / "m.npz", "4", 6, 10)
    pages = [Image.fromarray(np.full((6, 8), 255 * (k % 2), dtype=np.uint8)) for k in range(3)]
    for ext in ("gif", "tif"):
        pages[0].save(tmp_path / f"seq.{ext}", save_all=True, append_images=pages[1:])
        with pytest.raises(ValueError, match=r"^mask \S*seq\.%s cannot be read as an image: it holds 3 images \(an animation "
                                             r"or a multi-page file\); a mask image is one view at one frame" % ext):
            load_masks(tmp_path / f"seq.{ext}", [PinholeCamera.from_dict(cam)], 2)
    (tmp_path / "opaque.json").write_text(json.dumps({"cameras": [cam], "radius": 0.01, "opacity": 1.0}))
    with pytest.raises(ValueError, match=r"^camera file \S*opaque\.json: opacity = 1\.0 is not allowed: must be in "
                                         r"\[1e-06, 0\.999\]$"):
        load_cameras(tmp_path / "opaque.json")


def test_a_foreign_usd_targets_particles_are_read_in_metres_and_world_coordinates(tmp_path):
    """Another program's particles in centimetres (metersPerUnit 0.01), under a moved /World,
    or with a time-sampled transform of their own were compared with the scene in their
    local units, 100 x too far or off by the transforms, without a word; a mesh target was
    already read in metres and world coordinates. A stage that authors no metersPerUnit is
    in centimetres by USD's rule, with a warning (as a mesh)."""
    from pxr import Gf, Usd, UsdGeom

    from warp_esph.fit import load_target

    p = np.random.default_rng(0).uniform(0.0, 10.0, (8, 3))  # centimetres
    ok = {0: p, 1: p + 1.0, 2: p + 2.0}
    cm = _foreign_points_usd(tmp_path / "cm.usda", ok, rate=30, meters=0.01)
    np.testing.assert_allclose(load_target(cm).data, 0.01 * np.stack([p + 1.0, p + 2.0]).astype(np.float32), rtol=1e-6)
    stage = Usd.Stage.Open(cm)
    UsdGeom.Xformable(stage.GetPrimAtPath("/World")).AddTranslateOp().Set(Gf.Vec3d(0.0, 50.0, 0.0))
    spin = UsdGeom.Xformable(stage.GetPrimAtPath("/World/cloud")).AddRotateYOp()
    spin.Set(0.0, 1.0)
    spin.Set(90.0, 2.0)
    stage.Save()
    t = load_target(cm)
    moved = [p + 1.0, (p + 2.0)[:, [2, 1, 0]] * [1.0, 1.0, -1.0]]  # frame 2 turned 90 degrees about y, then up 50 cm
    np.testing.assert_allclose(t.data, 0.01 * (np.stack(moved) + [0.0, 50.0, 0.0]), rtol=1e-5, atol=1e-7)
    plain = _foreign_points_usd(tmp_path / "plain.usda", ok, rate=30, meters=None)
    with pytest.warns(UserWarning, match=r"plain\.usda: its stage does not author metersPerUnit, so USD's fallback of 0\.01 m "
                                         r"per unit \(centimetres\) is assumed"):
        assert load_target(plain).data[0] == pytest.approx(0.01 * (p + 1.0), rel=1e-6)


def test_a_foreign_usd_target_that_refers_to_other_files_reads_them_beside_it(tmp_path):
    """A file whose particles come from another by a relative reference ('./cloud.usda') was
    composed from an anonymous copy, where the path resolved nowhere: pxr printed a warning
    and the file read as holding no frames. A referenced file that is missing is named."""
    from pxr import Usd, UsdGeom

    from warp_esph.fit import load_target

    p = np.random.default_rng(0).uniform(0.0, 0.1, (8, 3))
    _foreign_points_usd(tmp_path / "cloud.usda", {0: p, 1: p + 0.01, 2: p + 0.02}, rate=30)
    shot = str(tmp_path / "shot.usda")
    stage = Usd.Stage.CreateNew(shot)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(30)
    UsdGeom.Xform.Define(stage, "/World")
    UsdGeom.Points.Define(stage, "/World/dough").GetPrim().GetReferences().AddReference("./cloud.usda", "/World/cloud")
    stage.Save()
    del stage  # which holds the referenced layer open
    t = load_target(shot)
    assert t.frames == [1, 2] and t.bodies == [("dough", 8)]
    np.testing.assert_allclose(t.data[1], (p + 0.02).astype(np.float32))
    os.remove(tmp_path / "cloud.usda")
    with pytest.raises(ValueError, match=rf"^cannot read '{re.escape(shot)}': the file \S*cloud\.usda it refers to \(at "
                                         r"/World/dough\) cannot be opened"):
        load_target(shot)


def test_silhouette_masks_beyond_the_scenes_frames_extend_the_fit_as_other_targets(tmp_path, capsys, dough_scene):
    """A mask at frame 3 of a 2-frame scene was refused as 'frames are 1..2 (--frames)' with
    --frames not given, while USD and .npz targets extend the run to their last frame. Now the
    masks do too; with --frames given it is still refused, naming --frames."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2))
    cam = PinholeCamera(64, 40, 200.0, 200.0, 31.5, 19.5, np.diag([1.0, -1.0, -1.0]), [0.0, 0.03, 0.5], "front")
    np.savez(tmp_path / "masks.npz", front_3=(np.arange(64)[None, :] < 32).repeat(40, axis=0).astype(np.uint8))
    doc = {"cameras": [{"name": "front", "width": 64, "height": 40, "K": [[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]],
                        "R": cam.R.tolist(), "t": cam.t.tolist()}], "radius": 0.01}
    (tmp_path / "cameras.json").write_text(json.dumps(doc))
    args = ["fit", str(guess), "--target", str(tmp_path / "masks.npz"), "--cameras", str(tmp_path / "cameras.json"),
            "--iterations", "0", "--no-progress", "--no-usd", "--no-diagnostics"]
    capsys.readouterr()
    assert main([*args, "--output-dir", str(tmp_path / "out")]) == 0, capsys.readouterr().err
    assert json.loads((tmp_path / "out" / "fit.json").read_text())["frames"] == 3
    capsys.readouterr()
    assert main([*args, "--output-dir", str(tmp_path / "out2"), "--frames", "2"]) == 2
    assert capsys.readouterr().err.strip().endswith("masks at frame 3 are not allowed: frames are 1..2 (--frames)")


def test_a_foreign_usd_target_of_widths_0_is_read_and_render_still_refuses_it(tmp_path):
    """A foreign USD whose widths are 0 was refused as damaged ('has widths that are not
    finite and > 0') as a fit target, which never reads widths; export reads none either.
    The renderer, which draws spheres of those diameters, still refuses it."""
    from pxr import Usd, UsdGeom, Vt

    from warp_esph.export import export_frames
    from warp_esph.fit import load_target
    from warp_esph.render import render_usd

    p = np.random.default_rng(0).uniform(0.0, 0.1, (8, 3))
    path = _foreign_points_usd(tmp_path / "w0.usda", {0: p, 1: p + 0.01}, rate=30)
    stage = Usd.Stage.Open(path)
    UsdGeom.Points(stage.GetPrimAtPath("/World/cloud")).GetWidthsAttr().Set(Vt.FloatArray([0.0] * 8))
    stage.Save()
    np.testing.assert_allclose(load_target(path).data, [(p + 0.01).astype(np.float32)])
    assert len(export_frames(path, "vtu", tmp_path / "vtu")) == 3  # two frames and frames.pvd
    with pytest.raises(ValueError, match=r"w0\.usda'?: body 'cloud' at frame 1 has widths that are not finite and > 0"):
        render_usd(path, tmp_path / "w0.png", width=32, height=24)


def test_fit_json_says_which_model_auto_ran(tmp_path, capsys, dough_scene):
    """``fit.json`` records, beside the requested fit (``"auto"``), what it resolved to at the
    initial values (``solver_initial``) and at the fitted ones (``solver``, ``FitResult.to_dict``):
    the dough that flows runs the linear incremental fit, and a model fitted to ``flow_rate = 0``
    ends on the rest-configuration model with the corrected fit and the control (before,
    neither was recorded)."""
    from warp_esph.cli import main
    from warp_esph.fit import FitResult

    truth = tmp_path / "truth.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--frames", "2", "--dtype", "float64", "--no-progress"]) == 0
    out = tmp_path / "fit"
    assert main(["fit", str(truth), "--target", str(run), "--output-dir", str(out), "--params", "mu",
                 "--iterations", "0", "--no-progress", "--no-usd", "--no-diagnostics", "--target-frames", "2"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    for record in (doc["solver_initial"], doc["solver"]):
        assert record == {"fit": "auto", "hourglass": None, "resolved_fit": "linear", "resolved_hourglass": 0.0,
                          "rest_model": False}
    capsys.readouterr()
    b = we.SceneBuilder(spacing=0.05)
    b.add_box((0.0, 0.1, 0.0), (0.15, 0.15, 0.15), we.Material(mu=1e4, lam=1e4, yield_stress=100.0, flow_rate=0.0))
    model = b.finalize()
    result = FitResult(params={"flow_rate": np.array([0.0])}, materials=list(model.materials), material_indices=[0],
                       loss=0.0, initial_loss=1.0, history=[], model=model)
    assert result.to_dict()["solver"] == {"fit": "auto", "hourglass": None, "resolved_fit": "curvature_corrected",
                                          "resolved_hourglass": 0.05, "rest_model": True}


def test_the_fit_summary_counts_what_ran_as_fit_json_does(tmp_path, capsys, dough_scene):
    """'loss a -> b in N evaluations' counted the descent's alone: a fit with a global stage
    said 2 where 5 had run, and nothing of the diagnostics' runs. The line now names each
    stage's count, the numbers fit.json records."""
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + np.random.default_rng(2).normal(0, 0.005, x0.shape)]), frames=[2])
    common = ["fit", str(guess), "--target", str(target), "--params", "yield_stress", "--iterations", "1",
              "--no-progress", "--no-usd"]

    capsys.readouterr()
    assert main([*common, "--samples", "2", "--output-dir", str(tmp_path / "a")]) == EXIT_NOT_CONVERGED  # the cap
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "a" / "fit.json").read_text())
    said = re.search(r"^loss (\S+) -> (\S+) in (\d+) evaluations: (\d+) of the global stage \(loss only: the guess "
                     r"and (\d+) samples\), (\d+) of the descent; then (\d+) runs of the diagnostics$", out, re.M)
    assert said, out
    total, samples, drawn, descent, diagnosed = map(int, said.groups()[2:])
    assert samples == doc["sample_evaluations"] == drawn + 1 == 3
    assert descent == doc["evaluations"] == sum(1 for h in doc["history"] if h["stage"] == "descent") > 0
    assert total == samples + descent == len(doc["history"])
    assert diagnosed == doc["diagnostics"]["evaluations"] > 0
    assert float(said.group(1)) == pytest.approx(doc["initial_loss"], rel=1e-3)
    assert float(said.group(2)) == pytest.approx(doc["loss"], rel=1e-3)

    assert main([*common, "--no-diagnostics", "--output-dir", str(tmp_path / "b")]) == EXIT_NOT_CONVERGED
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "b" / "fit.json").read_text())
    said = re.search(r"^loss \S+ -> \S+ in (\d+) evaluations of the descent$", out, re.M)
    assert said, out
    assert int(said.group(1)) == doc["evaluations"] == len(doc["history"]) and doc["sample_evaluations"] == 0


@pytest.mark.parametrize("lam, params, bounds, said", [
    # Named as typed, with what the material allows: it had embedded the material's own
    # refusal, "at -1e+06, Material.hardening = -1000000.0 is not allowed", a parameter of a
    # class the user never wrote, for the --bounds entry "hardening=-1e6:100".
    (3000.0, "hardening", "hardening=-1e6:100",
     "--bounds hardening=-1e6:100 is not allowed: its lower end, -1e+06, is a hardening the material refuses: hardening "
     "must be > -2 mu = -4000: a softening"),
    # lam fitted as itself (from 0): a lower end below -2 mu / 3 makes the bulk modulus negative.
    (0.0, "lam", "lam=-1e5:100", "--bounds lam=-1e5:100 is not allowed: its lower end, -100000, is a lam the material "
                                 "refuses: lam must be > -2 mu / 3"),
    (3000.0, "lam", "lam=-1e5:100", "--bounds lam=-1e5:100 is not allowed: need lo > 0: lam is fitted as its logarithm, "
                                    "its initial value 3000 being positive (from 0 or below it is fitted as itself"),
    (3000.0, "mu", "mu=-5:100", "--bounds mu=-5:100 is not allowed: need lo > 0: mu is positive"),
])
@pytest.mark.parametrize("stage", [[], ["--samples", "2"]])
def test_cli_fit_bounds_the_fit_refuses_are_one_line_naming_the_option(tmp_path, capsys, dough_scene, lam, params,
                                                                       bounds, said, stage):
    """Bounds refused once the scene is known (an end the material refuses: a softening past
    -2 mu, a bulk modulus below 0; lo <= 0 of a parameter fitted as its logarithm) were named
    as fit's Python parameter, "bounds['hardening'] = (-1e+06, 100)", not as the option typed;
    with --samples too, whose steps are sized from the bounds before the fit."""
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2).replace("lam = 3000.0", f"lam = {lam}"))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0]), frames=[2])
    capsys.readouterr()
    out = tmp_path / "fit"
    assert main(["fit", str(guess), "--target", str(target), "--params", params, "--bounds", bounds, "--iterations", "1",
                 "--no-progress", "--no-usd", "--output-dir", str(out), *stage]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("warp-esph fit: ")]
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {said}"), err
    assert not out.exists()


@pytest.mark.parametrize("stage", [[], ["--samples", "2"]])
def test_cli_fit_bounds_past_float32_advise_the_commands_dtype_option(tmp_path, capsys, dough_scene, stage):
    """An end of --bounds past float32's range is refused through the fit's bounds check; its
    advice said 'use dtype=float64', fit's Python parameter, which the command does not take:
    it names --dtype float64 as the command's other precision refusals do. fit() itself keeps
    its own spelling."""
    from warp_esph.cli import main
    from warp_esph.fit import fit
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0]), frames=[2])
    capsys.readouterr()
    out = tmp_path / "fit"
    assert main(["fit", str(guess), "--target", str(target), "--params", "mu", "--bounds", "mu=1:1e39", "--dtype",
                 "float32", "--iterations", "1", "--no-progress", "--no-usd", "--output-dir", str(out), *stage]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("warp-esph fit: ")]
    assert len(err) == 1 and err[0].startswith("warp-esph: error: --bounds mu=1:1e39 is not allowed: its upper end"), err
    assert err[0].endswith("use dtype=float64 (--dtype float64) or a smaller value"), err
    assert not out.exists()
    if stage:
        return
    model = load_scene(str(guess)).builder.finalize(dtype=wp.float32, requires_grad=True)
    with pytest.raises(ValueError, match=r"^bounds\['mu'\] = \(1, 1e\+39\) is not allowed: .*in float32: .*; "
                                         r"use dtype=float64 or a smaller value$"):
        fit(model, PositionLoss(x0[None], frames=[2]), ["mu"], steps=2, dt=1e-4, bounds={"mu": (1.0, 1e39)}, iterations=1,
            progress=False, diagnostics=False)


@pytest.mark.parametrize("stage", [[], ["--samples", "2"]])
def test_cli_fit_a_start_held_to_bounds_past_float32_advises_the_commands_dtype_option(tmp_path, capsys, dough_scene,
                                                                                       stage):
    """Lower ends of lam and mu each allowed alone (an elastic material) but together past
    what float32 holds of the pressure at a strain of 1 (about K / 2 by default) times two densities: the guess held to them is refused where the fit starts, and its
    advice said 'use dtype=float64', which the command does not take."""
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2).replace(
        "yield_stress = 200.0\nflow_rate = 20.0\nviscosity = 2.0\n", ""))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0]), frames=[2])
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(target), "--params", "lam,mu", "--bounds", "lam=5e32:5.5e32",
                 "--bounds", "mu=4e32:4.5e32", "--dtype", "float32", "--iterations", "1", "--no-progress", "--no-usd",
                 "--output-dir", str(tmp_path / "fit"), *stage]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("warp-esph fit: ")]
    assert len(err) == 1 and err[0].startswith("warp-esph: error: the initial values are not allowed within the bounds: "), err
    assert "the pressure force" in err[0] and err[0].endswith("use dtype=float64 (--dtype float64) or smaller values"), err
    # Named as typed, not as the class field Material.mu, which the command's user never wrote.
    assert "Material." not in err[0] and "--bounds mu=4e32:4.5e32 holds mu's guess, 2000, at its lower end" in err[0], err
    assert "--bounds lam=5e32:5.5e32 holds lam's guess, 3000, at its lower end" in err[0], err
    assert "lam's lower end, 5e+32, is a lam the material refuses in float32: " in err[0], err
    if stage:
        return
    from warp_esph.fit import fit

    model = load_scene(str(guess)).builder.finalize(dtype=wp.float32, requires_grad=True)
    with pytest.raises(ValueError, match=r"^the initial values are not allowed within the bounds: bounds\['lam'\] = "
                                         r"\(5e\+32, 5\.5e\+32\) holds lam's guess, 3000, at its lower end; bounds\['mu'\] = "
                                         r"\(4e\+32, 4\.5e\+32\) holds mu's guess, 2000, at its lower end"
                                         r": lam's lower end, 5e\+32, is a lam the material refuses in float32: .*"
                                         r"use dtype=float64 or smaller values$") as raised:
        fit(model, PositionLoss(x0[None], frames=[2]), ["lam", "mu"], steps=2, dt=1e-4, iterations=1, progress=False,
            bounds={"lam": (5e32, 5.5e32), "mu": (4e32, 4.5e32)}, diagnostics=False)
    assert "Material." not in str(raised.value)


def test_the_fit_help_says_the_iteration_cap_is_each_starts_as_it_is(tmp_path, capsys, dough_scene):
    """--help said 'gradient evaluations after the first': the cap is each start's (two
    starts at --iterations 1 make up to 4), Gauss-Newton's are forward runs, and --clip, which
    only Adam takes, read as an option of every fit."""
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "evaluations of each start after its first, line-search trials (gauss-newton: Jacobian runs) included" in text
    assert "--clip C Adam only:" in text
    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + np.random.default_rng(2).normal(0, 0.005, x0.shape)]), frames=[2])
    assert main(["fit", str(guess), "--target", str(target), "--params", "yield_stress", "--iterations", "1", "--starts",
                 "2", "--no-progress", "--no-usd", "--no-diagnostics", "--output-dir", str(tmp_path / "o")]) == EXIT_NOT_CONVERGED
    history = json.loads((tmp_path / "o" / "fit.json").read_text())["history"]
    per_start = [sum(1 for h in history if h.get("start") == k) for k in (0, 1)]
    assert 1 <= max(per_start) <= 2 and sum(per_start) == len(history) > 2, per_start


def test_a_fit_that_stops_without_converging_exits_5_with_its_results_written(tmp_path, capsys, dough_scene):
    """``warp-esph fit`` exited 0 whether the fit converged, stalled or hit the iteration cap: a
    script read a fit stopped short as fitted values. It now exits ``EXIT_NOT_CONVERGED`` (5)
    with every result written, its last line saying how it stopped and what to change; 0 for a
    converged fit, and for ``--iterations 0``, which asks for no descent."""
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + np.random.default_rng(2).normal(0, 0.005, x0.shape)]), frames=[2])
    common = ["fit", str(guess), "--params", "mu", "--no-progress", "--no-usd", "--no-diagnostics"]
    capsys.readouterr()
    assert main([*common, "--target", str(target), "--iterations", "1", "--output-dir", str(tmp_path / "a")]) == 5
    said = capsys.readouterr()
    doc = json.loads((tmp_path / "a" / "fit.json").read_text())
    assert doc["stopped"] == "iterations" and not doc["converged"] and (tmp_path / "a" / "history.csv").is_file()
    assert said.out.startswith("fit hit the iteration cap before converging"), said.out
    assert said.err.splitlines()[-1] == (
        "warp-esph fit: not converged: it hit the iteration cap (--iterations 1); run it again with a larger --iterations to "
        "go further (it starts again from the scene's values); its results are written as above (exit 5)"), said.err
    assert main([*common, "--target", str(target), "--iterations", "0", "--output-dir", str(tmp_path / "b")]) == 0
    assert "not converged" not in capsys.readouterr().err
    # The guess's own run: converged (a probe lr away reads a loss above the guess's 0).
    run = tmp_path / "run.usdc"
    assert main(["run", str(guess), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    capsys.readouterr()
    assert main([*common, "--target", str(run), "--iterations", "5", "--output-dir", str(tmp_path / "c")]) == 0
    assert "not converged" not in capsys.readouterr().err
    assert json.loads((tmp_path / "c" / "fit.json").read_text())["converged"]


def test_a_gauss_newton_fit_that_reaches_a_loss_of_zero_converges_not_flat(tmp_path, capsys, dough_scene):
    """Gauss-Newton said ``flat`` ("stopped at once: the gradient is exactly zero ... start
    elsewhere") wherever its Jacobian was all zeros, also after steps that took the loss to
    exactly 0: a dough block fitted from 200 Pa to its run at 1e5 Pa (a yield stress above
    every stress: any such value reproduces it) reached loss 0 and exited 5 as not converged,
    its last line saying the gradient was zero at the start, where L-BFGS converged. After a
    step a Jacobian of zeros is a minimum reached: ``converged``, exit 0."""
    from warp_esph.cli import main

    guess, hard = tmp_path / "guess.toml", tmp_path / "hard.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    hard.write_text(dough_scene(yield_stress=1e5, flow_rate=20.0, frames=2))
    run = tmp_path / "run.usdc"
    assert main(["run", str(hard), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    capsys.readouterr()
    status = main(["fit", str(guess), "--params", "yield_stress", "--target", str(run), "--iterations", "30", "--optimizer",
                   "gauss-newton", "--no-progress", "--no-usd", "--no-diagnostics", "--output-dir", str(tmp_path / "o")])
    said = capsys.readouterr()
    doc = json.loads((tmp_path / "o" / "fit.json").read_text())
    assert status == 0, said.err
    assert doc["stopped"] == "converged" and doc["loss"] == 0.0 and doc["params"]["yield_stress"][0] > 1000.0, doc["params"]
    assert len(doc["history"]) > 1 and said.out.startswith("fit converged"), said.out


def test_a_stalled_fits_last_line_names_what_stalled_it(tmp_path, capsys, dough_scene, monkeypatch):
    """A fit stalls by ``patience`` (evaluations in a row without a lower loss) or by its
    optimiser's own search (an L-BFGS line search shrunk below ``xtol``, the default
    optimiser's stall on a rough loss). The exit-5 line told both to raise ``--patience``,
    which the search's stall never reached; it now says which, and ``fit.json`` records it
    (``stalled_by``)."""
    from warp_esph import fit as fit_module
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    common = ["fit", str(guess), "--target", str(run), "--params", "yield_stress", "--no-progress", "--no-usd",
              "--no-diagnostics"]
    capsys.readouterr()
    # Adam's first step (lr 3 in log space) moves the yield stress past the truth: a higher loss.
    assert main([*common, "--optimizer", "adam", "--lr", "3", "--patience", "1", "--iterations", "5",
                 "--output-dir", str(tmp_path / "p")]) == EXIT_NOT_CONVERGED
    last = capsys.readouterr().err.splitlines()[-1]
    doc = json.loads((tmp_path / "p" / "fit.json").read_text())
    assert (doc["stopped"], doc["stalled_by"], len(doc["history"])) == ("stalled", "patience", 2), doc["history"]
    assert last == ("warp-esph fit: not converged: it stalled (no lower loss in --patience 1 evaluations); a larger "
                    "--patience waits longer for one, a larger --iterations with it; its results are written as above "
                    "(exit 5)"), last

    def line_search_stalled(evaluate, project, z, *args, **kwargs):
        evaluate(z)
        return "stalled"  # as _run_lbfgs returns where its line search shrank the step below xtol

    monkeypatch.setattr(fit_module, "_run_lbfgs", line_search_stalled)
    assert main([*common, "--optimizer", "lbfgs", "--iterations", "5", "--output-dir", str(tmp_path / "s")]) == EXIT_NOT_CONVERGED
    last = capsys.readouterr().err.splitlines()[-1]
    assert json.loads((tmp_path / "s" / "fit.json").read_text())["stalled_by"] == "search"
    assert "--patience 20" not in last and "which a larger --patience or --iterations does not change" in last, last


def test_a_sigterm_that_landed_in_a_finalizer_of_an_unconverged_fit_is_no_exit_5(tmp_path, capsys, dough_scene, monkeypatch):
    """A signal that lands in a finalizer cannot be raised there: it is recorded, and ``main``
    turned a finished command's 0 into the signal's status. A fit that stopped without
    converging returns 5 (``EXIT_NOT_CONVERGED``), which ``main`` passed on: a SIGTERM that
    landed while its results were written exited 5, not 143, and nothing said it was
    terminated. The results stay written; the status is the signal's."""
    from warp_esph import calibrate
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + np.random.default_rng(2).normal(0, 0.005, x0.shape)]), frames=[2])
    real = calibrate.write_outputs

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)

    def write_outputs(*args, **kwargs):
        Finalized()
        return real(*args, **kwargs)

    monkeypatch.setattr(calibrate, "write_outputs", write_outputs)
    capsys.readouterr()
    status = main(["fit", str(guess), "--params", "mu", "--target", str(target), "--iterations", "1", "--no-progress",
                   "--no-usd", "--no-diagnostics", "--output-dir", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert status == 143, err
    assert err.splitlines()[-1] == "warp-esph: terminated", err
    assert json.loads((tmp_path / "o" / "fit.json").read_text())["stopped"] == "iterations"


@pytest.mark.parametrize("signum, status, said", [(signal.SIGTERM, 143, "terminated (SIGTERM)"),
                                                  (signal.SIGINT, 130, "interrupted (Ctrl-C, SIGINT)")],
                         ids=["SIGTERM", "SIGINT"])
def test_an_interrupted_fit_names_the_signal_that_stopped_it(tmp_path, capsys, dough_scene, monkeypatch, signum, status, said):
    """A fit stopped by SIGTERM wrote 'interrupted (Ctrl-C)' as its termination in fit.json and
    'interrupted after ...' as its line, where run's and sweep's lines say 'terminated': the exit
    status (143) alone told. The signal is now named in both, and recorded in fit.json."""
    from warp_esph import fit as fit_module
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    calls, original = [], fit_module._Problem.value_and_grad

    def signalled(self, z, losses=None):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signum)  # main's handler, installed in this process, raises it here
        return original(self, z, losses)

    monkeypatch.setattr(fit_module._Problem, "value_and_grad", signalled)
    out = tmp_path / "fit"
    capsys.readouterr()
    # A process started in the background (nohup, '&') inherits SIGINT ignored, and main leaves an
    # ignored signal ignored, so the test gives this process Python's own Ctrl-C handler first.
    before = signal.signal(signum, signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL)
    try:
        got = main(["fit", str(guess), "--target", str(run), "--params", "yield_stress", "--iterations", "10",
                    "--optimizer", "adam", "--no-progress", "--no-usd", "--no-diagnostics", "--output-dir", str(out)])
    finally:
        signal.signal(signum, before)
    err = capsys.readouterr().err
    assert got == status, err
    doc = json.loads((out / "fit.json").read_text())
    assert doc["stopped"] == "interrupted" and doc["termination"].startswith(said), doc["termination"]
    assert doc["signal"] == signal.Signals(signum).name
    word = said.split()[0]
    assert f"warp-esph fit: {word} after 2 evaluations of the descent; wrote the best so far" in err, err
    assert err.splitlines()[-1].startswith(f"warp-esph: {word}"), err


def test_a_long_target_at_a_real_rate_is_warned_of_without_the_frame_interval_hint(tmp_path, capsys, dough_scene,
                                                                                   monkeypatch):
    """A target of many frames at the scene's own 30 fps plans 10 times the scene's duration: the
    plan warns of it, but it read 'if 30 is a frame interval (seconds per frame), the rate is
    0.03333 fps', a hint no 30 fps recording needs."""
    from warp_esph import fit as fit_module
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    scene = tmp_path / "s.toml"
    scene.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    x0 = load_scene(str(scene)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 - [0.0, 0.001 * k, 0.0] for k in (1, 2, 3)]), frames=[20, 40, 60], fps=30.0)

    def stand_in(*args, log, **kwargs):
        log("the fit would start here")  # the plan is said with the fit's first line
        raise ValueError("stopped by the test before the first evaluation")

    monkeypatch.setattr(fit_module, "fit", stand_in)
    capsys.readouterr()
    assert main(["fit", str(scene), "--target", str(target), "--no-progress", "--no-usd",
                 "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    warning = [line for line in err.splitlines() if "warning: each evaluation runs" in line]
    assert len(warning) == 1 and "10 times the scene's own 6 frames at 30 fps" in warning[0], err
    assert "frame interval" not in warning[0] and warning[0].endswith("the target's last frame, 60, sets its length"), err


@pytest.mark.parametrize("rate, warned", [(0.03, True), (30.0, False)], ids=["interval_as_rate", "scene_rate"])
def test_a_plan_of_far_more_steps_than_the_scene_needs_says_so_and_names_the_rate_read(tmp_path, capsys, dough_scene,
                                                                                      monkeypatch, rate, warned):
    """An .npz whose fps holds a frame interval (0.03 for 33 fps) planned 99966 steps an
    evaluation (about 6 minutes each), said only as '(99966 steps)' in the plan. The plan now
    says what each evaluation runs, and where that is far beyond the scene's own duration, it
    warns, naming the rate and the file it was read from and that it may be a frame interval.
    A low rate may be real: the fit goes on (here a stand-in for it stops the command)."""
    from warp_esph import fit as fit_module
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    scene = tmp_path / "s.toml"
    scene.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0))
    x0 = load_scene(str(scene)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    # Every stored frame 0.1 spacings or more from the start (0.002 m a frame): at 0.001 m the
    # first held it (calibrate.START_TOLERANCE), and the start-frame check ran the scene's own
    # 16661 steps to it at 0.03 fps, 10 of the test's 10.4 s of CPU, for a warning not asked here.
    np.savez(target, positions=np.stack([x0 - [0.0, 0.002 * k, 0.0] for k in (1, 2, 3)]), frames=[1, 2, 3], fps=rate)
    reached = []

    def stand_in(*args, log, **kwargs):
        reached.append(1)
        log("the fit would start here")
        raise ValueError("stopped by the test before the first evaluation")

    monkeypatch.setattr(fit_module, "fit", stand_in)
    capsys.readouterr()
    assert main(["fit", str(scene), "--target", str(target), "--no-progress", "--no-usd",
                 "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert reached == [1], err
    plan = next(line for line in err.splitlines() if "particles, 3 frames at" in line)
    steps = int(re.search(r"each evaluation runs (\d+) steps", plan).group(1))
    warning = [line for line in err.splitlines() if "warning: each evaluation runs" in line]
    if not warned:
        assert steps < 1000 and warning == [], err
        return
    assert steps > 10000, plan
    assert len(warning) == 1, err
    said = warning[0]
    assert f"each evaluation runs {steps} steps, 100 s simulated (3 frames at 0.03 fps)" in said, said
    assert "500 times the scene's own 6 frames at 30 fps (0.2 s" in said, said
    assert f"the rate 0.03 fps was read from the target {target}" in said, said
    assert "if 0.03 is a frame interval (seconds per frame), the rate is 33.33 fps" in said, said


def test_a_target_past_the_fits_frames_is_refused_saying_what_to_give(tmp_path, capsys, dough_scene):
    """``--frames`` shorter than the target (a user cutting a fit short) was refused as 'the
    target has frame 3, beyond --frames = 2', which named no way on: the line now says both,
    a --frames that reaches the target or target frames within the run."""
    from warp_esph.cli import main

    scene = tmp_path / "truth.toml"
    scene.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=3))
    run = tmp_path / "run.usdc"
    assert main(["run", str(scene), "-o", str(run), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["fit", str(scene), "--target", str(run), "--frames", "2", "--iterations", "0", "--no-progress",
                 "--output-dir", str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err
    assert (f"the target {run} has frame 3, beyond --frames = 2: give --frames 3 or more, or choose target frames "
            "up to 2 with --target-frames") in err, err
    assert not (tmp_path / "fit").exists()


def test_the_fit_says_the_fitted_values_as_a_lab_measures_them(tmp_path, capsys, dough_scene):
    """A rheometer's user fits ``yield_stress`` and ``flow_rate`` (the scene file may hold the
    lab's values, docs/scene_format.md) and reads the answer in the lab's terms: the summary
    gives the shear and uniaxial yield stress and the plastic viscosity of the fitted values
    (``Material.shear_yield_stress`` ...), which it had left to the user to convert."""
    from warp_esph.cli import main

    scene = tmp_path / "truth.toml"
    scene.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2))
    run = tmp_path / "run.usdc"
    assert main(["run", str(scene), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["fit", str(scene), "--target", str(run), "--iterations", "0", "--no-diagnostics", "--no-usd",
                 "--no-progress", "--output-dir", str(tmp_path / "fit")]) == 0
    out = capsys.readouterr().out
    assert "  yield_stress = 100 Pa\n  flow_rate = 10 1/s\n" in out, out
    fitted = we.Material(mu=2000.0, lam=3000.0, yield_stress=100.0, flow_rate=10.0)
    assert (f"  as a lab measures them: shear_yield_stress = {fitted.shear_yield_stress:.6g} Pa, uniaxial_yield_stress = "
            f"{fitted.uniaxial_yield_stress:.6g} Pa, plastic_viscosity = {fitted.plastic_viscosity:.6g} Pa s "
            "(Material.from_rheology's)\n") in out, out
    # Only what the fitted values set: the flow rate alone gives the plastic viscosity alone.
    assert main(["fit", str(scene), "--target", str(run), "--params", "flow_rate", "--iterations", "0",
                 "--no-diagnostics", "--no-usd", "--no-progress", "--output-dir", str(tmp_path / "fit")]) == 0
    out = capsys.readouterr().out
    assert f"  as a lab measures them: plastic_viscosity = {fitted.plastic_viscosity:.6g} Pa s (" in out, out
    # mu fitted with the flow rate held moves the plastic viscosity (mu / flow_rate): a scene's
    # plastic_viscosity (a rheometer's) ended elsewhere, and no line said it.
    assert main(["fit", str(scene), "--target", str(run), "--params", "mu", "--iterations", "0",
                 "--no-diagnostics", "--no-usd", "--no-progress", "--output-dir", str(tmp_path / "fit")]) == 0
    out = capsys.readouterr().out
    assert (f"  as a lab measures them: plastic_viscosity = {fitted.plastic_viscosity:.6g} Pa s (mu / flow_rate, the flow "
            "rate held: it moved with the fitted mu) (Material.from_rheology's)\n") in out, out
    # A material that never flows has none to say.
    elastic = tmp_path / "elastic.toml"
    elastic.write_text(dough_scene(yield_stress="inf", flow_rate=10.0, frames=2))
    assert main(["fit", str(elastic), "--target", str(run), "--params", "mu", "--iterations", "0",
                 "--no-diagnostics", "--no-usd", "--no-progress", "--output-dir", str(tmp_path / "fit")]) == 0
    assert "as a lab measures them" not in capsys.readouterr().out


def test_fit_material_selects_a_scene_files_material_by_its_name(tmp_path, capsys, monkeypatch, two_materials_scene):
    """``--material clay`` (a preset a body names) or ``soft`` (a ``[materials.soft]`` table):
    the material named as the scene file names it; refused before ('give a material index or
    a body name'), the user's own word for it."""
    from warp_esph import fit as fit_module
    from warp_esph.cli import main

    scene = tmp_path / "two.toml"
    scene.write_text(two_materials_scene)
    np.save(tmp_path / "t.npy", np.zeros((2, 64, 3)))  # what the stand-in never reads
    seen = []

    def stand_in(experiments, *args, **kwargs):
        seen.append(experiments[0].materials)
        raise ValueError("stopped by the test before the first evaluation")

    monkeypatch.setattr(fit_module, "fit", stand_in)
    # A material's name becomes its index; a body's name passes as it was (fit resolves it).
    for chosen, indices in ((["clay"], [1]), (["soft", "b"], [0, "b"]), (["a"], ["a"])):
        argv = ["fit", str(scene), "--target", str(tmp_path / "t.npy"), "--target-frames", "0,1", "--no-progress",
                "--no-usd", "--output-dir", str(tmp_path / "out")]
        for m in chosen:
            argv += ["--material", m]
        assert main(argv) == 2
        assert "stopped by the test" in capsys.readouterr().err
        assert seen[-1] == indices


def test_a_damaged_mask_file_is_said_in_words_not_by_the_class_numpy_raised(tmp_path):
    """A damaged .npz or .npy mask file said 'cannot be read: BadZipFile: File is not a zip file'
    or 'UnpicklingError: ...', the class raised first; it is said as a damaged target file is,
    and bytes that are no array file get no advice to load them unsafely."""
    cams = _cameras()
    np.savez(tmp_path / "whole.npz", front_3=np.zeros((24, 32)), side_3=np.zeros((24, 24)))
    (tmp_path / "cut.npz").write_bytes((tmp_path / "whole.npz").read_bytes()[:100])
    (tmp_path / "text.npy").write_bytes(b"a mask, said in words\n")
    for name, cameras, why in (("cut.npz", cams, "File is not a zip file"), ("text.npy", cams[:1], "not a numpy .npz/.npy file")):
        with pytest.raises(ValueError) as e:
            load_masks(tmp_path / name, cameras, 3)
        assert str(e.value) == f"mask file {tmp_path / name} cannot be read: {why} (a damaged or foreign file?)"


def test_a_resumed_force_log_that_cannot_be_opened_is_said_by_the_systems_reason(tmp_path):
    """checks.read_reason said an OSError by its str(): '[Errno 21] Is a directory: '<the path
    whole>'', in a message that names the path already; the force log of a run to resume that
    is a folder was refused so. It says the system's reason alone, as the other readers do."""
    import types

    from warp_esph.tools import ReactionLog

    (tmp_path / "out_tools.json").mkdir()
    log = types.SimpleNamespace(run_id="mine", rows=[], _kept=None)
    with pytest.raises(ValueError) as e:
        ReactionLog.resume(log, str(tmp_path / "out"), 3)
    assert str(e.value) == (f"the force log {tmp_path / 'out_tools.json'} of the run to resume cannot be read (Is a directory): resuming "
                            "would replace its rows of the finished frames; move it away to resume without them")


def test_a_mask_file_the_system_refuses_in_a_folder_named_pickles_is_said_by_the_systems_reason(tmp_path, monkeypatch):
    """fit.unreadable_arrays told numpy's refusal of pickled data by 'pickle' anywhere in the
    exception's words, an OSError's path among them: a mask file in a folder 'pickles' that
    the system refused to read (permission denied: not shown as root, so raised here as open
    raises it) was 'not a numpy .npz/.npy file'."""
    import errno

    import warp_esph.fit as fit_module

    folder = tmp_path / "pickles"
    folder.mkdir()
    np.savez(folder / "m.npz", front_3=np.zeros((24, 32)), side_3=np.zeros((24, 24)))

    def refused(path):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(fit_module, "read_arrays", refused)
    with pytest.raises(ValueError) as e:
        load_masks(folder / "m.npz", _cameras(), 3)
    assert str(e.value) == f"mask file {folder / 'm.npz'} cannot be read: Permission denied (a damaged or foreign file?)"


def test_a_target_given_twice_is_refused_not_counted_twice(tmp_path, capsys, dough_scene, monkeypatch):
    """``--target run.usdc --target run.usdc`` (or ``./run.usdc`` beside it) fitted the one
    recording as two: its 1152 observations counted as 2304, and the diagnostics reported
    standard errors 1/sqrt(2) of the data's (yield stress 19.69 Pa where the file alone gives
    27.85). Refused before any scene is built, naming the file and both places; the same file
    at other frames (``--target-frames`` once per target) is not."""
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    monkeypatch.chdir(tmp_path)
    # Other names of the one file: a symbolic link, and a hard link (the same inode, another
    # real path: it was fitted twice).
    os.symlink("run.usdc", tmp_path / "alias.usdc")
    os.link(run, tmp_path / "again.usdc")
    common = ["--iterations", "0", "--no-progress", "--no-diagnostics", "--no-usd", "--output-dir", str(tmp_path / "o")]
    for extra in (["--target", str(run), "--target", str(run)], ["--target", "run.usdc", "--target", "./run.usdc"],
                  ["--target", "run.usdc", "--target", "alias.usdc"], ["--target", "run.usdc", "--target", "again.usdc"],
                  ["--target", "run.usdc", "--target", "run.usdc", "--target-frames", "2,3", "--target-frames", "2,3"]):
        capsys.readouterr()
        assert main(["fit", str(guess), *extra, *common]) == 2, extra
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and re.search(r"^warp-esph: error: --target = '[^']*(run|alias|again)\.usdc' is not allowed twice \(--target "
                                           r"#1 and #2 are one file( at the same frames)?\): its observations would count twice", err[0]), (extra, err)
    assert not (tmp_path / "o").exists()
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", "run.usdc", "--target", "run.usdc", "--target-frames", "2",
                 "--target-frames", "3", *common]) == 0


def test_a_target_given_twice_at_frames_written_otherwise_or_shared_in_part_is_refused(tmp_path, capsys, dough_scene,
                                                                                        monkeypatch):
    """The check above compared the ``--target-frames`` as written: ``1:3`` and ``1,2,3``, or
    ``last`` and ``-1``, choose the same frames of one file and passed, each frame's
    observations counted twice. The frames chosen are compared now, and two choices that share
    some frames (``1,2`` and ``2:3``) count those twice too: refused, naming the frames, before
    any scene is built; a file without frame numbers (an .npy's entries) likewise."""
    from warp_esph import scenes
    from warp_esph.cli import main

    guess, run = _dough_guess_and_target(tmp_path, dough_scene)
    np.save(tmp_path / "t.npy", np.zeros((3, 64, 3)))
    monkeypatch.chdir(tmp_path)

    def built(*_, **__):
        raise AssertionError("a scene was built before the refusal")

    monkeypatch.setattr(scenes, "load_scaled_scene", built)
    common = ["--iterations", "0", "--no-progress", "--no-diagnostics", "--no-usd", "--output-dir", str(tmp_path / "o")]
    for target, first, second, frames in (("run.usdc", "1:3", "1,2,3", "frames 1, 2, 3"), ("run.usdc", "last", "-1", "frame 3"),
                                          ("run.usdc", "1,2", "2:3", "frame 2"), ("t.npy", "1:3", "3,2,1", "frames 1, 2, 3"),
                                          ("t.npy", "0,1", "1:2", "frame 1")):
        capsys.readouterr()
        assert main(["fit", str(guess), "--target", target, "--target", f"./{target}", "--target-frames", first,
                     "--target-frames", second, *common]) == 2, (first, second)
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and err[0] == (
            f"warp-esph: error: --target = './{target}' is not allowed twice at {frames} (--target #1 and #2 are one file, "
            f"and --target-frames '{first}' and '{second}' both choose {'them' if 'frames' in frames else 'it'}): its "
            "observations there would count twice, and the diagnostics' standard errors shrink by 1/sqrt(2); give the file "
            "once, with --target-frames naming every frame to fit"), (first, second, err)
    assert not (tmp_path / "o").exists()


def test_a_cloud_given_twice_at_its_default_frame_and_that_frame_named_is_refused(tmp_path, capsys, dough_scene):
    """A cloud's frame left out is the run's last, known once the targets set the run's length:
    an experiment's ``target_frames`` [null, "2"] of one cloud (the run ends at frame 2) fitted
    frame 2's observations twice; refused once the frame is known, naming it."""
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    np.savetxt(tmp_path / "c.xyz", load_scene(str(guess)).builder.finalize().particle_x0 + 0.001)
    exps = tmp_path / "e.json"
    exps.write_text(json.dumps([{"scene": str(guess), "target": ["c.xyz", "./c.xyz"], "target_frames": [None, "2"]}]))
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(tmp_path / "c.xyz"), "--experiments", str(exps), "--iterations", "0",
                 "--no-progress", "--no-usd", "--no-diagnostics", "--output-dir", str(tmp_path / "o")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].endswith(
        "c.xyz' is not allowed twice at frame 2 (target #1 and #2 are one file, and target_frames left out (the default) and "
        "'2' both choose it): its observations there would count twice, and the diagnostics' standard errors shrink by "
        "1/sqrt(2); give the file once, with target_frames naming every frame to fit"), err
    assert not (tmp_path / "o").exists()


def test_a_json_file_given_as_a_target_says_what_it_is_not_that_meshio_cannot_read_it(tmp_path):
    """The ``_tools.json`` a run writes beside its force log (or a fit's ``fit.json``, a camera
    or experiments file) given as ``--target`` was refused as a mesh meshio could not read
    ('Could not deduce file format'), naming no target the command takes. It is said to be
    JSON, with the force log's CSV named where the file is a run's record of one."""
    from warp_esph.fit import load_target

    (tmp_path / "run.usdc_tools.json").write_text('{"units": {"force": "N"}, "rows": []}')
    (tmp_path / "fit.json").write_text("{}")
    # A record copied without its CSV is not pointed to a CSV beside it as if it were there.
    with pytest.raises(ValueError, match=r"^target \S*run\.usdc_tools\.json is not allowed: it is a JSON file, not a "
                                         r"measurement; a run's force log is its CSV beside it, \S*run\.usdc_tools\.csv "
                                         r"\(the same rows\), which is not there \(give the run's log as it wrote it\)$"):
        load_target(tmp_path / "run.usdc_tools.json")
    (tmp_path / "run.usdc_tools.csv").write_text("frame,time,tool,fx,fy,fz\n")
    with pytest.raises(ValueError, match=r"^target \S*run\.usdc_tools\.json is not allowed: it is a JSON file, not a "
                                         r"measurement; a run's force log is its CSV beside it, \S*run\.usdc_tools\.csv "
                                         r"\(the same rows\)$"):
        load_target(tmp_path / "run.usdc_tools.json")
    with pytest.raises(ValueError, match=r"^target \S*fit\.json is not allowed: it is a JSON file, not a measurement; give "
                                         r"the run's USD.*\(a camera file goes with --cameras, experiments with --experiments\)$"):
        load_target(tmp_path / "fit.json")
