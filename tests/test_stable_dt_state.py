"""The stable step sees the state the step starts from: a flowed body made elastic
(``flow_rate`` set to 0) under ``fit="auto"`` keeps the curvature-corrected fit on the
incremental composition (``keeps_incremental``), whose step is ``CORRECTED_INCREMENTAL_STEP``
of the wave limit, where its parameters alone choose the rest model and the full limit
(docs/method.md §8). Measured before: the large breathing 6^3 cube so started ran away at the
full limit (float64 7030 x its energy at 6.7 periods) and kept 1.23 x over 10 periods at half."""

import contextlib
import io
import json
import re
import warnings

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph import fit as fit_module
from warp_esph.checkpoint import load_state, read_checkpoint
from warp_esph.cli import main
from warp_esph.fit import fit
from warp_esph.losses import PositionLoss
from warp_esph.scenes import load_scaled_scene
from warp_esph.sim.solver import keeps_incremental
from warp_esph.simulate import adaptive_timestep, resolve_timestep, simulate
from run_files import box_on_ground
from test_elastic_force import _elastic_block_and_a_flowed_start, _slump_block

HALF = "the wave limit x 0.5 for the curvature-corrected fit on the incremental composition"


def _slumped_block(steps=40):
    """The block of ``test_a_slumped_body_made_elastic_stays_at_rest`` (4x4x6, yield 30 Pa,
    ``flow_rate`` 200) after ``steps`` steps on the ground it stands on, then made elastic: its
    model, the solver that stepped it and its state, which has flowed."""
    model = _slump_block(-0.06)
    solver = we.Solver(model)
    dt = model.stable_dt()
    a, c = model.state(), model.state()
    for _ in range(steps):
        solver.step(a, c, dt)
        a, c = c, a
    assert a.has_flowed()
    # Flowing, the state changes nothing: the linear fit, the full limit.
    assert model.stable_dt(state=a) == model.stable_dt() == dt
    model.flow_rate.assign(np.array([0.0]))
    return model, solver, a


def test_a_flowed_body_made_elastic_is_given_half_the_wave_limit_from_its_state():
    model, solver, flowed = _slumped_block()
    assert keeps_incremental(flowed) and model.auto_runs_rest()
    full = model.stable_dt()  # the parameters alone: the rest model
    half = model.stable_dt(hourglass=0.05, fit="curvature_corrected")
    assert half < 0.51 * full
    # The solver's too, before a step has chosen the control the parameters now ask for.
    assert model.stable_dt(state=flowed) == half and solver.stable_dt(state=flowed) == half
    assert model.corrected_incremental(state=flowed) and not model.corrected_incremental()
    # A new state is handed to the rest model: its step is the full limit, as before.
    fresh = model.state()
    assert model.stable_dt(state=fresh) == full
    # The step's own check reads its state_in: at the full limit it warns from the flowed state,
    # not from a new one.
    out = model.state()
    with pytest.warns(RuntimeWarning, match=HALF):
        solver.step(flowed, out, full)
    assert out.rest_model is False and model.stable_dt(state=out) == half
    assert solver.stable_dt(state=flowed) == half and solver.stable_dt(state=fresh) == full
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        we.Solver(model).step(fresh, model.state(), full)


def test_a_state_the_step_hands_to_the_rest_model_keeps_the_full_limit_whatever_its_alpha():
    """Only a state an incremental step wrote keeps the incremental composition: a new state or
    one the rest model wrote, its ``alpha`` set by hand, is handed to the rest model
    (``Solver.runs_rest``), whose step is the full wave limit, and the step runs it there
    without a warning."""
    model, solver, _ = _slumped_block()
    full = model.stable_dt()
    fresh = model.state()
    fresh.alpha.fill_(0.01)
    assert fresh.rest_model is None and solver.runs_rest(fresh) and model.stable_dt(state=fresh) == full
    rested = model.state()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver.step(fresh, rested, full)
        assert rested.rest_model is True
        rested.alpha.fill_(0.01)
        assert solver.runs_rest(rested) and model.stable_dt(state=rested) == solver.stable_dt(state=rested) == full
        out = model.state()
        solver.step(rested, out, full)
    assert out.rest_model is True


