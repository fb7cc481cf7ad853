"""How well the data determine fitted parameters: Fisher (Gauss-Newton) diagnostics at an optimum.

A loss on observed positions is a scaled sum of squared residuals: ``S = c L`` with
``c`` from the loss's normalisation (``Loss.residual_scale``: e.g. frames x particles /
weight for a ``PositionLoss``). With independent Gaussian observation noise of standard
deviation ``sigma`` per residual, ``chi2 = S / sigma^2`` and the Fisher information of the
parameters ``z`` (optimiser space: ``log p`` for positive parameters) is

    I = J^T J / sigma^2      (Gauss-Newton: 1/2 d2 chi2 / dz2 at a zero-residual optimum)

with ``J`` the derivative of the residual vector (``Loss.residuals``) with respect to
``z``, from central differences of forward runs (``2 P + 1`` runs for ``P`` values). For a
loss without a residual vector, ``I`` is half the Hessian of ``chi2`` from central
differences of taped gradients: column ``j`` is ``(g(z + h e_j) - g(z - h e_j)) / (4 h)``,
``2 P`` forward + backward evaluations. The covariance of the estimate is ``I^-1`` (a
pseudo-inverse: a direction with no curvature has infinite variance); standard errors are
the square roots of its diagonal (in log space: relative errors), correlations its
normalised entries.

``sensitivity[i] = sqrt(I_ii)``: how many noise standard deviations (root of the chi-square
increase) a unit change of ``z_i`` alone moves the fit; a 1 % change of a log-space
parameter moves it by ``0.01 * sensitivity``.

A parameter is reported as **not determined** by the data when its relative standard
error exceeds ``max_relative_error``, when its sensitivity is below ``min_sensitivity``
times the largest (the data barely depend on it; e.g. a yield stress far below the
stresses that drive the flow, where the flow rule's ``(|s| - Y) / |s|`` hardly changes
with ``Y``), or when it is correlated with another beyond ``max_correlation`` (the data
fix a combination of the two, e.g. yield stress and flow rate along a valley).

The Fisher matrix describes the loss near the optimum only. A **range check** therefore
also moves each log-space parameter alone by a factor ``RANGE_FACTOR`` (1.5) both ways
(``2 P`` forward runs; ``Diagnostics.evaluations`` counts these, the differences' and the
run at ``z`` that sizes the noise, up to ``4 P + 1`` in all, with the Hessian too: Gauss-Newton's
residuals at ``z`` and the chi-square the range check starts from are read from that run's
observations, kept, where each had run ``z`` again for the same bits; after a fit that run is
the fit's own at its best point where it ran with the same inputs, ``4 P`` then): if the chi-square changes by less than 1 on either side, the data
cannot tell these values apart and the parameter is reported as not determined, whatever
the local curvature says (if it falls by 1 or more, the fit did not end at the minimum
along it, which a warning says: stopped short on a slope, or, where the slope and curvature
at ``z`` put no fall of 1 nearby, in a local minimum that more iterations do not leave) (a silhouette fit stopped at 1.88 x the true yield stress, where
the loss is curved but 0.15 % below its value at 1.5 x less).

A value held at one of the fit's bounds, where the chi-square falls beyond the bound by 1 or
more (``BOUND_FALL``, as the range check; by its slope and curvature there), is
named in ``at_bound`` and a warning: the data's best value lies outside the bounds, and its
Fisher error is the curvature at the bound, no interval about a value the data chose.

Silhouette residuals are pixels, and the pixels within a particle's splat rise and fall
together: each silhouette loss counts one observation per splat area ``pi (2 s)^2``
(``SilhouetteLoss.correlated_pixels``), i.e. its pixel noise is multiplied by the square
root of that area.

The model's own bias: with the paper's poly6 fit weight the particles of a material that
has flowed past a log strain of about 0.53 rearrange, and it carries 0.63-0.74 of the
Bingham stress at 8-12 particles across (docs/fitting.md, "Keep the measured flow to
moderate strains"); a fit to such a flow makes up for it with a larger yield stress or
flow rate. Where more than ``LARGE_STRAIN_SHARE`` of a run's particles end with a plastic
strain ``alpha`` above ``LARGE_STRAIN_ALPHA`` (of the particles whose material can flow),
``bias`` says so (``large_strain_bias``).

Noise: ``noise`` (m) for geometric losses; a loss with its own ``noise`` attribute (the
silhouette loss, in occupancy units) uses that. With ``noise=None`` it is estimated from
the ``N`` residuals at the optimum as ``sqrt(SSR / (N - P))`` (``estimated_noise``; ``P``
fitted values: the fit drew the residuals towards zero along ``P`` directions, so their
plain RMS ``sqrt(SSR / N)`` reads low), floored at 1 % of the particle spacing (a synthetic
target fits to round-off, which would make every parameter look perfectly determined);
where ``N <= P`` nothing is left to estimate it from, and a warning says the RMS used
instead understates it. Each experiment is charged all ``P`` (they share the values). A
force curve (``ReactionForceLoss``, newtons) whose noise was not stated gets its own
estimate the same way, floored at its ``noise`` (1 % of its RMS force); its residuals are
checked against a stated noise term by term (a warning naming the curve), since they cannot
join the metres of the experiment's RMS.

The residual test (``misfit_tests``): each group of residuals whose noise was stated (an
experiment's geometric residuals, a force curve) gives ``chi2 = SSR / sigma^2``, on ``n - P``
degrees of freedom where it is the only group and ``n`` where there are several (each holds at
most its share of the ``P`` values the fit drew the residuals along). Past its
``MISFIT_QUANTILE`` (99.9 %) quantile a warning says the model does not explain the data
within the stated noise and the standard errors understate the uncertainty: a held value
that is wrong biases the fitted ones by more than their errors, and this is the only sign of
it. A noise estimated from the residuals has nothing to be tested against.
"""

