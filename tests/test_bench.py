"""The step benchmark runs at a tiny size and writes every section of its JSON report."""

import contextlib
import json
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import step  # noqa: E402


def test_tiny_benchmark_writes_the_expected_json(tmp_path):
    out = tmp_path / "bench.json"
    argv = ["--sizes", "500", "--devices", "cpu", "--steps", "2", "--warmup", "1", "--blocks", "1",
            "--phase-steps", "1", "--taped-steps", "2", "--taped-repeats", "1", "--no-splishsplash", "--ground-images",
            "--json", str(out)]
    assert step.main(argv) == 0
    report = json.loads(out.read_text())
    for key in ("command", "machine", "config", "paper", "warp_esph", "splishsplash", "ratios"):
        assert key in report, key
    assert report["splishsplash"]["available"] is False
    r = report["warp_esph"]["cpu"]["500"]
    assert r["particles"] == 512 and r["finite"]
    assert r["forward"]["particle_steps_per_second"] > 0
    assert set(r["phases_fused"]["ms_per_step"]) == {"neighbors", "fused", "integrate", "deformation"}
    assert {"neighbors", "constitutive", "forces", "pressure", "integrate", "deformation"} <= set(
        r["phases_differentiable"]["ms_per_step"])
    assert r["forward_backward"]["particle_steps_per_second"] > 0 and r["forward_backward"]["gradients_finite"]
    for key in ("forward_bytes_per_particle", "model_and_two_states_bytes_per_particle",
                "taped_state_bytes_per_particle_per_step"):
        assert r["memory"][key] > 0
    ratio = report["ratios"]["cpu"]["500"]
    assert ratio["vs_splishsplash"] is None and ratio["vs_paper_fig1"] > 0 and ratio["vs_paper_fig5"] > 0
    images = report["ground_images"]["cpu"]["500"]
    assert images["plain"]["particle_steps_per_second_best_block"] > 0
    assert images["images_over_plain"]["particle_steps_per_second_best_block"] == pytest.approx(
        images["images"]["particle_steps_per_second_best_block"] / images["plain"]["particle_steps_per_second_best_block"])
    assert images["frictionless_images_over_plain"]["particle_steps_per_second_best_block"] == pytest.approx(
        images["frictionless_images"]["particle_steps_per_second_best_block"]
        / images["plain"]["particle_steps_per_second_best_block"])
    paper = report["paper"]
    assert 35e3 < paper["fig1"]["particle_steps_per_second"] < 37e3
    assert 45e3 < paper["fig5"]["particle_steps_per_second"] < 47e3


def test_fit_weight_option_reaches_the_benchmarked_models(tmp_path):
    """``--fit-weight`` names the weight of every model the main benchmark times (the fused
    forward and the taped window), and ``--fit-weights`` times the taped forward + backward
    window of each weight beside the forward rates: the benchmark behind the cost of a
    switch of the default (docs/physics.md, "The fit weight's default: the evidence")."""
    from warp_esph.sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS

    other = next(w for w in FIT_WEIGHTS if w != DEFAULT_FIT_WEIGHT)
    out = tmp_path / "bench.json"
    argv = ["--sizes", "64", "--devices", "cpu", "--steps", "1", "--warmup", "1", "--blocks", "1",
            "--phase-steps", "1", "--taped-steps", "1", "--taped-repeats", "1", "--no-splishsplash", "--fit-weights",
            "--fit-weight", other, "--json", str(out)]
    assert step.main(argv) == 0
    report = json.loads(out.read_text())
    assert report["config"]["fit_weight"] == other
    r = report["warp_esph"]["cpu"]["64"]
    assert r["fit_weight"] == other and r["forward_backward"]["fit_weight"] == other
    taped = report["fit_weights"]["cpu"]["64"]["taped"]
    assert {w: taped[w]["fit_weight"] for w in ("poly6", "biweight")} == {"poly6": "poly6", "biweight": "biweight"}
    assert all(taped[w]["backward_ms_per_step"] > 0 and taped[w]["backward_cpu_ms_per_step"] > 0
               and taped[w]["gradients_finite"] for w in ("poly6", "biweight"))
    assert taped["biweight_over_poly6"]["backward_ms_per_step"] == pytest.approx(
        taped["biweight"]["backward_ms_per_step"] / taped["poly6"]["backward_ms_per_step"])


