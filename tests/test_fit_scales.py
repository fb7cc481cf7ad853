"""The step size of a parameter fitted as itself (``fit(..., param_scales=...)``): a step of ``lr``
moves it by ``lr`` times its own size, whatever units the problem is written in."""

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.cli import EXIT_NOT_CONVERGED
from warp_esph.fit import fit
from warp_esph.losses import PositionLoss
from warp_esph.rollout import Rollout

DT = 1.0e-3
STEPS = 6
ALPHA0 = 0.02


def _block(units=1.0, **params):
    """A 5x4x4 block flowing under an affine velocity, its stresses and density in ``units``
    (times Pa, times kg/m^3): every acceleration, and so every position, is the same."""
    p = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "hardening": 0.0} | params
    p = {k: v * units for k, v in p.items()}
    b = we.SceneBuilder(spacing=0.02, gravity=(0.0, -9.81, 0.0))
    b.add_box((0.0, 0.0, 0.0), (0.1, 0.08, 0.08), we.Material(density=1000.0 * units, flow_rate=50.0,
                                                                  pressure_stiffness=1.0, **p))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=2e-5, size=model.particle_x0.shape)
    model.particle_v0 = 20.0 * model.particle_x0 * np.array((1.0, -0.5, 0.0))
    return model


@pytest.fixture(scope="module")
def target():
    x = Rollout(_block(hardening=300.0), STEPS, DT, frames=[3, 6]).forward(alpha0=ALPHA0)
    return {f: x[i] for i, f in enumerate([3, 6])}


def _path(target, units, optimizer, **kw):
    loss = PositionLoss(np.stack([target[3], target[6]]), frames=[3, 6])
    r = fit(_block(units), loss, ["hardening"], steps=STEPS, dt=DT, initial={"alpha0": ALPHA0}, iterations=4,
            optimizer=optimizer, progress=False, diagnostics=False, **kw)
    return (np.array([h["params"]["hardening"][0] / units for h in r.history]),
            np.array([h["loss"] for h in r.history]), r)


@pytest.mark.parametrize("optimizer", ["adam", "lbfgs", "gauss-newton"])
def test_a_hardening_fitted_from_zero_takes_the_same_path_in_any_units(target, optimizer):
    """From 0 the hardening had a step of 1 Pa whatever the problem's stresses: with mu = 1 kPa
    Adam's first step moved it 0.1 Pa, with the same problem in mPa (every stress and the
    density times 1e3) 1e-4 of that. Its size is now mu's, so both move alike; the fit
    leaves 0 by a share of mu, not by a part in 1e4 of it."""
    a, loss_a, ra = _path(target, 1.0, optimizer)
    b, loss_b, rb = _path(target, 1.0e3, optimizer)
    assert ra.param_scales == {"hardening": {"size": 1.0e3, "from": "material"}}  # mu
    assert rb.param_scales == {"hardening": {"size": 1.0e6, "from": "material"}}
    assert ra.to_dict()["param_scales"] == ra.param_scales
    assert len(a) == len(b)
    np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-9 * 1e3)
    np.testing.assert_allclose(loss_b, loss_a, rtol=1e-6, atol=1e-6 * loss_a[0])
    assert abs(a[1]) >= 10.0  # the first step (a Jacobian's difference with Gauss-Newton) moves it by a share of mu


def test_bounds_and_a_given_scale_size_the_steps_in_the_parameter_units(target):
    """A hardening from 0 bounded to (-500, 500) takes the bounds' width as its size; one
    given (``param_scales``) replaces it: the problem in other units with the bounds, or the
    scale, in those units follows the same path."""
    a, _, r = _path(target, 1.0, "adam", bounds={"hardening": (-500.0, 500.0)})
    b, _, _ = _path(target, 1.0e3, "adam", bounds={"hardening": (-5.0e5, 5.0e5)})
    np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-6)
    assert r.param_scales == {"hardening": {"size": 1000.0, "from": "bounds"}}
    assert a[1] == pytest.approx(-100.0, rel=1e-6) or a[1] == pytest.approx(100.0, rel=1e-6)
    c, _, rc = _path(target, 1.0, "adam", param_scales={"hardening": 200.0})
    d, _, _ = _path(target, 1.0e3, "adam", param_scales={"hardening": 2.0e5})
    np.testing.assert_allclose(d, c, rtol=1e-6, atol=1e-6)
    assert abs(c[1]) == pytest.approx(20.0, rel=1e-6)
    assert rc.param_scales == {"hardening": {"size": 200.0, "from": "given"}}  # lr 0.1 times 200 Pa


