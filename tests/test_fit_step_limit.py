"""A fit whose evaluations ran past the stable step says so: ``FitResult.step_limit``,
fit.json's ``step_limit`` and the command's summary. The step a fit chooses (``dt=None``)
is the guess's stable step; a descent toward stiffer values runs past it."""

import json

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.cli import EXIT_NOT_CONVERGED
from warp_esph.fit import fit
from warp_esph.rollout import Rollout

STEPS = 30


def _cube(mu, lam=None):
    """27 particles of an elastic-plastic cube landing at 1 m/s, float64 (lam: 1.5 mu)."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.035, 0.0), (0.06, 0.06, 0.06), we.Material(mu=mu, lam=1.5 * mu if lam is None else lam, density=1000.0,
              yield_stress=300.0, flow_rate=10.0), velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model


@pytest.mark.filterwarnings("ignore:dt = .* is above the explicit stability limit:RuntimeWarning")
def test_a_fit_that_descends_stiffer_than_its_guess_reports_how_far_past_the_stable_step_it_ran():
    """The guess at half the true mu sets the step; the descent toward the truth runs at
    stiffer values. ``step_limit`` is the evaluation furthest past its stable step, checked
    against ``Model.stable_dt`` of a model built at every evaluated value."""
    guess = _cube(1e3)
    dt = guess.stable_dt()
    # The truth at half the step, twice the steps: the same time at the truth's stable step.
    target = Rollout(_cube(2e3), 2 * STEPS, 0.5 * dt, frames=[2 * STEPS]).forward()
    result = fit(guess, target, ["mu"], steps=STEPS, frames=[STEPS], optimizer="lbfgs", iterations=6, progress=False,
                 diagnostics=False)
    assert result.params["mu"][0] > 1.2e3  # it went stiffer than the guess
    # The fit moves mu alone: lam stays the guess's.
    ratios = [(dt / _cube(h["params"]["mu"][0], lam=1.5e3).stable_dt(), h) for h in result.history]
    furthest, entry = max(ratios, key=lambda t: t[0])
    assert furthest > 1.05
    s = result.step_limit
    assert s["dt"] == pytest.approx(dt, rel=1e-12, abs=0.0)
    assert s["dt_over_stable"] == pytest.approx(furthest, rel=1e-9)
    assert s["stable_dt"] == pytest.approx(dt / furthest, rel=1e-9)
    assert s["params"] == entry["params"] and s["iteration"] == entry["iteration"]
    said = result.step_limit_said()
    assert f"{furthest:.3g} x the stable step" in said and f"mu = {entry['params']['mu'][0]:.4g}" in said
    assert result.to_dict()["step_limit"]["dt_over_stable"] == s["dt_over_stable"]


def test_a_fit_within_its_stable_step_records_its_margin_and_says_nothing():
    """Toward softer values the guess's step holds: the furthest evaluation is at the guess
    (ratio 1 to rounding) and nothing is said."""
    guess = _cube(2e3)
    target = Rollout(_cube(1e3), STEPS, 0.5 * guess.stable_dt(), frames=[STEPS]).forward()
    result = fit(guess, target, ["mu"], steps=STEPS, frames=[STEPS], dt=0.5 * guess.stable_dt(), optimizer="lbfgs",
                 iterations=3, progress=False, diagnostics=False)
    assert result.step_limit["dt_over_stable"] == pytest.approx(0.5, rel=1e-9)
    assert result.step_limit_said() == ""


def test_the_command_says_in_its_summary_and_fit_json_that_evaluations_ran_past_the_stable_step(tmp_path, capsys,
                                                                                                 dough_scene):
    """``warp-esph fit --params mu`` from a guess at half the true stiffness, its step the
    guess's stable step: the summary's warning and fit.json's ``step_limit`` name the ratio."""
    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2))
    guess.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2).replace("mu = 2000.0\nlam = 3000.0",
                                                                                       "mu = 1000.0\nlam = 1500.0"))
    assert "mu = 1000.0" in guess.read_text()
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["fit", str(guess), "--target", str(run), "--params", "mu", "--optimizer", "lbfgs", "--iterations", "4",
                 "--no-usd", "--no-progress", "--no-diagnostics", "--output-dir", str(tmp_path / "o")]) == EXIT_NOT_CONVERGED
    out = capsys.readouterr().out
    record = json.loads((tmp_path / "o" / "fit.json").read_text())["step_limit"]
    assert record["dt_over_stable"] > 1.0 + 1e-6, record
    assert f"warning: dough_block: evaluations ran past the stable step: dt = {record['dt']:.4g} s is " \
           f"{record['dt_over_stable']:.3g} x the stable step {record['stable_dt']:.4g} s at mu = " \
           f"{record['params']['mu'][0]:.4g}" in out, out


@pytest.mark.filterwarnings("ignore:dt = .* is above the explicit stability limit:RuntimeWarning")
def test_an_interrupted_fit_records_how_far_past_the_stable_step_its_evaluations_ran():
    """Ctrl-C (a KeyboardInterrupt from the callback) after the descent went stiffer than the
    guess: the interrupted result, which ``warp-esph fit`` writes to fit.json as a finished
    one's, holds the same ``step_limit`` over the evaluations that ran, not None."""
    guess = _cube(1e3)
    dt = guess.stable_dt()
    target = Rollout(_cube(2e3), 2 * STEPS, 0.5 * dt, frames=[2 * STEPS]).forward()

    def interrupt(evaluation, loss, params):
        if params["mu"][0] > 1.2e3:  # stiffer than the guess: past its step
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        fit(guess, target, ["mu"], steps=STEPS, frames=[STEPS], optimizer="lbfgs", iterations=6, progress=False,
            diagnostics=False, callback=interrupt)
    result = info.value.result
    assert result is not None and result.stopped == "interrupted"
    ratios = [dt / _cube(h["params"]["mu"][0], lam=1.5e3).stable_dt() for h in result.history]
    assert max(ratios) > 1.05
    assert result.step_limit is not None
    assert result.step_limit["dt_over_stable"] == pytest.approx(max(ratios), rel=1e-9)
    assert "x the stable step" in result.step_limit_said()
    assert result.to_dict()["step_limit"] == result.step_limit
