"""Runs whose bodies are too coarse for the deformation fit say so (the refusal of such a
scene where it is built is in test_scenes.py)."""

import warnings

import numpy as np
import pytest

import warp_esph as we
from warp_esph.cli import main
from warp_esph.simulate import SKIPPED_FIT_SHARE


def _skip_warnings(record) -> list[str]:
    return [str(w.message) for w in record if "deformation fit was skipped" in str(w.message)]


def _run(builder, frames=2):
    model = builder.finalize()
    solver = we.Solver(model)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        we.simulate(model, frames, fps=30.0, progress=False, solver=solver)
    counts = solver.guard_counts()
    share = (counts["few_neighbors"] + counts["ill_conditioned"]) / (model.particle_count * solver.step_count)
    return _skip_warnings(record), share


def test_a_run_of_a_sheet_one_layer_thick_warns_with_the_share_and_a_block_landing_does_not():
    """A sheet one particle layer thick has no 3-D neighbourhood: every fit is skipped, the
    run said nothing (only guard_counts() knew). A 4-layer block landing on the ground, where
    the guard may act on a few particles briefly, runs without the warning."""
    sheet = we.SceneBuilder(spacing=0.02)
    sheet.add_box((0.0, 0.1, 0.0), (0.1, 0.02, 0.1), we.Material.preset("clay"), name="sheet")
    sheet.add_ground()
    said, share = _run(sheet)
    assert share >= SKIPPED_FIT_SHARE
    assert len(said) == 1, said
    assert f"{100.0 * share:.3g} % of the run's particle-steps" in said[0]
    assert "a smaller spacing" in said[0]

    block = we.SceneBuilder(spacing=0.02)
    block.add_box((0.0, 0.05, 0.0), (0.08, 0.08, 0.08), we.Material.preset("clay"), velocity=(0.0, -1.0, 0.0), name="block")
    block.add_ground()
    said, share = _run(block, frames=4)
    assert share < SKIPPED_FIT_SHARE and said == []