@pytest.mark.parametrize("param_scales, said", [
    ({"hardening": 0.0}, r"^param_scales\['hardening'\] = 0\.0 is not allowed: must be > 0"),
    ({"hardening": float("inf")}, r"^param_scales\['hardening'\] = inf is not allowed"),
    ({"hardening": float("nan")}, r"^param_scales\['hardening'\] = nan is not allowed"),
    ({"lam": 10.0}, r"^param_scales for 'lam' is not allowed: lam is not fitted"),
    ([1.0], r"^param_scales = \[1\.0\] is not allowed: must be a mapping"),
])
def test_a_scale_that_is_not_a_positive_finite_size_of_a_fitted_parameter_is_refused(param_scales, said):
    with pytest.raises(ValueError, match=said):
        fit(_block(), PositionLoss(np.zeros((1, 80, 3)), frames=[2]), ["hardening"], steps=2, dt=DT,
            param_scales=param_scales, progress=False, diagnostics=False)


def test_a_scale_of_a_parameter_fitted_as_its_logarithm_is_refused():
    with pytest.raises(ValueError, match=r"^param_scales\['mu'\] = 5\.0 is not allowed: mu is fitted as its logarithm"):
        fit(_block(), PositionLoss(np.zeros((1, 80, 3)), frames=[2]), ["mu"], steps=2, dt=DT,
            param_scales={"mu": 5.0}, progress=False, diagnostics=False)


def test_a_log_space_parameter_starting_at_zero_is_refused_naming_why_and_a_linear_one_takes_its_bounds():
    """A yield stress of 0 (a Maxwell fluid, which the material takes) has no logarithm: the
    fit refuses it, saying it is fitted as its logarithm and how to start it. A viscosity
    from 0 with bounds (0, 4) is fitted as itself, its first Adam step lr times the width."""
    loss = PositionLoss(np.zeros((1, 80, 3)), frames=[2])
    with pytest.raises(ValueError, match=r"^yield_stress = 0 is not allowed as the start of a fit: it is fitted as its "
                                         r"logarithm, .*give a start above 0"):
        fit(_block(yield_stress=0.0), loss, ["yield_stress"], steps=2, dt=DT, bounds={"yield_stress": (1e-3, 10.0)},
            progress=False, diagnostics=False)
    r = fit(_block(), loss, ["viscosity"], steps=2, dt=DT, bounds={"viscosity": (0.0, 4.0)}, iterations=1,
            optimizer="adam", progress=False, diagnostics=False)
    assert [h["params"]["viscosity"][0] for h in r.history] == pytest.approx([0.0, 0.4], rel=1e-6)


@pytest.mark.parametrize("params, param_scales, said", [
    ("yield_stress", ["hardening=0"], "--param-scales 'hardening=0' is not allowed: the size must be > 0 and finite"),
    ("yield_stress", ["hardening=nan"], "--param-scales 'hardening=nan' is not allowed: the size must be > 0 and finite"),
    ("yield_stress", ["hardening"], "--param-scales 'hardening' is not allowed: use NAME=S"),
    ("yield_stress", ["hardening=5"], "--param-scales hardening=5 is not allowed: hardening is not fitted (--params = yield_stress)"),
    ("yield_stress", ["yield_stress=5"], "--param-scales yield_stress=5 is not allowed: yield_stress is fitted as its logarithm"),
])
@pytest.mark.parametrize("stage", [[], ["--samples", "2"]])
def test_cli_fit_param_scales_refused_are_one_line_naming_the_entry(tmp_path, capsys, dough_scene, params, param_scales,
                                                                    said, stage):
    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0]), frames=[2])
    capsys.readouterr()
    out = tmp_path / "fit"
    extra = [a for s in param_scales for a in ("--param-scales", s)]
    assert main(["fit", str(guess), "--target", str(target), "--params", params, *extra, "--iterations", "1",
                 "--no-progress", "--no-usd", "--output-dir", str(out), *stage]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("warp-esph fit: ")]
    assert len(err) == 1 and err[0].startswith(f"warp-esph: error: {said}"), err
    assert not out.exists()


