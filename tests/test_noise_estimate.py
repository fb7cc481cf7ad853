"""The noise the diagnostics estimate where none is stated: ``sqrt(SSR / (N - P))`` of the
``N`` residuals at the fitted point for ``P`` fitted values. Their plain RMS had been taken,
which the fit draws low (its square averages ``(N - P) / N`` of the variance)."""

import math

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.diagnostics import diagnose
from warp_esph.losses import PositionLoss
from warp_esph.rollout import Rollout

STEPS = 20
FRAMES = [10, 20]
PARAMS = ["yield_stress", "flow_rate"]


def _cube(yield_stress=300.0):
    """8 particles of a soft plastic cube landing on the ground at 1 m/s, float64."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.025, 0.0), (0.04, 0.04, 0.04), we.Material(mu=2e3, lam=3e3, density=1000.0,
              yield_stress=yield_stress, flow_rate=10.0), velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    return b.finalize(dtype=wp.float64, requires_grad=True)


@pytest.fixture(scope="module")
def landing():
    model = _cube()
    dt = 0.5 * model.stable_dt()
    x = Rollout(model, STEPS, dt, frames=FRAMES).forward()
    return dt, np.asarray(x, dtype=np.float64)


def test_estimated_noise_is_the_residuals_root_sum_of_squares_over_n_minus_p():
    from warp_esph.diagnostics import estimated_noise  # noqa: PLC0415

    assert estimated_noise(8.0, 10, 2) == pytest.approx(1.0)
    assert estimated_noise(8.0, 2, 2) is None and estimated_noise(8.0, 1, 2) is None


def test_the_noise_estimated_from_positions_counts_the_fitted_values(landing):
    """48 residuals (8 particles, 2 frames, 3 coordinates), 2 fitted values: the noise is
    ``sqrt(SSR / 46)``, the SSR from a run of its own at the diagnosed point; their RMS,
    ``sqrt(SSR / 48)``, is still reported as the residual RMS."""
    dt, truth = landing
    target = truth + 1e-3 * np.random.default_rng(7).standard_normal(truth.shape)
    d = diagnose(_cube(), PositionLoss(target, frames=FRAMES), PARAMS, steps=STEPS, dt=dt, frames=FRAMES)
    x = np.asarray(Rollout(_cube(), STEPS, dt, frames=FRAMES).forward(), dtype=np.float64)
    ssr = float(np.sum((x - target) ** 2))
    n = target.size
    assert d.observations == n == 48
    assert d.noise[0] == pytest.approx(math.sqrt(ssr / (n - len(PARAMS))), rel=1e-9, abs=0.0)
    assert d.residual_rms[0] == pytest.approx(math.sqrt(ssr / n), rel=1e-9, abs=0.0)
    assert not any("cannot be estimated" in w for w in d.warnings), d.warnings


def test_a_noise_with_no_more_residuals_than_fitted_values_is_said_not_estimable(landing):
    """One particle's height at one frame (3 residuals, of which the fit can zero as many as
    it fits values) against 3 fitted values: nothing is left to estimate the noise from, and
    the warning says the errors lean on an RMS that understates it."""
    dt, truth = landing
    one = truth[-1][:1] + 1e-4
    loss = PositionLoss({FRAMES[-1]: one}, particles=[0])
    d = diagnose(_cube(), loss, PARAMS + ["mu"], steps=STEPS, dt=dt)
    said = [w for w in d.warnings if w.startswith("the noise of the positions cannot be estimated from its 3 residuals "
                                                    "for 3 fitted values")]
    assert len(said) == 1, d.warnings
    stated = diagnose(_cube(), loss, PARAMS + ["mu"], steps=STEPS, dt=dt, noise=1e-4)
    assert not any("cannot be estimated" in w for w in stated.warnings), stated.warnings


def test_positions_whose_stated_noise_is_understated_fail_the_chi_square_and_the_true_noise_passes(landing):
    """Positions drawn with 1 mm noise, diagnosed with the noise stated at half that: their
    RMS is twice the stated noise, a chi-square of about 4 per degree of freedom, which no
    correct model and noise give, and nothing was said (the rule was an RMS above 3 x the
    noise). Stated at its true 1 mm, a fixed set of draws passes the test."""
    dt, truth = landing

    def target(seed):
        return PositionLoss(truth + 1e-3 * np.random.default_rng(seed).standard_normal(truth.shape), frames=FRAMES)

    low = diagnose(_cube(), target(0), PARAMS, steps=STEPS, dt=dt, frames=FRAMES, noise=0.5e-3)
    said = [w for w in low.warnings if w.startswith("the residuals of the experiment (RMS ")]
    assert len(said) == 1 and "46 degrees of freedom" in said[0] and "the noise understated" in said[0], low.warnings
    assert 1.5 < low.residual_rms[0] / 0.5e-3 < 3.0  # below the old rule's 3 x
    for seed in range(3):
        told = diagnose(_cube(), target(seed), PARAMS, steps=STEPS, dt=dt, frames=FRAMES, noise=1e-3)
        (test,) = told.misfit_tests
        assert test["passed"] and test["dof"] == 46 and test["noise"] == 1e-3, (seed, test)
        assert not any("degrees of freedom" in w for w in told.warnings), (seed, told.warnings)
