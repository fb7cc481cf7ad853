"""A fit whose data carry no information about its values says so, by every optimiser and in
both precisions, and is never reported as converged; a fit started at the values that made
an informative target still is."""

import json
import math

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.cli import EXIT_NOT_CONVERGED
from warp_esph.fit import fit
from warp_esph.rollout import Rollout

STEPS = 30
FRAMES = [15, 30]
TRUTH = {"mu": 2e3, "yield_stress": 300.0, "flow_rate": 10.0}


def _falling(dtype, factor=1.0):
    """27 particles of a plastic cube in free fall, 1 m above the ground (it does not land in
    the 30 steps): its motion is gravity's alone, whatever its material; the lattice jittered,
    so its elastic forces are round-off, not exactly 0. ``factor`` multiplies every value."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 1.0, 0.0), (0.06, 0.06, 0.06),
              we.Material(lam=3e3, density=1000.0, **{k: v * factor for k, v in TRUTH.items()}))
    b.add_ground(friction=0.5)
    model = b.finalize(dtype=dtype, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model


@pytest.mark.parametrize("dtype", [wp.float32, wp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("optimizer", ["adam", "lbfgs", "gauss-newton"])
def test_a_fit_to_frames_before_any_motion_the_values_make_is_not_informative(dtype, optimizer):
    """The target frames precede any motion the material makes: the loss and its gradient are
    round-off (float32: 1e-17 m^2). Adam's first step from such a gradient is below ``xtol``
    and the fit said "converged" after one evaluation, the values a factor 2 off; L-BFGS
    wandered on round-off until the cap."""
    truth = _falling(wp.float64)
    dt = 0.5 * truth.stable_dt()
    target = Rollout(truth, STEPS, dt, frames=FRAMES).forward()
    result = fit(_falling(dtype, factor=2.0), target, list(TRUTH), steps=STEPS, dt=dt, frames=FRAMES,
                 optimizer=optimizer, iterations=6, progress=False, noise=1e-4)
    assert result.stopped == "uninformative", (result.stopped, [(h["loss"], h["grad"]) for h in result.history])
    assert not result.converged
    assert result.to_dict()["converged"] is False and result.to_dict()["stopped"] == "uninformative"
    assert "not informative" in result.termination and "target frames after the motion" in result.termination
    assert any("did not converge (uninformative)" in w for w in result.diagnostics.warnings)
    # The values stay the guess's: the lowest loss of round-off is no fitted value.
    for name, value in TRUTH.items():
        assert result.params[name][0] == pytest.approx(2.0 * value, rel=1e-12), (name, result.params[name])
    assert result.loss == result.initial_loss
    if optimizer == "adam":
        # Its first step, swallowed by eps, asks one probe, which observes what the start did:
        # the fit ends there (it had gone on to the iteration cap on round-off).
        assert len(result.history) == 2, [h.get("note") for h in result.history]


def _landing(dtype, yield_stress=TRUTH["yield_stress"], mu=TRUTH["mu"]):
    """The same cube dropped at 1 m/s from 1.5 cm above the ground: it lands within the steps,
    and its yield stress and flow rate shape the landing."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.035, 0.0), (0.06, 0.06, 0.06),
              we.Material(lam=3e3, density=1000.0, **{**TRUTH, "yield_stress": yield_stress, "mu": mu}),
              velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    model = b.finalize(dtype=dtype, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_a_float32_fit_started_at_the_answer_of_informative_data_is_not_called_uninformative(optimizer):
    """At the values that made its target (in float32, its own precision) the loss and its
    gradient are round-off, as before any motion; but a probe ``lr`` away moves the landing
    by far more than round-off, so the fit reads as converged, not as uninformative."""
    dt = 0.5 * _landing(wp.float64).stable_dt()
    target = Rollout(_landing(wp.float32), STEPS, dt, frames=FRAMES).forward()
    result = fit(_landing(wp.float32), target, ["yield_stress", "flow_rate"], steps=STEPS, dt=dt, frames=FRAMES,
                 optimizer=optimizer, iterations=6, progress=False, diagnostics=False)
    assert result.stopped == "converged", (result.stopped, [(h["loss"], h["grad"], h.get("note")) for h in result.history])
    assert result.params["yield_stress"][0] == pytest.approx(TRUTH["yield_stress"], rel=1e-6)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_cli_fit_to_frames_before_the_body_lands_says_it_learned_nothing_and_why(tmp_path, capsys, dough_scene, dtype):
    """``warp-esph fit`` of a block 1 m above the ground observed over its first two frames
    (free fall: its material moves nothing): the first line says the fit learned nothing and
    to give later frames, fit.json says not converged, and the status is a finished fit's (0),
    as for one that stalled. With Adam it had said "fit converged" after one evaluation."""
    from warp_esph.cli import main

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2)
                     .replace("center = [0.0, 0.045, 0.0]", "center = [0.0, 1.0, 0.0]")
                     .replace("velocity = [0.0, -1.0, 0.0]", "velocity = [0.0, 0.0, 0.0]"))
    np.save(tmp_path / "t.npy", np.zeros((3, 64, 3)))
    out = tmp_path / "cal"
    capsys.readouterr()
    status = main(["fit", str(guess), "--target", str(tmp_path / "t.npy"), "--params", "mu", "--optimizer", "adam", "--dtype", dtype,
                   "--iterations", "4", "--no-usd", "--no-progress", "--output-dir", str(out)])
    said = capsys.readouterr().out.splitlines()
    assert status == EXIT_NOT_CONVERGED  # written, and not reported as success
    assert said[0].startswith("fit learned nothing (not informative): "), said
    assert "give target frames after the motion these parameters make" in said[0]
    doc = json.loads((out / "fit.json").read_text())
    assert doc["stopped"] == "uninformative" and doc["converged"] is False