def test_the_step_reads_alpha_back_once_and_only_where_the_path_hangs_on_it(monkeypatch):
    """Each read of ``alpha`` waits for the device on a GPU. The step reads it only where the
    parameters choose the rest model from a state an incremental step wrote that does not say it
    flowed, and then once for both the path (``_runs_rest``) and the stable step's check: the
    check read it a second time, and unguarded by the parameters' choice it would read it at
    every step of a flowing body, whose states an incremental step writes without ``flowed``."""
    from warp_esph import model as model_module

    reads = []
    real = model_module.flowed_by_hardening
    monkeypatch.setattr(model_module, "flowed_by_hardening", lambda alpha: reads.append(1) or real(alpha))
    model, solver, flowed = _slumped_block()
    assert len(reads) == 1  # _slumped_block's own has_flowed(): none in its 40 flowing steps
    assert flowed.rest_model is False and flowed.flowed is None
    del reads[:]
    a, b = flowed, model.state()
    dt = model.stable_dt(state=flowed)
    assert len(reads) == 1
    del reads[:]
    for _ in range(5):
        solver.step(a, b, dt)
        a, b = b, a
        if b is flowed:
            b = model.state()
    assert len(reads) == 1 and a.flowed is True and a.rest_model is False  # the first step's one read


def test_simulate_steps_a_flowed_start_made_elastic_at_half_the_wave_limit():
    """``simulate``'s default and adaptive steps, and its start check, read the start given."""
    model, _, flowed = _slumped_block()
    half = model.stable_dt(hourglass=0.05, fit="curvature_corrected")
    fps = 30.0
    n, dt = resolve_timestep(model, fps, state=flowed)
    assert dt <= half and n == int(np.ceil(1.0 / fps / half * (1.0 - 1e-12)))
    assert resolve_timestep(model, fps)[1] > 1.9 * dt  # from a new state: the rest model's step
    assert adaptive_timestep(model, flowed, fps)[1] <= half
    solver = we.Solver(model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # within the stable step: no warning
        end = simulate(model, 1, fps=fps, solver=solver, state=flowed, progress=False)
    assert solver.step_count == n and end.rest_model is False


def test_simulate_warns_of_a_dt_past_its_starts_limit_before_the_run_at_the_callers_line():
    """``simulate`` checks ``dt`` against its start's stable step before the progress bar, the
    warning pointing at the caller's line; left to the step's own check, it came from inside the
    package at the first step."""
    model, _, flowed = _slumped_block()
    dt = 1.0 / 30.0 / 20.0  # within a new state's limit, twice the flowed start's
    assert model.stable_dt(state=flowed) < 0.51 * dt < 0.51 * model.stable_dt()
    with pytest.warns(RuntimeWarning, match=HALF) as said:
        simulate(model, 1, fps=30.0, solver=we.Solver(model), state=flowed, dt=dt, progress=False)
    assert [w.filename for w in said] == [__file__]


def test_a_fits_step_from_a_flowed_start_is_the_corrected_incremental_fits():
    """A fit's chosen step (``dt=None``) and its ``step_limit`` read its rollout's start: from a
    flowed start of an elastic body (``initial_state`` an incremental step wrote, ``alpha`` >
    0), which its rollouts run on the corrected incremental fit, half the wave limit."""
    model, flowed = _elastic_block_and_a_flowed_start(requires_grad=True)
    loss = PositionLoss({2: model.particle_x0.astype(np.float64) - 0.001})
    args = dict(steps=2, iterations=0, progress=False, diagnostics=False)
    full = model.stable_dt()
    half = model.stable_dt(hourglass=0.05, fit="curvature_corrected")
    said = []
    r = fit(model, loss, ["mu"], initial={"initial_state": flowed}, log=said.append, **args)
    # The log says why: the guess's own step from that start (it said the guess's was the whole).
    assert said[0] == (f"the experiment: dt = {r.step_limit['dt']:.4g} s, the guess's stable step from the run's start "
                       f"(Model.stable_dt(state=); a new state's is {full:.4g} s)"), said[0]
    assert r.step_limit["dt"] == pytest.approx(half, rel=1e-12) and r.step_limit["stable_dt"] == pytest.approx(half, rel=1e-12)
    assert fit(model, loss, ["mu"], **args).step_limit["dt"] == pytest.approx(full, rel=1e-12)
    # At the full limit given, the rollouts run past it, and the fit says so.
    with pytest.warns(RuntimeWarning, match=HALF):
        r = fit(model, loss, ["mu"], initial={"initial_state": flowed}, dt=full, **args)
    assert r.step_limit["dt_over_stable"] == pytest.approx(full / half, rel=1e-9) and r.step_limit_said()


def test_a_fits_stable_step_follows_the_path_of_the_trial_values():
    """``_Values.stable_step`` judged the path (fit, control, rest model) by the values the
    model's arrays hold, not the trial values: on the imaged ground (the corrected fit runs the
    incremental composition) an elastic trial point of a plastic model was given the linear
    fit's full limit without the control, and a plastic trial point of an elastic model half."""
    def block(flow_rate):
        b = we.SceneBuilder(spacing=0.02)
        b.add_box((0.0, 0.05, 0.0), (0.06, 0.06, 0.06), we.Material(mu=2e3, lam=3e3, yield_stress=300.0, flow_rate=flow_rate))
        b.add_ground(0.0, images=True)
        return b.finalize(dtype=wp.float64)

    plastic, elastic = block(10.0), block(0.0)
    assert plastic.stable_dt() > 1.9 * elastic.stable_dt()
    for model, trial, other in ((plastic, 0.0, elastic), (elastic, 10.0, plastic)):
        before = model.stable_dt()
        values = fit_module._Values(model, [0], "the experiment")
        values.setup_tie(["flow_rate"], None)
        assert values.stable_step({"flow_rate": np.array([trial])}) == other.stable_dt()
        assert model.stable_dt() == before  # nothing written, nothing kept


@pytest.mark.parametrize("adaptive", [False, True])
def test_a_cli_run_resumed_from_a_flowed_checkpoint_made_elastic_takes_half_the_wave_limit(tmp_path, capsys, adaptive):
    """``warp-esph run --resume`` of a run that took the stable step chooses it again from the
    checkpoint's state (its step's bound, with ``--dt auto``): a checkpoint of a flowed body
    whose parameters were made elastic since (``flow_rate`` 0: the parameters a checkpoint
    holds may be edited) resumed at the full step it recorded, 20 steps a frame where the step
    runs the corrected incremental fit at half the wave limit, and warned only once running."""
    scene = tmp_path / "slump.toml"
    scene.write_text(box_on_ground("slump", 6, "m", "dough", "2e4"))  # lands and flows by frame 6
    out = tmp_path / "slump.usdc"
    ckpt = tmp_path / "slump.usdc.checkpoint.npz"
    assert main(["run", str(scene), "-o", str(out), "--checkpoint-every", "6", "--no-progress", "--dtype", "float64"]
                + ["--dt", "auto"] * adaptive) == 0
    with np.load(ckpt) as data:
        arrays = {k: data[k] for k in data.files}
    assert arrays["alpha"].max() > 0.0  # it flowed
    arrays["material_flow_rate"] = np.zeros_like(arrays["material_flow_rate"])
    np.savez(ckpt, **arrays)
    recorded = json.loads(arrays["meta"].tobytes())["run"]
    model = load_scaled_scene(str(scene), 1.0).builder.finalize(dtype=wp.float64)
    flowed, _ = load_state(ckpt, model)
    half, full = model.stable_dt(state=flowed), model.stable_dt()
    assert keeps_incremental(flowed) and half < 0.51 * full
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["run", "--resume", str(ckpt), "--frames", "12", "--no-progress"]) == 0
    said = capsys.readouterr()
    assert "warning" not in said.err, said.err
    dt, n = re.search(r"dt = ([0-9.e-]+) s \((\d+) steps/frame\)", said.out).groups()
    steps = int(np.ceil(1.0 / 30.0 / half * (1.0 - 1e-12)))
    assert int(n) == steps and float(dt) == pytest.approx(1.0 / 30.0 / steps, rel=1e-3)
    if not adaptive:
        assert recorded["dt"] > 1.9 / 30.0 / steps  # the flowing run's: the full limit
        assert read_checkpoint(ckpt)[0]["run"]["dt"] == pytest.approx(1.0 / 30.0 / steps, rel=1e-12)
        # The record's own check: a dt_stable that is no bool is refused by name, as its other keys.
        arrays = dict(np.load(ckpt))
        meta = json.loads(arrays["meta"].tobytes())
        meta["run"]["dt_stable"] = 1
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        np.savez(ckpt, **arrays)
        assert main(["run", "--resume", str(ckpt), "--frames", "14", "--no-progress"]) == 2
        assert "dt_stable = 1" in capsys.readouterr().err
        # A checkpoint written before the record kept dt_stable resumes at the dt it recorded (the
        # full step here), and the check before the run, of the checkpoint's state, warns ahead
        # of the run line (the step's own check warned after it).
        meta["run"].pop("dt_stable")
        meta["run"]["dt"] = recorded["dt"]
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        np.savez(ckpt, **arrays)
        both = io.StringIO()
        with contextlib.redirect_stdout(both), contextlib.redirect_stderr(both):
            main(["run", "--resume", str(ckpt), "--frames", "13", "--no-progress"])
        said = both.getvalue()
        warned = said.find(f"warning: dt = {recorded['dt']:g} s is above the explicit stability limit {half:.3g} s")
        ran = said.find(f"dt = {recorded['dt']:.4g} s (")
        assert -1 < warned < ran, said


