"""Multi-start fits over worlds (``fit(..., starts=K, worlds=True)``): the K starts run as
K worlds of one model, each with its own optimiser, and must make exactly the evaluations
that K separate starts, one after the other, make."""

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.cli import EXIT_NOT_CONVERGED
from warp_esph.fit import fit
from warp_esph.losses import PositionLoss, SlumpLoss
from warp_esph.rollout import Rollout

STEPS, DT, FRAMES = 50, 1.0e-3, [25, 50]


@pytest.fixture(scope="module")
def target(dropped_cube):
    return Rollout(dropped_cube(100.0, 10.0, size=0.06), STEPS, DT, frames=FRAMES).forward()


def _fit(dropped_cube, target, optimizer, worlds, **kw):
    return fit(dropped_cube(200.0, 20.0, size=0.06), PositionLoss(target, frames=FRAMES), ["yield_stress", "flow_rate"], steps=STEPS, dt=DT,
               iterations=3, optimizer=optimizer, progress=False, starts=3, worlds=worlds, diagnostics=False, seed=2, **kw)


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_worlds_make_the_evaluations_of_separate_starts(dropped_cube, target, optimizer):
    """Every start's losses, gradients and parameters, evaluation by evaluation, equal those
    of the same start run alone, bit for bit on the CPU (the tests' device), L-BFGS's line
    search included; the result is the best start's."""
    seq, par = _fit(dropped_cube, target, optimizer, False), _fit(dropped_cube, target, optimizer, True)
    key = lambda h: (h["start"], h["iteration"])  # noqa: E731
    a, b = sorted(seq.history, key=key), sorted(par.history, key=key)
    assert len(a) == len(b) and {h["start"] for h in a} == {0, 1, 2}
    by_start = [[h for h in a if h["start"] == s] for s in range(3)]
    assert all(len(h) >= 2 for h in by_start)
    # The starts are different points: the guess and two Latin-hypercube points.
    firsts = [h[0]["params"]["yield_stress"][0] for h in by_start]
    assert firsts[0] == pytest.approx(200.0, rel=1e-12) and len(set(firsts)) == 3
    for x, y in zip([h for s in by_start for h in s], sorted(b, key=lambda h: (h["start"], h["iteration"]))):
        assert y["loss"] == x["loss"]
        np.testing.assert_array_equal(y["grad"], x["grad"])
        assert y["params"] == x["params"]
    assert par.starts == seq.starts
    assert par.loss == seq.loss
    best = min(h["loss"] for h in a)
    assert par.loss == best
    for name in ("yield_stress", "flow_rate"):
        assert par.params[name][0] == pytest.approx(seq.params[name][0], rel=1e-12)
        # The returned model holds the winner's values (one world, like a plain fit).
        assert par.model.world_count == 1
        assert getattr(par.model, name).numpy()[0] == pytest.approx(par.params[name][0], rel=1e-12)