def test_adam_does_not_call_a_small_losss_guess_converged_because_its_eps_swallowed_the_step():
    """A position loss of weight 1e-6 on the landing cube, the yield stress 2 x off: its
    gradient (2.3e-14) is far below Adam's absolute eps (1e-8), so the first step was below
    ``xtol`` and the fit said "converged" after one evaluation, at 600 Pa. A probe ``lr`` away
    shows the loss rising by its slope, not by curvature alone: no minimum, and Adam goes on
    with eps relative to the gradient, to the truth's neighbourhood."""
    truth = _landing(wp.float64)
    dt = 0.5 * truth.stable_dt()
    target = Rollout(truth, STEPS, dt, frames=FRAMES).forward()
    loss = we.losses.PositionLoss(target, frames=FRAMES, weight=1e-6)
    result = fit(_landing(wp.float64, yield_stress=600.0), loss, ["yield_stress"], steps=STEPS, dt=dt,
                 optimizer="adam", iterations=8, progress=False, diagnostics=False)
    fitted = result.params["yield_stress"][0]
    assert abs(np.log(fitted / TRUTH["yield_stress"])) < 0.5 * np.log(2.0), (result.stopped, fitted, result.history)
    assert result.stopped != "uninformative"


def test_adam_takes_the_same_path_whatever_the_loss_s_units():
    """The landing cube's position loss in m^2 (weight 1, first gradient 1.4e-9) is of the
    size of Adam's absolute eps (1e-8): every step was damped, and 8 evaluations moved the
    yield stress from 600 Pa to 546 where the same loss times 2^20 (millimetres, nearly) reached
    294 (truth 300). eps is relative to the first gradient: a loss's scale changes no step."""
    truth = _landing(wp.float64)
    dt = 0.5 * truth.stable_dt()
    target = Rollout(truth, STEPS, dt, frames=FRAMES).forward()
    paths = []
    for weight in (1.0, 2.0**20):
        loss = we.losses.PositionLoss(target, frames=FRAMES, weight=weight)
        result = fit(_landing(wp.float64, yield_stress=600.0), loss, ["yield_stress"], steps=STEPS, dt=dt,
                     optimizer="adam", iterations=8, progress=False, diagnostics=False)
        paths.append([h["params"]["yield_stress"][0] for h in result.history])
    np.testing.assert_allclose(paths[0], paths[1], rtol=1e-9)
    assert abs(np.log(paths[0][-1] / TRUTH["yield_stress"])) < np.log(1.1), paths