def test_a_rollout_blown_up_from_a_flowed_start_made_elastic_quotes_half_the_wave_limit():
    """``NonFiniteRollout``'s (and ``DivergedRollout``'s) stable step is its start's: from a
    flowed body made elastic, at 0.8 x the limit of a new state, it quoted that limit, said the
    dt was within it and blamed the start; the step ran past the half its start keeps."""
    from warp_esph.rollout import NonFiniteRollout, Rollout

    model, flowed = _elastic_block_and_a_flowed_start(requires_grad=True)
    full, half = model.stable_dt(), model.stable_dt(state=flowed)
    assert half == pytest.approx(0.5 * full, rel=0.02)
    v = flowed.v.numpy()
    v[0, 0] = np.nan  # a start that goes non-finite at once, whatever the step
    flowed.v.assign(v)
    rollout = Rollout(model, 2, 0.8 * full)
    with pytest.warns(RuntimeWarning, match=HALF), pytest.raises(NonFiniteRollout) as e:
        rollout.forward(initial_state=flowed)
    said = str(e.value)
    assert f"(Model.stable_dt(state=) of its start = {half:.3g} s); use a smaller dt" in said, said
    assert "dt is within it" not in said


def test_the_steps_non_finite_warning_names_the_stable_step_of_its_state_in():
    """``Solver.step``'s warning of a non-finite ``state_in`` quotes the stable step of that
    state: from a flowed body made elastic it quoted the half as ``Model.stable_dt()``, which
    returns the whole."""
    model, solver, flowed = _slumped_block()
    half, full = model.stable_dt(state=flowed), model.stable_dt()
    out, nxt = model.state(), model.state()
    solver.step(flowed, out, half)
    x = out.x.numpy()
    x[0, 0] = np.nan
    out.x.assign(x)
    with pytest.warns(RuntimeWarning, match="non-finite position") as said:
        solver.step(out, nxt, half)
    text = str(said[0].message)
    assert f"Model.stable_dt(state=) of state_in = {half:.3g} s (dt is within it" in text, text
    assert f"Model.stable_dt() = {full:.3g}" not in text and "Model.stable_dt() =" not in text