def test_a_round_of_rejected_lbfgs_trials_whose_slopes_nothing_reads_runs_no_backward(dropped_cube, target,
                                                                                      monkeypatch):
    """A worlds round ran every world's backward, each start's gradient taken whether its
    optimiser read it or not; a single fit's rejected L-BFGS trial runs its backward only where
    its slope may decide the minimum-within test. A round whose every start is such a trial (or
    refused) now runs none, and the fit is the same to the bit: two starts 1e-7 apart (in log)
    near the answer, whose line searches reject their trials in the same rounds."""
    from warp_esph import fit as fit_module

    def run(mode):
        monkeypatch.setattr(fit_module, "LBFGS_TRIAL_BACKWARDS", mode)
        return fit(dropped_cube(100.0 * 1.0001, 10.0 * 1.0001, size=0.06), PositionLoss(target, frames=FRAMES),
                   ["yield_stress", "flow_rate"], steps=STEPS, dt=DT, iterations=30, optimizer="lbfgs", progress=False,
                   starts=2, worlds=True, sample_range=1.0000001, diagnostics=False)

    old, new = run("always"), run("read")
    assert old.starts == new.starts == ["converged", "converged"]
    assert len(old.history) == len(new.history)
    for a, b in zip(old.history, new.history):
        assert (a["params"], a["loss"], a["start"]) == (b["params"], b["loss"], b["start"])
        assert a["grad"] is not None and (b["grad"] is None or b["grad"] == a["grad"])
    # Whole rounds (recorded start after start): each start's evaluation of the round without its gradient.
    skipped = [k for k, h in enumerate(new.history) if h["grad"] is None]
    assert len(skipped) >= 4 and skipped[::2] == [k - 1 for k in skipped[1::2]]
    assert [new.history[k]["start"] for k in skipped] == [0, 1] * (len(skipped) // 2)
    assert new.loss == old.loss and all(np.array_equal(new.params[n], old.params[n]) for n in new.params)


def test_replicated_worlds_match_the_model(dropped_cube):
    """``replicate_worlds``: every world is the model (positions, parameters, rest density),
    and its rollout gives each world the model's positions."""
    model = dropped_cube(150.0, 15.0, size=0.06)
    model.yield_stress.assign(np.array([123.0]))  # a value the fit wrote: arrays, not materials
    three = we.replicate_worlds(model, 3)
    assert three.world_count == 3 and three.particle_count == 3 * model.particle_count
    np.testing.assert_array_equal(three.yield_stress.numpy(), [123.0] * 3)
    np.testing.assert_array_equal(three.particle_rest_density.numpy(), np.tile(model.particle_rest_density.numpy(), 3))
    one = Rollout(model, 20, DT, frames=[20]).forward()[0]
    many = Rollout(three, 20, DT, frames=[20]).forward()[0]
    for w in range(3):
        np.testing.assert_allclose(many[three.world_particles(w)], one, rtol=0.0, atol=1e-12)


def test_worlds_refuse_what_they_cannot_replicate(dropped_cube, target):
    model = dropped_cube(200.0, 20.0, size=0.06)
    loss = SlumpLoss(0.05, 0.05, STEPS, 0.02)
    with pytest.raises(ValueError, match="worlds=True is not allowed with SlumpLoss"):
        fit(model, loss, ["yield_stress"], steps=STEPS, dt=DT, iterations=1, starts=2, worlds=True, progress=False,
            diagnostics=False)
    with pytest.raises(ValueError, match="worlds = 0 is not allowed"):
        we.replicate_worlds(model, 0)


def test_replicate_worlds_refuses_more_worlds_than_finalize_or_memory_allow(dropped_cube, monkeypatch):
    """``replicate_worlds(model, 10**9)`` had neither ``finalize(worlds=)``'s cap nor its memory
    check: it spent minutes building the list of bodies (killed after 2 min)."""
    from warp_esph import builder

    model = dropped_cube(200.0, 20.0, size=0.06)
    with pytest.raises(ValueError, match=r"worlds = 1000000000 is not allowed: must be at most 100000"):
        we.replicate_worlds(model, 10**9)
    monkeypatch.setattr(builder, "_device_memory", lambda dev: 100 * 2**10)  # room for one copy, not two
    # (It said 'is not allowed' twice: 'worlds = 2 is not allowed: particles = 128 is not allowed on cpu: ...'.)
    with pytest.raises(ValueError, match=r"^worlds = 2 is not allowed on cpu: a model and two states of their \d+ particles "
                                         r"need about .* more than the 9.54e-05 GiB available; use fewer worlds, a larger spacing or "
                                         r"smaller bodies$"):
        we.replicate_worlds(model, 2)


def test_cli_starts_as_worlds(tmp_path, capsys, dough_scene):
    """``warp-esph fit --starts 3 --worlds``: three starts, one model of three worlds; the
    JSON has one history per start and the best start's result."""
    import json

    pytest.importorskip("pxr")
    from warp_esph.cli import main

    truth, guess = tmp_path / "truth.toml", tmp_path / "guess.toml"
    truth.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2))
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    run = tmp_path / "run.usdc"
    assert main(["run", str(truth), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    out = tmp_path / "fit"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(run), "--target-body", "dough", "--target-frames", "1,2",
                   "--iterations", "2", "--starts", "3", "--worlds", "--optimizer", "adam", "--output-dir", str(out),
                   "--no-progress", "--no-usd", "--no-diagnostics"])
    captured = capsys.readouterr()
    assert status == EXIT_NOT_CONVERGED, captured.err  # the cap of 2
    assert "3 starts as 3 worlds" in captured.err
    doc = json.loads((out / "fit.json").read_text())
    assert len(doc["starts"]) == 3
    descent = [h for h in doc["history"] if h["stage"] == "descent"]
    assert sorted({h["start"] for h in descent}) == [0, 1, 2] and len(descent) == 9
    assert doc["loss"] == min(h["loss"] for h in descent)