def _landing_beside_a_falling_body(yield_stress, mu_falling, dtype=wp.float64):
    """A 27-particle cube landing at 1 m/s (its yield stress ``yield_stress``) and, 1 m away, a
    second one of shear modulus ``mu_falling`` in free fall all the run, its velocities spread
    by 1e-12 m/s: its strain, and so the loss's dependence on its shear modulus, is next to
    nothing, but not exactly 0."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.055, 0.0), (0.06,) * 3, we.Material(mu=2e3, lam=3e3, yield_stress=yield_stress, flow_rate=10.0),
              velocity=(0.0, -1.0, 0.0))
    b.add_box((1.0, 0.5, 0.0), (0.06,) * 3, we.Material(mu=mu_falling, lam=3e3, yield_stress=100.0, flow_rate=10.0),
              velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    model = b.finalize(dtype=dtype, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    falling = model.particle_material_np == 1
    model.particle_v0[falling] += np.random.default_rng(6).normal(scale=1e-12, size=(int(falling.sum()), 3))
    model.compute_rest_density()
    return model


@pytest.mark.parametrize("dtype", [wp.float64, wp.float32])
def test_adam_leaves_a_value_the_loss_reads_at_round_off_where_it_is(dtype):
    """Adam's eps relative to each entry of the first gradient made every step of an entry the
    loss barely reads a full ``lr``: the falling body's shear modulus (gradient 2e-28, 2e-18 of
    the largest entry; in float32 3e-17) went 10 % a step, 1000 Pa to 2087 in 8 evaluations.
    Such an entry takes an eps that holds it, and the values the loss reads still move by
    ``lr`` a step."""
    steps, dt, frames = 40, 1e-3, [20, 40]
    target = Rollout(_landing_beside_a_falling_body(100.0, 2e3), steps, dt, frames=frames).forward()
    result = fit(_landing_beside_a_falling_body(200.0, 1e3, dtype), we.losses.PositionLoss(target, frames=frames),
                 ["yield_stress", "mu"], steps=steps, dt=dt, optimizer="adam", iterations=3, progress=False,
                 diagnostics=False)
    first = np.abs(result.history[0]["grad"])
    # The falling body's mu: read, but 1e-5 and less of what the landing body's values are
    # (a unit step of it moves the loss by 4.5e-3 of its round-off in float32, 3.5e-5 in float64).
    assert 0.0 < first[3] < 1e-5 * min(first[0], first[2]), first
    mus = np.array([h["params"]["mu"][1] for h in result.history])
    np.testing.assert_allclose(mus, 1e3, rtol=1e-6)
    # The landing body's values, which the loss reads, move a step of lr (0.1 in log) each.
    landing = [h["params"]["yield_stress"][0] for h in result.history[:2]]
    assert abs(np.log(landing[1] / landing[0])) == pytest.approx(0.1, rel=1e-3)


def _swallowed(probe_at, probe_result):
    """A loss of one value whose gradient at the start (2e-16) is far below Adam's absolute
    eps (1e-8), so its first step is below ``xtol``; ``probe_result`` is what an evaluation at
    ``probe_at`` returns. Returns the evaluate function and its list of evaluated points."""
    points = []

    def evaluate(z, wants=None):
        points.append(float(z[0]))
        if abs(z[0] - probe_at) < 1e-12:
            return probe_result
        return 1e-16 * (z[0] - 1.0) ** 2, np.array([2e-16 * (z[0] - 1.0)]), True

    return evaluate, points


def test_adam_does_not_call_a_start_uninformative_from_a_probe_that_did_not_run():
    """Adam's probe ``lr`` away from a start whose step eps swallowed is refused by the
    materials or blows up (not finite): it observed nothing, so nothing moved, and Adam had
    ended the fit "uninformative" from it, the start's values reported as all the data allow.
    A probe that did not run says nothing of round-off (as ``verdict``'s probes, which then ask
    the other side): Adam goes on with eps relative to the gradient, to the minimum at 1."""
    from warp_esph.fit import _run_adam

    evaluate, points = _swallowed(0.1, (math.inf, np.full(1, np.nan), False))
    stop = _run_adam(evaluate, lambda z: z, np.zeros(1), 40, 0.1, None, None, lambda text: None, xtol=1e-6,
                     told_apart=lambda: False)
    assert stop != "uninformative", points
    assert abs(points[-1] - 1.0) < 0.2, (stop, points)


def test_adam_ends_uninformative_at_its_probe_whatever_the_curvature_reads():
    """Adam's probe observed what the start did to round-off, but its loss read a rise of
    curvature alone (round-off can): Adam said "converged", and ``verdict`` then ran the very
    same probe again before saying "uninformative", an evaluation that could tell nothing new.
    The probe's observations decide first: "uninformative" after the start and the probe."""
    from warp_esph.fit import _run_adam

    # At 0.1 the loss rises by 1e-6 with a slope of 2e-16 x 0.1: a rise of curvature alone.
    evaluate, points = _swallowed(0.1, (1e-6, None, True))
    stop = _run_adam(evaluate, lambda z: z, np.ones(1) * 0.0, 40, 0.1, None, None, lambda text: None, xtol=1e-6,
                     told_apart=lambda: False)
    assert stop == "uninformative", (stop, points)
    assert points == [0.0, 0.1]