def test_a_dt_past_what_the_precision_resolves_quotes_the_stable_step_of_the_state_it_starts_from():
    """``resolvable_dt``'s refusal (one step's fall past the precision at the spacing) quotes the
    stable step for a stable run: from a flowed body made elastic it quoted the new state's,
    ``Model.stable_dt()``, twice the step ``check_dt`` holds that state to. ``check_dt`` and
    ``step`` now quote their state's, named so; without a state, as before."""
    model, solver, flowed = _slumped_block()
    half, full = solver.stable_dt(state=flowed), solver.stable_dt()
    assert half < 0.51 * full
    tail = f"(and for a stable run at most Model.stable_dt(state=) = {half:.3g} s from the state it starts at)"
    for refused in (lambda: solver.check_dt(1e30, flowed), lambda: solver.step(flowed, model.state(), 1e30)):
        with pytest.raises(ValueError, match="dt = 1e[+]30 is not allowed: one step's fall") as e:
            refused()
        assert str(e.value).endswith(tail), str(e.value)
    with pytest.raises(ValueError) as e:
        solver.check_dt(1e30)
    assert str(e.value).endswith(f"(and for a stable run at most Model.stable_dt() = {full:.3g} s)"), str(e.value)


def test_energy_growth_quotes_the_stable_step_of_the_runs_start():
    """``simulate.energy_growth``'s blow-up names the stable step of the run's start
    (``state=``; ``Rollout.bounds_hit`` passes its forward's): from a flowed body made elastic,
    half the limit it quoted, that of a new state."""
    from warp_esph.simulate import energy_growth

    model, flowed = _elastic_block_and_a_flowed_start()
    solver = we.Solver(model)
    full, half = solver.stable_dt(), solver.stable_dt(state=flowed)
    assert half < 0.51 * full
    x0 = model.particle_x0.astype(np.float64)
    v = np.full_like(x0, float(np.max(model.wave_speeds())))  # every particle at c_P: far past the limit
    for kw, quoted in (({"solver": solver}, full), ({"solver": solver, "state": flowed}, half), ({"state": flowed}, half)):
        why, _ = energy_growth(model, x0, np.zeros_like(x0), x0, v, **kw)
        assert why.endswith(f"the time step is likely above the stable limit {quoted:.3g} s"), why


