"""The time step (docs/method.md §1): ``Solver(model).step(state_in, state_out, dt)``.

``step`` reads ``state_in`` and writes only ``state_out``, so a rollout with one state
per step can be recorded on a ``wp.Tape`` and differentiated.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import math
import time
import warnings
import weakref

import numpy as np
import warp as wp

from .. import checks
from ..model import (CORRECTED_INCREMENTAL_STEP, FITS, Model, State, Unpicklable, flowed_by_hardening,  # noqa: F401 (FITS: re-exported)
                     keeps_incremental)
from .replay import recording_tape
from . import (comparison, curvature, deformation, fields, forces, fused, ghost_floor, hourglass, integrate, neighbors,
               plasticity, pressure)

#: The keys of ``Solver.guard_counts()``: particle-steps each guard of the deformation update skipped
#: (docs/method.md: the guards of §2, the flow skipped in §4, ``neighbors_cut`` the rows §1's search cut),
#: and ``pressure_regularised`` those whose isotropic pressure map was regularised (§6).
GUARD_NAMES = ("few_neighbors", "ill_conditioned", "inverted", "plasticity_skipped", "neighbors_cut",
               "pressure_regularised")
assert len(GUARD_NAMES) == deformation.COUNT_BODY  # the bodies' counts follow the guards'
assert GUARD_NAMES.index("pressure_regularised") == pressure.COUNT_PRESSURE_REGULARISED
#: Index of ``neighbors_cut``: particle-steps whose neighbour row may lack a neighbour of
#: non-zero weight (more such neighbours than the row width ``Model.max_neighbors``, or an
#: elastic stretch beyond ``neighbors.MAX_STRETCH``). Each is a possible jump of the loss.
COUNT_NEIGHBORS_CUT = 4

#: Default Verlet skin of the neighbour candidates, in units of the support radius
#: (measured in benchmarks/step.py, docs/performance.md).
DEFAULT_SKIN = 0.15

#: Relative amount by which a step may pass ``Model.stable_dt`` without the warning: the
#: default and adaptive steps (``simulate.resolve_timestep``, ``adaptive_timestep``) fit a
#: whole number of steps to a frame to 1e-12, so ``fps = 1 / (n stable_dt)`` got a step one
#: rounding above the limit, warned of as if the run might blow up.
STEP_ROUNDING = 1e-9

#: Factor by which a step must lie further past ``Model.stable_dt`` (``dt / limit``) than when
#: ``Solver.check_dt`` last warned of that ``dt`` before it warns again: a fit or a torch loop
#: moves the limit a little at every evaluation, and each new limit was warned of, the same
#: line at nearly every evaluation (17 of a 21-evaluation press fit).
STEP_REWARN = 1.1

#: Names ``profile_phases`` times: the fused step has neighbors, fused, integrate and
#: deformation; the differentiable one (under a tape, or ``fused=False``) splits
#: ``fused`` into density, constitutive, forces and pressure.
PHASES = ("neighbors", "density", "constitutive", "forces", "pressure", "fused", "integrate", "deformation")


_NO_PHASE = contextlib.nullcontext()


def tape_recording() -> bool:
    """Whether a ``wp.Tape`` is recording launches now."""
    return recording_tape() is not None


@functools.cache
def _float_info(scalar) -> tuple[float, float, float]:
    """``(tiny, max, eps)`` of ``scalar`` as Python floats: ``np.finfo`` at every step cost
    more than the checks that read it."""
    info = np.finfo(np.float32 if scalar is wp.float32 else np.float64)
    return float(info.tiny), float(info.max), float(info.eps)


@functools.lru_cache(maxsize=16)
def _length(vector: tuple) -> float:
    """The Euclidean length of a few floats (the model's gravity, which a caller may set
    between steps: kept by value)."""
    return float(np.linalg.norm(np.asarray(vector, dtype=np.float64)))


def representable_dt(scalar, dt) -> float:
    """``dt`` as a float, refused (ValueError) unless positive and representable in ``scalar``
    (``wp.float32`` or ``wp.float64``): ``Solver.check_dt`` without its stability warning."""
    dt = checks.positive("dt", dt)
    tiny, big, _ = _float_info(scalar)
    if not tiny <= dt <= big:
        # 1e-50 was 0 in float32 (a step that moved nothing while the time advanced), 1e39 inf.
        raise ValueError(f"dt = {checks.shorten(dt)!r} is not allowed in {scalar.__name__}: must be in "
                         f"[{tiny:.3g}, {big:.3g}] s")
    return dt


def resolvable_dt(model: Model, dt: float, name: str = "dt", stable: str | None = None,
                  fit: str | None = None, hourglass: float | None = None, state=None, flowed: bool | None = None) -> float:
    """``dt``, refused (ValueError) where one step's fall under gravity, ``|g| dt^2``, is so
    long that the model's precision holds a position after it to no better than a spacing
    (``eps |g| dt^2 > spacing``). A collider then takes the particle back from a height whose
    round-off is larger than the body, and the state it leaves is round-off that looks like a
    result: one float64 step of 1e30 s put every particle of a dough box at exactly (0, 0, 0)
    at rest, finite and inside every divergence bound. The bound reads no parameter, so a fit
    meets it at its start or never. ``name``, ``stable``: how the refusal names ``dt`` and the
    stable step (the CLI's ``--dt``; None: ``Model.stable_dt() =``); ``fit``, ``hourglass``: the
    solver's, whose stable step it gives (``Solver.stable_dt``; None: the model's); ``state``,
    ``flowed``: the step's start and its ``has_flowed()`` where read (``Model._stable_dt_from``),
    whose stable step it gives, as ``Solver.check_dt``'s warning does."""
    g = _length(tuple(model.gravity))
    eps = _float_info(model.scalar)[2]
    fall = g * dt * dt
    if eps * fall > model.spacing:
        longest = math.sqrt(model.spacing / (eps * g))
        # Down to the 3 digits shown: rounded to nearest, the bound printed could lie above it
        # (207.5 s shown as 208, itself refused).
        unit = 10.0 ** (math.floor(math.log10(longest)) - 2)
        longest = math.floor(longest / unit) * unit
        limit = model._stable_dt_from(0.3, hourglass, fit, state, flowed)
        # From a flowed body made elastic the step's own is half a new state's: the new state's
        # was quoted, twice what the step would take.
        of_state = state is not None and limit != model._stable_dt_from(0.3, hourglass, fit, None)
        said = stable if stable is not None else "Model.stable_dt(state=) =" if of_state else "Model.stable_dt() ="
        raise ValueError(
            f"{name} = {checks.shorten(dt)!r} is not allowed: one step's fall under gravity, |g| dt^2 = {fall:.3g} m, is more than "
            f"{model.scalar.__name__} resolves at the spacing {model.spacing:.3g} m (spacing / eps = {model.spacing / eps:.3g} m), "
            f"so the positions after it would be round-off; must be at most {longest:.3g} s (and for a stable run at most "
            f"{said} {limit:.3g} s{' from the state it starts at' if of_state else ''})")
    return dt


class StepScratch:
    """What the launches of one step share besides the model and the two states: the
    guard counters, the fast path's per-particle SPH pressure and volume ``m / rho`` (and
    ``m / rho_p`` of the pressure density, ``pressure_volume``, allocated where a material
    is ``energy_spiky``; all written and read within one step), and the guard thresholds.
    One thing outlives a step: ``kept_fits``, the fused step's cache of the fits of pinned
    particles at rest (``fused.KeptFits``: what it keeps, and how each step checks it against
    its ``state_in``)."""

    def __init__(self, model: Model, min_neighbors: int, max_condition: float):
        n, dev = model.particle_count, model.device
        # GUARD_NAMES' counts, then each body's skipped fits (deformation.COUNT_BODY + body).
        self.counters = wp.zeros(deformation.COUNT_BODY + len(model.bodies), dtype=wp.int32, device=dev)
        self.pressure = wp.zeros(n, dtype=model.scalar, device=dev)
        self.sph_volume = wp.zeros(n, dtype=model.scalar, device=dev)
        # Each particle's displacement over the step (fused.displacements), read by the fit.
        self.displacement = wp.zeros(n, dtype=model.types.vec3, device=dev)
        # 1 where the fused step left a particle's neighbour passes out (fused.out_of_reach):
        # written by its constitutive_forces, read by its update_deformation.
        self.far = wp.zeros(n, dtype=wp.int32, device=dev)
        # The fits and guards the fused step keeps for the sealed ones (fused.KeptFits), made
        # at the first step that keeps any.
        self.kept_fits = None
        self._pressure_volume = None
        # Solver(yield_with_pressure=True)'s pressure stress of untaped steps (_pressure_stress).
        self.pressure_stress = None
        # The neighbour selection's squared distances: read only within the search.
        self.neighbor_d2 = wp.zeros((n, model.max_neighbors), dtype=model.scalar, device=dev)
        self.min_neighbors = min_neighbors
        self.max_condition = max_condition

    def pressure_volume(self) -> wp.array:
        if self._pressure_volume is None:
            self._pressure_volume = wp.zeros_like(self.sph_volume)
        return self._pressure_volume