def test_the_warning_names_the_body_too_coarse_for_the_fit_and_the_counts_are_per_body():
    """A one-layer sheet beside a 4-layer block: the run's counts covered both bodies, so the
    warning could not say which was too coarse. Solver.skipped_fits() counts each body's
    skipped fits (summing to the guards' two counts) and the warning names the sheet alone."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.02, 0.1), we.Material.preset("clay"), name="sheet")
    b.add_box((0.3, 0.1, 0.0), (0.08, 0.08, 0.08), we.Material.preset("clay"), name="block")
    b.add_ground()
    model = b.finalize()
    solver = we.Solver(model)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        we.simulate(model, 2, fps=30.0, progress=False, solver=solver)
    counts, by_body = solver.guard_counts(), solver.skipped_fits()
    assert set(by_body) == {"sheet", "block"}
    assert sum(by_body.values()) == counts["few_neighbors"] + counts["ill_conditioned"]
    sheet = next(x for x in model.bodies if x.name == "sheet")
    assert by_body["sheet"] == sheet.count * solver.step_count and by_body["block"] == 0
    said = _skip_warnings(record)
    assert len(said) == 1 and "'sheet' 100 %" in said[0] and "'block'" not in said[0], said


@pytest.mark.parametrize("fused, fit, deformation", [(False, "linear", "incremental"), (True, "curvature_corrected", "incremental"),
                                                     (False, "curvature_corrected", "incremental"), (False, "linear", "rest"),
                                                     (False, "linear", "additive")])
def test_each_fit_counts_the_skipped_fits_of_its_body(fused, fit, deformation):
    """Every kernel that skips a fit (the plain and curvature-corrected fits, fused or not, and
    the comparison models' rest and additive fits) counts it at its body: the bodies' counts
    sum to the guards' own, and all of them are the one-layer sheet's."""
    b = we.SceneBuilder(spacing=0.02)
    clay = we.Material.preset("clay")
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.02, 0.1), clay.replace(deformation=deformation), name="sheet")
    b.add_box((0.3, 0.1, 0.0), (0.08, 0.08, 0.08), clay, name="block")
    model = b.finalize()
    solver = we.Solver(model, fused=fused, fit=fit)
    state_in, state_out = model.state(), model.state()
    for _ in range(2):
        solver.step(state_in, state_out, 0.5 * model.stable_dt())
        state_in, state_out = state_out, state_in
    counts, by_body = solver.guard_counts(), solver.skipped_fits()
    sheet = next(x for x in model.bodies if x.name == "sheet")
    assert counts["few_neighbors"] + counts["ill_conditioned"] == sheet.count * 2
    assert by_body == {"sheet": sheet.count * 2, "block": 0}
    solver.reset_counts()
    assert solver.skipped_fits() == {"sheet": 0, "block": 0}

def test_the_command_line_warns_and_sums_up_the_share_of_skipped_fits(tmp_path, capsys):
    """The star at scale 0.5 (2 cm spacing) is two layers thick with tips too narrow for the
    fit: its run skipped the tips' fits with exit 0 and a guard-count line only. It still runs
    (exit 0), with one warning naming the share and --scale, and the summary gives the share."""
    out = tmp_path / "star.usdc"
    assert main(["run", "star", "--scale", "0.5", "--frames", "1", "--no-progress", "-o", str(out)]) == 0
    captured = capsys.readouterr()
    warned = [line for line in captured.err.splitlines() if "deformation fit was skipped" in line]
    assert len(warned) == 1 and warned[0].startswith("warp-esph: warning: ") and "a larger --scale" in warned[0], captured.err
    summary = [line for line in captured.out.splitlines() if line.startswith("guard counts")]
    assert len(summary) == 1
    counts = dict(kv.split("=") for kv in summary[0].split(": ", 1)[1].split(";")[0].split(", "))
    shown = float(summary[0].rsplit("skipped in ", 1)[1].split(" % of ")[0])
    particle_steps = int(summary[0].rsplit(" % of ", 1)[1].split()[0])
    share = (int(counts["few_neighbors"]) + int(counts["ill_conditioned"])) / particle_steps
    assert shown == pytest.approx(100.0 * share, rel=1e-2) and share >= SKIPPED_FIT_SHARE
    assert f"{shown:.3g} % of the run's particle-steps" in warned[0]
    # Which body: the star's own share, in the warning and the summary.
    assert "by body, of its own particle-steps: 'star' " in warned[0], warned[0]
    assert "(by body, of its own: 'star' " in summary[0], summary[0]
    assert np.isfinite(shown)


@pytest.mark.parametrize("command", [["run"], ["fit", "--target", "TARGET", "--params", "yield_stress"],
                                     ["sweep", "--param", "yield_stress=100,200"]])
def test_each_command_refuses_a_scene_file_too_coarse_for_its_body_naming_spacing_and_scale(tmp_path, capsys, command):
    """A scene file whose box is one layer at its spacing: run, fit and sweep refuse it (exit
    2, before any output), naming the file's spacing and the option that resolves it (fit said
    'scale', its Python parameter, where --scale is 1). The fit reads its target first: the
    check launches kernels, and a bad target (a missing file, a force log's NaN row) is
    refused before any kernel runs."""
    path = tmp_path / "sheet.toml"
    path.write_text('[scene]\nspacing = 0.02\n[[bodies]]\nshape = "box"\nname = "sheet"\nmaterial = "clay"\n'
                    'center = [0, 0.5, 0]\nsize = [0.2, 0.02, 0.2]\n')
    np.savez(tmp_path / "t.npz", positions=np.zeros((2, 4, 3)))
    out = tmp_path / "out"
    args = [command[0], str(path), *[str(tmp_path / "t.npz") if a == "TARGET" else a for a in command[1:]], "-o",
            str(out / "x.usdc" if command[0] == "run" else out), "--no-progress"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {path}: [scene] spacing = 0.02 is not allowed: body "
                                               "'sheet' is under-resolved"), err
    assert err[0].endswith("the largest spacing that resolves it is 0.01 (--scale 2)")
    assert not out.exists()


def test_a_sweep_sample_too_coarse_for_the_fit_says_so_in_its_row():
    """A sweep's rows keep each sample's warnings: the star at scale 0.5 (its tips too narrow
    for the fit) says the share and that a larger scale resolves it, where the row held only
    its guard counts."""
    from warp_esph.sweep import sweep

    table = sweep("star", ["yield_stress=100"], frames=1, workers=1, scale=0.5)
    row = table.rows[0]
    assert row["status"] == "ok", row
    assert "deformation fit was skipped in" in row.get("warnings", "") and "a larger scale" in row["warnings"], row


def test_get_scene_and_load_scene_in_a_fresh_process_print_nothing_of_warps(tmp_path):
    """get_scene's resolution check starts Warp: a script that had not called init_warp saw
    Warp's banner, its missing-CUDA note and a line per kernel module the check loaded. Nothing
    of Warp's is printed now, and the script's own log level is left as it was."""
    from run_files import run_script

    script = tmp_path / "look.py"
    script.write_text("import warp as wp\n"
                      "import warp_esph as we\n"
                      "from warp_esph.scenes import get_scene, load_scene\n"
                      "level = wp.config.log_level\n"
                      "get_scene('star')\n"
                      "load_scene('lab_squeeze_flow')\n"
                      "assert wp.config.log_level == level, (wp.config.log_level, level)\n")
    done = run_script(script, tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "" and done.stderr == "", (done.stdout, done.stderr)


def test_the_resolution_check_builds_only_the_rest_guards_and_keeps_finalizes_overlap_refusal(monkeypatch):
    """The check built a whole model for the guards of the rest neighbourhoods: the rest
    density's search and the overlap check were 60 % of its cost (1.2 s of Fig. 7 at scale 1).
    It leaves both out on a resolved scene, and a scene both under-resolved and overlapping
    is still left to finalize's overlap refusal, as it was."""
    from warp_esph import scenes
    from warp_esph.model import Model

    calls = {"density": 0, "overlap": 0}
    density, overlap = Model.compute_rest_density, we.SceneBuilder._check_overlap

    def counted_density(self):
        calls["density"] += 1
        return density(self)

    def counted_overlap(self):
        calls["overlap"] += 1
        return overlap(self)

    monkeypatch.setattr(Model, "compute_rest_density", counted_density)
    monkeypatch.setattr(we.SceneBuilder, "_check_overlap", counted_overlap)
    block = we.SceneBuilder(spacing=0.02)
    block.add_box((0.0, 0.1, 0.0), (0.08, 0.08, 0.08), we.Material.preset("clay"), name="a")
    block.add_box((0.3, 0.1, 0.0), (0.08, 0.08, 0.08), we.Material.preset("clay"), name="b")
    assert scenes.unresolved_bodies(block) == []
    assert calls == {"density": 0, "overlap": 0}

    sheets = we.SceneBuilder(spacing=0.02)
    sheets.add_box((0.0, 0.1, 0.0), (0.1, 0.02, 0.1), we.Material.preset("clay"), name="sheet")
    sheets.add_box((0.0, 0.1, 0.0), (0.1, 0.02, 0.1), we.Material.preset("clay"), name="on_it")
    with pytest.raises(ValueError, match="overlap"):
        sheets.finalize()
    assert scenes.unresolved_bodies(sheets) == []  # finalize's refusal, in the caller's words
    apart = we.SceneBuilder(spacing=0.02)
    apart.add_box((0.0, 0.1, 0.0), (0.1, 0.02, 0.1), we.Material.preset("clay"), name="sheet")
    assert [b[0] for b in scenes.unresolved_bodies(apart)] == ["sheet"]


def test_each_worlds_bodies_count_their_own_skipped_fits():
    """With worlds each world's copy of a body is a body of its own ('w1/sheet'): its skipped
    fits are counted there, not at world 0's copy."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.1, 0.0), (0.1, 0.02, 0.1), we.Material.preset("clay"), name="sheet")
    b.add_box((0.3, 0.1, 0.0), (0.08, 0.08, 0.08), we.Material.preset("clay"), name="block")
    model = b.finalize(worlds=2)
    solver = we.Solver(model)
    state_in, state_out = model.state(), model.state()
    solver.step(state_in, state_out, 0.5 * model.stable_dt())
    sheet = next(x for x in model.bodies if x.name == "w1/sheet").count
    assert solver.skipped_fits() == {"w0/sheet": sheet, "w0/block": 0, "w1/sheet": sheet, "w1/block": 0}