@pytest.mark.slow
def test_multi_start_over_worlds_finds_what_the_guess_alone_misses():
    """A 64-particle block dropped at 1 m/s (yield stress 100 Pa, flow rate 10/s, 102 steps,
    three observed frames), guessed at 700 Pa and 75/s: L-BFGS from the guess alone stops in
    another valley of the loss, far from the truth; seven more Latin-hypercube starts, run as
    worlds of the same model, reach the truth. The guess's descent is start 0 (its evaluations
    are those of a fit from the guess alone: ``test_worlds_make_the_evaluations_of_separate_starts``).
    Measured on this code: start 0 ends at Y = 214.8, flow rate 10.90; with 4 starts the best
    also stops in a valley (111.7, 10.10); with 8 one start reaches 100.0000, 10.0000. (On the
    earlier spiky pressure force, start 0 climbed to 1410, 51 and 4 starts sufficed.)"""

    def block(yield_stress, flow_rate):
        b = we.SceneBuilder(spacing=0.02, support_radius=0.05)
        b.add_box((0.0, 0.045, 0.0), (0.08, 0.08, 0.08),
                  we.Material(mu=2e3, lam=3e3, density=1000.0, yield_stress=yield_stress, flow_rate=flow_rate,
                              viscosity=2.0), velocity=(0.0, -1.0, 0.0))
        b.add_ground(friction=0.5)
        return b.finalize(dtype=wp.float64, requires_grad=True)

    dt, steps, frames = 1.0 / (30 * 17), 102, [34, 68, 102]
    target = Rollout(block(100.0, 10.0), steps, dt, frames=frames).forward()
    result = fit(block(700.0, 75.0), PositionLoss(target, frames=frames), ["yield_stress", "flow_rate"], steps=steps,
                 dt=dt, iterations=20, optimizer="lbfgs", progress=False, starts=8, worlds=True, diagnostics=False,
                 seed=0, bounds={"yield_stress": (30.0, 3000.0), "flow_rate": (3.0, 300.0)}, sample_range=10.0)
    assert result.params["yield_stress"][0] == pytest.approx(100.0, rel=0.02)
    assert result.params["flow_rate"][0] == pytest.approx(10.0, rel=0.02)
    guess_alone = [h for h in result.history if h["start"] == 0]
    best_alone = min(guess_alone, key=lambda h: h["loss"])
    assert abs(best_alone["params"]["yield_stress"][0] / 100.0 - 1.0) > 0.5
    assert best_alone["loss"] > 1e3 * result.loss


def test_a_callback_that_stops_the_fit_stops_every_world_at_once(dropped_cube, target):
    """A callback's True on one start's evaluation let the other starts run one more round
    (a forward and backward pass of every world), recorded after the stop and eligible as the
    result; now the fit ends with that round, as one start after the other does."""
    seen = []

    def stop_at_third(k, value, params):
        seen.append(k)
        return k == 2

    result = _fit(dropped_cube, target, "adam", True, callback=stop_at_third)
    assert result.stopped == "callback"
    assert seen == [0, 1, 2] and len(result.history) == 3  # the three starts' first evaluations
    assert result.loss == min(h["loss"] for h in result.history)