def _check_ghost_floor(model: Model, fit: str):
    """What ``add_particle_floor(ghost=True)`` supports: the linear incremental fit with the
    variational elastic force, on the non-fused kernels (``sim/ghost_floor.py``)."""
    if fit != "linear":
        raise ValueError(f"fit = {checks.shorten(fit)!r} is not allowed with a ghost floor (add_particle_floor(ghost=True)): "
                         f"its ghosts enter the linear fit only ('linear' or 'auto')")
    kinds = sorted({m.elastic_force for m in model.materials} - {"variational"})
    if kinds:
        raise ValueError(f"Material.elastic_force = {checks.shorten(kinds)!r} is not allowed with a ghost floor: only 'variational' "
                         f"(its ghosts hand on the forces of the fit energy)")
    if model.uses_comparison_models:
        raise ValueError("Material.deformation 'rest' or 'additive' is not allowed with a ghost floor: only 'incremental'")
    if model.image_plane is not None:
        raise ValueError("add_ground(images=True) is not allowed with a ghost floor: one floor in the fits")


def _check_images(model: Model):
    """What ``SceneBuilder.add_ground(images=True)`` supports so far: the incremental fit
    (linear or curvature-corrected) with either elastic force (docs/physics.md, "The ground
    collider's thin-layer strength"). Refused before any kernel runs."""
    kinds = sorted({m.deformation for m in model.materials} - {"incremental"})
    if kinds:
        raise ValueError(f"Material.deformation = {checks.shorten(kinds)!r} is not allowed with add_ground(images=True): "
                         f"the images enter the incremental fit only ('incremental')")


def _material_named(model, k: int) -> str:
    """Model material ``k`` as ``set_material`` takes it: with worlds, its index within its
    world (a two-world model's ``set_material(1, ..., world=1)`` read 'material 3')."""
    starts = model.world_material_start
    if len(starts) <= 2:
        return f"material {k}"
    w = int(np.searchsorted(starts, k, side="right")) - 1
    return f"material {k - int(starts[w])} of world {w} (model material {k})"


def _distinct(a: float, b: float) -> tuple[str, str]:
    """``a`` and ``b`` as a message shows them: ``:g`` where that tells them apart, else every
    digit (a mu written from 1000 to 1000.0001 read '1000 now, 1000 when ...')."""
    short = (f"{a:g}", f"{b:g}")
    return short if short[0] != short[1] else (repr(a), repr(b))


def _fixed_when_made(name: str, doc: str, read: str | None = None) -> property:
    """A ``Solver`` setting read from what it was made with (``_made_with``), or from the
    attribute ``read`` where the steps resolve it (``fit``), and refused when set on a made
    solver (``Solver._refuse_remade``)."""
    get = (lambda self: self._made_with[name]) if read is None else (lambda self: getattr(self, read))
    return property(get, lambda self, value: self._refuse_remade(name, value), doc=doc)


