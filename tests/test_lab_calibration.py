"""``examples/calibrate_from_lab.py`` at CI size: the closed-form inversions invert their
forward formulas, and the joint fit of a slump (final height and spread) and a compression
force curve, from synthetic lab files with noise, recovers the hidden yield stress and
plastic viscosity from 2x guesses (within 3 standard errors; without the noise, within 1 %)."""

import json
import math

import pytest

from warp_esph.fit import LR_OPTIMIZERS, OPTIMIZERS

def test_closed_form_inversions_invert_their_formulas(load_example):
    ex = load_example("calibrate_from_lab")
    rho_g = ex.RHO * ex.G
    for S in (0.05, 0.3, 0.8):
        h = 0.1 * S * (1.0 - math.log(S))
        assert ex.invert_slump_height(h, 0.1) == pytest.approx(S * rho_g * 0.1, rel=1e-9)
    volume, tau_y = 7.85e-4, 120.0
    R = (225.0 * rho_g * volume**2 / (128.0 * math.pi**2 * tau_y)) ** 0.2
    assert ex.invert_spread(R, volume) == pytest.approx(tau_y, rel=1e-9)
    # A perfectly plastic sample at constant volume: F = sigma_y * volume / H.
    press = {"height": 0.02, "speed": 0.1, "volume": 6.0e-6}
    rows = [{"frame": f, "time": f / 200.0, "tool": "plate",
             "force": [0.0, -300.0 * press["volume"] / (0.02 - 0.1 * f / 200.0), 0.0]} for f in range(11)]
    assert ex.invert_plateau(rows, press) == pytest.approx(300.0, rel=1e-12)


def test_joint_fit_of_slump_and_compression_recovers_yield_stress_and_plastic_viscosity(tmp_path, load_example):
    """48-particle slump (0.3 s) and 48-particle compression (250 steps). With the lab's
    noise each value lies within 3 of the diagnostics' standard errors, which are below a
    quarter of the value; without it, started where the noisy fit ended, the fit recovers
    the truth within 1 % (measured +0.07 / +0.17 % yield stress, +0.03 / +0.08 % flow rate,
    poly6 / biweight). The noise alone moves the fit by up to about twice its standard
    error, which is 13-17 % of the yield stress at this size: the noise's seeds 1-6 put the
    yield stress 0.0-1.9 / 0.2-1.5 standard errors off (-0.0 to +27.7 / +3.0 to +25.9 %), so
    the bound of 15 % this test had held at seed 1 for poly6 (+12.3 %) and not for the
    biweight (+19.3 %), and missed two of the six seeds with either (docs/physics.md, "The
    switch list worked through")."""
    import dataclasses

    ex = load_example("calibrate_from_lab")
    assert ex.main(["--size", "ci", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "result.json").read_text())
    assert (tmp_path / "compression_tools.csv").exists() and (tmp_path / "slump.json").exists()
    true, fitted, se = doc["true"], doc["fitted"], doc["standard_error"]
    for name in ("yield_stress", "flow_rate"):
        assert abs(fitted[name] - true[name]) < 3.0 * se[name], name
        assert se[name] < 0.25 * true[name], name
    # The same lab without noise (1e-9 of it: the chi-square's weights stay finite), the fit
    # started where the noisy one ended.
    quiet = dataclasses.replace(ex.SETUPS["ci"], length_noise=1e-9, force_noise=1e-9)
    ex.measure(str(tmp_path / "quiet"), quiet)
    result = ex.calibrate(str(tmp_path / "quiet"), quiet, fitted)
    for name, value in ex.TRUE.items():
        assert result.params[name][0] == pytest.approx(value, rel=1e-2), (name, result.params, result.stopped)


def test_an_out_that_is_a_file_or_an_unknown_optimizer_is_one_line_of_usage_error_before_any_work(tmp_path, capsys, monkeypatch,
                                                                                                  load_example):
    """``--out`` naming a file ended in os.makedirs' FileExistsError traceback, and a
    ``LAB_OPTIMIZER`` the fit does not know in the fit's traceback after both lab runs; each is
    now one line of usage error (exit 2) before anything runs."""
    a_file = tmp_path / "taken"
    a_file.write_text("")
    for env, argv, words in ((None, ["--size", "ci", "--out", str(a_file)], f"argument --out: {str(a_file)!r} is a file, not a folder"),
                             ("sgd", ["--size", "ci", "--out", str(tmp_path / "lab")],
                              # fit's own list: the example kept a copy of its own.
                              f"LAB_OPTIMIZER = 'sgd' is not allowed: must be one of {', '.join(map(repr, OPTIMIZERS))}")):
        if env is None:
            monkeypatch.delenv("LAB_OPTIMIZER", raising=False)
        else:
            monkeypatch.setenv("LAB_OPTIMIZER", env)
        ex = load_example("calibrate_from_lab")  # reads LAB_OPTIMIZER as it is loaded
        ran = []
        monkeypatch.setattr(ex, "measure", lambda *a, **k: ran.append(a))
        with pytest.raises(SystemExit) as info:
            ex.main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert info.value.code == 2 and ran == []
        assert err[-1].split(": error: ", 1)[1] == words
    assert not (tmp_path / "lab").exists()


def test_fit_dough_star_offers_the_optimizers_fit_sizes_by_lr(tmp_path, capsys, load_example):
    """fit_dough_star's --optimizer kept its own copy of fit's names; it offers those of
    ``fit.LR_OPTIMIZERS`` (it gives fit an lr, which Gauss-Newton refuses): each is taken, up to
    the --out check before any run, and every other one of fit's is one line of usage error."""
    ex = load_example("fit_dough_star")
    a_file = tmp_path / "taken"
    a_file.write_text("")
    for optimizer in OPTIMIZERS:
        with pytest.raises(SystemExit) as info:
            ex.main(["--optimizer", optimizer, "--out", str(a_file)])
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert info.value.code == 2
        if optimizer in LR_OPTIMIZERS:
            assert err.endswith(f"argument --out: {str(a_file)!r} is a file, not a folder"), err
        else:
            assert f"argument --optimizer: invalid choice: {optimizer!r}" in err, err


@pytest.mark.parametrize("name", ["calibrate_from_lab", "fit_dough_star", "press_and_fit"])
def test_each_example_runs_from_a_checkout_without_the_package_installed(name):
    """``python examples/NAME.py`` from a checkout where warp_esph is not installed: the other
    two examples put the checkout on the path, calibrate_from_lab ended in
    ``ModuleNotFoundError: No module named 'warp_esph'``. ``-S`` leaves out the site packages'
    .pth files (the editable install's among them); the folder holding warp is given by hand."""
    import pathlib
    import subprocess
    import sys

    import warp

    root = pathlib.Path(__file__).resolve().parents[1]
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(pathlib.Path(warp.__file__).resolve().parents[1]), "CI": "true"}
    done = subprocess.run([sys.executable, "-S", str(root / "examples" / f"{name}.py"), "--help"], cwd=root, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith(f"usage: {name}.py")
