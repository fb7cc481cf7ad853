"""``examples/fit_dough_star.py`` itself (the notebook of the same name calls its functions one
step per cell; tests/test_notebook.py runs it at a size that checks the wiring only, so this
is the one test that the fit recovers the parameters): at the notebook's CI size (142 particles, frames 2..9, 20
evaluations after the first) the example's ``main`` fits mu, yield stress and flow rate from
the factor-2 guess back within its 10 % (measured: 21 evaluations, loss 7.0e-7 -> 1.0e-21,
converged, every parameter within 0.00 %; 18 s with the diagnostics and plots)."""

import json

import pytest

def test_fit_dough_star_example_recovers_the_three_parameters(tmp_path, load_example):
    pytest.importorskip("matplotlib")
    ex = load_example("fit_dough_star")
    assert ex.main(["--frames", "9", "--iterations", "20", "--no-usd", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["particles"] == 142 and doc["frames"] == list(range(2, 10))
    for name in ex.PARAMS:
        assert doc["initial"][name] == pytest.approx(2.0 * doc["truth"][name])
        assert doc["fitted"][name] == pytest.approx(doc["truth"][name], rel=0.10), name
    assert doc["loss"] < 1e-6 * doc["initial_loss"]
    assert (tmp_path / "target.npz").exists() and (tmp_path / "fit_loss.png").stat().st_size > 10_000