import dataclasses
import math
import statistics

import numpy as np
import warp as wp

from . import checks
from .losses import Loss, SumLoss
from .material import UNITS

__all__ = ["Diagnostics", "diagnose", "diagnose_problem", "chi_square_loss", "leaf_terms", "large_strain_bias", "chi_square_quantile",
           "estimated_noise"]

#: Defaults of the warnings (see the module doc).
MAX_RELATIVE_ERROR = 0.25
MIN_SENSITIVITY = 1e-3
MAX_CORRELATION = 0.95
#: Relative eigenvalue below which a direction of the Fisher matrix counts as flat.
_FLAT = 1e-10
#: The accumulated plastic strain ``State.alpha`` past which the poly6 packing has
#: rearranged: in sustained uniaxial flow (``benchmarks.validation.uniaxial_flow``, 8 and 12
#: across) alpha's median follows 1.22 x the log strain (``sqrt(3/2)``, the norm of an
#: isochoric uniaxial strain) and the body's stress falls from log strain 0.53-0.60, where
#: the median is 0.63-0.69.
LARGE_STRAIN_ALPHA = 0.65
#: The share of a run's particles past ``LARGE_STRAIN_ALPHA`` from which the bias is said.
LARGE_STRAIN_SHARE = 0.1
#: The quantile of the chi-square distribution past which residuals with a stated noise are
#: said not to be explained by it: a correctly specified fit is warned about at a rate of
#: ``1 - MISFIT_QUANTILE`` (0.1 %) per tested group. The RMS rule it replaces (3 x the noise)
#: let a held ``lam`` 60 % wrong bias the press's ``mu`` by 8 standard errors unsaid.
MISFIT_QUANTILE = 0.999


