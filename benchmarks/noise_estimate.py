"""The noise the diagnostics estimate where none is stated, over noise draws of known
standard deviation: ``sqrt(SSR / (N - P))`` (``diagnostics.estimated_noise``) against the
residuals' plain RMS, ``sqrt(SSR / N)``, which it replaced, and the standard errors against
the spread of the fitted values.

    python -m benchmarks.noise_estimate                          # 40 draws, every particle
    python -m benchmarks.noise_estimate --draws 400 --particles 0,7

An 8-particle elastic cube (mu = 2 kPa, lambda = 3 kPa, float64) lands on the ground at
1 m/s; its positions after 100 steps, plus Gaussian noise ``--sigma`` (m), are fitted for
mu and lambda (P = 2) by Gauss-Newton from the truth, 15 iterations, and diagnosed with
``noise=None``. Prints the mean over draws of each variance estimate over the true variance
(1 is unbiased) and, per parameter, the spread of the fitted log values against the RMS of
their standard errors (the old estimate's: scaled by the ratio of the two noises). Not a test.
"""

import sys

import numpy as np
import warp as wp

import warp_esph as we
from warp_esph.fit import fit
from warp_esph.losses import PositionLoss
from warp_esph.rollout import Rollout

from . import _cli

PROG = "python -m benchmarks.noise_estimate"

STEPS = 100
PARAMS = ["mu", "lam"]
TRUTH = {"mu": 2e3, "lam": 3e3}


def cube(**values):
    v = {**TRUTH, **values}
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.025, 0.0), (0.04, 0.04, 0.04), we.Material(mu=v["mu"], lam=v["lam"], density=1000.0,
              yield_stress=300.0, flow_rate=10.0), velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    return b.finalize(dtype=wp.float64, requires_grad=True)


def main(argv=None):
    ap = _cli.Parser(prog=PROG, description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=_cli.int_at_least(2), default=40, help="noise draws, each a fit (default 40)")
    ap.add_argument("--sigma", type=_cli.number(lo=0.0, lo_open=True), default=1e-3, help="noise (m, default 1e-3)")
    ap.add_argument("--particles", default="all", help="observed particles: 'all' or indices in 0..7, e.g. 0,7")
    ap.add_argument("--seed", type=_cli.nonnegative_int, default=11)
    a = ap.parse_args(argv)
    if a.particles == "all":
        parts = list(range(8))
    else:
        parts = _cli.int_list(lo=0)(a.particles, "--particles")
        if max(parts) > 7 or len(set(parts)) != len(parts):
            raise _cli.refuse("--particles", a.particles, "must be distinct particle indices in 0..7, or 'all'")
    from warp_esph.startup import init_warp  # noqa: PLC0415

    init_warp()
    model = cube()
    dt = 0.5 * model.stable_dt()
    truth = np.asarray(Rollout(model, STEPS, dt, frames=[STEPS]).forward(), dtype=np.float64)[-1][parts]
    rng = np.random.default_rng(a.seed)
    n, p = truth.size, len(PARAMS)
    noise, rms, logs, rel = [], [], [], []
    for _ in range(a.draws):
        target = truth + a.sigma * rng.standard_normal(truth.shape)
        r = fit(cube(), PositionLoss({STEPS: target}, particles=parts), PARAMS, steps=STEPS, dt=dt,
                optimizer="gauss-newton", iterations=15, progress=False)
        d = r.diagnostics
        noise.append(d.noise[0])
        rms.append(d.residual_rms[0])
        logs.append(np.log([r.params[q][0] for q in PARAMS]))
        rel.append(d.relative_error)
    noise, rms, logs, rel = (np.array(v, dtype=np.float64) for v in (noise, rms, logs, rel))
    new, old = noise**2 / a.sigma**2, rms**2 / a.sigma**2
    print(f"N = {n} residuals, P = {p}, {a.draws} draws of sigma = {a.sigma:g} m")
    print(f"mean estimated variance / true: sqrt(SSR/(N-P)) {new.mean():.3f} +- {new.std() / np.sqrt(a.draws):.3f}, "
          f"RMS (before) {old.mean():.3f} (expected (N-P)/N = {(n - p) / n:.3f})")
    scale = np.sqrt(old.mean() / new.mean())
    for j, q in enumerate(PARAMS):
        se = float(np.sqrt(np.mean(rel[:, j] ** 2)))
        print(f"{q}: spread of log {q} {np.std(logs[:, j], ddof=1):.4f}; RMS standard error {se:.4f} "
              f"(before: {se * scale:.4f})")


if __name__ == "__main__":
    sys.exit(_cli.run(main, PROG))