def test_a_rollouts_energy_blow_up_quotes_the_stable_step_of_its_start(monkeypatch):
    """``Rollout.bounds_hit`` passes its forward's start to ``energy_growth`` (the monitor's
    bounds, which quote no step, set aside here to reach it)."""
    from warp_esph.rollout import Rollout
    from warp_esph.simulate import DivergenceMonitor

    model, flowed = _elastic_block_and_a_flowed_start(requires_grad=True)
    half = model.stable_dt(state=flowed)
    rollout = Rollout(model, 2, half)
    rollout.forward(initial_state=flowed)
    last = rollout.final_state()
    last.v.assign(np.full(last.v.shape + (3,), float(np.max(model.wave_speeds()))))
    monkeypatch.setattr(DivergenceMonitor, "check", lambda *args, **kwargs: None)
    why, _ = rollout.bounds_hit()
    assert why.endswith(f"the time step is likely above the stable limit {half:.3g} s"), why


def test_the_step_refusals_from_a_flowed_start_made_elastic_weigh_the_control_against_half_the_wave_limit():
    """``resolve_timestep``'s and ``adaptive_timestep``'s refusals (more than a million steps a
    frame) name what sets the stable step of the start given: from a flowed body made elastic the
    wave limit is the half, so a control whose limit lies between the half and the whole (0.75
    of it) does not set it. They said it did, against the whole wave limit, and advised a
    smaller strength, which lengthens the step to half the wave limit at most (0.42 x it here)."""
    from warp_esph.simulate import StepRefusal

    model, flowed = _elastic_block_and_a_flowed_start()
    wave = 0.3 * model.spacing / float(np.max(model.wave_speeds()))
    c = 1.0 * (model._hourglass_limit(0.3, 1.0)[0] / (0.75 * wave)) ** 2  # its limit is 1 / sqrt(c)
    assert model._hourglass_limit(0.3, c)[0] == pytest.approx(0.75 * wave, rel=1e-9)
    stable = model.stable_dt(hourglass=c, state=flowed)
    assert stable == pytest.approx(wave / np.sqrt(4.0 + 1.0 / 0.75**2), rel=1e-9)
    fps = 0.5 / (stable * 1e6)  # two million steps a frame
    with pytest.raises(StepRefusal) as fixed:
        resolve_timestep(model, fps, hourglass=c, state=flowed)
    with pytest.raises(StepRefusal) as adaptive:
        adaptive_timestep(model, flowed, fps, hourglass=c)
    for e in (fixed, adaptive):
        said = str(e.value)
        assert "hourglass control" not in said and "softer material" in said, said


def test_each_worlds_step_alone_reads_its_own_part_of_the_start():
    """``world_stable_dts(state=)``: a world whose body flowed keeps the corrected incremental
    fit alone, at half the wave limit; one that did not is handed over to the rest model, at the
    whole. ``resolve_timestep``'s worlds warning counts them from the start given: from a start
    where both identical elastic worlds flowed it said each ran half the count alone."""
    mat = we.Material.from_young(2.0e5, 0.3, pressure_stiffness=0.0)
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, 0.0, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.06,) * 3, mat)
    model = b.finalize(dtype=wp.float64, worlds=2)
    full = model.stable_dt()
    both = model.state()
    both.alpha.fill_(0.01)
    both.rest_model = False
    half = model.stable_dt(state=both)
    assert half < 0.51 * full and model.world_stable_dts() == [full, full]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # each world alone runs the count the model runs
        n, _ = resolve_timestep(model, 30.0, state=both)
    assert model.world_stable_dts(state=both) == [half, half]
    one = model.state()
    alpha = np.zeros(model.particle_count)
    alpha[model.world_particles(0)] = 0.01
    one.alpha.assign(alpha)
    one.rest_model = False
    assert model.world_stable_dts(state=one) == [half, full]
    alone = int(np.ceil(1.0 / 30.0 / full * (1.0 - 1e-12)))
    with pytest.warns(RuntimeWarning, match=rf"\({n} a frame\) is the stiffest world's; alone, a world runs its own \(world 1: {alone} steps a frame\)"):
        assert resolve_timestep(model, 30.0, state=one)[0] == n