@dataclasses.dataclass
class Diagnostics:
    """Fisher diagnostics at a point of a fit (see the module doc).

    Per fitted value (``labels``, e.g. ``yield_stress`` or ``yield_stress[1]``): ``values``,
    ``spaces`` (``log``/``linear``), ``standard_error`` (parameter units), ``relative_error``
    (``standard_error / |value|``), ``sensitivity`` (``sqrt(I_ii)``), ``gradient`` (of the
    chi-square, optimiser space). ``fisher``, ``covariance`` (optimiser space),
    ``correlation``; ``noise``: the sigma used per experiment; ``residual_rms`` per
    experiment; ``observations``; ``warnings`` (sentences), ``undetermined`` and ``at_bound`` (labels).
    ``weakest``: the least determined direction of optimiser space (unit vector) and its
    standard error.
    """

    labels: list[str]
    values: np.ndarray
    spaces: list[str]
    standard_error: np.ndarray
    relative_error: np.ndarray
    sensitivity: np.ndarray
    gradient: np.ndarray
    fisher: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    noise: list[float]
    residual_rms: list[float]
    observations: int
    weakest: np.ndarray
    weakest_error: float
    warnings: list[str]
    undetermined: list[str]
    evaluations: int
    step: float
    method: str = "gauss-newton"
    #: Per value: the chi-square's change when it alone is divided and multiplied by
    #: ``RANGE_FACTOR`` (NaN: not checked, a linear-space value or at a bound).
    range_rise: np.ndarray | None = None
    notes: list[str] = dataclasses.field(default_factory=list)
    #: Sentences on the model's own bias at this point (``large_strain_bias``): not about
    #: what the data determine, so they do not join ``warnings``.
    bias: list[str] = dataclasses.field(default_factory=list)
    #: Labels of the values held at one of their bounds with the chi-square falling beyond it:
    #: the data's best value lies outside the bounds (a warning says so).
    at_bound: list[str] = dataclasses.field(default_factory=list)
    #: The goodness-of-fit test of each group of residuals whose noise was stated (an
    #: experiment's positions, a force curve): ``residuals`` (which), ``chi_square``, ``dof``,
    #: ``limit`` (its ``MISFIT_QUANTILE`` quantile), ``noise`` (in ``unit``), ``passed``. A noise estimated
    #: from the residuals has nothing to be tested against.
    misfit_tests: list[dict] = dataclasses.field(default_factory=list)

    @property
    def units(self) -> list[str]:
        """Each value's unit (``material.UNITS``; of its value and standard error)."""
        return [UNITS.get(label.split("[")[0], "") for label in self.labels]

    def summary(self) -> str:
        """A table of values, standard errors, sensitivities and correlations, then warnings."""
        noise = ", ".join(f"{s:.3g}" for s in self.noise)
        lines = [f"diagnostics ({self.method}, observation noise sigma = {noise}; "
                 f"{self.observations} observations):"]
        w = max(len(label) for label in self.labels)
        lines.append(f"  {'parameter':<{w}}  {'value':>11}  {'std. error':>11}  {'relative':>9}  {'sensitivity':>11}  unit")
        for k, label in enumerate(self.labels):
            rel = self.relative_error[k]
            rel_s = f"{100 * rel:8.3g}%" if math.isfinite(rel) else "     inf"
            lines.append(f"  {label:<{w}}  {self.values[k]:11.5g}  {self.standard_error[k]:11.4g}  {rel_s:>9}  "
                         f"{self.sensitivity[k]:11.4g}  {self.units[k]}")
        if len(self.labels) > 1:
            lines.append("  correlation:")
            for k, label in enumerate(self.labels):
                row = " ".join(f"{c:+6.3f}" if math.isfinite(c) else "   nan" for c in self.correlation[k])
                lines.append(f"    {label:<{w}}  {row}")
            terms = " ".join(f"{c:+.3f}*{'log ' if s == 'log' else ''}{label}"
                             for c, s, label in zip(self.weakest, self.spaces, self.labels))
            lines.append(f"  least determined direction: {terms} (std. error {self.weakest_error:.3g})")
        for note in self.notes:
            lines.append(f"  ({note})")
        for t in self.misfit_tests:
            # Passed or not: a chi-square near its limit says as much as one past it.
            unit = f" {t['unit']}" if t["unit"] else ""
            lines.append(f"  against the stated noise {t['noise']:.3g}{unit}, {t['residuals']}: chi-square {t['chi_square']:.4g} on "
                         f"{t['dof']} degrees of freedom ({t['chi_square'] / t['dof']:.3g} per degree; "
                         f"{100 * MISFIT_QUANTILE:g} % limit {t['limit'] / t['dof']:.3g})")
        for message in self.warnings:
            lines.append(f"  WARNING: {message}")
        if not self.warnings:
            lines.append("  every fitted parameter is determined by the data at this noise level")
        for message in self.bias:
            lines.append(f"  WARNING (model): {message}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        def fl(a):
            return [float(x) if math.isfinite(float(x)) else None for x in np.ravel(a)]

        n = len(self.labels)
        return {
            "labels": list(self.labels), "values": fl(self.values), "spaces": list(self.spaces),
            "standard_error": fl(self.standard_error), "relative_error": fl(self.relative_error),
            "sensitivity": fl(self.sensitivity), "gradient": fl(self.gradient),
            "fisher": [fl(r) for r in np.reshape(self.fisher, (n, n))],
            "covariance": [fl(r) for r in np.reshape(self.covariance, (n, n))],
            "correlation": [fl(r) for r in np.reshape(self.correlation, (n, n))],
            "noise": list(self.noise), "residual_rms": list(self.residual_rms), "observations": self.observations,
            "weakest": fl(self.weakest), "weakest_error": self.weakest_error if math.isfinite(self.weakest_error) else None,
            "warnings": list(self.warnings), "undetermined": list(self.undetermined),
            "evaluations": self.evaluations, "step": self.step, "method": self.method,
            "range_rise": None if self.range_rise is None else [fl(r) for r in np.reshape(self.range_rise, (n, 2))],
            "notes": list(self.notes), "bias": list(self.bias), "at_bound": list(self.at_bound), "units": self.units,
            "misfit_tests": [dict(t) for t in self.misfit_tests],
        }


def large_strain_bias(model, alpha, where: str = "") -> str | None:
    """The sentence ``Diagnostics.bias`` gets where more than ``LARGE_STRAIN_SHARE`` of the
    particles of materials that can flow (finite yield stress, flow rate > 0) end with their
    ``alpha`` (a final ``State.alpha``, one per particle of ``model``) past
    ``LARGE_STRAIN_ALPHA``, in a model with the poly6 fit weight; else None. ``where`` names
    the run ("experiment 2: ")."""
    alpha = np.asarray(alpha, dtype=np.float64)
    if model.fit_weight != "poly6" or alpha.size == 0:
        return None
    # Only the particles of materials that can flow: an elastic floor or body (alpha 0 for
    # ever) would dilute the share of the flowing ones.
    flows = np.isfinite(model.yield_stress.numpy()) & (model.flow_rate.numpy() > 0.0)
    alpha = alpha[flows[model.particle_material_np]]
    if alpha.size == 0:
        return None
    share = float((alpha > LARGE_STRAIN_ALPHA).mean())
    if share <= LARGE_STRAIN_SHARE:
        return None
    return (f"{where}{100 * share:.0f} % of the particles end past a plastic strain of {LARGE_STRAIN_ALPHA:g} (alpha; a "
            f"uniaxial log strain of about 0.53), where the poly6 fit weight's packing rearranges and carries 0.63-0.74 "
            f"of the Bingham stress at 8-12 particles across: the fitted yield stress or flow rate may be up to 1.6 x "
            f"the material's; measure less flow, or fit a model of the biweight fit weight (SceneBuilder(fit_weight="
            f"'biweight'), [solver] fit_weight = \"biweight\" or --fit-weight biweight; docs/fitting.md, \"Keep the "
            f"measured flow to moderate strains\")")


def leaf_terms(loss: Loss) -> list[Loss]:
    """The individual losses of a (possibly summed) loss."""
    if isinstance(loss, SumLoss):
        return [leaf for _, leaf in loss.terms]
    return [loss]


def leaf_noise(leaf: Loss, noise: float, positions=None) -> float:
    """The noise of one residual of ``leaf``: its own ``noise`` attribute when set, else
    ``noise``; for a leaf whose residuals are correlated in groups (silhouette pixels within
    a splat: ``correlated_pixels``) times the square root of the group size, so that a group
    counts as one observation."""
    sigma = getattr(leaf, "noise", None) or noise
    if positions is not None and hasattr(leaf, "correlated_pixels"):
        sigma *= math.sqrt(leaf.correlated_pixels(positions))
    return sigma


def chi_square_loss(loss: Loss, noise: float, positions=None, sigmas=None) -> Loss:
    """``sum_leaves residual_scale / sigma^2 * leaf``: the chi-square of ``loss``'s residuals
    (``sigma``: ``sigmas[id(leaf)]`` where given, else ``leaf_noise``; ``positions``, numpy
    ``{step: (n, 3)}``, size the groups of correlated residuals). The leaves must have been
    evaluated once (their residual counts are known then)."""
    terms = []
    for leaf in leaf_terms(loss):
        sigma = (sigmas or {}).get(id(leaf)) or leaf_noise(leaf, noise, positions)
        terms.append((leaf.residual_scale() / sigma**2, leaf))
    return SumLoss(terms)


def _term_name(leaf: Loss) -> str:
    return getattr(leaf, "term_name", None) or type(leaf).__name__


def estimated_noise(ssr: float, count: int, fitted: int) -> float | None:
    """``sqrt(SSR / (N - P))``, the noise of ``count`` (N) residuals whose squares sum to
    ``ssr`` after a fit of ``fitted`` (P) values; None where ``N <= P`` (nothing left to
    estimate it from). The fit drew the residuals towards zero along P directions, so their
    plain RMS, ``sqrt(SSR / N)``, reads low: its square's mean is ``(N - P) / N`` of the noise's
    variance."""
    if count <= fitted:
        return None
    return math.sqrt(max(ssr, 0.0) / (count - fitted))


def chi_square_quantile(dof: float, q: float = MISFIT_QUANTILE) -> float:
    """The ``q`` quantile of the chi-square distribution with ``dof`` degrees of freedom, by the
    Wilson-Hilferty cube-root normal approximation (no scipy here): at ``q = 0.999`` 3 % high
    for 1 dof (11.16 against 10.83), 1 % for 5, 0.2 % for 29; high, so it errs towards not
    warning."""
    a = 2.0 / (9.0 * dof)
    return dof * (1.0 - a + statistics.NormalDist().inv_cdf(q) * math.sqrt(a)) ** 3


def misfit_test(which: str, ssr: float, count: int, sigma: float, dof: int, unit: str = "m",
                per: str = "", whose: str = "the") -> tuple[dict, str | None]:
    """The goodness-of-fit test of ``count`` residuals whose squares sum to ``ssr`` against a
    stated noise ``sigma``: ``chi2 = ssr / sigma^2`` on ``dof`` degrees of freedom, past the
    ``MISFIT_QUANTILE`` quantile. Returns the test (a dict for ``Diagnostics.misfit_tests``)
    and its warning, None where it passes."""
    chi2 = ssr / sigma**2
    limit = chi_square_quantile(dof)
    test = {"residuals": which, "chi_square": chi2, "dof": dof, "limit": limit, "noise": sigma, "unit": unit,
            "passed": bool(chi2 <= limit)}
    if chi2 <= limit:
        return test, None
    rms = math.sqrt(ssr / count)
    u = f" {unit}" if unit else ""
    return test, (f"the residuals of {which} (RMS {rms:.3g}{u}{per}) are {rms / sigma:.3g} times {whose} stated "
                  f"noise {sigma:.3g}{u}: chi-square {chi2:.4g} on {dof} degrees of freedom, {chi2 / dof:.3g} per "
                  f"degree, past {limit / dof:.3g}, its {100 * MISFIT_QUANTILE:g} % limit (a correct model with the stated "
                  f"noise passes it but once in {1.0 / (1.0 - MISFIT_QUANTILE):.0f} fits): the model does not explain the "
                  "data within the stated noise (a held value wrong, an effect the model lacks, a fit short of its minimum, "
                  "or the noise understated), and the standard errors, which assume it does, understate the uncertainty")


def _unestimated(which: str, count: int, fitted: int) -> str:
    return (f"the noise of {which} cannot be estimated from its {count} residuals for {fitted} fitted values (it needs "
            f"more residuals than fitted values): the diagnostics use their RMS, which understates the noise, so the "
            f"errors are too small; state the noise")


def _own_noise_terms(loss: Loss, positions, fitted: int = 0) -> list[tuple]:
    """``(leaf, residual RMS, sigma, stated, residual count)`` of each term whose residuals are in
    units of their own, with their own noise (a force curve, a slump's stated lengths), at the
    last forward (``positions``: numpy observations). Silhouettes (pixels grouped by splat) are
    left to their own noise. ``sigma`` is the stated noise, or, where the term's noise was not
    stated (``noise_stated`` False), ``estimated_noise`` of its residuals for ``fitted`` values
    (their RMS where there are too few), floored at its ``noise``: as positions' noise is
    estimated, so that the errors follow the data's scatter."""
    out = []
    for leaf in leaf_terms(loss):
        if getattr(leaf, "noise", None) is None or hasattr(leaf, "correlated_pixels") or not hasattr(leaf, "residuals"):
            continue
        res = np.asarray(leaf.residuals(positions), dtype=np.float64).ravel()
        if hasattr(leaf, "reset_residuals"):
            leaf.reset_residuals()  # nearest points chosen here are not the diagnostics' own
        ssr = float(np.sum(res * res))
        t_rms = math.sqrt(ssr / res.size) if res.size else 0.0
        stated = getattr(leaf, "noise_stated", True)
        unbiased = estimated_noise(ssr, res.size, fitted)
        t_sigma = leaf.noise if stated else max(t_rms if unbiased is None else unbiased, leaf.noise)
        out.append((leaf, t_rms, t_sigma, stated, res.size))
    return out


def _residuals(run, positions) -> tuple[float, int, float]:
    """(sum of squared geometric residuals, their count, spacing) of a run observed at ``positions``."""
    total, count = 0.0, 0
    for leaf in leaf_terms(run.loss):
        if getattr(leaf, "noise", None) is not None:
            continue
        total += leaf.residual_scale() * leaf.value(positions)
        count += leaf.observation_count()
    return total, count, run.model.spacing


#: Geometric residuals past this many times the particles' own spread at the start are no noise (``_no_noise``).
NO_NOISE_SPREAD = 2.0


def _no_noise(r: float, model, which: str) -> str | None:
    """A sentence where the geometric residuals' RMS ``r`` (per coordinate of positions; a
    cloud's or a mesh's is a distance per point) is past ``NO_NOISE_SPREAD`` times the scene's
    particles' own spread about their centroid at the start (per coordinate; a cube's is 0.29
    of its side, so the bar is 0.58 of it): no measurement misses by that much, and a material
    value only where the fit stopped far from the target (a local minimum, a bound). A run of
    another scene (the dough block placed 0.5 m away) was fitted with its residuals taken for
    the noise (0.289 m per coordinate, 12.9 times the block's spread), the values said only to
    be undetermined."""
    x0 = np.asarray(model.particle_x0, dtype=np.float64)
    if not r > 0.0 or len(x0) < 2:
        return None
    size = float(np.sqrt(np.mean((x0 - x0.mean(axis=0)) ** 2)))
    if not r > NO_NOISE_SPREAD * size > 0.0:
        return None
    return (f"{which}positions' residuals (RMS {r:.3g} m per coordinate) are {r / size:.3g} times the spread of the scene's "
            f"particles at the start ({size:.3g} m per coordinate): no noise misses by that much, so the target does not "
            "follow this scene (a run of another scene, placement or --scale, or positions in other units or axes) or the "
            "fit stopped far from it (a local minimum, a bound); the standard errors, read against these residuals, mean "
            "nothing")


def _has_residuals(prob) -> bool:
    return all(hasattr(leaf, "residuals") for run in prob.runs for leaf in leaf_terms(run.loss))


def _scaled_residuals(prob, z, sigmas, leaf_sigmas) -> np.ndarray:
    """Every residual of every experiment divided by its noise, at ``z`` (forward passes)."""
    prob.apply(z)
    observed = []
    for run in prob.runs:
        run.value_forward()
        observed.append(run.rollout.observations(numpy=True))
    return _scaled_residuals_of(prob, observed, sigmas, leaf_sigmas)


def _scaled_residuals_of(prob, observed, sigmas, leaf_sigmas) -> np.ndarray:
    """``_scaled_residuals`` of runs already made: ``observed``, each run's numpy observations."""
    out = []
    for run, sigma, positions in zip(prob.runs, sigmas, observed):
        for leaf in leaf_terms(run.loss):
            out.append(leaf.residuals(positions) / leaf_sigmas.get(id(leaf), sigma))
    return np.concatenate(out)


def _scaled_residuals_kept(prob, at_z, sigmas, leaf_sigmas) -> np.ndarray:
    """``_scaled_residuals`` at the point whose observations ``at_z`` (``_kept_observations``,
    one per run) were kept: no run."""
    return _scaled_residuals_of(prob, [_numpy_observations(o) for o in at_z], sigmas, leaf_sigmas)


def _kept_observations(run) -> dict:
    """The observations of ``run``'s last forward, copied: the next forward overwrites the
    rollout's own (and on the CPU ``numpy=True`` gives views of them)."""
    return {k: wp.clone(v) if isinstance(v, wp.array) else v for k, v in run.rollout.observations().items()}


def _numpy_observations(observed: dict) -> dict:
    return {k: v.numpy() if isinstance(v, wp.array) else v for k, v in observed.items()}


#: The range check: each log-space parameter alone is moved by this factor both ways.
RANGE_FACTOR = 1.5


def _chi_square_at(prob, z, chi2s) -> float:
    """The chi-square of every experiment at ``z`` (forward passes only)."""
    prob.apply(z)
    total = 0.0
    for run, chi2 in zip(prob.runs, chi2s):
        run.value_forward()
        total += chi2.value(run.rollout.observations())
    return total


def _chi_square_of(chi2s, observed) -> float:
    """``_chi_square_at`` of runs already made: ``observed``, each run's observations."""
    total = 0.0
    for chi2, positions in zip(chi2s, observed):
        total += chi2.value(positions)
    return total


def diagnose_problem(prob, z, noise: float | None = None, step: float = 1e-3, method: str = "auto",
                     max_relative_error: float = MAX_RELATIVE_ERROR, min_sensitivity: float = MIN_SENSITIVITY,
                     max_correlation: float = MAX_CORRELATION, kept=None) -> Diagnostics:
    """Diagnostics of ``fit``'s problem at optimiser-space point ``z`` (see the module doc).

    ``method``: ``"gauss-newton"`` (``I = J^T J`` from central differences of the residual
    vectors, forward passes only; every loss must have ``residuals``, as ``PositionLoss``,
    ``ChamferLoss`` (nearest points kept from ``z``), ``MeshLoss`` (tangent planes kept
    from ``z``) and ``SilhouetteLoss`` do), ``"hessian"`` (central differences of taped gradients of
    the chi-square; any loss) or ``"auto"`` (the first where possible).

    ``kept``: one ``fit._KeptRun`` (or None) per run, the fit's runs at its best point: where
    one ran with the inputs ``z`` gives (``ran_as``), its observations are read and the
    diagnostics do not run ``z`` again (``evaluations`` counts ``4 P``, not ``4 P + 1``).
    """
    z = np.asarray(z, dtype=np.float64)
    if method not in ("auto", "gauss-newton", "hessian"):
        raise ValueError(f"method = {checks.shorten(method)!r} is not allowed: must be auto, gauss-newton or hessian")
    if method == "auto":
        method = "gauss-newton" if _has_residuals(prob) else "hessian"
    elif method == "gauss-newton" and not _has_residuals(prob):
        raise ValueError("method = 'gauss-newton' is not allowed: a loss of the fit has no residual vector; use 'hessian'")
    prob.apply(z)
    P = len(z)
    sigmas, rms, chi2s, observations, leaf_sigmas, grouped = [], [], [], 0, {}, 0
    misfits, geometric = [], []
    # (which, ssr, count, sigma, unit, per, whose) of each group of residuals whose noise was stated,
    # tested once the groups are counted (their degrees of freedom depend on it).
    stated_groups, groups = [], 0
    bias = []
    # The runs at z, kept: Gauss-Newton's residuals at z and the chi-square the range check
    # starts from read them (each had run the rollouts at z again, for the same bits).
    at_z, ran = [], False
    for k_run, run in enumerate(prob.runs):
        held = kept[k_run] if kept is not None else None
        if held is not None and held.ran_as(run.rollout):
            # The fit's run at this point: the same inputs, so the same bits as running it.
            positions, alpha = held.observations, held.alpha
        else:
            run.value_forward()
            ran = True
            positions, alpha = _kept_observations(run), run.rollout.final_state().alpha
        at_z.append(positions)
        where = f"experiment {k_run}: " if len(prob.runs) > 1 else ""
        said = large_strain_bias(run.rollout.model, alpha.numpy(), where)
        if said is not None:
            bias.append(said)
        arrays = _numpy_observations(positions)
        for leaf in leaf_terms(run.loss):
            leaf.value(positions)  # records the residual counts
        s, n, spacing = _residuals(run, positions)
        r = math.sqrt(s / n) if n else 0.0
        which = f"experiment {k_run}'s " if len(prob.runs) > 1 else "the "
        said = _no_noise(r, run.model, which)
        if said is not None:
            misfits.append(said)
        sigma = run.noise or noise
        groups += bool(n)
        if sigma and n:
            stated_groups.append((f"experiment {k_run}" if len(prob.runs) > 1 else "the experiment", s, n, sigma, "m",
                                  " per coordinate", "the"))
        if not sigma:
            # Each experiment is charged all P fitted values (they are shared): with several
            # whose noise is estimated, a little high, never low.
            unbiased = estimated_noise(s, n, P) if n else None
            if n and unbiased is None:
                misfits.append(_unestimated(f"{which}positions", n, P))
            sigma = max(r if unbiased is None else unbiased, 0.01 * spacing)
        own_terms = _own_noise_terms(run.loss, arrays, P)
        groups += len(own_terms) + sum(hasattr(leaf, "correlated_pixels") for leaf in leaf_terms(run.loss))
        for leaf, t_rms, t_sigma, stated, count in own_terms:
            if not stated and count <= P:
                misfits.append(_unestimated(f"{which}{_term_name(leaf)}", count, P))
            if stated and count:
                # These residuals are in units of their own (a force curve's newtons) and
                # never enter the experiment's: a curve the model cannot follow was
                # reported determined, without a word.
                stated_groups.append((f"{which}{_term_name(leaf)}", t_rms**2 * count, count, t_sigma,
                                      getattr(leaf, "noise_unit", ""), "", "its"))
        for leaf in leaf_terms(run.loss):
            said = leaf.opposite_sign(arrays) or leaf.other_axes(arrays) if hasattr(leaf, "opposite_sign") else None
            if said is None and hasattr(leaf, "size_mismatch"):
                said = leaf.size_mismatch(arrays)  # a curve of the opposite sign is that already
            if said is not None:
                misfits.append(f"experiment {k_run}: {said}" if len(prob.runs) > 1 else said)
        own = [t_sigma for _, _, t_sigma, _, _ in own_terms] or [
            leaf.noise for leaf in leaf_terms(run.loss) if getattr(leaf, "noise", None) is not None]
        # A run observed only through losses with their own noise (silhouettes, force curves)
        # reports that noise and those residuals.
        sigmas.append(sigma if n or not own else own[0])
        rms.append(r if n or not own_terms else own_terms[0][1])
        geometric.append(bool(n))
        sigma_geometric = sigma
        estimated = {id(leaf): t_sigma for leaf, _, t_sigma, _, _ in own_terms}
        for leaf in leaf_terms(run.loss):
            leaf_sigmas[id(leaf)] = estimated.get(id(leaf)) or leaf_noise(leaf, sigma_geometric, arrays)
            count = leaf.observation_count()
            if hasattr(leaf, "correlated_pixels"):
                count = count / leaf.correlated_pixels(arrays)
                grouped += 1
            observations += count
        chi2s.append(chi_square_loss(run.loss, sigma_geometric, arrays, estimated))
    tests = []
    for which, ssr, count, sigma, unit, per, whose in stated_groups:
        # The fit draws the residuals towards zero along P directions: the whole of them, one
        # group, has chi-square n - P degrees of freedom; one group of several holds at most n
        # (at most its share of the P), so n keeps its test from warning too often.
        dof = count - P if groups == 1 else count
        if dof < 1:
            continue  # as many values as residuals: they can match them exactly, nothing is left to test
        test, said = misfit_test(which, ssr, count, sigma, dof, unit, per, whose)
        tests.append(test)
        if said is not None:
            misfits.append(said)
    lo, hi = prob.z_bounds()
    # Central where the bounds allow, one-sided at a bound.
    ups = np.minimum(z + step, hi)
    downs = np.maximum(z - step, lo)
    if method == "gauss-newton":
        for run in prob.runs:
            for leaf in leaf_terms(run.loss):
                if hasattr(leaf, "reset_residuals"):
                    leaf.reset_residuals()
        r0 = _scaled_residuals_kept(prob, at_z, sigmas, leaf_sigmas)
        J = np.zeros((len(r0), P))
        for j in range(P):
            zp, zm = z.copy(), z.copy()
            zp[j], zm[j] = ups[j], downs[j]
            J[:, j] = (_scaled_residuals(prob, zp, sigmas, leaf_sigmas) - _scaled_residuals(prob, zm, sigmas, leaf_sigmas)) / (ups[j] - downs[j])
        fisher = J.T @ J
        gradient = 2.0 * J.T @ r0
        # The run at z above that sizes the noise is one too (it had gone uncounted); r0 is
        # read from it.
        evaluations = int(ran) + 2 * P
    else:
        H = np.zeros((P, P))
        gsum = np.zeros(P)
        for j in range(P):
            zp, zm = z.copy(), z.copy()
            zp[j], zm[j] = ups[j], downs[j]
            _, gp = prob.value_and_grad(zp, losses=chi2s)
            _, gm = prob.value_and_grad(zm, losses=chi2s)
            H[:, j] = (gp - gm) / (ups[j] - downs[j])
            gsum += 0.5 * (gp + gm)
        fisher = 0.25 * (H + H.T)
        gradient = gsum / P
        evaluations = int(ran) + 2 * P
    # The range check: the curvature at z describes the loss near z only. A loss that is
    # flat over a wide range but curved at the optimum (a silhouette fit that stopped at
    # 1.88 x the true yield stress, its loss 0.15 % below that at 1.5 x less) looks
    # determined there; moving each value by a factor RANGE_FACTOR both ways shows it.
    chi0 = _chi_square_of(chi2s, at_z)
    log_space = [prob.spaces[name] == "log" for name in prob.params for _ in range(prob.k)]
    rises = np.full((P, 2), np.nan)
    for j in range(P):
        if not log_space[j]:
            continue
        for side, sign in enumerate((-1.0, 1.0)):
            zj = z.copy()
            zj[j] = min(max(z[j] + sign * math.log(RANGE_FACTOR), lo[j]), hi[j])
            if zj[j] != z[j]:
                rises[j, side] = _chi_square_at(prob, zj, chi2s) - chi0
                evaluations += 1
    prob.apply(z)
    d = _summarise(prob, z, fisher, gradient, sigmas, rms, observations, evaluations, step,
                   max_relative_error, min_sensitivity, max_correlation, rises, (lo, hi), misfits=misfits)
    d.method = method
    d.bias = bias
    d.misfit_tests = tests
    if grouped:
        d.notes.append("silhouettes: one observation per splat area of pixels (pixels within a splat move together)")
    return d


def _summarise(prob, z, fisher, gradient, sigmas, rms, observations, evaluations, step,
               max_relative_error, min_sensitivity, max_correlation, rises=None, z_bounds=None, misfits=()) -> Diagnostics:
    P = len(z)
    labels = list(prob.labels)
    spaces = [prob.spaces[name] for name in prob.params for _ in range(prob.k)]
    scales = np.array([prob.scales.get(name, 1.0) for name in prob.params for _ in range(prob.k)])
    p = prob.from_z(z)
    values = np.concatenate([p[name] for name in prob.params])
    lam, V = np.linalg.eigh(np.where(np.isfinite(fisher), fisher, 0.0))  # a NaN one: flagged below, per value
    top = max(float(lam.max()), 0.0)
    flat = lam <= _FLAT * top if top > 0 else np.ones(P, dtype=bool)
    inv = np.where(flat, 0.0, 1.0 / np.where(flat, 1.0, lam))
    cov = (V * inv) @ V.T
    var = np.diag(cov).copy()
    # A flat direction has unbounded variance: every value that takes part in it is free.
    for k in np.flatnonzero(flat):
        var[np.abs(V[:, k]) > 1e-2] = math.inf
    se_z = np.sqrt(np.maximum(var, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(np.maximum(np.diag(cov), 0.0))
        corr = cov / np.outer(d, d)
    corr[~np.isfinite(corr)] = np.nan
    for k in np.flatnonzero(flat):  # a flat pair: perfectly correlated along that direction
        members = np.flatnonzero(np.abs(V[:, k]) > 1e-2)
        for a in members:
            for b in members:
                if a != b:
                    corr[a, b] = math.copysign(1.0, V[a, k] * V[b, k])
    np.fill_diagonal(corr, 1.0)
    se = np.where(np.array(spaces) == "log", se_z * np.abs(values), se_z * scales)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(np.array(spaces) == "log", se_z, se / np.abs(values))
    sens = np.sqrt(np.maximum(np.diag(fisher), 0.0))
    k_weak = int(np.argmin(lam))
    weakest = V[:, k_weak] * (1.0 if V[np.argmax(np.abs(V[:, k_weak])), k_weak] > 0 else -1.0)
    weakest_error = math.inf if flat[k_weak] else 1.0 / math.sqrt(lam[k_weak])

    warnings, undetermined = [], []
    at_bound = _held_at_bounds(z, z_bounds, labels, values, spaces, scales, fisher, gradient, warnings)
    if top > 0 and float(lam.min()) < -1e-6 * top:
        warnings.append(f"the curvature is negative along some direction (eigenvalue {lam.min():.3g}, largest {top:.3g}): "
                        f"this is not a minimum, or the loss is rough at the difference step; the errors are unreliable")
    warnings.extend(misfits)
    smax = float(sens.max()) if P else 0.0
    for k, label in enumerate(labels):
        reasons = []
        if not sens[k] > min_sensitivity * smax:
            reasons.append(f"the data barely depend on it (sensitivity {sens[k]:.3g}, "
                           f"{sens[k] / smax if smax > 0 else 0.0:.2g} of the largest)")
        if not np.isfinite(fisher).all():
            # Differences of round-off or of blown-up runs: no verdict is drawn from them.
            reasons.append("its curvature could not be measured (the Fisher matrix is not finite)")
        elif values[k] == 0.0 and spaces[k] != "log":
            # A linear value at 0 (a viscosity fitted to none) has no relative error ("unbounded
            # of its value" said a finite error made it free): judged in its own scale.
            if not se_z[k] <= max_relative_error:
                reasons.append(f"its standard error is {se[k]:.3g} at a value of 0 (limit {max_relative_error:g} of its "
                               f"scale {scales[k]:g})")
        elif not rel[k] <= max_relative_error:
            shown = "unbounded" if not math.isfinite(rel[k]) else f"{100 * rel[k]:.3g} %"
            reasons.append(f"its standard error is {shown} of its value (limit {100 * max_relative_error:.3g} %)")
        partners = [labels[j] for j in range(P) if j != k and abs(corr[k, j]) > max_correlation]
        if partners:
            r = max(abs(corr[k, labels.index(q)]) for q in partners)
            reasons.append(f"it is correlated with {', '.join(partners)} (|r| = {r:.3f} > {max_correlation:g}): "
                           f"the data fix a combination, not each")
        lowest = float(np.nanmin(rises[k])) if rises is not None and np.isfinite(rises[k]).any() else math.inf
        if -1.0 < lowest < 1.0:
            reasons.append(f"moving it alone by a factor {RANGE_FACTOR:g} changes the chi-square by only {lowest:.3g} "
                           f"(less than 1 either way: the data cannot tell these values apart)")
        if reasons:
            undetermined.append(label)
            warnings.append(f"{label} is not determined by the data: " + "; ".join(reasons))
        if lowest <= -1.0:
            side = int(np.nanargmin(rises[k]))
            lower = values[k] / RANGE_FACTOR if side == 0 else values[k] * RANGE_FACTOR
            factor = f"1/{RANGE_FACTOR:g}" if side == 0 else f"{RANGE_FACTOR:g}"
            said = (f"{label} is not at the data's best value: moving it alone by a factor {RANGE_FACTOR:g} "
                    f"lowers the chi-square by {-lowest:.3g}, at {lower:.4g} ({factor} x)")
            if _local_minimum(float(gradient[k]), float(fisher[k, k])):
                # The slope and curvature here leave no fall of 1 within reach: a valley of its own
                # (a 1 cm landing's yield stress converged at 599.4 Pa, its loss least at 300 Pa),
                # which more iterations only return to.
                warnings.append(f"{said}; the fit sits in a local minimum of the loss (its slope and curvature here "
                                f"put no lower value nearby), which more iterations do not leave: start beyond it, "
                                f"e.g. at {lower:.4g}, or let a global stage choose the start (samples, --samples)")
            else:
                # Still sloping down towards a lower value: the fit stopped short.
                warnings.append(f"{said}; the fit stopped short of the minimum (more iterations, or a start nearer it)")
    return Diagnostics(
        labels=labels, values=values, spaces=spaces, standard_error=se, relative_error=rel, sensitivity=sens,
        gradient=gradient, fisher=fisher, covariance=cov, correlation=corr, noise=list(sigmas), residual_rms=list(rms),
        observations=int(round(observations)), weakest=weakest, weakest_error=weakest_error, warnings=warnings,
        undetermined=undetermined, evaluations=evaluations, step=step,
        range_rise=np.full((P, 2), np.nan) if rises is None else rises, at_bound=at_bound,
    )


def _local_minimum(gradient: float, curvature: float) -> bool:
    """Whether one value's chi-square ``chi2 + gradient d + curvature d^2`` (its slope and
    Fisher curvature at the fit's point) falls by less than 1 (``BOUND_FALL``, the change the
    range check takes as telling values apart) at its own minimum: the point is a minimum of
    the loss along that value, so a lower chi-square the range check finds lies in another
    valley, not down a slope the fit stopped short on."""
    if not (math.isfinite(gradient) and math.isfinite(curvature) and curvature > 0.0):
        return False
    return gradient * gradient / (4.0 * curvature) < BOUND_FALL


#: The fall of the chi-square beyond a bound (its slope and curvature there) from which a value
#: on the bound is named held by it (``at_bound``): the change the range check takes as telling
#: two values apart. A fit whose best value is the bound itself has a slope of round-off there.
BOUND_FALL = 1.0


def _held_at_bounds(z, z_bounds, labels, values, spaces, scales, fisher, gradient, warnings) -> list[str]:
    """The labels of the values at a bound (optimiser space ``z_bounds``) whose chi-square
    falls beyond it by ``BOUND_FALL`` or more, each with a warning in ``warnings``: there the
    fit stopped because the bound held it, not because the data chose the value, and the
    Fisher errors (an interval about it) had been reported as for a free value."""
    if z_bounds is None:
        return []
    held = []
    for k, label in enumerate(labels):
        for side, end, outward in (("lower", z_bounds[0][k], -1.0), ("upper", z_bounds[1][k], 1.0)):
            if not (math.isfinite(end) and abs(z[k] - end) <= 1e-12 * max(1.0, abs(end))):
                continue
            slope = outward * float(gradient[k])  # the chi-square's, per unit of z past the bound
            if not (math.isfinite(slope) and slope < 0.0):
                continue
            # chi2(z + d) ~ chi2 + gradient d + fisher d^2 along this value alone.
            curvature = float(fisher[k, k]) if math.isfinite(float(fisher[k, k])) else 0.0
            # Without curvature the model falls without end: no bound on the fall to weigh.
            if curvature > 0.0 and slope * slope / (4.0 * curvature) < BOUND_FALL:
                continue
            beyond = ""
            if curvature > 0.0:
                d = -float(gradient[k]) / (2.0 * curvature)
                best = values[k] * math.exp(d) if spaces[k] == "log" else values[k] + d * scales[k]
                beyond = f" (by about {slope * slope / (4.0 * curvature):.3g} at {best:.4g}, from its slope and curvature there)"
            held.append(label)
            warnings.append(f"{label} is at its {side} bound {values[k]:g}: the chi-square falls beyond it{beyond}, so the "
                            f"data's best value lies outside the bounds; the fitted value is the bound's, and its standard "
                            f"error describes the curvature there, not the uncertainty of a value the data chose (widen the "
                            f"bound where the material allows)")
    return held


def diagnose(model, target, params=("yield_stress", "flow_rate"), *, noise: float | None = None, step: float = 1e-3,
             **fit_kwargs) -> Diagnostics:
    """Diagnostics at the model's current parameter values (no fitting): ``fit`` with
    ``iterations=0``, so ``model``, ``target`` and ``fit_kwargs`` are ``fit``'s."""
    from .fit import Experiment, fit  # noqa: PLC0415
    from .losses import WorldLoss, _leaves  # noqa: PLC0415

    losses = [e.target for e in model] if isinstance(model, (list, tuple)) and model and \
        all(isinstance(e, Experiment) for e in model) else [target]
    if any(isinstance(leaf, WorldLoss) for loss in losses if isinstance(loss, Loss) for leaf in _leaves(loss)):
        # fit skips the diagnostics of worlds (one Fisher matrix of W hypotheses describes
        # none of them): diagnose returned None without a word.
        raise ValueError("target is not allowed: a WorldLoss has no diagnostics (diagnose each world's fit on its own "
                         "model)")
    fit_kwargs.setdefault("progress", False)
    return fit(model, target, params, iterations=0, diagnostics=True, noise=noise, fd_step=step, **fit_kwargs).diagnostics