class Solver(Unpicklable):
    """Explicit elastoplastic step of Gerszewski et al. 2009.

    ``min_neighbors`` and ``max_condition`` are the guards of paper §4 on the
    deformation update; ``guard_counts()`` says how often each fired. From ``cond(A) =
    max_condition`` (default ``neighbors.MAX_CONDITION`` = 20) to twice it a fit's increment
    and its variational force fade out, and beyond the guard holds (``guards.py``): it
    bounds the local stiffness of a fit that ``Model.stable_dt`` does not see, without a
    jump in the step (docs/method.md §2 and §8). Likewise from ``min_neighbors`` (default 6)
    same-body neighbours down to one fewer, counted smoothly (each neighbour fades from 0.95
    ``h`` to ``h``, where its fit weight ends), so no neighbour crossing ``h`` makes a jump.
    The rest-configuration model reads the same thresholds on its rest neighbourhoods, once
    (``Model.rest_guard_for``): a guarded one keeps its ``F``, without the fade.

    ``neighbor_skin`` (in units of the support radius ``h``, in [0, 1]; default
    ``DEFAULT_SKIN``) is the Verlet margin of the neighbour candidates: they are rebuilt only when two
    particles may have moved by more than it relative to each other, and the rows
    (every particle within ``h sigma_max(F)`` where a material uses the paper's elastic
    force or a comparison model, or the hourglass control runs, else within ``h``
    (``_stretch_rows``); the nearest ``Model.max_neighbors`` where there are more,
    in rows reaching ``h sigma_max(F)`` those of smallest ``neighbors.weight_key``) are
    selected from them every step, so the lists are those of a fresh search (``0``: search afresh every step). ``guard_counts()["neighbors_cut"]`` counts
    the particle-steps whose row may lack a neighbour of non-zero weight (docs/method.md §1);
    the first one is warned about. ``fused`` (default on) runs the
    constitutive update and all pair forces in one kernel with one SVD per particle; under
    a recording ``wp.Tape`` it still does, unrecorded, with the differentiable kernels'
    hand-written adjoints recorded in its place, where ``fast_under_tape()`` (and the
    states have gradients), else the differentiable kernels run. Untaped, it keeps the fits
    of particles pinned among a set at rest from step to step, a cache of this solver's
    checked against each step's ``state_in`` (``fused.KeptFits``); a taped step keeps none.

    Whether SPH pressure and viscosity run, and the stable time step ``check_dt`` warns
    against, follow the model's parameter arrays at each step (``Model.sph_active``,
    ``Model.stable_dt``): values a fit or ``warp_esph.torch`` wrote are the ones used. Under a
    recording ``wp.Tape`` of a ``requires_grad`` model they run also where every pressure
    stiffness and viscosity is 0, adding zero forces, so the gradients in both are the
    loss's slopes from 0, not 0.

    A model with a material of a Fig. 8 comparison deformation model (``Material.deformation``
    ``"rest"`` or ``"additive"``, docs/method.md §7) always runs the non-fused kernels, with the
    constitutive and deformation updates of ``comparison.py``.

    ``fit`` chooses the incremental fit of the deformation update and of the variational
    elastic force (docs/method.md §2; ``FITS``; None: the model's ``Model.fit``, which a scene
    file's ``[solver] fit`` sets): ``"auto"`` (default) picks one of the next two by the
    materials (``Model.solver_choice``): the curvature-corrected fit with the hourglass
    control at ``model.AUTO_HOURGLASS`` where no material can flow and all use the variational
    force, else the paper's linear fit; ``"linear"``, the paper's affine fit (eqs. 5-6), with
    the fused fast path; ``"curvature_corrected"``, the fit that also carries the mixed
    quadratic terms and keeps only the gradient (``curvature.py``; docs/physics.md, "Bending
    stiffness": a bent beam within a few % of Timoshenko instead of 1.16x too soft at 6
    particles thick). The corrected fit runs the non-fused kernels (under a tape with
    hand-written adjoints for its elastic force, ``curvature.variational_forces_adjoint``, and
    its deformation update) and cannot be combined with a comparison deformation model, except
    where every material is ``"rest"``: then it is the rest model's total fit that is corrected
    (with ``elastic_force="variational"`` a conservative elastic force, docs/physics.md, "The
    energy of undamped elastic bodies"). Where ``"auto"`` chose the corrected fit and the scene
    allows it (``Model.may_run_rest``: no floor images, no ghost floor, which enter the
    incremental fit only; tools are allowed), the step runs the
    rest-configuration model for every material (``rest_model``; the kernels read the
    deformation code ``"rest"``,
    ``Model.material_arrays(rest=True)``): the corrected total fit against the rest
    neighbourhood with its variational force, a conservative elastic force (under a tape
    with hand-written adjoints for both, ``comparison.adjoint_kernels``, as for any model
    whose materials are all ``"rest"``). When a parameter
    makes a material flow the step turns to the incremental composition from the stored ``F``
    (an inverted rest fit as ``-F``, which that composition can follow, ``_handed_back``);
    a rest step after an incremental one (``State.rest_model`` False) hands the stored ``F``
    over (``F_p = F^-1 G(x)``, ``comparison.rest_handover``), so the body keeps its stress,
    where the body has not flowed; a state whose body has flowed (``State.flowed``: ``alpha``
    > 0 somewhere) is never handed over, the step keeps the incremental composition for it
    (its rest neighbourhoods no longer describe it), and ``runs_rest``, ``record`` and
    ``label`` of that state say so. The step writes what it ran on ``state_out`` only
    (``State.rest_model``, ``State.flowed``), never on the solver, so one solver may step
    several runs, and a rollout's backward pass may replay its segments, without changing what
    any record says of another state. A new state's ``F_p`` (``I``) and a checkpoint's are
    taken as they are. With
    ``"auto"`` the choice follows the model's parameter arrays at every step (a fit that makes
    ``flow_rate`` positive turns it to the linear fit, without the control); ``fit`` and
    ``hourglass`` hold what runs now. The model's force fields (``fields.CompressionField``)
    act while active at ``state_in.time``.

    A model with a ghost floor (``add_particle_floor(ghost=True)``, ``ghost_floor.py``) runs the
    non-fused kernels with the ghosts' three launches, the linear fit and the variational
    force only (anything else is refused when the solver is made and at every step).

    ``hourglass`` (>= 0; None: ``Model.hourglass``, which by default is ``AUTO_HOURGLASS`` with
    the fit ``"auto"`` made curvature-corrected and 0 otherwise: off, not launched) is the
    strength ``c`` of the control of the fit's zero-energy modes (``hourglass.py``;
    docs/physics.md, "Hourglass modes"): for elastic solids (a held sphere indenter keeps its
    force with ``c = 0.1``); it measures the motion against the rest positions, so it would
    pull a plastically flowed body back towards its rest shape: a strength above 0 where a
    material can flow (``Model.flowing_materials``) warns once (a ``RuntimeWarning`` at the
    first such step, naming the bodies) and runs.

    ``yield_with_pressure`` (default False: the paper's yield test on the stored ``F`` alone)
    adds each particle's SPH pressure stress, the virial of its pressure pair forces over its
    volume (``pressure.launch_pressure_stress``), to the elastic stress in the yield test
    (``plasticity.flow_under``: ``|2 mu dev(V_L) + dev(sigma_p)|`` against ``Y + K
    alpha``); the flow still relaxes the elastic part, so a flowing particle stops where the
    sum sits on the yield surface. The discrete pressure is not isotropic at a free surface
    and carries load there that a test on ``F`` does not see (docs/physics.md, "Still open",
    the SPH pressure). It runs the non-fused kernels (Warp's generated adjoints for the two
    launches), on the incremental deformation model only (refused with a comparison model),
    and not beside floor images (``add_ground(images=True)``; refused): their pressure, which
    holds the body up at the floor, is not in the stress it reads.
    Off by default because, measured, it lifts the 4-across near-yield column from 0.45 to
    0.77 x its 1-D plastic shortening but spreads the S = 0.2 pile to -20.5 % of its 1-D
    height (from -6.1 %), still flowing at 8 s (docs/physics.md, the same bullet).
    """

    UNPICKLABLE = ("it holds its Model's Warp arrays and kernels; make another with Solver(model, ...) of this one's "
                   "settings (warp_esph.checkpoint.solver_settings(solver) lists them)")

    def __init__(
        self,
        model: Model,
        *,
        min_neighbors: int = neighbors.MIN_NEIGHBORS,
        max_condition: float = neighbors.MAX_CONDITION,
        neighbor_skin: float | None = None,
        fused: bool = True,
        fit: str | None = None,
        hourglass: float | None = None,
        yield_with_pressure: bool = False,
    ):
        if not isinstance(model, Model):
            raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph.Model "
                             "(SceneBuilder.finalize())")
        self.model = model
        if fit is not None and (not isinstance(fit, str) or fit not in FITS):
            raise ValueError(f"fit = {checks.shorten(fit)!r} is not allowed: must be one of {', '.join(map(repr, FITS))}")
        if hourglass is not None:
            checks.hourglass("hourglass", hourglass)
        self._made_with = {"min_neighbors": checks.positive_int("min_neighbors", min_neighbors)}
        if self.min_neighbors > model.max_neighbors and self.min_neighbors == neighbors.MIN_NEIGHBORS:
            # The default guard against a row the scene made too narrow: name what the user set.
            raise ValueError(f"max_neighbors = {model.max_neighbors} is not allowed with the default min_neighbors = "
                             f"{neighbors.MIN_NEIGHBORS}: a neighbour row that narrow never holds the neighbours a fit "
                             f"needs, so every deformation update would be dropped; give max_neighbors >= "
                             f"{neighbors.MIN_NEIGHBORS} (or Solver(min_neighbors=...) at most {model.max_neighbors})")
        if self.min_neighbors > model.max_neighbors:
            # No row holds more: every deformation update would be dropped, every step.
            raise ValueError(f"min_neighbors = {checks.shorten(min_neighbors)!r} is not allowed: must be at most the model's max_neighbors = "
                             f"{model.max_neighbors} (a neighbour row holds no more; the default is "
                             f"{neighbors.MIN_NEIGHBORS})")
        self._made_with["max_condition"] = checks.greater_than("max_condition", max_condition, 1.0, "1")
        skin = DEFAULT_SKIN if neighbor_skin is None else checks.in_range("neighbor_skin", neighbor_skin, 0.0, 1.0)
        # (numpy's bools too, as Solver.fused takes them set)
        fused = checks.boolean("fused", fused)
        yield_with_pressure = checks.boolean("yield_with_pressure", yield_with_pressure)
        if yield_with_pressure and model.uses_comparison_models:
            raise ValueError("yield_with_pressure = True is not allowed with a comparison deformation model "
                             "(Material.deformation 'rest' or 'additive'): its constitutive update has no such test; "
                             "only with the default 'incremental'")
        if yield_with_pressure and model.image_plane is not None:
            # Their pressure carries the body's weight at the floor: without it a bottom particle's
            # stress lacked the floor's push (a settled 4 x 4 x 4 block's bottom layer read a
            # 361 Pa deviator against a 40 Pa yield stress, tests/test_yield_with_pressure.py).
            raise ValueError("yield_with_pressure = True is not allowed with floor images (add_ground(images=True)): "
                             "their pressure, which holds the body up at the floor, is not in the stress the yield "
                             "test reads; use the plain ground or a particle floor (add_particle_floor)")
        asked = model.fit if fit is None else fit
        if asked == "curvature_corrected" and model.uses_comparison_models and any(
                mt.deformation != "rest" for mt in model.materials):
            raise ValueError(f"fit = {checks.shorten(asked)!r} is not allowed with a comparison deformation model "
                             f"(Material.deformation 'rest' or 'additive') unless every material is 'rest' "
                             f"(whose total fit it then corrects): only 'linear'")
        if model.image_plane is not None:
            _check_images(model)
        self._asked = (fit, hourglass)
        self._made_with["fit"] = asked
        # Whether the fit (and with it a strength of None) follows the parameters.
        self._auto = asked == "auto"
        differ = model.worlds_auto_differ(asked)
        if differ:
            # One fit for the whole model: an elastic world next to a plastic one ran the linear
            # fit, 5e-3 m off its separate run's 81-particle ball (0.07 m), without a word.
            # Alone, such a world runs the rest model where the scene allows it (Model.may_run_rest:
            # its materials are incremental and variational, being elastic_only).
            # Alone, a world without a ghost floor allows the rest model unless the floor is imaged.
            rest = model.image_plane is None
            ghost = sorted({b.world for b in model.bodies if b.ghost_floor > 0})
            why = (f"a ghost floor in world(s) {ghost} enters the linear fit only" if ghost
                   else "a world's material can flow")
            warnings.warn(f"fit = 'auto' runs the linear fit for every world: {why}; world(s) "
                          f"{differ}, all elastic, alone would run 'curvature_corrected' with the hourglass control"
                          f"{' on the rest-configuration model' if rest else ''}, so "
                          f"they differ from their separate runs; set SceneBuilder(fit=...) (and hourglass) to compare "
                          f"worlds with separate runs", RuntimeWarning, stacklevel=2)
        # The control's rest positions and the rest set's: one array where both are taken at once
        # from the same particle_x0 (_set_hourglass); two where taken at different moments (the
        # control switched on first, or particle_x0 edited between), each keeping what it took.
        self._rest = None
        self._rest_set = None
        # The particle_x0 each was taken from (_take_rest_configuration).
        self._rest_from = self._rest_set_from = None
        # Before _choose builds them: the rest configuration is particle_x0 as it is now.
        model._drop_stale_rest()
        self._choose()
        if model.ghost_floor is not None:
            _check_ghost_floor(model, self.fit)
        self._made_with["neighbor_skin"] = skin
        self.search = neighbors.NeighborSearch(
            model.particle_count, model.scalar, model.device, model.support_radius,
            min_neighbors=self.min_neighbors, max_condition=self.max_condition,
            skin=skin * model.support_radius, spacing=model.spacing, bodies_interact=model.bodies_interact,
            **model.neighbor_options(),
        )
        self.search.image_args = model.image_args() if model.image_plane is not None else None
        #: The ghost floor's stencil search (``sim/ghost_floor.py``); None without one.
        self.ghost_search = ghost_floor.StencilSearch(model) if model.ghost_floor is not None else None
        self._fused = fused
        self._made_with["yield_with_pressure"] = yield_with_pressure
        self.scratch = StepScratch(model, self.min_neighbors, self.max_condition)
        #: Seconds per phase, summed over steps while ``profile_phases`` is on, else None.
        self.phase_times: dict[str, float] | None = None
        self._cmp = model.uses_comparison_models
        # Whether a material runs the conservative rest-configuration variational force.
        self._rest_variational = any(mt.deformation == "rest" and mt.elastic_force == "variational"
                                     for mt in model.materials)
        if self._cmp:
            self.rest_set()
        # With yield_with_pressure every world alone runs the non-fused kernels too.
        plain, why = (model.worlds_fused_differ() if self.fused and not self._curved and not self.yield_with_pressure
                      else ([], ""))
        # A world whose fit differs alone (the warning above) differs by more than round-off:
        # alone it runs the curvature-corrected fit, not the fused kernels.
        plain = [w for w in plain if w not in differ]
        if plain:
            # One kernel path for the whole model: a world beside a ghost floor ended 2e-17 m off
            # its separate run, where worlds are each world's separate run to the bit, unsaid.
            # Beside a comparison model the other worlds' fits run its kernels too: a separate run
            # with fused=False was still 2e-16 m off (measured), so no advice is given there.
            advice = "" if self._cmp else "; make the separate runs with Solver(fused=False) to compare them to the bit"
            warnings.warn(f"{why} runs the non-fused kernels for every world: world(s) {plain}, alone on the fused "
                          f"ones, differ from their separate runs by round-off (their sums run in another order)"
                          f"{advice}", RuntimeWarning, stacklevel=2)
        self._warned_dt = {}  # dt -> dt / limit when check_dt last warned of it
        self._tape_seen = None  # (the recording tape, the states its steps wrote): _check_taped_step
        self._warned_tape = False
        self._warned_cut = False
        self._cut_view = None  # (scratch.counters, a view of its memory) on the CPU, for _warn_cut
        self._warned_non_finite = False
        self._caller_checking = 0  # caller_checks() depth
        self._warned_worlds_kept = False
        self._warned_hourglass_flow = False
        self._hourglass_flow_asked = None  # the model's _parameters_key when the flow was last asked
        #: Steps taken since construction, replays of a rollout's backward pass included (as
        #: ``guard_counts``): a count of work, not a fact about any state.
        self.step_count = 0
        self._weak_self = weakref.ref(self)  # State.written_by of the states this solver's steps write
        #: Under a tape, run the hand-written adjoints (``deformation.update_deformation_adjoint``,
        #: the rest model's ``comparison.adjoint_kernels``) in place of Warp's generated ones;
        #: False: the generated ones (the tests' reference).
        self.hand_adjoints = True
        #: ``(impulse, angular impulse)`` arrays of the static colliders' rows that untaped
        #: steps add ``dt`` times their reaction to (``tools.ReactionLog`` sets them); None: off.
        self.collider_impulse = None

    def _choose(self) -> bool:
        """Set ``fit`` and ``hourglass`` to what the step runs now (``Model.solver_choice``);
        returns ``rest_model`` at the same parameters. Both follow the parameter arrays alone,
        so every step at the same parameters sets the same values."""
        fit, c = self.model.solver_choice(*self._asked)
        rest = self._auto and self.model.auto_runs_rest(self._asked[0])
        if rest:
            self.rest_set()
        self._fit = fit
        self._curved = fit == "curvature_corrected"
        # Checked by solver_choice: the setter's check ran again at every step of an automatic solver.
        self._set_hourglass(c)
        return rest

    @property
    def rest_model(self) -> bool:
        """Whether a step from a new state runs the rest-configuration model for materials that
        say ``"incremental"`` at the model's current parameters (``Model.auto_runs_rest``:
        ``fit="auto"`` on a purely elastic model). From a given state: ``runs_rest(state)``;
        what the step that wrote a state ran: ``State.rest_model``."""
        return self._auto and self.model.auto_runs_rest(self._asked[0])

    def runs_rest(self, state: State | None = None) -> bool:
        """Whether a step from ``state`` runs the rest-configuration model at the model's current
        parameters: ``rest_model``, except from a state an incremental step wrote whose body has
        flowed (``State.rest_model`` False, ``State.flowed``), for which the step keeps the
        incremental composition (``_runs_rest``). For the state a step wrote, at the parameters
        it ran with, that is what the step ran. None: a new state. Only reads ``state`` (its
        ``alpha``, where ``flowed`` is not True and the parameters allow the rest model)."""
        rest = self.rest_model
        if state is None:
            return rest
        # Whatever the parameters choose: checked only where they chose the rest model, a string
        # or another model's state was answered for as a state of this one.
        checks.same_state(self.model, "state", state)
        return rest and not keeps_incremental(state)

    def _refuse_remade(self, name: str, value):
        # Set on a made solver these were taken without a word: the guards' and the skin never
        # read by its steps (the search and the scratch keep what they were made with) while a
        # checkpoint recorded the value set; yield_with_pressure read, past the checks Solver()
        # runs of it (floor images, comparison models) and the kernel path it chose.
        raise ValueError(f"Solver.{name} = {checks.shorten(value)!r} is not allowed: the solver was made with {name} = "
                         f"{self._made_with[name]!r}, and its steps are set up for that; make a "
                         f"Solver(model, {name}={checks.shorten(value)!r})")

    min_neighbors = _fixed_when_made("min_neighbors", "The fewest neighbours a particle's fit takes "
                                                      "(``Solver(min_neighbors=...)``).")
    max_condition = _fixed_when_made("max_condition", "The fit's condition number where the guard starts to fade it "
                                                      "out (``Solver(max_condition=...)``).")
    neighbor_skin = _fixed_when_made("neighbor_skin", "The neighbour search's skin, in units of the support radius "
                                                      "(``Solver(neighbor_skin=...)``).")

    @property
    def fused(self) -> bool:
        """Whether the steps run the fused kernels (``Solver(fused=...)``); a rollout sets it False
        where a tape would not run them (``fast_under_tape``), so its untaped steps compute what
        its taped ones do."""
        return self._fused

    @fused.setter
    def fused(self, value):
        # "no" was taken as the truthy text it is.
        self._fused = checks.boolean("Solver.fused", value)

    # Set by hand it was taken without a word: an automatic solver's next step chose over it, and
    # another kept the kernel path chosen when made (fit='linear' set to 'curvature_corrected'
    # ran the linear fit, reading the corrected one).
    fit = _fixed_when_made("fit", "The incremental fit the step runs (``'linear'`` or ``'curvature_corrected'``, "
                                  "chosen from ``Solver(fit=...)``; an automatic solver's at each step); the corrected "
                                  "one runs the non-fused kernels.", read="_fit")
    yield_with_pressure = _fixed_when_made(
        "yield_with_pressure", "Whether the yield test adds each particle's SPH pressure stress to the elastic one "
        "(``pressure.launch_pressure_stress``, ``plasticity.flow_under``); it runs the non-fused kernels "
        "(``Solver(yield_with_pressure=...)``).")

    @property
    def hourglass(self) -> float:
        """Strength ``c`` of the hourglass control the step runs (``hourglass.py``); 0: off. An
        automatic solver sets it from the materials at every step (``next_hourglass``); another
        runs what is set here, checked as ``Solver(hourglass=...)``."""
        return self._hourglass

    @hourglass.setter
    def hourglass(self, c):
        self._set_hourglass(checks.hourglass("Solver.hourglass", c))

    def _set_hourglass(self, c: float):
        """``c`` (checked) as the strength the step runs."""
        # The control measures against the rest positions: taken when it is first switched on,
        # also by hand on a solver made without it (its step read no array there and crashed).
        if c > 0.0 and self._rest is None:
            m = self.model
            held = self._rest_set
            if held is not None and held[0] is m.rest_x and np.array_equal(m._rest_from, m.particle_x0):
                # This solver's rest set holds particle_x0 as it is now (the rest model chooses
                # both at once): its positions serve the control too, not a second copy.
                self._rest = held[0]
            else:
                self._rest = wp.array(m.particle_x0, dtype=m.types.vec3, device=m.device)
            self._rest_from = m.particle_x0.copy()
        self._hourglass = c

    def record(self, state: State | None = None) -> dict:
        """What a step of this solver from ``state`` runs at the model's current parameters, for
        a run's records: the requested ``fit`` (None: the model's) with
        ``Model.solver_record``'s ``resolved_fit``, ``resolved_hourglass`` and ``rest_model``;
        ``resolved_hourglass`` is the strength the next step runs (``next_hourglass``), also
        where it was set by hand. ``rest_model`` is ``runs_rest(state)``: False from a state
        whose body flowed under the incremental composition (``State.flowed``), as every step
        after it on that body. Pass the state a run's last step wrote to record what that step
        ran (the parameters it ran with choose the same); None: what a step from a new state
        runs. The solver holds no record of its last step: it may have stepped another run's
        state since (a rollout's backward pass replays its first segment last)."""
        # A strength set by hand on a solver of a fixed fit runs as set, where the model's
        # choice from the requested values recorded 0 for a control that ran.
        r = {"fit": self.model.fit if self._asked[0] is None else self._asked[0],
             **self.model.solver_record(*self._asked), "resolved_hourglass": float(self.next_hourglass())}
        if state is not None:
            r["rest_model"] = bool(self.runs_rest(state))
        return r

    def label(self, state: State | None = None) -> str:
        """``record(state)`` in a few words: ``"rest curvature_corrected c=0.05"`` (the
        rest-configuration model, its total fit and the hourglass strength) or ``"incremental
        linear c=0"`` (the incremental composition and its fit), as a sweep's ``solver`` column
        and a USD file's ``warp_esph:solver_frames`` write it."""
        r = self.record(state)
        return f"{'rest' if r['rest_model'] else 'incremental'} {r['resolved_fit']} c={r['resolved_hourglass']:g}"

    def rest_set(self) -> tuple:
        """``(X, neighbours, counts, guard, moments)``: the rest neighbourhoods this solver's rest
        model and comparison models run against (``Model.rest_neighbors``, with the guard of its
        own thresholds, ``Model.rest_guard_for``, and their moments per fit and fit weight,
        ``Model.rest_moments(curved, rest)``, evaluated when a step first needs them), obtained
        once, when it first needs them (when made, where it runs them then), and kept. A solver
        made, or first needing them, after ``particle_x0`` changed has the model build new ones
        (``Model._drop_stale_rest``) without touching these: read from the model at every step,
        they switched under this solver, whose unstressed body then sprang towards the new
        shape (0.48 m/s in 20 steps of a 4^3 block scaled by 2 %), while its hourglass control
        kept measuring against the old one; and its fit of the old offsets read the new set's
        moments (a 1 % stretch of the old positions fitted 6e-4 off)."""
        if self._rest_set is None:
            m = self.model
            # The rest configuration as particle_x0 is now, as the hourglass control takes it: a
            # solver first needing it after particle_x0 changed took the model's set of the old
            # positions where another solver had built one (0.48 m/s in 20 steps of a 4^3 block
            # scaled by 2 %), the new ones where none had.
            m._drop_stale_rest()
            # The model's moments dict of these neighbourhoods, not a copy: solvers on the same
            # ones evaluate each fit's moments once between them, and the model starts a new
            # dict when it builds new neighbourhoods.
            self._rest_set = (*m.rest_neighbors(), m.rest_guard_for(self.min_neighbors, self.max_condition),
                              m._rest_moments)
            self._rest_set_from = m._rest_from
        return self._rest_set

    def _take_rest_configuration(self):
        """Take the rest configuration again where ``particle_x0`` changed since this solver
        took its rest set (``rest_set``) or its hourglass control's rest positions: what a new
        solver of the model runs against now. ``Rollout.forward`` calls it, whose start is
        ``particle_x0`` as it is now: a rollout reused after the body was scaled by 2 % started
        it stressed against the old positions (0.48 m/s in 20 steps, a new rollout 1e-14)."""
        m = self.model
        if self._rest_set is not None and not np.array_equal(self._rest_set_from, m.particle_x0):
            self._rest_set = None  # the next step that needs it takes the new one (rest_set)
        if self._rest is not None and not np.array_equal(self._rest_from, m.particle_x0):
            self._rest = None
            self.hourglass = self._hourglass

    def _runs_rest(self, state_in: State, rest: bool, flowed: bool | None = None) -> tuple[bool, bool | None]:
        """``(rest_model, flowed)``: whether a step from ``state_in`` runs the rest model where
        the parameters choose it (``rest``: ``rest_model``), and whether its body has flowed
        (``State.flowed``; None: not known). A state an incremental step wrote
        (``State.rest_model`` False) whose body has flowed (``alpha`` > 0 somewhere) is not
        handed over: its rest neighbourhoods no longer describe the body (a 4x4x6 block
        slumped on the ground for 0.4 s and set then inverted 15 of its 96 rest fits every step,
        and its kinetic energy grew 200-fold), so the step keeps the incremental composition,
        with the fit and control the parameters chose. ``alpha`` is read back only there, for a
        state whose ``flowed`` is not True (``State.has_flowed``: a False may predate an
        ``alpha`` set by hand); the states the step writes carry what it found. ``flowed``:
        ``has_flowed()`` as the step read it for its check already (None: read here)."""
        if not (rest and state_in.rest_model is False):
            return rest, getattr(state_in, "flowed", None)
        flowed = state_in.has_flowed() if flowed is None else flowed
        if flowed and self.model.world_count > 1 and not self._warned_worlds_kept:
            self._warn_worlds_kept(state_in)
        return not flowed, flowed

    def _handed_back(self, state_in: State) -> State:
        """A view of ``state_in`` whose ``F`` is what the incremental composition takes over
        from a rest step (``comparison.rest_handback``: an inverted rest fit as ``-F``, which
        that composition otherwise kept for good); its other arrays are ``state_in``'s own, and
        ``state_in`` is only read. Under a tape the hand-back's adjoint carries ``F``'s gradient
        back to ``state_in.F``."""
        F = wp.empty_like(state_in.F, requires_grad=state_in.F.requires_grad)
        comparison.launch_rest_handback(self.model, state_in, F)
        view = copy.copy(state_in)
        view.F = F
        return view

    def _warn_worlds_kept(self, state: State):
        """Once: the worlds whose bodies did not flow keep the incremental composition with the
        rest, where alone each would be handed over to the rest model. One choice runs every
        world, as for the parameters (the warning of ``Model.worlds_auto_differ``): a world that
        never flowed beside one that did differed from its separate run without a word."""
        self._warned_worlds_kept = True
        m = self.model
        alpha = state.alpha.numpy()
        still = [w for w in range(m.world_count) if not flowed_by_hardening(alpha[m.world_particles(w)])]
        if still:
            warnings.warn(f"fit = 'auto' keeps the incremental composition for every world: a world's body has flowed "
                          f"(State.flowed); world(s) {still}, which did not flow, alone would be handed over to the "
                          f"rest-configuration model, so they differ from their separate runs; set SceneBuilder(fit=...) "
                          f"(and hourglass) to compare worlds with separate runs", RuntimeWarning, stacklevel=4)

    def start_deformation(self, state: State) -> np.ndarray:
        """The ``(n, 3, 3)`` elastic deformation gradients the body holds at ``state`` as a step
        from it sees them, with the parameters as they are now: where that step runs the rest
        model (``_runs_rest``, or a ``"rest"`` material) on a state not handed over, the rest
        fit of its positions (``G(x) F_p^-1``, ``comparison.rest_start_fit``), else the stored
        ``F`` (an incremental step's from a state a rest step wrote: its inverted fits as
        ``-F``, ``_handed_back``). A start whose positions are strained against the rest shape holds that strain's
        energy although its stored ``F`` is ``I``: the first step writes the fit
        (``simulate.DivergenceMonitor`` counts it). Only reads ``state``."""
        m = self.model
        F = state.F.numpy()
        rest_model = self.runs_rest(state)
        if rest_model and state.rest_model is False:
            return F  # handed over (F_p = F^-1 G): the rest model goes on from the stored F
        if not rest_model and state.rest_model is True:
            state = self._handed_back(state)  # a rest step's inverted fits, as the step takes them
            F = state.F.numpy()
        if not (self._cmp or rest_model):
            return F
        curved = self._curved if not self._auto else m.solver_choice(*self._asked)[0] == "curvature_corrected"
        rest = self.rest_set()
        return comparison.start_fit(m, state, curved, m.material_arrays(rest=True) if rest_model else None, rest[3],
                                    rest)

    def next_hourglass(self) -> float:
        """The strength of the hourglass control the next ``step`` runs: an automatic
        solver's follows the materials as they are now (``Model.solver_choice``, which its
        step asks again), another's is ``hourglass`` as it is set now."""
        return self.model.solver_choice(*self._asked)[1] if self._auto else self.hourglass

    def _stretch_rows(self) -> bool:
        """Whether the neighbour rows reach ``h sigma_max(F)`` (``neighbors.select_neighbors``):
        where a term weighs a pair by more than its current distance, the paper's elastic
        force (its kernel at ``F^-1 (x_j - x_i)``, eq. 11), the hourglass control and the
        comparison models (rest distances). The variational force, the incremental fit and
        the SPH terms weigh the current distance, each weight 0 from ``h`` on with its
        derivatives, so rows within ``h`` hold every pair of non-zero weight: the step, its
        gradients and the loss's smoothness are those of the wider rows, which only added
        zero terms (docs/performance.md, "The 50k forward rate against the issue's baseline")."""
        return self.hourglass > 0.0 or any(mt.elastic_force == "paper" or mt.deformation != "incremental"
                                           for mt in self.model.materials)

    def fast_under_tape(self) -> bool:
        """Whether a taped step runs the fused forward kernels (not recorded) and records the
        hand-written adjoints (and the constitutive update's generated one) in their place:
        with ``fused`` and ``hand_adjoints``, a ``requires_grad`` model and no comparison model
        (either elastic force: ``forces.elastic_forces_adjoint`` for eqs. 10-13,
        ``forces.variational_forces_adjoint`` for the variational one) and without
        ``yield_with_pressure``, whose steps never take the fused kernels. Otherwise the
        differentiable kernels run."""
        m = self.model
        return (self.fused and self._hand() and m.requires_grad and not self._cmp and not self._curved
                and self.ghost_search is None and not self.yield_with_pressure)

    def _pressure_stress(self, state_in: State, state_out: State, sph: bool, tape) -> wp.array | None:
        """With ``yield_with_pressure``, each particle's SPH pressure stress this step (zero
        where no SPH term runs), for the yield test; else None. Under a tape a fresh array each
        step: the backward pass reads each step's own."""
        if not self.yield_with_pressure:
            return None
        m = self.model
        sigma = self.scratch.pressure_stress
        if tape is not None or sigma is None:
            sigma = wp.zeros(m.particle_count, dtype=m.types.mat33, device=m.device,
                             requires_grad=tape is not None and m.requires_grad)
            if tape is None:
                self.scratch.pressure_stress = sigma
        if sph:
            pressure.launch_pressure_stress(m, state_in, state_out, sigma)
        else:
            sigma.zero_()
        return sigma

    def _hand(self) -> bool:
        """Whether the taped step records the hand-written adjoints: ``hand_adjoints`` (with
        floor images, ``add_ground(images=True)``, their image terms too; docs/physics.md,
        "The ground collider's thin-layer strength")."""
        return self.hand_adjoints

    def _check_taped_step(self, tape, state_in, state_out) -> None:
        """Under a recording tape: a state an earlier step of the same tape wrote is refused as
        ``state_out`` (swapping two states under a tape overwrote what the backward pass reads:
        a gradient 4.5 x the true one, without a word); a model or a state without gradients
        is said once (nothing flows back through such a step: a gradient of 0, or of part of
        the rollout, read as the answer)."""
        if self._tape_seen is None or self._tape_seen[0]() is not tape:
            self._tape_seen = (weakref.ref(tape), weakref.WeakValueDictionary())
        written = self._tape_seen[1]
        if written.get(id(state_out)) is state_out:
            raise ValueError("state_out is not allowed under this wp.Tape: an earlier step of the same tape wrote it, and "
                             "the tape's backward pass reads what that step wrote; give each taped step a state of its own "
                             "(as Rollout does)")
        written[id(state_out)] = state_out
        missing = [what for what, ok in (("the model", self.model.requires_grad), ("state_in", state_in.x.requires_grad),
                                         ("state_out", state_out.x.requires_grad)) if not ok]
        if missing and not self._warned_tape:
            self._warned_tape = True
            warnings.warn(f"Solver.step under a recording wp.Tape with {' and '.join(missing)} made without "
                          "requires_grad: no gradient flows back through this step (finalize(requires_grad=True), "
                          "model.state(requires_grad=True))", RuntimeWarning, stacklevel=3)

    def _check_taped_parameters(self, rows: np.ndarray, materials: tuple) -> None:
        """In the backward pass of a tape this solver's step was recorded on: the parameter
        arrays still hold the values the step ran with (``rows``), and the materials are still
        those it ran with (``materials``). The adjoints read both as they are then: a mu written
        in place between the taped steps and ``tape.backward()`` gave the gradient of neither
        value without a word (-1: 4 % off; NaN: every gradient NaN), and so did a
        ``set_material`` to another ``elastic_force`` (mu's gradient 63 % off).
        ``Rollout.backward`` refuses the same before it runs the tape."""
        m = self.model
        now = m._read_parameters()
        # One comparison in the common case: the per-field search below costs twice the read
        # again, once per taped step of every backward pass.
        same_rows = bool((rows == now).all())
        # A tuple compares its items by identity first, in C: the same materials cost no dataclass
        # comparison, and an equal one set again is no change.
        if same_rows and materials == tuple(m.materials):
            return
        for f, name in enumerate(() if same_rows else m.MATERIAL_FIELDS):
            changed = np.flatnonzero(~(rows[f] == now[f]))
            if len(changed) == 0:
                continue
            k = int(changed[0])
            try:
                m.materials[k].replace(**{name: float(now[f, k])})
                why = ""
            except ValueError as e:
                why = f" ({e})"
            new, old = _distinct(float(now[f, k]), float(rows[f, k]))
            raise RuntimeError(f"tape.backward() is not allowed: the model's {name} ({_material_named(m, k)}) = {new} "
                               f"now{why}, {old} when Solver.step ran under this wp.Tape; the backward "
                               "pass reads the parameter arrays again, so its gradient would be that of neither value: "
                               "record the steps again after changing a parameter")
        for k, (before, after) in enumerate(zip(materials, m.materials)):
            if before is after or before == after:
                continue
            diff = [f.name for f in dataclasses.fields(before) if getattr(before, f.name) != getattr(after, f.name)]
            said = ", ".join(f"{n} = {getattr(after, n)!r} now, {getattr(before, n)!r} then" for n in diff)
            raise RuntimeError(f"tape.backward() is not allowed: {_material_named(m, k)} was replaced (set_material) since Solver.step "
                               f"ran under this wp.Tape: {said}; the backward pass reads the materials again, so its "
                               "gradient would be that of neither material: record the steps again after changing a material")

    def _fast_under_tape(self, state_in, state_out) -> bool:
        return (self.fast_under_tape() and state_in.x.grad is not None and state_out.x.grad is not None
                and state_in.F.grad is not None)

    @contextlib.contextmanager
    def caller_checks(self):
        """Inside, a step from a state with a non-finite position does not warn (``step``):
        the caller reads its states back and stops on a blow-up in its own words (``simulate``,
        ``Rollout``)."""
        self._caller_checking += 1
        try:
            yield self
        finally:
            self._caller_checking -= 1

    def _warn_non_finite(self, state_in, dt):
        """Once per solver: ``state_in`` holds a non-finite position, seen by the neighbour
        search's displacement check, which reads its bounds back every step anyway (with a
        skin, after the first step): an earlier step blew up, and this one carries it on."""
        self._warned_non_finite = True
        stable = self.stable_dt(state=state_in)
        # Named as what it is: from a flowed body made elastic, half of what Model.stable_dt() returns.
        named = "Model.stable_dt()" if stable == self.stable_dt() else "Model.stable_dt(state=) of state_in"
        warnings.warn(
            f"Solver.step: state_in holds a non-finite position: an earlier step blew up, and the steps from it carry "
            f"NaN on; dt = {dt:g} s, {named} = {stable:.3g} s"
            + (" (dt is above it: use a smaller one)" if dt > stable * (1.0 + STEP_ROUNDING) else
               " (dt is within it: check the start state and the parameters)")
            + "; step does not read the particles back, so check a run's states where it reads them "
            "(simulate.DivergenceMonitor, or np.isfinite(state.x.numpy()))", RuntimeWarning, stacklevel=4)

    def _warn_hourglass_flow(self):
        """Once: the hourglass control runs where a material can flow. It measures the motion
        against the rest positions, which plastic flow leaves behind, so it holds the flow back
        (docs/physics.md, "Hourglass modes"): an opt-in strength on a plastic body ran without
        a word, though the control is for elastic solids. Asked until it warns, at each step
        whose parameter arrays changed since it was last asked (a fit, ``set_material`` or a
        caller's write may make a material flow after the solver was made)."""
        m = self.model
        self._hourglass_flow_asked = m._parameters_key()
        flowing = m.flowing_materials()
        if not flowing:
            return
        self._warned_hourglass_flow = True
        names = [b.name for b in m.bodies if b.material in flowing or b.floor_material in flowing]
        warnings.warn(f"the hourglass control (strength c = {self.hourglass:g}) runs on bodies whose material can flow "
                      f"plastically ({', '.join(map(repr, names))}: a finite yield_stress and flow_rate > 0): it measures "
                      f"the motion against the rest positions, so it pulls a flowed body back towards its rest shape and "
                      f"holds its flow back; it is for elastic solids: leave it off (hourglass = 0, what fit = 'auto' "
                      f"runs for them)", RuntimeWarning, stacklevel=4)

    def _warn_cut(self):
        # One small read per step until the first cut (the Verlet check reads too); on the CPU
        # through a view kept while the counters are the same array (a view a step cost more
        # than the read).
        counters = self.scratch.counters
        held = self._cut_view
        if held is None or held[0] is not counters:
            held = (counters, counters.numpy())
            if counters.device.is_cpu:
                self._cut_view = held
        if int(held[1][COUNT_NEIGHBORS_CUT]) > 0:
            self._warned_cut = True
            m = self.model
            warnings.warn(
                f"a neighbour row was cut: more than max_neighbors = {m.max_neighbors} particles that a kernel "
                f"of the step may weigh, or an elastic stretch above {neighbors.MAX_STRETCH:g}; the step is "
                f"then not smooth in the parameters (gradients may disagree with finite differences). "
                f"Raise max_neighbors (default for this support radius: "
                f"{neighbors.default_max_neighbors(m.support_radius / m.spacing)}); "
                f"Solver.guard_counts()['neighbors_cut'] counts these particle-steps",
                RuntimeWarning,
                stacklevel=3,
            )

    def _warn_all_few(self):
        """After the first step: every particle's fit dropped by the neighbour-count guard, with
        ``min_neighbors`` above what an interior lattice particle has (``min_neighbors=30``, the
        paper's row width, against 26 within h = 2 spacings), means the setting, not a sparse
        scene (a lone particle has no fit either way), keeps the material from ever deforming
        elastically: it slumps like a liquid, with only the guard count to say so."""
        m = self.model
        r = m.support_radius / m.spacing
        lattice = neighbors.lattice_neighbor_count(r)
        if self.min_neighbors <= lattice or int(self.scratch.counters.numpy()[0]) < m.particle_count:
            return
        warnings.warn(
            f"min_neighbors = {self.min_neighbors}: every particle's deformation update was dropped in the first step, "
            f"none having that many same-body neighbours within the support radius (an interior lattice particle has "
            f"{lattice} at h = {r:g} spacings); the material does not deform elastically. Lower min_neighbors "
            f"(default {neighbors.MIN_NEIGHBORS})", RuntimeWarning, stacklevel=3)

    def _phase(self, name: str):
        return _NO_PHASE if self.phase_times is None else self._timed_phase(name)

    @contextlib.contextmanager
    def _timed_phase(self, name: str):
        wp.synchronize_device(self.model.device)
        t0 = time.perf_counter()
        yield
        wp.synchronize_device(self.model.device)
        self.phase_times[name] = self.phase_times.get(name, 0.0) + time.perf_counter() - t0

    def profile_phases(self, on: bool = True):
        """Time each phase of ``step`` (synchronising around it) into ``phase_times``
        (seconds, summed over steps); ``profile_phases(False)`` stops. Instrumented
        steps are slower: use them for the split, not for the rate."""
        self.phase_times = {} if on else None

    def guard_counts(self) -> dict[str, int]:
        """How many particle-steps each guard skipped since construction or ``reset_counts``
        (``pressure_regularised``: whose isotropic pressure map was regularised, not skipped)."""
        return dict(zip(GUARD_NAMES, (int(c) for c in self.scratch.counters.numpy()[:len(GUARD_NAMES)])))

    def skipped_fits(self) -> dict[str, int]:
        """``{body name: particle-steps}`` whose deformation fit a guard of paper §4 skipped
        (``few_neighbors`` or ``ill_conditioned``) since construction or ``reset_counts``, per
        body (``Model.body_names``); they sum to those two counts."""
        counts = self.scratch.counters.numpy()[deformation.COUNT_BODY:]
        return {name: int(c) for name, c in zip(self.model.body_names, counts)}

    def reaction_forces(self, state: State) -> dict:
        """``{tool name: (force, torque)}`` each moving collider and pinned set exerted on the
        material in the step that produced ``state`` (definitions in ``warp_esph/tools.py``)."""
        # A state of another model was read as this one's (rows of other tools), None raised an AttributeError.
        checks.same_state(self.model, "state", state)
        return {} if self.model.tools is None else self.model.tools.reaction(state)

    def collider_reactions(self, state: State) -> dict:
        """``{collider name: (force, torque)}`` each static collider (``SceneBuilder.add_ground``,
        ``add_plane``, ``add_sphere_collider``, ``add_box_collider``) exerted on the material in
        the step that produced ``state`` (N and N m; torque about a plane's point nearest the
        origin, a sphere's or box's centre). Names ``plane<k>``, ``sphere<k>``, ``box<k>`` by
        the order each kind was added, ``w<w>/...`` with worlds (``warp_esph/sim/integrate.py``)."""
        checks.same_state(self.model, "state", state)
        f = state.collider_force.numpy()
        tq = state.collider_torque.numpy()
        return {name: (f[r].astype(np.float64), tq[r].astype(np.float64))
                for r, name in enumerate(integrate.static_collider_names(self.model))}

    def reset_counts(self):
        """Zero the counts ``guard_counts`` reports."""
        self.scratch.counters.zero_()

    @property
    def asked_fit(self) -> str | None:
        """The fit this solver was asked for (``Solver(fit=)``; None: the model's), which
        ``Model.stable_dt(fit=)`` reads as a solver's ``solver_choice`` does."""
        return self._asked[0]

    def stable_dt(self, courant: float = 0.3, state: State | None = None) -> float:
        """``Model.stable_dt`` of the step this solver runs next from ``state`` (None: a new
        state): with the hourglass strength that step runs (``next_hourglass``) and the fit it
        was asked for (the curvature-corrected fit on the incremental composition keeps half the
        wave limit, ``model.CORRECTED_INCREMENTAL_STEP``, also from a flowed state that keeps
        that composition where the parameters choose the rest model, ``keeps_incremental``)."""
        # next_hourglass, not hourglass: between a parameter write and the next step an automatic
        # solver's hourglass is still the last step's (0 for a flowing body, 0.05 once elastic).
        return self.model.stable_dt(courant, hourglass=self.next_hourglass(), fit=self.asked_fit, state=state)

    def check_dt(self, dt, state: State | None = None) -> float:
        """``dt`` as a float, refused (ValueError) unless positive, representable in the
        model's precision and short enough for it to resolve a step's fall (``resolvable_dt``);
        warns once per value above ``stable_dt(state=state)`` (with the hourglass strength this
        solver runs; ``state``: the step's start, None: a new state) by more than rounding,
        ``STEP_ROUNDING``, and again for that value only where new parameters put it
        ``STEP_REWARN`` times further past its limit than when it last warned. ``step`` checks its
        ``state_in`` so."""
        return self._check_dt(dt, state, self.next_hourglass(), 4)

    def _check_dt(self, dt, state: State | None, c: float, stacklevel: int, flowed: bool | None = None) -> float:
        # ``c``: the control the step runs; the step passes the one it has just chosen, which
        # next_hourglass would ask the parameters for again (3 us a step); ``flowed``: its
        # reading of state.has_flowed() (None: not read), which a GPU would wait for again.
        dt = resolvable_dt(self.model, representable_dt(self.model.scalar, dt), fit=self.asked_fit, hourglass=c, state=state,
                           flowed=flowed)
        stable = self.model._stable_dt_from(0.3, c, self.asked_fit, state, flowed)
        past = dt / stable
        if past > 1.0 + STEP_ROUNDING and past > self._warned_dt.get(dt, 0.0) * STEP_REWARN:
            self._warned_dt[dt] = past
            warnings.warn(
                f"dt = {dt:g} s is above the explicit stability limit {stable:.3g} s "
                f"(Model.stable_dt: 0.3 * spacing / p-wave speed, docs/method.md §8, the viscous limit "
                f"0.025 rho0 h^2 / viscosity"
                + (f", the wave limit x {CORRECTED_INCREMENTAL_STEP:g} for the curvature-corrected fit on the incremental "
                   f"composition" if self.model.corrected_incremental(self.asked_fit, state) else "")
                + (f", and that of the hourglass control at c = {c:g}" if c > 0.0 else "")
                + (f", and that of {self.model._field_words(field[2])} at net strength k = {field[1]:g} 1/s^2, "
                   f"2 / (1.5 sqrt(k))" if (field := self.model._field_limit(0.3))[1] > 0.0 else "")
                + (f", and that of {self.model._repulsion_words(pair[1])} at contact, 2 / (1.5 omega)"
                   if (pair := self.model._repulsion_limit(0.3))[1] else "")
                + "); the run may blow up",
                RuntimeWarning,
                stacklevel=stacklevel,
            )
        return dt

    def step(self, state_in: State, state_out: State, dt: float):
        """One step of the method, stage by stage (docs/physics.md has the table).

        The hot path: it reads back from the device only a few numbers it needs to go on (the
        material parameter rows, which set ``stable_dt`` and which terms run; the neighbour
        search's nine displacement bounds, which say whether its candidate lists still hold;
        the cut-row count until a row is first cut), never the particles. Its checks are of
        what it has: ``dt`` (``check_dt``: refused unless positive and resolvable; above
        ``Model.stable_dt()`` a ``RuntimeWarning``, once per value, and the step runs), the
        states' shapes, the static colliders' values (``Model.check_colliders``), on the CPU the
        arrays the kernels index (``Model.check_particles``), and, from the displacement bounds, whether ``state_in`` holds a
        non-finite position (a ``RuntimeWarning``, once per solver; with the default
        ``neighbor_skin``, from the second step). A step past the stable one returns what the
        kernels computed, NaN included, without raising; the step after it warns. The
        blow-up checks live where a run reads its states anyway: ``simulate`` (and
        ``warp-esph run``) checks every frame with ``simulate.DivergenceMonitor`` (one read of
        the particles a frame), ``Rollout.forward`` raises ``NonFiniteRollout``; their steps
        run inside ``caller_checks``, which keeps the step's own warning quiet. A loop of one's
        own checks as often as it reads the states: ``DivergenceMonitor(model,
        state0).check(x, v, t)`` on the read ``x``, ``v`` (a blow-up that stays finite too), or
        ``np.isfinite(state.x.numpy()).all()`` (docs/errors.md)."""
        launches, searches = self.model.launches, self.search.launches
        tape = recording_tape()
        if tape is None:
            # (After a backward pass that raised between its steps' switches.)
            launches.keep_in(None)
            self._step(state_in, state_out, dt)
            return
        # A taped step's launches are kept in records of its state_out, which its rollout steps
        # to from the same state_in at every forward: the next forward finds them on the very
        # arrays (sim/replay.py). The backward pass switches to them around this step's adjoints.
        records = launches.records(state_out)
        tape.record_func(lambda: launches.keep_in(None), [])  # run after this step's adjoints
        launches.keep_in(records)
        searches.keep_in(searches.records(state_out))
        try:
            self._step(state_in, state_out, dt)
        finally:
            launches.keep_in(None)
            searches.keep_in(None)
        tape.record_func(lambda: launches.keep_in(records), [])  # run before them

    def _step(self, state_in: State, state_out: State, dt: float):
        checks.step_states(self.model, state_in, state_out)
        m = self.model
        if m.tools is not None:
            # Before any launch: the tools' arrays as a caller or an optimiser left them.
            m.tools.check_arrays()
        if m.device.is_cpu:
            # Through views, bytes compared (a GPU's arrays are judged by state() and forward).
            m.check_particles()
        tape = recording_tape()
        with m._parameters_read_once():  # one read-back of the parameter arrays for the three
            m.check_colliders()  # on the static colliders' values read with them
            # Only an automatic solver's choice follows the parameters (rest_model is False otherwise).
            chose_rest = self._choose() if self._auto else False
            # Read once for the check and the path (_runs_rest), only where the path hangs on it.
            flowed = state_in.has_flowed() if chose_rest and state_in.rest_model is False else None
            dt = self._check_dt(dt, state_in, self.hourglass, 3, flowed)
            # Not asked where "auto" chose the corrected fit: it did so because nothing can flow
            # (a question more a step of every elastic default run); elsewhere asked again only
            # of parameters changed since (this step's read tells), not every step for ever.
            if (self.hourglass > 0.0 and not self._warned_hourglass_flow and not (self._auto and self._curved)
                    and self._hourglass_flow_asked != m._parameters_key()):
                self._warn_hourglass_flow()
            # Under a tape of a model with gradients the SPH terms run also where every pressure
            # stiffness and viscosity is 0 (adding exact zeros to the forces): their adjoints
            # carry the loss's slope in both from 0, where a fit may start them, which a skipped
            # term made 0 (a fit of the viscosity from 0 stopped as 'flat').
            sph = m.sph_active or (tape is not None and m.requires_grad)
            taped_rows = m._read_parameters() if tape is not None else None  # the same read, held
        taped_materials = tuple(m.materials) if tape is not None else None
        scratch = self.scratch
        if tape is not None:
            self._check_taped_step(tape, state_in, state_out)
        hand = self._hand()
        ghosts = self.ghost_search
        if ghosts is not None:
            # Again each step: Model.set_material may have changed a material's force since.
            _check_ghost_floor(m, self.fit)
        # What runs is a fact of this step, carried by state_out (State.rest_model) alone: the
        # solver's attributes would describe whichever state it stepped last.
        rest_model, flowed = self._runs_rest(state_in, chose_rest, flowed)
        cmp = self._cmp or rest_model
        if not rest_model and state_in.rest_model is True:
            # Handed back from the rest model (a parameter made a material flow, or a solver of
            # the incremental composition goes on from a rest run): its inverted fits mirrored,
            # which that composition kept for good.
            state_in = self._handed_back(state_in)
        # The material struct the comparison kernels read: with the rest model switched on, every
        # material's deformation code reads "rest" (its own arrays otherwise, None).
        mats = m.material_arrays(rest=True) if rest_model else None
        if self.yield_with_pressure and m.isotropic_pressure:
            # Its pair virial (pressure.pressure_stress) has no isotropic term: the yield test
            # would see no pressure at all.
            raise ValueError("Solver(yield_with_pressure=True) is not allowed with Material.pressure_force = "
                             "'isotropic': the yield test's pressure stress is the pair forces' virial; use another "
                             "pressure force or yield_with_pressure=False")
        # The isotropic pressure (docs/method.md §6) is the unfused kernels' alone.
        fast = (self.fused and not cmp and not self._curved and ghosts is None and not self.yield_with_pressure
                and not m.isotropic_pressure and (tape is None or self._fast_under_tape(state_in, state_out)))
        # With comparison models the corrected fit is the rest model's total fit (every material 'rest').
        curved_rest = cmp and self._curved
        Fp_in = None
        # This solver's rest neighbourhoods, with their guard of its thresholds, as the incremental fit's.
        rest = self.rest_set() if cmp else None
        rest_guard = rest[3] if cmp else None
        if rest_model and state_in.rest_model is False:
            # Elastic again after a step of the incremental composition: F_p such that the rest
            # model's F_e is the stored F (comparison.rest_handover); state_in is only read.
            if tape is not None and state_in.F.requires_grad and state_out.F_p.grad is None:
                raise RuntimeError("step is not allowed under a tape here: a parameter turned the model elastic, so "
                                   "this step hands its F over to the rest-configuration model (State.rest_model), "
                                   "and the states' F_p carry no gradient (made before the model's fit or materials "
                                   "allowed the rest model, Model.may_run_rest); make the states again "
                                   "with Model.state(requires_grad=True)")
            Fp_in = wp.empty_like(state_in.F_p, requires_grad=state_in.F.requires_grad)
            comparison.launch_rest_handover(m, state_in, Fp_in, curved_rest, rest_guard, rest)
        fast_tape = tape if fast else None
        phase = self._phase

        # 1. Neighbour lists and neighbourhood guards (integers, not taped). The fast
        # path also sums the SPH density (and an energy_spiky material's pressure density)
        # there (docs/method.md, Warp pitfall 1: it is finished before any pressure uses it).
        own = fast and sph and m.separate_pressure_density
        stretch = self._stretch_rows()
        with phase("neighbors"):
            self.search.update(
                state_in.x, m.particle_body, state_out.neighbors, scratch.neighbor_d2, state_out.neighbor_count,
                None if fast else state_out.guard,
                (m.particle_mass, m.particle_material, m.particle_rest_density, m.material_arrays(),
                 state_out.density, scratch.pressure, scratch.sph_volume,
                 pressure.pressure_density(m, state_out) if own else None,
                 scratch.pressure_volume() if own else None) if fast and sph else None,
                F=state_in.F if stretch else None, counters=scratch.counters, cut_index=COUNT_NEIGHBORS_CUT,
                rest=self._rest if self.hourglass > 0.0 else None,
                flow=(m.particle_material, m.material_arrays()) if stretch else None,
            )
            # Untaped, the fused step keeps the fits of particles sealed among a resting set.
            fused.keep_fits(m, state_in, scratch, self.search, fast and tape is None and not stretch)
            if ghosts is not None:
                # The ghost floor's stencils and weights at the step's start.
                ghosts.update(state_in, state_out, scratch.counters, COUNT_NEIGHBORS_CUT)
            if not self._warned_cut:
                self._warn_cut()
            if self.search.found_non_finite and not self._warned_non_finite and not self._caller_checking:
                self._warn_non_finite(state_in, dt)
        state_out.force.zero_()
        # Each floor image's own F flows as the particles' does (State.F_image; docs/physics.md,
        # "The floor images' energy is not stored").
        images = m.image_plane is not None

        if fast:
            # 2-4 fused: plastic flow, stress, F^-1 and every pair force in one launch.
            with phase("fused"):
                if images:
                    plasticity.launch_image_constitutive_update(m, state_in, state_out, dt, scratch.counters)
                fused.launch_constitutive_forces(m, state_in, state_out, dt, scratch, sph, fast_tape)
        else:
            # 2. SPH density (and pressure density), finished before any pressure uses it
            # (docs/method.md, Warp pitfall 1).
            if sph:
                with phase("density"):
                    pressure.launch_state_densities(m, state_in.x, state_out, hand)
            # 3. Plastic flow of the stored F, stress, F^-1.
            with phase("constitutive"):
                if cmp:
                    comparison.launch_constitutive_update(m, state_in, state_out, dt, scratch.counters, mats, Fp_in)
                else:
                    plasticity.launch_constitutive_update(m, state_in, state_out, dt, scratch.counters,
                                                          self._pressure_stress(state_in, state_out, sph, tape))
                if images:
                    plasticity.launch_image_constitutive_update(m, state_in, state_out, dt, scratch.counters)
            # 4. Elastic pair forces, pressure and viscosity.
            with phase("forces"):
                if self._curved and not cmp:
                    curvature.launch_elastic_forces(m, state_in, state_out, hand, scratch.max_condition,
                                                    scratch.min_neighbors)
                elif not rest_model:
                    # (With the rest model switched on every material is variational and 'rest':
                    # this kernel would add nothing.)
                    forces.launch_elastic_forces(m, state_in, state_out, hand, scratch.max_condition, scratch.min_neighbors)
                if self._rest_variational or rest_model:
                    comparison.launch_rest_variational_forces(m, state_out, curved_rest, mats, rest_guard, hand, rest)
                if ghosts is not None:
                    # The energies' forces on the ghosts go to their stencils.
                    ghost_floor.launch_hand_over(m, state_out)
            if sph:
                with phase("pressure"):
                    if m.isotropic_pressure:
                        pressure.launch_isotropic_pressure_forces(m, state_in, state_out, hand, scratch.counters)
                    else:
                        pressure.launch_pressure_forces(m, state_in, state_out, hand)

        # Opt-in control of the fit's zero-energy modes (hourglass.py), on either path.
        if self.hourglass > 0.0:
            with phase("hourglass"):
                hourglass.launch_hourglass_forces(m, state_in, state_out, self._rest, self.hourglass)

        # External force fields active at the step's start time.
        fields.launch_force_fields(m, state_in, state_out)

        # 5. Symplectic Euler, gravity, colliders (and the moving tools and pinned sets,
        # docs/tools.md, when the model has them).
        with phase("integrate"):
            if m.tools is not None:
                m.tools.integrate(self, state_in, state_out, dt)
            else:
                integrate.launch_integrate(m, state_in, state_out, dt)
            if m.image_plane is not None:
                # The ground's images act on the material too: their force joins its row.
                integrate.launch_floor_image_reaction(m, state_in, state_out)
            if self.collider_impulse is not None and tape is None:
                integrate.accumulate_impulse(m, state_out, dt, self.collider_impulse)

        # 6. Incremental deformation gradient over the step (eqs. 1-8); the fast path
        # evaluates the neighbourhood guards here, on the fit's own moment matrix.
        with phase("deformation"):
            if fast:
                fused.launch_update_deformation(m, state_in, state_out, scratch, fast_tape)
            elif cmp:
                comparison.launch_update_deformation(m, state_in, state_out, scratch.counters, curved_rest,
                                                     scratch.max_condition, scratch.min_neighbors, mats, rest_guard,
                                                     hand, rest)
            elif self._curved:
                deformation.launch_update_deformation(m, state_in, state_out, scratch.counters, hand,
                                                      max_condition=scratch.max_condition,
                                                      min_neighbors=scratch.min_neighbors, fit="curvature_corrected")
            elif ghosts is not None:
                ghost_floor.launch_fit_positions(m, state_in, state_out)
                deformation.launch_update_deformation(m, state_in, state_out, scratch.counters, hand,
                                                      state_out.ghost_y, state_out.ghost_y_lo, scratch.max_condition,
                                                      scratch.min_neighbors)
            else:
                deformation.launch_update_deformation(m, state_in, state_out, scratch.counters, hand,
                                                      max_condition=scratch.max_condition,
                                                      min_neighbors=scratch.min_neighbors)
            if not fast and cmp:
                # Their updates rebuild F without carrying its round-off (State.F_lo).
                state_out.F_lo.zero_()
            if images:
                # Each image's hardening, blended by the share the update just wrote.
                plasticity.launch_image_hardening_update(m, state_out)
        if tape is not None:
            # Last on the tape, so first in its backward pass: before this step's adjoints read the
            # parameter arrays and the materials again (and every earlier step's), a value written there
            # in place since (a negative or NaN mu), or a material set since, is named, not differentiated at.
            tape.record_func(lambda: self._check_taped_parameters(taped_rows, taped_materials), [])
        # A Python float whatever the user set: a np.float32 time would sum every later step in float32.
        state_out.time = float(state_in.time) + dt
        state_out.rest_model = rest_model
        # alpha never decreases, and the rest model does not flow (it runs on elastic parameters):
        # a flowed body stays flowed, an unflowed one stays so on the rest model, and an
        # incremental step may have made it flow (read at a later hand-over, not here).
        state_out.flowed = True if flowed else (flowed if rest_model else None)
        state_out.written_by = self._weak_self
        # The work up to it is simulate's to count (it reads the tools' sum once a frame): a
        # value carried from an earlier state would be stale.
        state_out.tool_work = None
        if self.step_count == 0:
            self._warn_all_few()
        self.step_count += 1