def test_an_error_in_a_round_of_the_worlds_ends_the_fit_with_it(dropped_cube, target, monkeypatch):
    """An error raised while a round of the worlds was evaluated (a warning made an error,
    Ctrl-C) left the starts' threads waiting for that round's answers, and the fit waiting
    for them, for ever. The fit now ends with the error (here the second round's)."""
    import threading

    from warp_esph import fit as fit_module

    evaluate = fit_module._WorldsProblem.evaluate
    rounds = []

    def failing(self, batch, wants=None):
        rounds.append(sorted(batch))
        if len(rounds) == 2:
            raise RuntimeError("the second round failed")
        return evaluate(self, batch, wants)

    monkeypatch.setattr(fit_module._WorldsProblem, "evaluate", failing)
    raised = []

    def run():
        try:
            _fit(dropped_cube, target, "adam", True)
        except RuntimeError as e:
            raised.append(str(e))

    t = threading.Thread(target=run, daemon=True)
    t.start()
    # Generous: the two rounds compile the worlds' kernels where the cache is cold, which on a
    # loaded two-core machine took over 20 s (the fit was taken for hung); a hang still fails.
    t.join(timeout=300.0)
    assert not t.is_alive(), "the fit hung after the error"
    assert raised == ["the second round failed"] and rounds == [[0, 1, 2], [0, 1, 2]]


def _lockstep_two_starts(descend, recorded):
    """``fit._lockstep`` of two starts at 0, each run by ``descend`` (its optimiser), over fake
    worlds whose every evaluation is loss 1 with a zero gradient; the start of each evaluation
    recorded is appended to ``recorded``. What the fit does around the optimisers alone."""
    from warp_esph import fit as fit_module

    class Worlds:
        def evaluate(self, batch, wants=None):
            return {w: (1.0, np.zeros(1), 0.0, None) for w in batch}

    def record(track, z, value, gz, seconds, note):
        recorded.append(track)
        return value, gz, True

    return fit_module._lockstep([0, 1], [np.zeros(1)] * 2, descend, Worlds(), record)


def test_a_start_between_rounds_when_the_fit_stops_ends_with_it(monkeypatch):
    """Ctrl-C while the fit waited for the next round, with one start still computing its
    next point (answered, not yet asking), left that start out of the clean-up: it then
    asked, waited for an answer for ever, and the fit's join with it. It now gets a stop
    at once and the fit ends with the Ctrl-C. The interrupt is put into the round's wait,
    and the start asks only once the fit joins its threads (the race, made certain)."""
    import threading

    between, go = threading.Event(), threading.Event()
    recorded, asked_late, raised, main = [], [], [], []

    class InterruptedCondition(threading.Condition):
        def wait(self, timeout=None):
            if main and threading.current_thread() is main[0] and len(recorded) == 2:
                while not between.is_set():  # until the first start has its answer, and computes
                    super().wait(0.01)  # (this lets go of the lock the starts need to take theirs)
                raise KeyboardInterrupt
            return super().wait(timeout)

    class JoinedThread(threading.Thread):
        def join(self, timeout=None):
            go.set()
            return super().join(timeout)

    def descend(evaluate, z, track):
        evaluate(z)
        if track == 0:
            between.set()
            go.wait(5.0)
            try:
                evaluate(z)
            except BaseException as e:
                asked_late.append(type(e).__name__)
                raise
        else:
            evaluate(z)
        return "done"

    def run():
        try:
            _lockstep_two_starts(descend, recorded)
        except BaseException as e:  # noqa: BLE001
            raised.append(type(e).__name__)

    t = threading.Thread(target=run, daemon=True)
    main.append(t)
    monkeypatch.setattr(threading, "Condition", InterruptedCondition)
    monkeypatch.setattr(threading, "Thread", JoinedThread)
    t.start()
    t.join(timeout=2.0)
    assert not t.is_alive(), "the fit hung after Ctrl-C"
    assert raised == ["KeyboardInterrupt"] and asked_late == ["_Stop"] and recorded == [0, 1]