def test_cli_fit_param_scales_reach_the_fit(tmp_path, dough_scene):
    """--param-scales hardening=S sizes the steps of a hardening fitted from 0: the first Adam step
    moves it by --lr times S."""
    import json

    from warp_esph.cli import main
    from warp_esph.scenes import load_scene

    guess = tmp_path / "guess.toml"
    guess.write_text(dough_scene(yield_stress=200.0, flow_rate=20.0, frames=2))
    x0 = load_scene(str(guess)).builder.finalize().particle_x0
    target = tmp_path / "t.npz"
    np.savez(target, positions=np.stack([x0 + 1e-3]), frames=[2])
    out = tmp_path / "fit"
    assert main(["fit", str(guess), "--target", str(target), "--params", "hardening", "--param-scales", "hardening=250",
                 "--optimizer", "adam", "--iterations", "1", "--no-progress", "--no-usd", "--no-diagnostics",
                 "--output-dir", str(out)]) == EXIT_NOT_CONVERGED  # the cap of 1
    doc = json.loads((out / "fit.json").read_text())
    assert doc["param_scales"] == {"hardening": {"size": 250.0, "from": "given"}}
    steps = [h["params"]["hardening"][0] for h in doc["history"]]
    assert steps[0] == 0.0 and abs(steps[1]) == pytest.approx(25.0, rel=1e-6)


@pytest.mark.parametrize("name, truth, size", [("viscosity", 2.0, None), ("lam", 500.0, 1.0e3)])
def test_a_viscosity_or_lam_fitted_from_zero_takes_the_same_path_in_any_units(name, truth, size):
    """As the hardening: a viscosity (Pa s) from 0 is sized by mu times the stable step, lam
    (Pa) by mu, so Adam visits the same values in units 1e3 times smaller; with the old size
    of 1 in any unit the mPa problem moved a thousandth as far."""
    x = Rollout(_block(**{name: truth}), STEPS, DT, frames=[3, 6]).forward(alpha0=ALPHA0)
    paths = []
    for units in (1.0, 1.0e3):
        r = fit(_block(units, **{name: 0.0}), PositionLoss(x, frames=[3, 6]), [name], steps=STEPS, dt=DT,
                initial={"alpha0": ALPHA0}, iterations=3, optimizer="adam", progress=False, diagnostics=False)
        assert r.param_scales[name]["from"] == "material"
        if size is not None:
            assert r.param_scales[name]["size"] == pytest.approx(size * units, rel=1e-12)
        paths.append(np.array([h["params"][name][0] / units for h in r.history]))
    np.testing.assert_allclose(paths[1], paths[0], rtol=1e-6, atol=1e-9 * abs(paths[0]).max())
    assert abs(paths[0][1]) > 0.01 * truth  # lr = 0.1 of its size: a step of its own order


@pytest.mark.parametrize("stage, method, kw", [("descent", "value_and_grad", {}),
                                               ("global stage", "value", {"samples": 3})])
def test_an_interrupted_fit_records_its_param_scales(target, monkeypatch, stage, method, kw):
    """A Ctrl-C keeps the evaluations so far and their best (``FitInterrupted.result``, which
    ``warp-esph fit`` writes to fit.json): its history's steps were sized by the scales as a
    finished fit's were, and its ``param_scales`` came back empty, so the record of an interrupted
    fit did not say what a step of lr had moved."""
    from warp_esph import fit as fit_module
    from warp_esph.fit import FitInterrupted

    calls, original = [], getattr(fit_module._Problem, method)

    def interrupted(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3 - (stage == "global stage"):
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(fit_module._Problem, method, interrupted)
    with pytest.raises(FitInterrupted) as info:
        _path(target, 1.0, "adam", **kw)
    result = info.value.result
    assert result is not None and result.stopped == "interrupted"
    assert {h["stage"] for h in result.history} == {"sample" if stage == "global stage" else "descent"}
    assert result.param_scales == {"hardening": {"size": 1.0e3, "from": "material"}}  # mu, as the finished fit's
    assert result.to_dict()["param_scales"] == result.param_scales