def test_floors_benchmark_times_every_floor_against_the_particle_floor(tmp_path):
    """``benchmarks.floors`` at a tiny size: every floor of the validation suite (and the
    particle floor's non-fused step, and with ``--reach`` its step that runs the floor
    particles out of reach too) as a ratio to the particle floor's fused step, and the taped
    float64 window of the particle and ghost floors."""
    from benchmarks import floors, validation

    out = tmp_path / "floors.json"
    report = floors.main(["--resolution", "4", "--steps", "2", "--warmup", "1", "--repeat", "1", "--taped",
                          "--taped-steps", "1", "--reach", "--json", str(out)])
    assert json.loads(out.read_text()) == report
    assert set(report["forward"]) == set(validation.FLOORS) | {"particles (non-fused)", "particles (every pass)"}
    # The floor under 3.2 R0 reaches far past the 4-across cylinder's support radius.
    assert report["forward"]["particles"]["left_out"] > 0 == report["forward"]["particles (every pass)"]["left_out"]
    assert report["forward"]["particles"]["ratio"] == 1.0
    assert all(r["s_per_step"] > 0 for r in report["forward"].values())
    assert set(report["taped"]) == {"particles", "ghost_particles"}
    assert all(v > 0 for r in report["taped"].values() for v in r.values())


def test_launches_benchmark_times_the_replayed_step_against_plain_launches(tmp_path):
    """``benchmarks.launches`` at a tiny size: the three scenes, each step timed with the
    launches replayed, replayed with the argument struct filled again at every call, and
    through ``wp.launch``."""
    from benchmarks import launches

    out = tmp_path / "launches.json"
    report = launches.main(["--sizes", "27", "--steps", "2", "--blocks", "1", "--warmup", "2", "--json", str(out)])
    assert json.loads(out.read_text()) == report
    assert [r["scene"] for r in report["rows"]] == ["ground", "particle floor", "taped press (float64)"]
    assert all(r["plain_ms"] > 0 and r["rebuilt_ms"] > 0 and r["replayed_ms"] > 0 for r in report["rows"])
    assert all(r["kept_struct_speedup"] == pytest.approx(r["rebuilt_ms"] / r["replayed_ms"]) for r in report["rows"])


def test_gradient_benchmark_profiles_every_kernel_of_the_step_and_of_its_backward():
    """``benchmarks.gradient_bench --profile``: every kernel the fused forward and the
    backward pass launch is in the profile, the replayed ones (``sim/replay.py``, which
    bypass ``wp.launch``: every launch of the step and the hand-written adjoints) as well as
    those through ``wp.launch`` (the generated adjoint of the integration). The profile had
    timed ``wp.launch`` alone, and printed an empty forward and a backward of the
    integration's adjoint alone."""
    import warp as wp

    from benchmarks import gradient_bench
    from benchmarks.blocks import block_model

    r = gradient_bench.measure(block_model(27, wp.float64), steps=2, repeats=1, profile=True)
    fused, backward = r["fused_launch_ms_per_step"], r["adjoint_ms_per_step"]
    assert {"constitutive_forces", "update_deformation", "select_neighbors", "integrate"} <= set(fused), fused
    # (The pressure's pairs are taken in variational_forces_adjoint's pass.)
    assert {"variational_forces_adjoint", "update_deformation_adjoint", "constitutive_update_adjoint", "density_adjoint",
            "integrate (generated adjoint)"} <= set(backward), backward


def test_gradient_benchmark_times_the_steps_memos_off_and_on_and_puts_them_back():
    """``benchmarks.gradient_bench --step-memos``: the star's fused forward, taped forward and
    backward with the step's two memos off and on (docs/performance.md) give the same bits,
    and the memos are on again after it."""
    import warp as wp

    from benchmarks import gradient_bench
    from warp_esph.model import Model, State

    kept = State.BOOKKEEPING, Model._answer
    r = gradient_bench.step_memos(gradient_bench.star_model(wp.float64), steps=3, blocks=1)
    assert r["same_bits"]
    assert all(r[k]["off_ms"] > 0.0 and r[k]["on_ms"] > 0.0 for k in ("fused", "taped", "backward", "gradient")), r
    assert (State.BOOKKEEPING, Model._answer) == kept