def test_an_error_in_one_start_ends_the_other_starts_at_the_next_round():
    """An error in one start's optimiser (raised in its thread) did not stop the fit: the
    other starts ran on to their end, every round a batched rollout, and only then was the
    error raised. It now ends the lockstep before the next round: the other start gets a
    stop and the error reaches the caller."""
    from warp_esph import fit as fit_module

    recorded, stopped = [], []

    def descend(evaluate, z, track):
        evaluate(z)
        if track == 0:
            raise ValueError("start 0 failed")
        try:
            for _ in range(5):
                evaluate(z)
        except fit_module._Stop as e:
            stopped.append(str(e))
            return str(e)
        return "done"

    with pytest.raises(ValueError, match="start 0 failed"):
        _lockstep_two_starts(descend, recorded)
    assert sorted(recorded) == [0, 1] and stopped == ["callback"]


def _elastic_drop(mu):
    """27 particles of an elastic block (stable step 2e-3 s at mu = 2 kPa) dropped at 1 m/s."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.055, 0.0), (0.06, 0.06, 0.06), we.Material(mu=mu, lam=1.5 * mu, density=1000.0),
              velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model


def test_a_start_that_blows_up_fails_alone_as_run_alone_and_its_world_stops_blowing_up(monkeypatch):
    """Three starts of mu (guess 4 kPa, truth 2 kPa) in a box a factor 1000 wide, at a dt of
    1e-3 s: start 2 begins at 2.8 MPa, 20 x past its stable step, and its block blows up
    (finite). As worlds, the healthy starts make the evaluations they make alone (nothing of
    the diverged world reaches another), the failed start is noted as alone (its particle
    named by its index in the one-world model: it was the worlds model's, 54 higher), and its
    world no longer reruns the values that blew up in every later round (each such round took
    4-5 x a healthy one's time, 3 worlds of 216 particles): it runs the guess."""
    import warnings

    from warp_esph import fit as fit_module

    steps, dt, frames = 60, 1e-3, [30, 60]
    target = Rollout(_elastic_drop(2e3), steps, dt, frames=frames).forward()
    ran = []  # the mu of every world, round by round
    apply = fit_module._Run.apply

    def spy(self, p):
        if self.model.world_count > 1:
            ran.append(np.array(p["mu"], dtype=np.float64))
        return apply(self, p)

    monkeypatch.setattr(fit_module._Run, "apply", spy)

    def run(worlds):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # dt past the stiff start's stable step
            return fit(_elastic_drop(4e3), PositionLoss(target, frames=frames), ["mu"], steps=steps, dt=dt,
                       iterations=3, progress=False, starts=3, worlds=worlds, diagnostics=False, seed=1,
                       sample_range=1e3)

    seq, par = run(False), run(True)
    assert seq.starts == par.starts == ["iterations", "iterations", "failed"]
    key = lambda h: (h["start"], h["iteration"])  # noqa: E731
    a, b = sorted(seq.history, key=key), sorted(par.history, key=key)
    assert [h["start"] for h in a] == [h["start"] for h in b]
    for x, y in zip(a, b):
        assert y["params"] == x["params"]
        assert y["loss"] == x["loss"]  # on the CPU, bit for bit (WorldLoss sums as the loss alone)
        np.testing.assert_array_equal(y["grad"], x["grad"])
        assert y.get("note") == x.get("note")
    failed = [h for h in b if h["start"] == 2]
    assert len(failed) == 1 and failed[0]["loss"] == np.inf and failed[0]["params"]["mu"][0] > 1e6
    assert failed[0]["note"].startswith("diverged: ") and "(particle " in failed[0]["note"]
    assert int(failed[0]["note"].split("(particle ")[1].split(",")[0]) < 27
    # Round 1 ran the failing values; every later round runs the guess in that world.
    assert len(ran) == 4 and ran[0][2] == failed[0]["params"]["mu"][0]
    assert [r[2] for r in ran[1:]] == [pytest.approx(4e3, rel=1e-12)] * 3
