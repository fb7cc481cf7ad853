"""The functions of examples/press_and_fit.py (and of notebooks/press_and_fit.ipynb, which
imports them): the tape's derivatives of both losses match float64 central differences, and
the two optimisations reach their targets."""

import pathlib
import sys

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "examples"))
import press_and_fit as pf  # noqa: E402

TARGET = 0.021


def test_press_optimisation_reaches_the_target_top_height_and_its_keyframe_derivative_is_the_central_difference():
    """``optimise_press`` (the notebook's part 1): measured depth 13.84 mm, mean top 21.00 mm
    for the 21 mm target in 6 evaluations (docs/tools.md; with the poly6 fit weight, the default
    before, 14.31 mm in 6, and 13.86 mm in 7 before the tool contact's tangential displacement
    was taken from the particle's start).

    Its third evaluation, at a 16 mm press depth (two fixed 2 mm steps down from 20 mm), is
    the tape's derivative checked against float64 central differences: the search's own
    taped run, as the notebook reads it (this was a test of its own, which ran that taped
    press again). Measured: tape +1.0846837622e-3, central difference with h = 1e-8 m
    +1.0846837645e-3, 2e-9 apart relative to it (with poly6 7.994066e-4 and 2.8e-8, on an
    earlier build 7.918920e-4 and 3e-8); with the tape's derivative off by 1e-4 of itself the check fails.
    The loss is only piecewise smooth in the depth (the base's friction and the yielding
    switch on and off at kinks): with h = 1e-6, 1e-5, 1e-4 m the central differences were
    7.918e-4, 7.43e-4, 8.84e-4 on that build (7.993e-4 at 1e-6 and 8.94e-4 at 1e-4 m on the
    next; the same sign, the scale of the trend), so the exact check needs the small step."""
    history, positions = [], {}
    depth = pf.optimise_press(TARGET, history=history, positions=positions)
    d16, _, _, g = history[2]
    assert d16 == pytest.approx(0.016, abs=1e-12)
    h = 1e-8
    fd = (pf.press_loss(np.array([d16 + h, 0.03]), TARGET)[0] - pf.press_loss(np.array([d16 - h, 0.03]), TARGET)[0]) / (2 * h)
    print(f"d loss / d depth at 16 mm: tape {g:+.10e}, central difference {fd:+.10e}")
    assert g == pytest.approx(fd, rel=1e-5)
    # The search returns the depth it evaluated last: its top is read there, not run again.
    last, _, top, _ = history[-1]
    assert last == depth
    assert top == pytest.approx(TARGET, abs=1e-4)
    assert depth < TARGET  # the dough springs back: the press must go below the target
    # The final positions each evaluation kept (the notebook plots them rather than run the
    # press again): their top layer's mean height is the top that evaluation measured.
    assert list(positions) == [h[0] for h in history]
    for d, _, t, _ in history:
        x0, x = positions[d]
        layer = x0[:, 1] > x0[:, 1].max() - 0.5 * pf.DX
        assert x.shape == x0.shape and layer.sum() == 36
        assert float(np.mean(x[layer, 1])) == pytest.approx(t, rel=1e-12)


def test_force_curve_loss_derivative_matches_central_differences_and_the_fit_recovers_E():
    measured = pf.force_curve(2.0e4)
    assert measured[-1] < 0.0  # the plate pushes the sample down
    logE, h = np.log(1.3e4), 1e-5
    _, _, g = pf.force_curve(np.exp(logE), measured)
    fd = (pf.force_curve(np.exp(logE + h), measured)[1] - pf.force_curve(np.exp(logE - h), measured)[1]) / (2 * h)
    print(f"d loss / d log E: tape {g:+.8e}, central difference {fd:+.8e}")
    assert g == pytest.approx(fd, rel=1e-4)
    E = pf.fit_stiffness(E_true=2.0e4, E_start=1.0e4)
    assert E == pytest.approx(2.0e4, rel=1e-3)


def test_the_example_refuses_an_option_it_does_not_have_before_any_work(capsys, monkeypatch):
    """The example takes no options. It used to read none either: ``--help`` or a mistyped
    option ran both searches (most of a minute on the shared machine) and exited 0, where the
    other two examples print their usage or refuse it, exit 2."""
    ran = []
    monkeypatch.setattr(pf, "optimise_press", lambda *a, **k: ran.append("press"))
    monkeypatch.setattr(pf, "fit_stiffness", lambda *a, **k: ran.append("fit"))
    with pytest.raises(SystemExit) as info:
        pf.main(["--iterations", "3"])
    assert info.value.code == 2 and ran == []
    assert "unrecognized arguments: --iterations 3" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        pf.main(["--help"])
    assert info.value.code == 0 and ran == []
    assert "Gradients through a tool" in capsys.readouterr().out