def test_gradient_benchmark_times_the_kept_launch_records_off_and_on_and_puts_them_back(monkeypatch):
    """``benchmarks.gradient_bench --kept-records``: the star's passes with a taped step's kept
    launch records off (its launches repacked in the shared slots) and on give the same bits,
    the off blocks keep no records, and the step keeps them again after it."""
    import warp as wp

    from benchmarks import gradient_bench
    from warp_esph.sim import replay
    from warp_esph.sim.solver import Solver

    step = Solver.step
    model = gradient_bench.star_model(wp.float64)
    without, kept_in = gradient_bench._without_kept_records, replay.Launches.keep_in
    off, kept = [False], []

    @contextlib.contextmanager
    def marked(turned_off):
        off[0] = turned_off
        with without(turned_off):
            yield
        off[0] = False

    monkeypatch.setattr(gradient_bench, "_without_kept_records", marked)
    monkeypatch.setattr(replay.Launches, "keep_in", lambda self, records: kept.append(
        (off[0], records is not None)) or kept_in(self, records))
    r = gradient_bench.kept_records(model, steps=3, blocks=1)
    assert r["same_bits"]
    assert all(r[k]["off_ms"] > 0.0 and r[k]["on_ms"] > 0.0 for k in ("fused", "taped", "backward", "gradient")), r
    # Switched to a step's records in the blocks with them on, never in the blocks with them off.
    assert any(switched and not was_off for was_off, switched in kept)
    assert not any(switched and was_off for was_off, switched in kept)
    assert Solver.step is step


@pytest.fixture(scope="module")
def loss_only_bench(tmp_path_factory):
    """``benchmarks.fit_bench --loss-only`` at a tiny size, run once for the two tests that
    read it (each ran it alone): its rows, and per call of ``fit`` whether its runs were taped
    and how many forward runs it made (counted by wrappers that call through unchanged)."""
    from benchmarks import fit_bench
    from warp_esph import fit as fit_module

    forward, fit = fit_module._Run.forward, fit_module.fit
    ran, per_fit = [0], []

    def counted(self, *args, **kwargs):
        ran[0] += 1
        return forward(self, *args, **kwargs)

    def counted_fit(*args, **kwargs):
        ran[0] = 0
        result = fit(*args, **kwargs)
        per_fit.append((fit_module._Run.tape_values, ran[0]))
        return result

    out = tmp_path_factory.mktemp("fit_bench") / "fit_bench.json"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fit_module._Run, "forward", counted)
        mp.setattr(fit_module, "fit", counted_fit)
        assert fit_bench.main(["--loss-only", "--particles", "27", "--steps", "4", "--repeats", "1", "--json", str(out)]) == 0
    return json.loads(out.read_text())["rows"], per_fit


def test_fit_benchmark_times_a_fits_loss_only_runs_untaped_against_taped(loss_only_bench):
    """``benchmarks.fit_bench --loss-only`` at a tiny size: a Gauss-Newton fit (every run loss
    only) and an L-BFGS fit (its diagnostics' runs loss only), each timed with those runs
    untaped and taped, and the two histories equal."""
    rows, _ = loss_only_bench
    assert [r["optimizer"] for r in rows] == ["gauss-newton", "lbfgs"]
    assert all(r["same_history"] for r in rows)
    gauss, lbfgs = rows
    assert gauss["gradient_runs"] == 0 and gauss["loss_only_runs"] == gauss["forward_runs"]
    assert 0 < lbfgs["gradient_runs"] < lbfgs["forward_runs"]
    assert all(r["cpu_ratio"] == pytest.approx(r["untaped_cpu_s"] / r["taped_cpu_s"]) for r in rows)