def _vibrating(dtype, offset, mu=TRUTH["mu"]):
    """27 particles of an elastic cube without gravity or ground, its centre ``offset`` m from
    the origin along x, started expanding (2 (x - c) m/s): it swells and springs back as its
    shear modulus says, so positions alone inform the fit (no collider records forces)."""
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_box((offset, 0.0, 0.0), (0.06, 0.06, 0.06), we.Material(lam=3e3, mu=mu, density=1000.0))
    model = b.finalize(dtype=dtype, requires_grad=True)
    model.particle_v0 = 2.0 * (model.particle_x0 - model.particle_x0.mean(axis=0))
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model


def test_where_the_body_sits_does_not_make_informative_data_uninformative():
    """The same swelling cube 10 m from the origin, float32, mu fitted from 2 x off: its
    positions move by 2.3e-5 m for a 10 % move of mu, 19.5 units of float32's round-off of
    their largest magnitude (10 m) and so below the 1000 units of it ``_tells_apart`` read as
    round-off; the fit was said to have learned nothing and reported the guess, 4000 Pa,
    where at the origin (and before the rule) it finds 2000 Pa. Round-off in the coordinates
    themselves is a few units of their magnitude; the rest scales with the body, not with its
    distance from the origin. The cube in free fall 10 m off stays uninformative."""
    dt = 0.5 * _vibrating(wp.float64, 10.0).stable_dt()
    target = Rollout(_vibrating(wp.float32, 10.0), STEPS, dt, frames=FRAMES).forward()
    result = fit(_vibrating(wp.float32, 10.0, mu=2.0 * TRUTH["mu"]), target, ["mu"], steps=STEPS, dt=dt, frames=FRAMES,
                 optimizer="lbfgs", iterations=12, progress=False, diagnostics=False)
    assert result.stopped != "uninformative", [(h["loss"], h["params"], h.get("note")) for h in result.history]
    assert result.params["mu"][0] == pytest.approx(TRUTH["mu"], rel=0.05), result.history

    def falling(dtype, factor=1.0):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((10.0, 1.0, 0.0), (0.06, 0.06, 0.06),
                  we.Material(lam=3e3, density=1000.0, **{k: v * factor for k, v in TRUTH.items()}))
        model = b.finalize(dtype=dtype, requires_grad=True)
        model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
        model.compute_rest_density()
        return model

    target = Rollout(falling(wp.float64), STEPS, dt, frames=FRAMES).forward()
    still = fit(falling(wp.float32, factor=2.0), target, list(TRUTH), steps=STEPS, dt=dt, frames=FRAMES,
                optimizer="lbfgs", iterations=6, progress=False, diagnostics=False)
    assert still.stopped == "uninformative", [(h["loss"], h.get("note")) for h in still.history]


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs"])
def test_a_probe_already_evaluated_is_not_run_again(optimizer):
    """Started at the values that made its float32 target in free fall: the loss is exactly 0
    and so is its gradient, and the fit's zero-gradient check evaluates a point ``lr`` away,
    whose observations are compared with the start's as every evaluation's are. ``verdict``
    then ran that very point again as its informativeness probe (the same values, the same
    loss): a forward run that could tell nothing new. Each point is evaluated once."""
    dt = 0.5 * _falling(wp.float64).stable_dt()
    target = Rollout(_falling(wp.float32), STEPS, dt, frames=FRAMES).forward()
    result = fit(_falling(wp.float32), target, list(TRUTH), steps=STEPS, dt=dt, frames=FRAMES, optimizer=optimizer,
                 iterations=6, progress=False, diagnostics=False)
    points = [tuple(v for k in sorted(h["params"]) for v in h["params"][k]) for h in result.history]
    assert len(points) == len(set(points)), [(h["loss"], h["params"], h.get("note")) for h in result.history]
    assert result.stopped == "uninformative", result.stopped