def test_fit_benchmark_times_lbfgs_fits_whose_rejected_trials_run_no_backward_unread(tmp_path, monkeypatch):
    """``benchmarks.fit_bench --rejected`` at a tiny size and one start: the fit whose rejected
    trials run their backward only where it is read runs fewer backwards than the same fit
    with every trial's, to the same points, verdict and diagnostics, bit for bit."""
    from benchmarks import fit_bench

    monkeypatch.setattr(fit_bench, "REJECTED_FACTORS", (1.0001,))
    out = tmp_path / "fit_bench.json"
    assert fit_bench.main(["--rejected", "--particles", "27", "--steps", "20", "--repeats", "1", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())["rows"]
    assert row["same_fit"] and row["stopped"] == "converged"
    assert row["backwards_before"] == row["evaluations"] > row["backwards_now"] > 0
    assert row["cpu_ratio"] == pytest.approx(row["cpu_now_s"] / row["cpu_before_s"])


def test_fit_benchmark_times_worlds_fits_whose_rounds_of_unread_trials_run_no_backward(tmp_path, monkeypatch):
    """``benchmarks.fit_bench --rejected --starts 2`` at a tiny size: worlds fits of two starts
    1e-7 apart run fewer backwards than with every round's, to the same fit, bit for bit."""
    from benchmarks import fit_bench

    monkeypatch.setattr(fit_bench, "REJECTED_FACTORS", (1.0001,))
    out = tmp_path / "fit_bench.json"
    assert fit_bench.main(["--rejected", "--starts", "2", "--sample-range", "1.0000001", "--particles", "27", "--steps",
                           "20", "--repeats", "1", "--json", str(out)]) == 0
    (row,) = json.loads(out.read_text())["rows"]
    assert row["same_fit"] and row["starts"] == 2 and row["sample_range"] == 1.0000001
    assert row["backwards_before"] == row["evaluations"] > row["backwards_now"] > 0


@pytest.mark.parametrize("argv, said", [
    (["--starts", "2"], "--starts = 2 is not allowed without --rejected"),
    (["--rejected", "--sample-range", "2"], "--sample-range = 2 is not allowed without --starts > 1"),
    (["--rejected", "--starts", "2", "--sample-range", "1"], "--sample-range"),
])
def test_fit_benchmark_refuses_starts_it_does_not_run(argv, said, capsys):
    from benchmarks import fit_bench

    with pytest.raises(SystemExit) as e:
        fit_bench.main(argv)
    assert e.value.code == 2 and said in capsys.readouterr().err


def test_fit_benchmarks_loss_only_rows_count_the_runs_that_ran(loss_only_bench):
    """``forward_runs`` of ``fit_bench --loss-only`` is what its fit ran: it added two runs of
    the diagnostics at the fitted point to ``Diagnostics.evaluations``, which had come to
    count them itself (and then no longer made them)."""
    rows, per_fit = loss_only_bench
    # Per optimizer: two warm-ups and one timed pair; the row's counts are the untaped fit's.
    untaped = [n for taped, n in per_fit if not taped]
    assert len(untaped) == 2 * len(rows)
    assert [r["forward_runs"] for r in rows] == untaped[1::2]


def test_noise_estimate_benchmark_reads_the_variance_n_over_n_minus_p_above_the_rms(capsys, monkeypatch):
    """``python -m benchmarks.noise_estimate`` (two draws here): the estimate the diagnostics
    use, sqrt(SSR / (N - P)), is the residuals' RMS times sqrt(N / (N - P)) in every draw,
    so the mean variances it prints stand in that ratio; bad options are refused by name.
    Both are read from one SSR, so the ratio holds wherever a fit stops: each draw's fit runs
    one Gauss-Newton iteration here (of the benchmark's 15), its diagnostics as after 15."""
    import re

    from benchmarks import noise_estimate

    fit, iterations = noise_estimate.fit, []

    def one_iteration(*args, **kwargs):
        iterations.append(kwargs["iterations"])
        return fit(*args, **dict(kwargs, iterations=1))

    monkeypatch.setattr(noise_estimate, "fit", one_iteration)
    noise_estimate.main(["--draws", "2"])
    assert iterations == [15, 15]  # the benchmark's own fits, shortened here
    out = capsys.readouterr().out
    n, p = (int(v) for v in re.search(r"N = (\d+) residuals, P = (\d+)", out).groups())
    new, old = (float(v) for v in re.search(r"\(N-P\)\) ([\d.]+) \+- [\d.]+, RMS \(before\) ([\d.]+)", out).groups())
    assert (n, p) == (24, 2)
    assert new / old == pytest.approx(n / (n - p), rel=3e-3)  # the printed 3 decimals
    with pytest.raises(SystemExit):
        noise_estimate.main(["--draws", "1"])
    assert "--draws = 1 is not allowed" in capsys.readouterr().err