def test_adam_moves_a_value_whose_first_gradient_was_0_once_the_loss_reads_it():
    """A value the loss does not read at the start (its gradient exactly 0, as a yield stress
    set too high is where nothing yields) but reads once another value has moved (particles
    yield): Adam held it with eps = 1e8 times the loss's round-off for the whole run, so in
    float32 (round-off 1.2e-7 of the loss) its later gradient of order 1 moved it a few % of a step
    and it ended 0.9 from its minimum after 40 evaluations. Judged round-off while its gradient
    stays at or below the round-off, it takes eps relative to its first gradient above it, and
    reaches its minimum as the other value does."""
    from warp_esph.fit import _run_adam

    points, values = [], []

    def evaluate(z):
        # z[1]'s term switches on where z[0] passes 0.5, as yielding does where the load grows.
        on = max(z[0] - 0.5, 0.0)
        value = (z[0] - 2.0) ** 2 + on * (z[1] - 1.0) ** 2
        grad = np.array([2.0 * (z[0] - 2.0) + (z[1] - 1.0) ** 2 * (z[0] > 0.5), 2.0 * on * (z[1] - 1.0)])
        points.append(z.copy())
        values.append(value)
        return value, grad, True

    float32 = float(np.finfo(np.float32).eps)
    _run_adam(evaluate, lambda z: z, np.zeros(2), 40, 0.1, None, None, lambda text: None, xtol=1e-9,
              loss_roundoff=lambda: float32 * abs(values[-1]))
    assert points[1][1] == 0.0, points[:2]  # held while the loss does not read it
    assert abs(points[-1][1] - 1.0) < 0.1, points[-1]
    assert values[-1] < 0.05 * values[0], (values[0], values[-1])


def test_adam_judges_a_held_value_against_the_round_off_of_the_loss_it_is_read_at():
    """A value the loss reads late and weakly (its term switched on by the other value's move,
    weighing 1e-3 against a start of 4e4): held as round-off at the start (gradient 0), its
    later gradient of up to 1e-3 is far above the round-off of the loss by then (float32's
    1.2e-7 of a loss of a few units), but below that of the start's loss (4.8e-3), which alone
    was read: it stayed at its guess for the run. Judged against the round-off of the loss its
    gradient is of, it moves to its minimum."""
    from warp_esph.fit import _run_adam

    points, values = [], []

    def evaluate(z):
        on = max(z[0] - 1.5, 0.0)
        value = 1e4 * (z[0] - 2.0) ** 2 + 1e-3 * on * (z[1] - 1.0) ** 2
        grad = np.array([2e4 * (z[0] - 2.0) + 1e-3 * (z[1] - 1.0) ** 2 * (z[0] > 1.5), 2e-3 * on * (z[1] - 1.0)])
        points.append(z.copy())
        values.append(value)
        return value, grad, True

    float32 = float(np.finfo(np.float32).eps)
    _run_adam(evaluate, lambda z: z, np.zeros(2), 60, 0.1, None, None, lambda text: None, xtol=1e-9,
              loss_roundoff=lambda: float32 * abs(values[-1]))
    assert points[1][1] == 0.0, points[:2]  # held while the loss does not read it
    assert abs(points[-1][0] - 2.0) < 0.1, points[-1]
    assert abs(points[-1][1] - 1.0) < 0.2, points[-1]


def test_adam_moves_a_yield_stress_nothing_reached_at_the_start_once_the_body_yields():
    """The landing cube in float32 from a shear modulus half the target's and a yield stress
    of 1500 Pa (the target's 300) that the softer landing never reaches: nothing yields, and
    the yield stress's first gradient is exactly 0. As the shear modulus climbs the landing
    yields (from the 4th evaluation) and the loss reads the yield stress; Adam had held it
    for the run with eps = 1e8 times the first loss's round-off: 1500.00 Pa, to the hundredth,
    after 21 evaluations. Judged again, it falls towards the target's as soon as it is read
    (904 Pa after 11 evaluations, 449 after 21)."""
    truth = _landing(wp.float64)
    dt = 0.5 * truth.stable_dt()
    target = Rollout(truth, STEPS, dt, frames=FRAMES).forward()
    result = fit(_landing(wp.float32, yield_stress=1500.0, mu=1e3), we.losses.PositionLoss(target, frames=FRAMES),
                 ["mu", "yield_stress"], steps=STEPS, dt=dt, optimizer="adam", iterations=10, progress=False,
                 diagnostics=False)
    assert result.history[0]["grad"][1] == 0.0, result.history[0]["grad"]
    ys = [h["params"]["yield_stress"][0] for h in result.history]
    assert ys[-1] < 0.8 * ys[0], ys
