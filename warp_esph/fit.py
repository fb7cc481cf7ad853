"""Fit material parameters to observed motion by gradient descent through a ``Rollout``.

::

    result = fit(model, target, params=["yield_stress", "flow_rate"], steps=300, dt=1e-3,
                 frames=[100, 200, 300], iterations=60)
    result.materials[0]        # the fitted Material
    result.history             # loss and parameter values per iteration
    result.stopped             # converged, stalled, iterations, flat, tol or callback
    result.diagnostics         # warp_esph.diagnostics.Diagnostics at the optimum

    fit([Experiment(model_a, loss_a, ...), Experiment(model_b, loss_b, ...)], None, params)
                               # a joint fit: several experiments sharing one material

``model`` is a ``Model`` finalized with ``requires_grad=True``, a ``SceneBuilder``, or a
callable returning either (builders are finalized in ``dtype``, float64 by default; a ``Model``
keeps its own precision, and a ``dtype`` of another one is refused). The
values the model holds are the initial guess. ``target`` is a ``warp_esph.losses.Loss``,
or target positions (``(frames, n, 3)``, ``{step: (n, 3)}``) fitted with a
``PositionLoss``.
A tool's force curve is a ``warp_esph.losses.ReactionForceLoss`` (``load_target`` reads
the ``<output>_tools.csv`` of ``warp-esph run`` as one).

Positive parameters are optimised in log space (a step of Adam changes them by about
``lr`` relative), others (e.g. ``hardening = 0``) in linear space scaled by a size in their
own units: ``param_scales={name: size}`` where given, else their initial magnitude, else (from 0)
their finite bounds' width, else their materials' (``_natural_scale``). ``bounds={"flow_rate": (1, 1e3)}`` keeps them in a box: every evaluated point is
clipped into it, and the optimisers hold a value on a bound while the loss falls beyond it,
fitting the others (an active set; Adam drops a held value's moment). ``clip`` caps the norm
of the optimiser-space gradient (long horizons can give exploding gradients, docs/method.md).

``tie_pressure``: a ``Material`` whose ``pressure_stiffness`` was left at its default
follows ``mu`` and ``lam`` (``k_p = share (lam + 2 mu / 3) / rho0``, ``share`` the pressure
force's ``material.PRESSURE_BULK_SHARE``); with ``None`` (the
default) each fitted material whose ``k_p`` equals that formula keeps following it while
``mu``/``lam`` change, with the chain rule applied to the gradient.

The ``warp-esph fit`` subcommand is ``warp_esph.cli.fit_cli`` (``add_fit_arguments``
declares its options); see ``docs/fitting.md``.
"""

import dataclasses
import functools
import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import warp as wp

from . import checks
from ._optimizers import LR_OPTIMIZERS, OPTIMIZERS
from ._types import scalar_type
from .builder import SceneBuilder
from .losses import (ChamferLoss, Loss, MeshLoss, PositionLoss, SlumpLoss, SumLoss, WorldLoss, _leaves, is_tools_csv,
                     read_tools_csv, surface_particles)
from .material import LAB_QUANTITIES, PRESSURE_BULK_SHARE, Material, _following_force, lab_value_note, material_setting_note
from .model import Model, State, check_material_precision
from .rollout import FRAME_BUFFERS, PARAMETERS, TOOL_GRADIENTS, Rollout, RolloutMemoryError, _RolloutMemory, check_initial
from .sim.neighbors import NeighborOverflow
from .sim.solver import STEP_ROUNDING, keeps_incremental

__all__ = ["fit", "FitResult", "Experiment", "Adam", "memory_estimate", "choose_checkpointing", "latin_hypercube",
           "load_target", "save_target", "Target", "write_fitted_usd"]

#: Parameters that must stay > 0 (log space always).
_POSITIVE = ("mu", "yield_stress", "flow_rate")
#: Parameters every material takes from 0 up: bounded below by 0 when fitted in linear space.
_NON_NEGATIVE = ("viscosity", "pressure_stiffness")


class Adam:
    """Adam (Kingma & Ba 2015) on a numpy vector, with optional bias correction."""

    def __init__(self, size: int, lr: float = 0.1, betas=(0.9, 0.999), eps: float = 1e-8):
        self.lr = checks.positive("lr", lr)
        self.b1, self.b2 = (checks.in_range("beta", b, 0.0, 0.999999) for b in betas)
        self.eps = eps
        self.m = np.zeros(size)
        self.v = np.zeros(size)
        self.t = 0

    def step(self, z: np.ndarray, g: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """The next point from ``z`` and its gradient ``g``. ``held``: entries on a bound whose
        gradient points out of the box (``_held``): they do not move, and their first moment
        is dropped, so that they leave the bound at the first gradient pointing back in."""
        if held is not None and held.any():
            # The momentum of a value the bound stops is motion that never happened: kept, it
            # went on pushing into the bound after the gradient had turned (14 evaluations on
            # the landing cube, docs/fitting.md, "Bounds").
            self.m = np.where(held, 0.0, self.m)
            g = np.where(held, 0.0, g)
        self.t += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * g * g
        mh = self.m / (1 - self.b1**self.t)
        vh = self.v / (1 - self.b2**self.t)
        return z - self.lr * mh / (np.sqrt(vh) + self.eps)


#: The guard of paper §4 a fit's history counts (``Solver.guard_counts``): too few neighbours,
#: particle-steps whose fit has faded out wholly (``sim/guards.py``: both guards fade the fit
#: out before they hold, so their counts changing between evaluations makes no jump).
GUARDS = ("few_neighbors",)


def _guarded(runs) -> int:
    """Particle-steps the guards held in the runs' forwards since their rollouts were made
    (``Rollout.guard_counts``: a checkpointed backward's re-run of the steps not again)."""
    return sum(r.rollout.guard_counts(last=False)[k] for r in runs for k in GUARDS)


@dataclasses.dataclass
class FitResult:
    """What ``fit`` returns.

    ``params``: the fitted values (lowest loss seen), ``{name: one value per fitted
    material}``; ``materials``: every material of the (first) model with those values;
    ``history``: one dict per evaluation (``iteration, stage, loss, params, grad,
    seconds``; ``stage`` is ``sample`` for the forward-only global stage, whose ``grad`` is
    None, else ``descent``; ``grad`` is in optimiser space: ``p dL/dp`` for log-space
    parameters, and None for a run that took none: Gauss-Newton's, a rejected L-BFGS trial's
    whose slope nothing reads, ``_slope_may_decide``). ``stopped``: why the fit ended: ``converged`` (step or gradient below
    its tolerance), ``stalled`` (no lower loss for ``patience`` evaluations, or a line
    search that found none), ``iterations`` (the cap), ``flat`` (the initial gradient is
    exactly zero; at a loss of 0, ``converged`` where a forward-only evaluation ``lr`` away
    reads a loss above 0), ``uninformative`` (no evaluation's observations differ from the
    start's by more than round-off, nor do those of one forward-only probe ``lr`` away in every
    value: the data do not tell the start from values nearby; docs/fitting.md), ``tol``, ``callback``;
    ``converged`` is True only for ``converged`` and ``tol``. ``diagnostics``: a
    ``warp_esph.diagnostics.Diagnostics`` at the optimum (None when not asked for).
    ``models``/``experiment_materials``: per experiment of a joint fit. An entry's
    ``seconds`` is the wall-clock time of its evaluation; with ``worlds`` each round's starts
    run in one pass, and its entries share its time (``seconds``, the round's divided by the
    starts it evaluated; ``round_seconds``, the round's). ``evaluations``: the descent's
    evaluations, every start's (``to_dict``: ``iterations``, those after each start's first,
    and ``sample_evaluations``, the global stage's). Each descent
    entry of the history records ``guarded``: the particle-steps without a fit for too few
    neighbours in that evaluation (paper §4; not recorded for a worlds fit). ``starts``:
    each start's ``stopped``, or ``failed`` for a start other than the guess whose first
    point failed (its rollout blew up, or its materials refuse the values). An entry's
    ``note`` says why a trial failed (``refused: ...``) and how Adam stepped back.
    """

    params: dict[str, np.ndarray]
    materials: list[Material]
    material_indices: list[int]
    loss: float
    initial_loss: float
    history: list[dict]
    model: Model
    stopped: str = "iterations"
    diagnostics: object = None
    models: list = dataclasses.field(default_factory=list)
    experiment_materials: list = dataclasses.field(default_factory=list)
    starts: list = dataclasses.field(default_factory=list)
    evaluations: int = 0
    #: Why the gradient was zero, where a loss knows (``Loss.out_of_reach``); else "".
    flat_cause: str = ""
    #: Per experiment, whether its start is a flowed body an incremental step wrote, which the
    #: rest model is never handed (``sim.solver.keeps_incremental``): it runs the incremental
    #: composition.
    flowed_starts: list = dataclasses.field(default_factory=list)
    #: For ``stopped`` "interrupted": the signal that stopped the fit where the caller knows it
    #: ("SIGINT", "SIGTERM"; ``warp-esph fit`` sets it); "" where only a ``KeyboardInterrupt``
    #: was seen. A SIGTERM had been reported as Ctrl-C in ``fit.json``'s termination.
    signal: str = ""
    #: For ``stopped`` "stalled": what stopped it, "patience" (``patience`` evaluations in a row
    #: without a lower loss: a larger ``patience`` waits longer) or "search" (the optimiser's
    #: own: an L-BFGS line search that shrank its step below ``xtol`` without a lower loss; a
    #: Gauss-Newton damping grown past 1e8 without one, or a Jacobian column whose runs failed on
    #: both sides; which no larger ``patience`` or ``iterations`` changes); else "".
    stalled_by: str = ""
    #: Of each parameter fitted as itself, the size one unit of optimiser space is and where
    #: it came from (``{"size": S, "from": "given" | "start" | "bounds" | "material"}``): what a
    #: step of ``lr`` moves it by, which the history alone does not say.
    param_scales: dict = dataclasses.field(default_factory=dict)
    #: The evaluation whose run stepped furthest past its stable step (``Model.stable_dt`` at
    #: the values it ran, the hourglass control and fields included): ``{"dt_over_stable",
    #: "dt", "stable_dt", "params", "iteration", "experiment"}``, None where nothing ran (an
    #: interrupted fit's too, over what it ran). A dt
    #: chosen from the guess's stable step (``dt=None``) is past it wherever the descent went
    #: stiffer; ``step_limit_said`` says so.
    step_limit: dict | None = None

    def step_limit_said(self) -> str:
        """One sentence where an evaluation ran past its stable step (by more than rounding,
        ``STEP_ROUNDING``), else ""."""
        s = self.step_limit
        if not s or s["dt_over_stable"] <= 1.0 + STEP_ROUNDING:
            return ""
        values = ", ".join(f"{k} = {', '.join(f'{x:.4g}' for x in v)}" for k, v in s["params"].items())
        where = "" if s["experiment"] == "the experiment" else f"{s['experiment']}: "
        return (f"{where}evaluations ran past the stable step: dt = {s['dt']:.4g} s is {s['dt_over_stable']:.3g} x the "
                f"stable step {s['stable_dt']:.4g} s at {values} (evaluation {s['iteration']}, the furthest past); "
                f"such runs may blow up or flow otherwise than a stable step's: give a dt (--dt) of at most the stable "
                f"step at the stiffest values the fit may reach, or bounds that keep it within")

    TERMINATION = {
        "converged": "converged: the last step (or the gradient) fell below its tolerance",
        "tol": "converged: the loss fell below tol",
        "stalled": "stalled: the loss stopped decreasing before the step or gradient tolerance was met "
                   "(a rough loss, or a valley the optimiser cannot follow); the result may not be a minimum",
        "iterations": "hit the iteration cap before converging; the result may not be a minimum "
                      "(raise the iteration cap; with Adam, try L-BFGS)",
        "flat": "stopped at once: the gradient is exactly zero, the loss does not depend on the fitted parameters "
                "here (e.g. no particle reaches the yield stress); start elsewhere or observe another experiment",
        "uninformative": "learned nothing (not informative): the data do not tell the start from values nearby "
                         "(moving every fitted value by lr, forward only, changes no observed position or force by "
                         "more than round-off), so no value is fitted; give target frames after the motion these "
                         "parameters make (e.g. after the body lands or flows) or observe another experiment",
        "callback": "stopped by the callback",
        "interrupted": "interrupted (a KeyboardInterrupt, as Ctrl-C raises): the best of the evaluations so far, "
                       "not a minimum",
    }
    #: The interrupted fit's termination by the signal that stopped it (``signal``).
    INTERRUPTED_BY = {
        "SIGINT": "interrupted (Ctrl-C, SIGINT): the best of the evaluations so far, not a minimum",
        "SIGTERM": "terminated (SIGTERM): the best of the evaluations so far, not a minimum",
    }

    @property
    def converged(self) -> bool:
        return self.stopped in ("converged", "tol")

    @property
    def termination(self) -> str:
        """One sentence: how the fit ended and what it means."""
        if self.stopped == "flat" and self.flat_cause:
            return f"stopped at once: the gradient is exactly zero: {self.flat_cause}"
        if self.stopped == "interrupted" and self.signal in self.INTERRUPTED_BY:
            return self.INTERRUPTED_BY[self.signal]
        return self.TERMINATION.get(self.stopped, self.stopped)

    @property
    def material(self) -> Material:
        """The first fitted material."""
        return self.materials[self.material_indices[0]]

    def to_dict(self) -> dict:
        def mat(m: Material) -> dict:
            d = dataclasses.asdict(m)
            return {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in d.items()}

        return _json_safe({
            "params": {k: [float(x) for x in v] for k, v in self.params.items()},
            "material_indices": list(self.material_indices),
            "materials": [mat(m) for m in self.materials],
            "loss": self.loss,
            "initial_loss": self.initial_loss,
            # Each start's first evaluation is no iteration: evaluations - 1 had counted the
            # other starts' first ones as iterations of one descent.
            "iterations": self.evaluations - len({h.get("start", 0) for h in self.history if h.get("stage") == "descent"}),
            "evaluations": self.evaluations,
            "sample_evaluations": sum(1 for h in self.history if h.get("stage") == "sample"),
            "stopped": self.stopped,
            "converged": self.converged,
            "termination": self.termination,
            **({"signal": self.signal} if self.stopped == "interrupted" and self.signal else {}),
            **({"stalled_by": self.stalled_by} if self.stopped == "stalled" and self.stalled_by else {}),
            "starts": list(self.starts),
            "param_scales": self.param_scales,
            "step_limit": self.step_limit,
            "diagnostics": None if self.diagnostics is None else self.diagnostics.to_dict(),
            "solver": self.solver_record(),
            "history": self.history,
        })

    def solver_record(self) -> dict | None:
        """What the experiments' default solvers run at the fitted values (``solvers_record``
        of ``models``, or of ``model``): the requested ``fit`` and ``hourglass`` with
        ``Model.solver_record``'s ``resolved_fit``, ``resolved_hourglass`` and ``rest_model``
        (``fit="auto"`` resolves by the values, so a fit of ``flow_rate`` that ends at 0 ends
        on the rest-configuration model); None without a model. ``rest_model`` is what the
        experiments' rollouts run from their starts: False for one whose start is a flowed
        body (``flowed_starts``). Each is a list, one per experiment, where they differ."""
        m = self.model
        if not isinstance(m, Model):
            return None
        return solvers_record(self.models or [m], self.flowed_starts or None)


def solvers_record(models: Sequence[Model], flowed: Sequence[bool] | None = None) -> dict:
    """What each model's default solver runs at its current values: its requested ``fit`` and
    ``hourglass`` and ``Model.solver_record``, ``rest_model`` False where ``flowed`` says its
    start is a flowed body an incremental step wrote (``_Run.flowed_start``,
    ``sim.solver.keeps_incremental``: the rollouts ran it on the incremental composition; from
    the values alone it said True), so ``Solver.runs_rest`` of that start. A key holds one value where every model
    agrees and a list, one per model, where they differ: the experiments of a joint fit may
    be scenes of their own solver settings (the first's alone had been recorded for all)."""
    flowed = flowed or [False] * len(models)
    records = []
    for m, f in zip(models, flowed):
        r = {"fit": m.fit, "hourglass": m.hourglass, **m.solver_record()}
        r["rest_model"] = r["rest_model"] and not f
        records.append(r)
    out = {}
    for key in records[0]:
        values = [r[key] for r in records]
        out[key] = values[0] if all(v == values[0] for v in values) else values
    return out


def _json_safe(obj):
    """Non-finite floats become None (JSON has no NaN/inf)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _as_model(model_or_factory, dtype) -> Model:
    """The experiment's model; ``dtype``: the precision ``fit`` was given (``None``: float64
    for a builder, a model's own)."""
    obj = model_or_factory
    if callable(obj) and not isinstance(obj, (Model, SceneBuilder)):
        obj = obj()
    if isinstance(getattr(obj, "builder", None), SceneBuilder):  # a scenes.Scene
        obj = obj.builder
    if isinstance(obj, SceneBuilder):
        return obj.finalize(dtype=wp.float64 if dtype is None else dtype, requires_grad=True)
    if isinstance(obj, Model):
        if not obj.requires_grad:
            raise ValueError("model is not allowed: finalize it with requires_grad=True (or pass the SceneBuilder)")
        if dtype is not None and obj.scalar is not dtype:
            # A model keeps the precision it was finalized in: fit(model32, ..., dtype=wp.float64)
            # ran the whole fit in float32 without a word.
            raise ValueError(f"dtype = {dtype.__name__} is not allowed with a {obj.scalar.__name__} model: a Model keeps "
                             f"the precision it was finalized in; finalize it with dtype=wp.{dtype.__name__}, pass "
                             "the SceneBuilder, or leave dtype out")
        return obj
    raise ValueError(f"model = {checks.shorten(model_or_factory)!r} is not allowed: give a Model, a SceneBuilder or a callable returning one")


def _material_indices(model: Model, materials, what: str = "material", material_names=()) -> list[int]:
    # ``what``: how a refusal names one entry of ``materials`` (the CLI's ``--material``);
    # ``material_names``: a scene file's names, which the commands take (Scene.material_index)
    # and a refusal lists.
    # An elastic particle floor's material is a wall's: no selection but its index fits it.
    walls = {b.floor_material for b in model.bodies if b.floor_material >= 0}
    if materials is None:
        return [k for k in range(len(model.materials)) if k not in walls]
    names = [b.name for b in model.bodies]
    if isinstance(materials, np.ndarray) and materials.ndim == 0:  # a 0-d array is the value it holds
        materials = materials.item()
    if isinstance(materials, (bytes, bytearray, memoryview, Mapping)):
        # Iterated, b'0' was the index 48 ("material 48 is not allowed") and a dict its keys.
        raise ValueError(f"materials = {checks.shorten(materials)!r} is not allowed: a {type(materials).__name__} is no "
                         f"selection; give a material index, a body name ({', '.join(names)}) or a list of them")
    if isinstance(materials, (int, np.integer, str)):  # numpy's int too: np.int64(0) was iterated, a TypeError
        materials = [materials]
    try:
        materials = list(materials)
    except TypeError:  # 0.5, a 0-d array: Python's "'float' object is not iterable", naming no parameter
        raise ValueError(f"materials = {checks.shorten(materials)!r} is not allowed: give a material index, a body name "
                         f"({', '.join(names)}) or a list of them") from None
    out = []
    for m in materials:
        if isinstance(m, str):
            if m not in names:
                named = [n for n in material_names if n]
                raise ValueError(f"{what} {m!r} is not allowed: give a material index" + (
                    f", a body name ({', '.join(names)}) or a material name of the scene file ({', '.join(named)})"
                    if named else f" or a body name ({', '.join(names)})"))
            # Every material the body's particles use (one per particle after split_materials).
            b = model.bodies[names.index(m)]
            for k in np.unique(model.particle_material_np[b.start: b.start + b.count]):
                if int(k) not in out and int(k) not in walls:
                    out.append(int(k))
            continue
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 0 <= m < len(model.materials):
            raise ValueError(f"{what} {checks.shorten(m)!r} is not allowed: indices are 0..{len(model.materials) - 1}")
        if int(m) not in out:
            out.append(int(m))
    if not out:
        # An empty selection fitted nothing and failed in numpy ("zero-size array").
        raise ValueError(f"materials = {checks.shorten(materials)!r} is not allowed: it selects no fitted material; "
                         f"give material indices 0..{len(model.materials) - 1} or body names ({', '.join(names)})")
    return out


def _target_loss(target, frames) -> Loss:
    if isinstance(target, (Loss, Mapping)) and frames is not None:
        # Ignored without a word: frames = [5] beside {2: x} fitted step 2, any value taken. The
        # target's own steps, given again, say the same and are taken.
        loss = target if isinstance(target, Loss) else PositionLoss(target)
        what = f"a {type(target).__name__}" if isinstance(target, Loss) else "a {step: positions} mapping"
        try:
            same = sorted(int(f) for f in frames) == sorted(int(f) for f in loss.frames) and len(frames) > 0
        except (TypeError, ValueError, OverflowError):
            same = False
        if not same:
                raise ValueError(f"frames = {checks.shorten(frames)!r} is not allowed with a target that carries its own "
                             f"steps ({what}, steps {list(loss.frames)}): give the steps there, or leave frames out")
    if isinstance(target, Loss):
        return target
    if isinstance(target, (str, os.PathLike)):
        raise ValueError("target is a file: load it with load_target(path).loss(model, ...) first (or use 'warp-esph fit')")
    if isinstance(target, Mapping):
        return PositionLoss(target)
    a = checks.host_values("target", target)
    # Refused before the cast: numpy's float() of 1j raised a bare TypeError, and of an array of
    # complex positions kept the real part with only a ComplexWarning.
    try:
        complex_ = np.iscomplexobj(a)
        a = None if complex_ else np.asarray(a, dtype=np.float64)
    except checks.ARRAY_ERRORS:
        raise ValueError(f"target = {checks.shorten(target)!r} is not allowed: must be positions, an array of shape (n, 3) "
                         "or (frames, n, 3), a {step: positions} mapping or a Loss") from None
    if complex_:
        raise ValueError(f"target = {checks.shorten(target)!r} is not allowed: it holds complex numbers; positions are real")
    if frames is None:
        raise ValueError("frames is required with target positions: the step index of each target frame")
    return PositionLoss(a, frames=frames)


def _world_leaves(loss: Loss, world: int | None):
    """``(leaf, world)`` of every leaf of ``loss``, a ``WorldLoss``'s with the index of its world
    (its particles numbered within it). A module function: recursing as a closure over its own
    name made a reference cycle at every fit, left to the cyclic collector."""
    for leaf in _leaves(loss):
        if isinstance(leaf, WorldLoss):
            for w, inner in enumerate(leaf.losses):
                yield from _world_leaves(inner, w)
        else:
            yield leaf, world


def _check_target_range(loss: Loss, model: Model, what: str) -> None:
    """Refuse target coordinates whose square the loss cannot hold in the model's precision
    (``checks.squarable_coordinates``, as ``warp-esph fit --target``), before any rollout:
    ``fit(model, target)`` with a coordinate of 1e300 failed only after its first one, and
    a cloud's or mesh's such point, or one in a world's loss, was silently left unmatched
    (numpy warning only of an overflow), the fit running on without it. A slump height or
    spread (``SlumpLoss``, m) is bounded the same way, in float64, the precision that loss is
    evaluated in on the host (a ``ReactionForceLoss`` refuses such a force when made)."""
    for leaf, world in _world_leaves(loss, None):
        at = f"world {world}, " if world is not None else ""
        if isinstance(leaf, PositionLoss):
            # A missing marker (NaN) is no coordinate to square: checked as 0.
            items = [(step, np.where(leaf.observed[step][:, None], t, 0.0), "particle") for step, t in leaf.targets.items()]
        elif isinstance(leaf, ChamferLoss):
            items = [(step, t, "point") for step, t in leaf.targets.items()]
        elif isinstance(leaf, MeshLoss):
            items = [(step, m[0], "vertex") for step, m in leaf.meshes.items()]
        elif isinstance(leaf, SlumpLoss):
            # Squared on the host in float64 too: a height of 1e300 stopped the fit after its
            # first rollout with Python's OverflowError ('Numerical result out of range').
            for quantity, value in (("height", leaf.height), ("spread", leaf.spread)):
                if value is not None:
                    checks.squarable_coordinates(what, [value], "float64",
                                                 lambda where, leaf=leaf, at=at: f"{at}step {leaf.frames[0]}",
                                                 quantity=quantity, hint="give heights and spreads in metres")
            continue
        else:
            continue
        for k, (step, t, name) in enumerate(items):
            def place(where, k=k, step=step, name=name, leaf=leaf, at=at):
                i = int(where[0])
                if name == "particle" and leaf.particles is not None:
                    i = int(leaf.particles[i])
                return f"{at}frame {k} (step {step}), {name} {i}"

            # A cloud's points and a mesh's vertices are searched in float32 (hash grid, BVH)
            # whatever the model's precision: in a float64 model a point at 1e100 became inf
            # there and was silently unmatched, under the float64 bound.
            precision = model.scalar.__name__ if name == "particle" else "float32"
            checks.squarable_coordinates(what, t, precision, place)


def pinned_particles(model: Model, floors: bool = False) -> np.ndarray | None:
    """Which of the model's particles are pinned (a particle floor's, a clamp's: no parameter
    moves them; a boolean mask), or None where none is; ``floors``: a particle floor's alone
    (``add_particle_floor``: no part of the sample)."""
    tools = getattr(model, "tools", None)
    pin_of = None if tools is None else tools.pin.numpy()
    if pin_of is not None and floors:
        pin_of = np.where(np.isin(pin_of, [len(tools.colliders) + j for j, p in enumerate(tools.pins) if p.floor]), pin_of, -1)
    pinned = None if pin_of is None else pin_of >= 0
    return pinned if pinned is not None and pinned.any() else None


def unpinned_particles(model: Model, floors: bool = False) -> np.ndarray | None:
    """The indices of the model's particles that are not pinned (``floors``: not a particle
    floor's), for a loss's ``particles`` (a measurement of the sample: a mesh, camera masks);
    None where none is pinned (or all)."""
    pinned = pinned_particles(model, floors)
    return None if pinned is None or pinned.all() else np.flatnonzero(~pinned)


def _check_slump_geometry(loss: Loss, model: Model, what: str) -> None:
    """Refuse, before any rollout, a ``SlumpLoss`` that cannot describe this model's pile: a
    ``spacing`` other than the model's (the measured edge is read half of it past the outer
    particles' centres: spacing=0.2 on a 0.02 m model added 0.1 m to the height and spread it
    compared), an axis (``center``) outside the observed particles' horizontal extent at the
    start, or a ``floor`` above any of them there (the default (0, 0) and 0 for a pile built
    elsewhere measured it from another place). Each was fitted without a word."""
    for leaf, world in _world_leaves(loss, None):
        if not isinstance(leaf, SlumpLoss):
            continue
        at = f"{what} (world {world})" if world is not None else what
        if not math.isclose(leaf.spacing, model.spacing, rel_tol=1e-6):
            raise ValueError(f"{at}: SlumpLoss spacing = {leaf.spacing!r} is not allowed: the model's spacing is "
                             f"{model.spacing!r} m, and the loss reads the measured height and spread half of it past the "
                             "outer particles' centres; give spacing=model.spacing")
        if world is not None or model.world_count != 1:
            continue  # a world's particles are its own slice, placed at its origin
        x = np.asarray(model.particle_x0, dtype=np.float64)
        pinned = pinned_particles(model)
        held = 0 if pinned is None else int(np.count_nonzero(pinned if leaf.particles is None else pinned[leaf.particles]))
        if held:
            # A particle floor's, observed: its layers under the pile were refused as a floor given
            # too high (the plate given right), and its margin wider than the pile read as spread.
            raise ValueError(f"{at}: SlumpLoss particles = {'None (every particle)' if leaf.particles is None else checks.shorten(leaf.particles)} is not allowed: they include "
                             f"{checks.plural(held, 'pinned particle')} (a particle floor's, a clamp's), whose height and "
                             "spread are no pile's; give particles= the pile's (np.flatnonzero(model.tools.pin.numpy() < 0))")
        x = x if leaf.particles is None else x[leaf.particles]
        lo, hi = x[:, [0, 2]].min(axis=0), x[:, [0, 2]].max(axis=0)
        if leaf.spread is not None and ((leaf.center < lo - 0.5 * leaf.spacing) | (leaf.center > hi + 0.5 * leaf.spacing)).any():
            raise ValueError(f"{at}: SlumpLoss center = ({leaf.center[0]:g}, {leaf.center[1]:g}) is not allowed: the spread "
                             "is measured from the vertical axis through it, and the observed particles start at x in "
                             f"[{lo[0]:g}, {hi[0]:g}], z in [{lo[1]:g}, {hi[1]:g}] m: give the pile's axis (x, z)")
        low = float(x[:, 1].min())
        if low < leaf.floor - 0.5 * leaf.spacing:
            raise ValueError(f"{at}: SlumpLoss floor = {leaf.floor:g} is not allowed: the observed particles start as low "
                             f"as y = {low:g} m, below it; give the height (y) of the plate the pile rests on")


#: The factor between the spread of target positions about their centroid and the scene's
#: particles' at the start past which ``_warn_target_scale`` asks for the units: far above
#: what a body's flow makes of its shape (a slump's pancake spreads 2-3 times), below
#: centimetres' 100 and inches' 39 per metre.
TARGET_SCALE_FACTOR = 20.0


def _spread(points: np.ndarray) -> float:
    """RMS distance of ``points`` (``(n, 3)``) from their centroid."""
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def _warn_target_scale(loss: Loss, model: Model, what: str) -> None:
    """Warn where every frame of a ``PositionLoss`` spreads ``TARGET_SCALE_FACTOR`` times as
    far (or as little) as the scene's observed particles at the start: positions in
    millimetres were fitted as metres without a word (with the default noise, the residual
    RMS, the diagnostics' residual warning cannot fire either). A frame of no spread at all (a
    body's points at one place, a placeholder target) is not a unit's mistake and is not named
    as one."""
    x0 = np.asarray(model.particle_x0, dtype=np.float64)
    for leaf in _leaves(loss):
        if isinstance(leaf, (ChamferLoss, MeshLoss)):
            _warn_surface_scale(leaf, x0, what)
            continue
        if not isinstance(leaf, PositionLoss):
            continue  # a WorldLoss numbers its particles within a world
        start = x0 if leaf.particles is None else x0[np.asarray(leaf.particles)]
        ratios = []
        for step, t in leaf.targets.items():
            # The markers a frame sees against the same particles at the start (a NaN, missing,
            # made the spread NaN and the check silent).
            seen = leaf.observed[step]
            same = start[seen] if len(seen) == len(start) else start  # a wrong count is refused elsewhere
            reference = _spread(same) if seen.sum() > 1 and len(same) > 1 else 0.0
            if reference > 0.0:
                ratios.append(_spread(np.asarray(t[seen], dtype=np.float64)) / reference)
        if not ratios:
            continue
        if all(r > TARGET_SCALE_FACTOR for r in ratios) or all(0.0 < r < 1.0 / TARGET_SCALE_FACTOR for r in ratios):
            import warnings  # noqa: PLC0415

            r = float(np.median(ratios))
            warnings.warn(f"{what}: its positions spread {r:.3g} times as far as the scene's particles at the start "
                          f"(RMS distance from their centroid, the median over its {len(ratios)} frames): targets in "
                          "other units than metres? (millimetres are 1000 times, centimetres 100 times the metres' "
                          "numbers); positions are fitted as metres", UserWarning, stacklevel=2)


#: The share of a target's points under a plane collider past which ``_warn_target_below_planes`` speaks.
TARGET_BELOW_SHARE = 0.2


def _warn_target_below_planes(loss: Loss, model: Model, what: str) -> None:
    """Warn where more than ``TARGET_BELOW_SHARE`` of a target's positions, scanned points or
    mesh vertices (all frames together) lie more than half a spacing on the solid side of one
    of the scene's planes, where no particle goes (a dough block's centres landing at 1 m/s
    reached 0.0004 m into the ground): a lab's file with z up, where the scene's y is up, put a third of a landed
    cube under the ground and was fitted without a word, the diagnostics saying only that the
    yield stress was not determined. A few points there (a scanner's noise) are not named."""
    planes = list(getattr(model, "planes", ()))
    if not planes:
        return
    kinds = {PositionLoss: "positions", ChamferLoss: "points", MeshLoss: "vertices"}
    for leaf in _leaves(loss):
        kind = kinds.get(type(leaf))
        if kind is None:
            continue  # a WorldLoss's worlds may stand elsewhere
        if isinstance(leaf, PositionLoss):
            clouds = [np.asarray(t, dtype=np.float64)[leaf.observed[f]] for f, t in leaf.targets.items()]
        elif isinstance(leaf, ChamferLoss):
            clouds = [np.asarray(t, dtype=np.float64) for t in leaf.targets.values()]
        else:
            clouds = [np.asarray(m[0], dtype=np.float64) for m in leaf.meshes.values()]
        points = np.concatenate(clouds) if clouds else np.zeros((0, 3))
        if not len(points):
            continue
        for i, plane in enumerate(planes):
            depth = float(plane.offset) - points @ np.asarray(plane.normal, dtype=np.float64)
            under = depth > 0.5 * model.spacing
            share = float(under.mean())
            if share > TARGET_BELOW_SHARE:
                import warnings  # noqa: PLC0415

                # The y-up hint only where the plane is a y-up ground: a scene whose gravity and
                # ground are along -z was told its y is up, and a wall was called the floor's.
                normal = tuple(float(c) for c in plane.normal)
                if normal == (0.0, 1.0, 0.0):
                    name, hint = f"ground (plane{i})", "whose up axis is not the scene's y (a lab's with z up: its z is the scene's y)"
                else:
                    name, hint = f"plane{i}", f"in other axes than the scene's (the plane's normal, out of its solid side, is {list(normal)})"
                warnings.warn(f"{what}: {100 * share:.0f} % of its {kind} lie more than half a spacing "
                              f"({0.5 * model.spacing:.3g} m) below the scene's {name} (up to {depth.max():.3g} m), "
                              f"where no particle goes: a file {hint}, or in other coordinates than the scene's",
                              UserWarning, stacklevel=3)
                break


def _watch_scan_coverage(loss: Loss, model: Model, what: str) -> None:
    """Have each full-coverage ``ChamferLoss`` of ``loss`` check, at its first evaluation,
    whether its cloud shows only part of the body (``ChamferLoss.watch_coverage``): fitted
    two-way, a top-half scan pulled the bottom onto the top and the fit from a guess did not
    move (1.434e-4 -> 1.433e-4 m^2) without a word. The body's surface is the model's
    surface particles (those a scan can see) among those the loss compares; a pinned one
    (a particle floor's, a clamp's) is held, not counted unseen where a scan of the sample
    leaves it out. A ``WorldLoss``'s losses each watch their own world's particles."""
    leaves = [(leaf, world) for leaf, world in _world_leaves(loss, None)
              if isinstance(leaf, ChamferLoss) and leaf.coverage == "full"]
    if not leaves:
        return
    surface = surface_particles(model)
    tools = getattr(model, "tools", None)
    pinned = np.zeros(model.particle_count, dtype=bool) if tools is None else tools.pin.numpy() >= 0
    starts = np.asarray(model.world_start, dtype=np.int64)
    for leaf, world in leaves:
        lo, hi = (0, model.particle_count) if world is None else (int(starts[world]), int(starts[world + 1]))
        mine = surface[(surface >= lo) & (surface < hi)] - lo
        if leaf.particles is None:
            local = mine
            held = pinned[lo:hi][local]
        else:
            compared = np.asarray(leaf.particles, dtype=np.int64)
            local = np.flatnonzero(np.isin(compared, mine))
            held = pinned[lo:hi][compared[local]]
        label = what if world is None else f"{what} (world {world})"
        leaf.watch_coverage(local[~held], model.spacing, label, held=local[held])


def _warn_surface_scale(leaf, x0: np.ndarray, what: str) -> None:
    """A point cloud's or a mesh's side of ``_warn_target_scale``: a scan in millimetres was
    fitted as metres without a word (its points all beyond the truncated loss's radius, the
    loss flat). Only the larger side: a scan of part of the body spreads less than the body."""
    reference = _spread(x0) if len(x0) > 1 else 0.0
    if not reference > 0.0:
        return
    if isinstance(leaf, ChamferLoss):
        clouds, kind = list(leaf.targets.values()), "points"
    else:
        clouds, kind = [m[0] for m in leaf.meshes.values()], "vertices"
    ratios = [_spread(np.asarray(c, dtype=np.float64)) / reference for c in clouds if len(c) > 1]
    if ratios and all(r > TARGET_SCALE_FACTOR for r in ratios):
        import warnings  # noqa: PLC0415

        r = float(np.median(ratios))
        warnings.warn(f"{what}: its {kind} spread {r:.0f} times as far as the scene's particles at "
                      "the start (RMS distance from their centroid): a scan in other units than metres? (millimetres "
                      "are 1000 times the metres' numbers); points are fitted as metres", UserWarning, stacklevel=3)


@dataclasses.dataclass
class Experiment:
    """One experiment of a joint fit: its own scene (``model``) and observation (``target``).

    ``model``, ``target``, ``steps``, ``dt``, ``frames``, ``materials``, ``initial`` and
    ``checkpoint_every`` mean what they mean for ``fit``. Every experiment fits the same
    parameters: material ``k`` of each experiment's ``materials`` shares its values with
    material ``k`` of every other (so each must select the same number of materials), and
    the initial guess is the first experiment's. ``weight`` scales this experiment's loss
    in the joint sum; ``noise`` is its observation noise for the diagnostics (None: the
    ``noise`` given to ``fit``). ``name`` labels it in messages. ``monitor_exempt`` names
    bodies whose finite blow-up the divergence monitor's bounds ignore (a scene showing a
    method fail; None: a ``scenes.Scene`` given as ``model``, or made by it, brings its own
    ``diverges``), as ``simulate``'s: a non-finite position or velocity in them still fails
    the trial.
    """

    model: object
    target: object
    steps: int | None = None
    dt: float | None = None
    frames: Sequence[int] | None = None
    materials: object = None
    initial: Mapping[str, object] | None = None
    checkpoint_every: int | str | None = "auto"
    weight: float = 1.0
    noise: float | None = None
    name: str | None = None
    monitor_exempt: Sequence[str] | None = None


def _opposite_signs(runs) -> list[str]:
    """``ReactionForceLoss.opposite_sign`` (else ``other_axes``) of every term of ``runs`` at
    their last forward, said as at the fit's start."""
    out = []
    for r in runs:
        for leaf in _leaves(r.loss):
            if not hasattr(leaf, "opposite_sign"):
                continue
            try:
                obs = r.rollout.observations(numpy=True)
                said = leaf.opposite_sign(obs) or leaf.other_axes(obs)
            except (KeyError, ValueError):  # no forces recorded at this evaluation
                continue
            if said is not None:
                where = "" if r.name == "the experiment" else f"{r.name}: "
                out.append(f"{where}{said} (at the start)")
    return out


def _refuse_unread_noise(runs, noise) -> None:
    """Refuse a geometric noise (m) no term reads: every term of a force curve or a silhouette
    has a noise of its own (N, occupancy), and ``noise=0.05`` given for a force-only fit (meant
    as newtons) was dropped without a word. ``noise``: ``fit``'s, for a joint fit (a single
    experiment's is its own)."""
    from .diagnostics import leaf_terms  # noqa: PLC0415

    def reads(run):
        return any(getattr(leaf, "noise", None) is None for leaf in leaf_terms(run.loss))

    def own(runs_):
        names = dict.fromkeys(type(leaf).__name__ for r in runs_ for leaf in leaf_terms(r.loss))
        return (f"every term of the target has a noise of its own ({', '.join(names)}: give it there, e.g. "
                "ReactionForceLoss(..., noise=) in N)")

    for r in runs:
        if r.noise is not None and not reads(r):
            where = "" if r.name == "the experiment" else f"{r.name}: "
            raise ValueError(f"{where}noise = {checks.shorten(r.noise)!r} is not allowed: it is the noise (m) of position, cloud, mesh "
                             f"and slump terms, and {own([r])}")
    if noise is not None and not any(reads(r) for r in runs):
        raise ValueError(f"noise = {checks.shorten(noise)!r} is not allowed: it is the noise (m) of position, cloud, mesh and slump terms, "
                         f"and in every experiment {own(runs)}")


#: Default memory budget (bytes) of ``checkpoint_every="auto"``.
MEMORY_LIMIT = 1 << 30


def _state_bytes(model: Model) -> tuple[int, int, int]:
    """Bytes of one taped ``State``, one untaped ``State`` and one checkpoint of ``model``."""
    from .rollout import _Checkpoint, state_nbytes  # noqa: PLC0415

    return (state_nbytes(model._scratch_state(requires_grad=True)), state_nbytes(model._scratch_state()),
            _Checkpoint(model).nbytes)


def memory_estimate(model: Model, steps: int, checkpoint_every: int | None, _sizes=None, *, taped: bool = True,
                    frames: int = 1) -> int:
    """Bytes the rollout's Warp arrays will hold at most: ``steps + 1`` taped states for a full
    tape; ``S + 1`` taped states, two untaped ones, ``steps / S`` checkpoints and the two
    adjoints a backward pass carries between segments (each a checkpoint's size) with
    ``checkpoint_every = S`` (measured from this model's own ``State``, not a constant).
    ``taped=False``: a rollout whose runs record no tape (``Rollout(taped=False)``, every run
    of a Gauss-Newton fit): the two untaped states its forward steps between, whatever
    ``steps`` (``checkpoint_every`` must be None: it keeps no checkpoints). Besides, in every
    case: the untaped copy of the start every forward begins from (``Rollout._initial``) and,
    for each of ``frames`` observed steps, ``rollout.FRAME_BUFFERS`` positions' worth (the
    positions kept, the loss's target, its copy of them and their gradient, the gradient handed
    back) and 4 kB of small arrays. The start's copy and the frames had been left out: an 8 x 8 x
    8 untaped rollout held 1.5 x the estimate. Measured at 8-1728 particles, a run's Warp arrays
    at their peak are at most this and within 4 % of it."""
    if not isinstance(taped, bool):
        raise ValueError(f"taped = {checks.shorten(taped)!r} is not allowed: must be True or False")
    if not taped and checkpoint_every is not None:
        raise ValueError(f"checkpoint_every = {checks.shorten(checkpoint_every)!r} is not allowed with taped = False: an untaped "
                         "rollout keeps no checkpoints; give None")
    heavy, light, ck = _sizes or _state_bytes(model)
    # 4 kB for the few small arrays besides (the loss's accumulator and its gradient: 8 bytes
    # over, measured).
    besides = (light + frames * FRAME_BUFFERS * model.particle_count * 3 * np.dtype(model.types.np_dtype).itemsize
               + 4096)
    if not taped:
        return 2 * light + besides
    if checkpoint_every is None or checkpoint_every >= steps:
        return (steps + 1) * heavy + besides
    return (checkpoint_every + 1) * heavy + 2 * light + (math.ceil(steps / checkpoint_every) + 2) * ck + besides


def choose_checkpointing(model: Model, steps: int, memory_limit: float = MEMORY_LIMIT, *,
                         taped: bool = True, frames: int = 1) -> int | None:
    """The segment length for ``checkpoint_every="auto"``: ``None`` (one full tape, the
    fastest) when that fits in ``memory_limit`` bytes, else the longest segment whose
    rollout fits, and never shorter than the segment that needs the least memory. A rollout's
    bytes here are its arrays' (``memory_estimate``, ``frames`` observed steps) and their Python
    objects' and the tape's besides (``rollout._RolloutMemory.need``). A ``memory_limit`` above the device's memory counts as that
    memory: a rollout fits where ``Rollout`` takes it (its force rows included; on a GPU its
    arrays in the GPU's memory and the states' own in the host's). ``taped=False`` (runs
    without a tape, a Gauss-Newton fit's): None, whatever the limit: such a run holds two
    states, and a checkpoint would only add to them (``Rollout`` refuses one that cannot fit)."""
    if not isinstance(taped, bool):
        raise ValueError(f"taped = {checks.shorten(taped)!r} is not allowed: must be True or False")
    if not taped:
        return None
    memory = _RolloutMemory(model, steps, frames=frames)

    def fits(segment):
        # The arrays alone chose segments of 89475 steps for 8 particles and 1e5 steps: 6.5 GiB
        # with the states' own bytes, for a limit of 1 GiB. A limit above the machine's memory
        # chose a segment the rollout then refused, where a shorter one would run.
        return sum(memory.need(segment)) <= memory_limit and not memory.overrun(segment)

    if fits(None):
        return None
    shortest = memory.least()
    lo, hi = shortest, steps - 1
    if not fits(lo):
        return shortest
    while lo < hi:  # the memory grows with S beyond the least
        mid = (lo + hi + 1) // 2
        if fits(mid):
            lo = mid
        else:
            hi = mid - 1
    return lo


#: The keys of ``fit``'s and ``Experiment``'s ``initial`` (``Rollout.forward``'s keywords).
INITIAL_KEYS = ("x0", "v0", "F0", "alpha0", "initial_state")


class _Values:
    """The fitted values' side of an experiment: its model's materials ``idx`` and their
    values, and what writing fitted values would give (``written``, ``refusal``,
    ``stable_step``), without a rollout."""

    def __init__(self, model: Model, idx, name):
        self.model, self.idx, self.name = model, idx, name
        self._read_values()

    def _read_values(self):
        # In float64 whatever the model's precision, the materials' own values where the arrays
        # hold them: a float32 guess taken through log in float32 moved the start by 1e-7.
        self.values = self.model.parameter_values()
        self.rho = np.array([m.density for m in self.model.materials])
        # k_p = share K / rho0 of the tied materials (material.PRESSURE_BULK_SHARE)
        self.kp_share = np.array([PRESSURE_BULK_SHARE[m.pressure_force] for m in self.model.materials])

    def setup_tie(self, params, tie_pressure):
        m = self.model.materials
        if tie_pressure is None:
            self.tied = [k for k in self.idx if m[k].has_default_pressure_stiffness]
        else:
            self.tied = list(self.idx) if tie_pressure else []
        self.tie = bool(self.tied) and ("mu" in params or "lam" in params) and "pressure_stiffness" not in params

    def written(self, p) -> dict[str, np.ndarray]:
        """The parameter arrays ``apply`` writes for the fitted values ``p`` (the tied
        pressure stiffness included)."""
        v = self.values
        full = {name: _full(v[name], self.idx, val) for name, val in p.items()}
        if self.tie:
            mu = full.get("mu", v["mu"])
            lam = full.get("lam", v["lam"])
            kp = v["pressure_stiffness"].copy()
            kp[self.tied] = self.kp_share[self.tied] * (lam[self.tied] + 2.0 * mu[self.tied] / 3.0) / self.rho[self.tied]
            full["pressure_stiffness"] = kp
        return full

    def refusal(self, p, cli: bool = False) -> str | None:
        """Why a fitted material would refuse the values ``p`` (``Material``'s own checks and
        the model's precision), or None; ``cli``: a precision's advice names ``--dtype`` too."""
        full = self.written(p)
        for k in sorted(set(self.idx) | set(self.tied if self.tie else [])):
            try:
                m = self.model.materials[k].replace(**{n: float(a[k]) for n, a in full.items()})
                check_material_precision(m, self.model.scalar, cli=cli)
            except ValueError as e:
                return str(e)
        return None

    def stable_step(self, p, rows=None) -> float:
        """``Model.stable_dt(state=)`` of the run's start were the materials to hold the fitted
        values ``p`` (the tied pressure stiffness included), from the values alone: nothing is
        written to the model. The path is the one ``p`` chooses (under ``fit="auto"``, values
        that make the body elastic run the corrected fit, on the rest model or, from a start
        that keeps the incremental composition, ``_start_kept``, on that at half the wave limit),
        not the one of the values the arrays hold. ``rows``: the model's parameter rows as read
        now (``Model._read_parameters``)."""
        m = self.model
        rows = (m._read_parameters() if rows is None else rows).astype(np.float64)
        full = self.written(p)
        for i, name in enumerate(m.MATERIAL_FIELDS):
            if name in full:
                rows[i] = full[name]
        return m._stable_dt_now(0.3, None, rows, kept=self._start_kept())

    def _start_kept(self) -> bool:
        """Whether the start keeps the incremental composition (``sim.solver.keeps_incremental``):
        without a rollout, a new state's, which does not."""
        return False


def _step_limit(runs, history) -> dict | None:
    """``FitResult.step_limit``: over every evaluation of ``history`` (samples, trials and
    probes ran too) and every run, the one whose ``dt`` stood furthest past the stable step
    of the values it ran. From the values alone (``_Run.stable_step``): no run again."""
    rows = [r.model._read_parameters() for r in runs]
    best = None
    for h in history:
        params = h.get("params")
        if not params:
            continue
        p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
        for r, row in zip(runs, rows):
            try:
                stable = r.stable_step(p, row)
            except (ValueError, FloatingPointError, ZeroDivisionError):
                continue  # a point the materials refuse ran nothing
            if not (stable > 0.0 and math.isfinite(stable)):
                continue
            ratio = r.dt / stable
            if best is None or ratio > best["dt_over_stable"]:
                best = {"dt_over_stable": ratio, "dt": float(r.dt), "stable_dt": float(stable), "params": params,
                        "iteration": h.get("iteration"), "experiment": r.name}
    return best


class _KeptRun:
    """What the diagnostics read of a run (its observations and final plastic strain), copied
    after its forward, with the inputs it ran with (``Rollout._forward_inputs``): a fit's run
    at its best point, which the diagnostics' first run at that point would repeat."""

    #: The tools' arrays a step reads besides the differentiable ones ``_forward_inputs``
    #: holds where they keep gradients: what a caller may write in place (a mesh tool's
    #: vertices, triangles and bounds among them).
    TOOL_ARRAYS = TOOL_GRADIENTS + ("param", "pin_center", "mesh_id", "mesh_lo", "mesh_hi", "mesh_verts", "mesh_tris",
                                    "mesh_vofs", "mesh_fofs")
    #: The model's arrays a step reads that neither the parameter arrays nor the start hold:
    #: the particles' masses, energy volumes, rest densities and materials, and the static
    #: colliders (planes, spheres, boxes).
    MODEL_ARRAYS = ("particle_mass", "particle_volume", "particle_rest_density", "particle_material", "plane_normal",
                    "plane_offset", "plane_friction", "sphere_center", "sphere_radius", "sphere_friction", "box_center",
                    "box_half", "box_friction")

    def __init__(self, rollout: Rollout, initial_state: State | None = None):
        self.inputs = rollout._forward_inputs
        # What else decides the run and ``_forward_inputs`` leaves out: the start a forward
        # takes from the model, the tools' arrays and the Scripted poses it evaluated. A fit's
        # callback that moved particle_x0, changed particle_v0, a plate's size or a Scripted
        # motion's speed after this run left them as they were, and the diagnostics read the
        # old scene's run (their gradient and range check off their own run's bits).
        self.scene = self._scene(rollout.model)
        self.scripted = rollout._scripted_poses
        # The state the run started from (``initial``'s ``initial_state``), as it was: the
        # forward copies it in each time, and a callback may write it in place. Device copies,
        # read only where the diagnostics ask.
        self.initial_state = initial_state
        self.start = None if initial_state is None else self._start(initial_state)
        # Copies: the next forward writes the rollout's own buffers.
        self.observations = {k: wp.clone(v) if isinstance(v, wp.array) else v for k, v in rollout.observations().items()}
        self.alpha = wp.clone(rollout.final_state().alpha)

    @classmethod
    def _scene(cls, model: Model) -> dict[str, np.ndarray]:
        out = {"particle_x0": np.array(model.particle_x0), "particle_v0": np.array(model.particle_v0)}
        # A callback that wrote a plane's offset, the particles' masses or rest densities after
        # the run left the diagnostics reading the old scene's run, as for the start above.
        out.update({name: getattr(model, name).numpy().copy() for name in cls.MODEL_ARRAYS})
        # The step's kernels are made for these counts (a collider added to the lists).
        out["colliders"] = np.array([len(model.planes), len(model.spheres), len(model.boxes)])
        if model.tools is not None:
            out.update({f"tools.{name}": getattr(model.tools, name).numpy().copy() for name in cls.TOOL_ARRAYS})
            # The float32 copy of each mesh that the contact's queries pick faces from.
            out.update({f"tools.meshes[{k}].points": mesh.points.numpy().copy()
                        for k, mesh in enumerate(model.tools.meshes)})
        return out

    @staticmethod
    def _start(state: State) -> tuple:
        return ({name: wp.clone(getattr(state, name)) for name in State.STATE_FIELDS},
                (state.time, state.rest_model, getattr(state, "flowed", None)))

    def _same_start(self) -> bool:
        if self.initial_state is None:
            return True
        arrays, flags = self.start
        now = self.initial_state
        return flags == (now.time, now.rest_model, getattr(now, "flowed", None)) and all(
            np.array_equal(a.numpy(), getattr(now, name).numpy()) for name, a in arrays.items())

    def _same_scripted(self, model: Model) -> bool:
        """Whether each Scripted motion gives now the poses this run evaluated (it must, as a
        re-run's check, ``Rollout._check_scripted``, asks)."""
        if not self.scripted:
            return True
        motions = model.tools.motions
        try:
            return all(motions[k].pose(t) == pose for (k, t), pose in self.scripted.items())
        except ValueError:  # it refuses the time now: the diagnostics' own run says so
            return False

    def ran_as(self, rollout: Rollout) -> bool:
        """Whether a forward of ``rollout`` now would run with the inputs this one ran with:
        the parameter arrays, tools (their arrays, meshes and Scripted poses), the model's start
        positions and velocities, particle masses, volumes, rest densities and materials, static
        colliders, the state it started from and the settings bit for bit, and the materials in every field
        the parameter arrays do not hold (``finish`` writes the fitted values into the
        materials, which the kernels read from the arrays)."""
        rows, materials, tools, settings = self.inputs
        now_rows, now_materials, now_tools, now_settings = rollout._inputs()
        scene = self._scene(rollout.model)
        # NaN as NaN: a particle_v0 a given start replaces may hold it (Model.check_start), and
        # the run that kept it was taken for another, and run again.
        if scene.keys() != self.scene.keys() or not all(_same(self.scene[k], scene[k]) for k in scene):
            return False
        if not (self._same_scripted(rollout.model) and self._same_start()):
            return False
        if not (np.array_equal(rows, now_rows) and settings == now_settings and tools.keys() == now_tools.keys()
                and all(np.array_equal(tools[k], now_tools[k]) for k in tools) and len(materials) == len(now_materials)):
            return False
        for a, b in zip(materials, now_materials):
            if a is b or a == b:
                continue
            if type(a) is not type(b) or any(getattr(a, f.name) != getattr(b, f.name) for f in dataclasses.fields(a)
                                             if f.name not in Model.MATERIAL_FIELDS):
                return False
        return True


class _SceneGuard:
    """What a fit's runs read besides the values it writes, so that a callback that changed
    the scene mid-fit is refused (``check``) rather than fitted: the evaluations after it ran
    another scene than those before (a plane moved, a material's density, a tool's speed), the
    optimiser's pairs and the best point mixed the two, and the diagnostics read a run of
    either. Taken as the descent begins: the particles' start, masses, volumes, rest
    densities and materials, the static colliders, the tools' arrays and meshes, the materials
    (their fields the parameter arrays do not hold), the state a run starts from, and each
    Scripted motion's pose at the run's start and end (``scene``), and the target
    (``Loss.target_items``: the loss's positions, clouds, meshes, masks or force curves, copied
    once here). The parameter arrays, which the fit writes, and the run's settings (``dt``,
    gravity, the solver's, which follow the values: ``fit="auto"``) are read just before each
    callback and after it (``light``); each Scripted motion is called at every time the latest
    run evaluated it (``scripted``)."""

    def __init__(self, runs):
        self.runs = runs
        self.scenes = [self.scene(r) for r in runs]
        # The targets are the caller's arrays, not the device's: copied once here and compared
        # where they lie after each callback, no copy then (``target_items``).
        self.targets = [{k: _snapshot(v) for k, v in r.loss.target_items().items()} for r in runs]

    @staticmethod
    def scene(run) -> dict:
        m = run.model
        out = _KeptRun._scene(m)
        out.update({f"materials[{k}]": mat for k, mat in enumerate(m.materials)})
        init = run.initial.get("initial_state")
        if isinstance(init, State):
            out.update({f"initial_state.{name}": getattr(init, name).numpy().copy() for name in State.STATE_FIELDS
                        if getattr(init, name, None) is not None})
            out["initial_state.time"] = init.time
        if m.tools is not None:
            t0 = float(init.time) if isinstance(init, State) else 0.0
            for k in m.tools._scripted:
                # Two poses, not the run's every one: a Python call each (2 per step).
                motion = m.tools.motions[k]
                out[f"tools.motions[{k}]"] = (motion, motion.pose(t0), motion.pose(t0 + run.steps * run.dt))
        return out

    @staticmethod
    def scripted(run) -> list[str]:
        """The Scripted motions that give now another pose than the latest run evaluated at any
        of its times (``scene`` holds the start's and end's: a motion changed between them
        only, a press's dwell, passed it)."""
        log = run.rollout._scripted_poses
        if not log or run.model.tools is None:
            return []
        motions, out = run.model.tools.motions, []
        for (k, t), pose in log.items():
            name = f"tools.motions[{k}]"
            if name in out:
                continue
            try:
                now = motions[k].pose(t)
            except (ValueError, IndexError):  # refused now, or the tool is gone
                now = None
            if not _same(now, pose):
                out.append(name)
        return out

    def light(self) -> list:
        return [(r.model._read_parameters(), r.rollout.run_settings()) for r in self.runs]

    def check(self, light, evaluation: int) -> None:
        """Raise a ``ValueError`` naming what the callback after ``evaluation`` changed, if anything."""
        said = []
        for r, scene, targets, (rows, settings) in zip(self.runs, self.scenes, self.targets, light):
            now = self.scene(r)
            changed = [k for k in dict.fromkeys([*scene, *now]) if not _same(scene.get(k), now.get(k))]
            changed += [k for k in self.scripted(r) if k not in changed]
            now = r.loss.target_items()
            changed += [k for k in dict.fromkeys([*targets, *now]) if not _same(targets.get(k), now.get(k))]
            now_rows = r.model._read_parameters()
            changed += [name for k, name in enumerate(Model.MATERIAL_FIELDS) if not np.array_equal(rows[k], now_rows[k])]
            now_settings = r.rollout.run_settings()
            changed += [f"{k} ({settings[k]!r}, now {now_settings[k]!r})" for k in settings
                        if settings[k] != now_settings.get(k)]
            if changed:
                where = "" if r.name == "the experiment" else f"{r.name}: "
                said.append(where + ", ".join(changed))
        if said:
            raise ValueError(f"callback is not allowed to change the scene mid-fit: after evaluation {evaluation} it "
                             f"changed {'; '.join(said)}; the evaluations after it would fit another scene than "
                             "those before (and the diagnostics read either): have it return True to stop the fit, "
                             "and fit the new scene anew")


def _snapshot(v):
    if isinstance(v, np.ndarray):
        return v.copy()
    return tuple(_snapshot(x) for x in v) if isinstance(v, (tuple, list)) else v


def _same(a, b) -> bool:
    if a is b:
        return True
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        # A position target's NaN is a missing marker, the same as it was.
        nan = isinstance(a, np.ndarray) and a.dtype.kind in "fc"
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.shape == b.shape
                and a.dtype.kind == b.dtype.kind and np.array_equal(a, b, equal_nan=nan and b.dtype.kind in "fc"))
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    try:
        return bool(a == b)
    except ValueError:  # e.g. a pose of arrays
        return False


class _Run(_Values):
    """One experiment made ready: its model, rollout, loss and fitted materials. ``taped``:
    whether the fit takes gradients through its runs (False: a Gauss-Newton fit, whose every
    run reads the loss alone, ``value_forward``); its rollout is weighed for what they hold."""

    def __init__(self, exp: Experiment, dtype, memory_limit, name, taped: bool = True):
        self.name = name
        self.exp = exp
        # tape_values: every loss-only run taped all the same (the benchmark's baseline).
        self.taped = taped or self.tape_values
        from .simulate import exempt_bodies  # noqa: PLC0415

        exempt = exp.monitor_exempt
        made = exp.model
        if callable(made) and not isinstance(made, (Model, SceneBuilder)):
            made = made()  # once: a factory's Scene brings its diverges too
        self.model = _as_model(made, dtype)
        names = [b.name for b in self.model.bodies]
        exempt = exempt_bodies(tuple(getattr(made, "diverges", ()) or ()) if exempt is None else exempt, names)
        #: The particles the divergence monitor's bounds read (``_divergence``; the non-finite
        #: check reads every one).
        self.checked = ~np.isin(self.model.particle_body_np, [names.index(b) for b in exempt])
        self.idx = _material_indices(self.model, exp.materials)
        self.loss = _target_loss(exp.target, exp.frames)
        loss = self.loss
        try:  # here, not at the first evaluation after the first rollout
            loss.check_positions(self.model.particle_count)
        except ValueError as e:
            raise ValueError(f"{name}: target is not allowed for this model: {e}") from None
        _check_target_range(loss, self.model, "target" if name == "the experiment" else f"{name}: target")
        _check_slump_geometry(loss, self.model, "target" if name == "the experiment" else f"{name}: target")
        _warn_target_scale(loss, self.model, "target" if name == "the experiment" else f"{name}: target")
        _warn_target_below_planes(loss, self.model, "target" if name == "the experiment" else f"{name}: target")
        _watch_scan_coverage(loss, self.model, "target" if name == "the experiment" else f"{name}: target")
        if exp.steps is None and max(loss.frames) == 0:
            # "steps = 0 is not allowed" named an option the caller had not given.
            raise ValueError(f"{name}: the target's frames = {list(loss.frames)} end at step 0, the initial state, which "
                             "no material parameter moves: give targets at later steps (and steps = the run's length)")
        self.steps = max(loss.frames) if exp.steps is None else checks.positive_int("steps", exp.steps)
        if max(loss.frames) > self.steps:
            raise ValueError(f"{name}: the target has frames up to step {max(loss.frames)}, beyond steps = {self.steps}")
        self.dt = self.model.stable_dt() if exp.dt is None else checks.positive("dt", exp.dt)
        ck = auto = exp.checkpoint_every
        if isinstance(ck, str):
            if ck != "auto":
                raise ValueError(f"checkpoint_every = {checks.shorten(ck)!r} is not allowed: give 'auto', None or a number of steps")
            ck = choose_checkpointing(self.model, self.steps, memory_limit, taped=self.taped,
                                      frames=len(loss.frames))
        if not self.taped:
            if ck is not None:
                checks.positive_int("checkpoint_every", ck)  # refused as before, though unread
            # No run goes back through its steps: no tape to checkpoint, whatever was asked; a
            # full tape weighed for each run refused or checkpointed fits that hold two states.
            ck = None
        self._segment = ck
        try:
            self.rollout = Rollout(self.model, self.steps, self.dt, frames=sorted(loss.frames), checkpoint_every=ck,
                                   taped=self.taped)
        except RolloutMemoryError as e:
            # Named by the experiment, as its other refusals; and 'auto' as given: its choice
            # (the least memory here) read as a checkpoint_every the caller had given.
            if not e.taped:
                said = (f"steps = {e.steps} is not allowed on {e.device}: even untaped, as every run of a Gauss-Newton "
                        f"fit is, {e.reason}; give fewer steps")
            elif auto == "auto":
                said = (f"steps = {e.steps} is not allowed with checkpoint_every = 'auto' on {e.device}: even at its "
                        f"least memory, a checkpoint every {e.least} steps, {e.reason}; give fewer steps")
            else:
                said = str(e)
            raise e.reworded(f"{name}: {said}", experiment=exp) from None
        self.memory = memory_estimate(self.model, self.steps, self.rollout.segment if self.rollout.checkpointing else None,
                                      taped=self.taped, frames=len(self.rollout.frames))
        initial = {} if exp.initial is None else exp.initial
        if not isinstance(initial, Mapping):
            raise ValueError(f"initial = {checks.shorten(initial)!r} is not allowed: must be a mapping of "
                             f"Rollout.forward keywords ({', '.join(INITIAL_KEYS)})")
        unknown = [k for k in initial if k not in INITIAL_KEYS]
        if unknown:
            # A TypeError out of Rollout.forward at the first evaluation, after the set-up.
            raise ValueError(f"initial[{unknown[0]!r}] is not allowed: the keys are {', '.join(INITIAL_KEYS)}")
        self.initial = dict(initial)
        # Checked once, here: each evaluation ran Rollout.forward(**initial), which checked the
        # starts again (x0's search for coincident particles, milliseconds at tens of thousands
        # of particles, every evaluation), and a refused start surfaced only at the first one.
        self.starts = {name: check_initial(self.model, name, value) for name, value in self.initial.items()
                       if name != "initial_state" and value is not None}
        self._check_speeds()
        self.weight = checks.positive("weight", exp.weight)  # a negative weight would maximise its loss
        self.noise = None if exp.noise is None else checks.noise("noise", exp.noise)
        self._read_values()

    def _check_speeds(self) -> None:
        """Refuse, before any rollout, a start or a tool (or pinned set) that moves more than
        one spacing in a step, as ``simulate`` and ``warp-esph fit`` do: the rollouts ran them
        and the fit fitted to what they made (a box pressing at two spacings a step drove a
        block 0.25 m through the ground). The fitted parameters are the materials', so the
        speeds are those of the whole fit."""
        from .simulate import START_ADVICE, StepRefusal, check_particle_speed  # noqa: PLC0415

        m = self.model
        init = self.initial.get("initial_state")
        if not (isinstance(init, State) and init.particle_count == m.particle_count):
            init = None  # Rollout.forward refuses another one by name
        v = self.starts.get("v0")
        if v is None:
            v = init.v.numpy() if init is not None else m.particle_v0
        t0 = float(init.time) if init is not None else 0.0
        try:
            check_particle_speed(m, v, self.dt)
            if m.tools is not None:
                m.tools.check_speed(self.dt, t0, t0 + self.steps * self.dt)
        except StepRefusal as e:
            advice = "; give a smaller velocity (or angular_velocity, or v0) or a smaller dt=" if e.advice == START_ADVICE else e.advice
            raise ValueError(f"{self.name}: {e.reason}{advice}") from None

    def retime(self, dt: float) -> None:
        """Run the rollout at ``dt`` (the same steps and frames; before any run)."""
        self.dt = dt
        self.rollout = Rollout(self.model, self.steps, dt, frames=sorted(self.loss.frames), checkpoint_every=self._segment,
                               taped=self.taped)

    _flowed = None  # flowed_start, read once for the stable steps (_start_kept)

    def _start_kept(self) -> bool:
        # The start is the fit's own throughout (initial, starts): one read-back, not one a point.
        if self._flowed is None:
            self._flowed = self.flowed_start()
        return self._flowed

    def flowed_start(self) -> bool:
        """Whether the rollout's start keeps the incremental composition whatever the values
        allow (``sim.solver.keeps_incremental``: a flowed body an incremental step wrote): the
        start ``Rollout.forward`` builds from ``initial``, asked as its solver's step asks it
        (``Solver.runs_rest`` is the parameters' choice and not this)."""
        # The rollout's own start, not a reading of initial beside it: the two had to agree on
        # what F0, alpha0 and a given state's flags make of it.
        self.rollout._load_initial(self.initial.get("initial_state"), self.starts)
        return keeps_incremental(self.rollout._initial)

    #: Whether the runs for a loss value alone (``value_forward``) record a tape all the same,
    #: as every run did before: the baseline ``benchmarks.fit_bench --loss-only`` times.
    tape_values = False
    #: Whether each forward keeps a copy of what the diagnostics read (``kept``): set by a fit
    #: whose diagnostics will run, so they need not run its best point again.
    keep = False
    #: The latest forward's ``_KeptRun`` where ``keep`` (None before, or after a failed one).
    kept = None

    def forward(self, taped: bool = True) -> np.ndarray:
        """The rollout from this experiment's starts (checked once, at set-up). A neighbour
        search whose row overflows (``NeighborOverflow``) raises ``Collapsed``, a failed trial."""
        # check=False: a non-finite trial is the fit's to fail (a failed trial, loss inf;
        # with worlds the one world's start alone), not an error ending the fit.
        self.kept = None
        try:
            out = self.rollout._forward_checked(self.starts, self.initial.get("initial_state"), check=False,
                                                taped=taped)
        except NeighborOverflow as e:
            # A blow-up the search met before the monitor could read it: it had ended the whole fit.
            raise Collapsed(e) from None
        if self.keep:
            self.kept = _KeptRun(self.rollout, self.initial.get("initial_state"))
        return out

    def value_forward(self) -> np.ndarray:
        """``forward`` for an evaluation that reads the loss alone (Gauss-Newton's residuals,
        the global stage, the diagnostics' forward differences): no tape is recorded, the
        same bits in less time (``Rollout.forward(taped=False)``)."""
        return self.forward(taped=self.tape_values)

    def value_and_grad(self, loss, before_backward=None) -> tuple[float, dict[str, np.ndarray]]:
        """``Rollout.value_and_grad(loss, **initial)`` from the starts checked at set-up.
        ``before_backward(self)``: called between the forward and the backward; what it
        raises ends the evaluation before the backward runs."""
        check = getattr(loss, "check_positions", None)
        if check is not None:
            check(self.model.particle_count)
        self.forward()
        if before_backward is not None:
            before_backward(self)
        return self.rollout.backward(loss)

    def apply(self, p):
        self.rollout.set_parameters(self.written(p))

    def grads(self, params, grads) -> dict[str, np.ndarray]:
        """Gradients of the fitted values (chain rule through the pressure tie)."""
        out = {}
        for name in params:
            g = grads[name].copy()
            if self.tie and name in ("mu", "lam"):
                factor = self.kp_share * (2.0 / 3.0 if name == "mu" else 1.0) / self.rho
                g[self.tied] += grads["pressure_stiffness"][self.tied] * factor[self.tied]
            out[name] = g[self.idx]
        return out

    def finish(self, p, params):
        """Leave the model holding the fitted materials; returns its material list."""
        self.apply(p)
        fitted = list(self.model.materials)
        kp_now = self.rollout.get_parameters()["pressure_stiffness"]
        for j, k in enumerate(self.idx):
            changes = {name: float(p[name][j]) for name in params}
            if self.tie and k in self.tied:
                changes["pressure_stiffness"] = float(kp_now[k])
            # A force left to its default stays so (its replace(deformation=...) follows the new
            # model); dataclasses.replace alone marked the resolved 'variational' as given.
            fitted[k] = dataclasses.replace(self.model.materials[k], **_following_force(self.model.materials[k], changes))
        for k in self.idx:
            self.model.set_material(k, fitted[k])
        return fitted


def bounds_said(name: str, lo: float, hi: float, flag=lambda name: name) -> str:
    """A parameter's bounds as the caller gave them: ``bounds['mu'] = (1, 10)`` to ``fit``,
    ``--bounds mu=1:10`` on the command line (``flag`` names options with ``--``; it was
    ``--bounds['mu'] = (1.0, 10.0)``, which no one types)."""
    if flag("bounds").startswith("--"):
        return f"{flag('bounds')} {name}={lo:g}:{hi:g}"
    return f"{flag('bounds')}[{name!r}] = ({lo:g}, {hi:g})"


class BoundsError(checks.Rebuilt, ValueError):
    """Bounds of a fitted parameter that the fit refuses once the model is known (``lo`` of a
    log-space parameter at or below 0; an end the material refuses). ``said(flag)``: the
    message naming them as ``flag`` names options (the command line's ``--bounds NAME=LO:HI``),
    with ``cli_reason`` where the reason's advice has the command's spelling (a precision's
    ``use dtype=float64 (--dtype float64)``: the command takes no ``dtype=``)."""

    def __init__(self, name: str, lo: float, hi: float, reason: str, cli_reason: str | None = None):
        self.name, self.lo, self.hi, self.reason = name, lo, hi, reason
        self.cli_reason = reason if cli_reason is None else cli_reason
        super().__init__(self.said())

    def said(self, flag=lambda name: name, typed: str | None = None) -> str:
        """``typed``: the entry as the user wrote it (``hardening=-1e6:100``), named so."""
        given = f"{flag('bounds')} {typed}" if typed is not None else bounds_said(self.name, self.lo, self.hi, flag)
        reason = self.cli_reason if flag("bounds").startswith("--") else self.reason
        return f"{given} is not allowed: {reason}"


class ParamScaleRefused(checks.Rebuilt, ValueError):
    """A given scale of a parameter fitted as its logarithm, refused once the model gives its
    start. ``said(flag, typed)``: named as ``flag`` names options (the command line's
    ``--param-scales NAME=S``, ``typed`` the entry as written). Not ``scenes.ScaleRefused``,
    a scene's resolution refused."""

    def __init__(self, name: str, size: float, reason: str):
        self.name, self.size, self.reason = name, size, reason
        super().__init__(self.said())

    def said(self, flag=lambda name: name, typed: str | None = None) -> str:
        given = (f"{flag('param_scales')} {typed}" if typed is not None
                 else f"{flag('param_scales')}[{self.name!r}] = {self.size!r}")
        return f"{given} is not allowed: {self.reason}"


class StartRefused(checks.Rebuilt, ValueError):
    """The guess, held to the bounds, refused by a material (each end allowed alone, but two
    ends together past a precision's range). ``held``: ``(name, lo, hi, side)`` of each
    parameter whose guess the bounds moved, and that guess (None: several materials'), the
    one the refusal is said of first; ``reason``
    the material's refusal, ``cli_reason`` with the command's spelling of a precision's advice
    (``--dtype float64``). ``said(flag, typed)`` names the bounds as ``BoundsError.said`` does:
    the message had quoted ``Material.mu = 1e+38``, a field of a class neither the command's
    user (who typed ``--bounds mu=1e38:1.1e38``) nor fit's had written."""

    def __init__(self, held: list, reason: str, cli_reason: str):
        self.held, self.reason, self.cli_reason = held, reason, cli_reason
        super().__init__(self.said())

    def said(self, flag=lambda name: name, typed: dict | None = None) -> str:
        """``typed``: the ``--bounds`` entries as the user wrote them, by parameter."""
        typed = typed or {}
        reason = self.cli_reason if flag("bounds").startswith("--") else self.reason
        said = "the initial values are not allowed within the bounds: "
        if not self.held:
            return said + reason

        def entry(name, lo, hi):
            return f"{flag('bounds')} {typed[name]}" if name in typed else bounds_said(name, lo, hi, flag)

        (name, lo, hi, side, _), *others = self.held

        def holds(n, lo, hi, s, v):
            return f"{entry(n, lo, hi)} holds {n}'s guess{'' if v is None else f', {v:g},'} at its {s} end"

        also = "".join(f"; {holds(*h)}" for h in others)
        end, whose = (lo if side == "lower" else hi), f"{name}'s"
        return f"{said}{holds(*self.held[0])}{also}: {_end_refused(name, side, end, reason, whose)}"


def _refused_field(why: str):
    """The parts of a material's refusal ``Material.<field> = <value> [(material k)] is not
    allowed[ in <precision>]: <what is allowed>``, or None where it reads otherwise."""
    import re  # noqa: PLC0415

    return re.match(r"(?:Material\.)?(\w+) = (\S+?)(?: \(material \d+\))? is not allowed( in \w+)?: (.*)$", why, re.S)


def _end_refused(name: str, side: str, end: float, why: str, whose: str = "its") -> str:
    """Why the ``side`` end of ``name``'s bounds is refused, from the material's refusal
    ``why`` of it: said of the parameter and the end, not as the material's own
    ``Material.hardening = -1000000.0 is not allowed`` (a field of a class the user, who
    typed ``--bounds hardening=-1e6:100``, never wrote), with what is allowed. ``whose``: the
    end's owner as the sentence names it (``mu's`` where several bounds were said before)."""
    m = _refused_field(why)
    if m is None:
        return f"at {whose} {side} end, {end:g}, the material refuses it: {why}"
    other, value, where, rest = m.group(1), m.group(2), m.group(3) or "", m.group(4)
    said = f"{other} {rest}" if rest.startswith("must") else rest
    if other == name:
        return f"{whose} {side} end, {end:g}, is a {name} the material refuses{where}: {said}"
    return f"{whose} {side} end, {end:g}, gives the material {other} = {value}, which it refuses{where}: {said}"


class RefusedPoint(FloatingPointError):
    """A point of optimiser space whose values the materials refuse; the optimisers treat it
    as a failed trial (as a rollout that blew up), its reason kept in the history's note."""


class Diverged(FloatingPointError):
    """A rollout that blew up, to non-finite values or while staying finite
    (``simulate.DivergenceMonitor``'s bounds, which stop ``simulate`` and the CLI's runs, on
    its last state, or ``simulate.energy_growth``, which fails a ``sweep`` sample): a failed trial, its reason kept in the history's note. Its loss, finite,
    had been taken as a result (a block at 1 km scored 1.6e6 m^2 and the fit reported its
    values); a NaN one was recorded as NaN with no word of where the run went non-finite."""


class Collapsed(checks.Rebuilt, Diverged):
    """A rollout whose neighbour search stopped it (``NeighborOverflow``: a particle with more
    than ``MAX_CANDIDATES`` candidates, a body crushed together or a blow-up whose stretch
    widened the search over it): a failed trial, as a divergence. ``particles``: those past
    the limit (with worlds, the worlds whose starts fail)."""

    def __init__(self, error, first: int = 0, particles=None):
        self.error = error
        self.particles = error.particles if particles is None else particles
        super().__init__(_collapse_note(error, self.particles, first))


def _collapse_note(error, particles, first: int = 0) -> str:
    from .sim.neighbors import MAX_CANDIDATES  # noqa: PLC0415 (read when raised: a test may lower it)

    p = int(particles[0]) - first if len(particles) else None
    return (f"diverged: the neighbour search found up to {error.need} particles within a particle's search radius, "
            f"more than {MAX_CANDIDATES} (a body crushed together, or a blow-up whose stretch widened the search over "
            f"it){'' if p is None else f' (particle {p})'}")


def _divergence(model: Model, rollout: Rollout, particles=None, first: int = 0, checked=None) -> str | None:
    """Why the rollout is a blow-up, or None: a non-finite position or velocity among
    ``particles`` (a boolean mask, None: all; at a frame or in the last state; the first step
    found so), else ``simulate.DivergenceMonitor``'s bounds from its initial state on the last
    state, or the energy growth ``sweep`` fails a sample on (``Rollout.bounds_hit``), of ``checked`` (``particles`` less the monitor's exempt bodies; None: ``particles``).
    An exempt body is left out of the bounds alone, as ``simulate`` leaves it: a non-finite
    value is no blow-up a scene shows but a lost state, which spreads to what it meets and
    makes the gradient of its material NaN (a fit whose exempt body went non-finite at the
    guess had gone on and reported 'converged'). The particle is named by its index less
    ``first``: a world's first particle, so that a start run as a world is noted as it is run
    alone (its history describes the one-world model)."""
    checked = particles if checked is None else checked
    bad = rollout.first_non_finite(particles)
    if bad is not None:
        step, p, last_finite = bad
        since = "" if step - last_finite <= 1 else f", finite after step {last_finite}"
        return (f"diverged: non-finite position or velocity (particle {p - first}, after step {step} of "
                f"{rollout.steps}{since})")
    hit = rollout.bounds_hit(checked)
    return None if hit is None else f"diverged: {hit[0]} (particle {hit[1] - first}, at the rollout's last step)"


def _check_diverged(run) -> None:
    why = _divergence(run.model, run.rollout, checked=run.checked)
    if why is not None:
        raise Diverged(why)


#: How ``_natural_scale`` sizes a parameter fitted as itself from 0 without bounds.
_NATURAL_SCALE_SAID = {"lam": "mu", "hardening": "mu", "pressure_stiffness": "its default share K / density",
                       "viscosity": "mu times the stable step"}


def _natural_scale(name: str, run: _Values, guess) -> float:
    """The size of a parameter that starts at 0 from the fitted materials' other values, in
    its own units: a stress modulus (``lam``, ``hardening``) by ``mu``; ``pressure_stiffness``
    by the one the material gives by default (``share K / rho0``); ``viscosity`` by the one
    whose stress over a step is ``mu``'s over the strain the step makes (``mu dt`` at the
    stable step of the start). Each scales with the units of the others, so the same problem
    in other units takes the same path."""
    idx = run.idx
    mu = run.values["mu"][idx]
    if name in ("lam", "hardening"):
        return float(np.max(mu))
    if name == "pressure_stiffness":
        lam = guess["lam"] if "lam" in guess else run.values["lam"][idx]
        mu_k = guess["mu"] if "mu" in guess else mu
        return float(np.max(run.kp_share[idx] * (lam + 2.0 * mu_k / 3.0) / run.rho[idx]))
    return float(np.max(mu)) * run.stable_step({n: np.asarray(v, dtype=np.float64) for n, v in guess.items()})


class _Problem:
    """The shared parameter vector of one or more experiments, in optimiser space.

    ``z = log(p)`` for positive parameters, ``p / scale`` for the others (``_linear_scale``);
    ``bounds`` clip.
    """

    def __init__(self, runs: list[_Run], params, bounds, param_scales=None):
        self.runs, self.params = runs, params
        first = runs[0]
        self.k = len(first.idx)
        for r in runs[1:]:
            if len(r.idx) != self.k:
                raise ValueError(f"{r.name} fits {len(r.idx)} materials, {first.name} {self.k}: a joint fit shares "
                                 f"material k of every experiment, so each must select the same number (materials=...)")
        values = first.values
        self.spaces, self.scales, self.scale_source = {}, {}, {}
        for name in params:
            v = values[name][first.idx]
            if name in _POSITIVE or (v > 0).all():
                if not (v > 0).all():
                    # 'must be > 0 to be fitted' read as the material's refusal of a value it takes
                    # (a yield stress of 0 is a Maxwell fluid): it is the logarithm that has none.
                    said = f"{v[0]:g}" if self.k == 1 else str(v.tolist())
                    raise ValueError(f"{name} = {said} is not allowed as the start of a fit: it is fitted as its "
                                     "logarithm, which has no value at or below 0; give a start above 0 (a bound lo > 0 "
                                     "keeps it there)")
                self.spaces[name] = "log"
            else:
                self.spaces[name] = "linear"
        for name, s in (param_scales or {}).items():  # their form checked by check_options
            if self.spaces[name] == "log":
                raise ParamScaleRefused(name, s, f"{name} is fitted as its logarithm (its initial value"
                                   f"{'s' if self.k > 1 else ''} {', '.join(f'{x:g}' for x in values[name][first.idx])} "
                                   "being positive), whose steps are relative to the value and take no size; give "
                                   "sizes only of parameters fitted from 0 or below it")
        self.bounds = {}
        for name, (lo, hi) in (bounds or {}).items():  # their form checked by check_options
            lo, hi = float(lo), float(hi)
            if self.spaces[name] == "log" and lo <= 0.0 and lo != -math.inf:
                # Fitted as log(value): lam or a hardening of positive initial values is too, and
                # 'a positive parameter' did not say why, nor how to fit one across 0.
                why = (f"{name} is positive" if name in _POSITIVE else
                       f"{name} is fitted as its logarithm, its initial value{'s' if self.k > 1 else ''} "
                       f"{', '.join(f'{x:g}' for x in values[name][first.idx])} being positive (from 0 or below it is "
                       "fitted as itself, and may cross 0)")
                raise BoundsError(name, lo, hi, f"need lo > 0: {why}")
            self.bounds[name] = (lo, hi)
        for name in params:
            # A value fitted in linear space whose range starts at 0 (a viscosity, a pressure
            # stiffness fitted from 0) stays in it: the global stage, the starts and the
            # diagnostics' differences do not step below what every material takes.
            if self.spaces[name] == "linear" and name in _NON_NEGATIVE and name not in self.bounds:
                self.bounds[name] = (0.0, math.inf)
        guess = {name: values[name][first.idx] for name in params}
        for name in params:
            if self.spaces[name] == "linear":
                self.scales[name], self.scale_source[name] = self._linear_scale(name, guess, param_scales or {})
        for name, (lo, hi) in self.bounds.items():
            # A bound a material refuses would only make refused trials: said at once.
            for side, end in (("lower", lo), ("upper", hi)):
                if math.isfinite(end):
                    at_end = guess | {name: np.full(self.k, end)}
                    why = self.refusal(at_end)
                    if why is not None:
                        raise BoundsError(name, lo, hi, _end_refused(name, side, end, why),
                                          _end_refused(name, side, end, self.refusal(at_end, cli=True)))
        # The start is the guess itself (a value outside the box, its bound), not exp(log p):
        # that missed the user's value by an ulp (300 Pa ran as 300.00000000000006), and the
        # fit's first evaluation and its initial loss were not the guess's. Each coordinate at
        # its start's z reads its start's value (``from_z``), so a point that moved some values
        # (a Jacobian's difference, a value held on a bound) keeps the others as given.
        self._start = None
        start = {name: np.clip(v, *self.bounds[name]) if name in self.bounds else np.array(v, dtype=np.float64)
                 for name, v in guess.items()}
        why = self.refusal(start)
        if why is not None:
            # Said of the bounds that moved the guess, as given (the field the material names
            # first where the bounds moved it): the guess itself was the model's, and allowed.
            held = []
            for name in params:
                if name in (bounds or {}):
                    lo, hi = self.bounds[name]
                    if np.any(guess[name] < lo) or np.any(guess[name] > hi):
                        held.append((name, lo, hi, "lower" if np.any(guess[name] < lo) else "upper",
                                     float(guess[name][0]) if self.k == 1 else None))
            field = _refused_field(why)
            held.sort(key=lambda h: field is None or h[0] != field.group(1))
            raise StartRefused(held, why, self.refusal(start, cli=True))
        self.z0 = self.to_z(start)
        self._start = (self.z0.copy(), np.concatenate([start[n] for n in params]))
        #: One label per entry of z: ``name`` or ``name[k]`` with several materials.
        self.labels = [name if self.k == 1 else f"{name}[{j}]" for name in params for j in range(self.k)]

    def _linear_scale(self, name: str, guess, param_scales) -> tuple[float, str]:
        """The size of one unit of ``z`` for a parameter fitted as itself, and where it came
        from. A step of ``lr`` moves the value by ``lr`` times it, so it must be the value's
        own size: it was ``max(|start|, 1)`` in whatever units the parameter has, so a
        hardening fitted from 0 Pa against mu = 1e5 Pa moved 0.1 Pa a step, and the same
        problem in other units took another path."""
        if name in param_scales:
            return float(param_scales[name]), "given"
        v = float(np.abs(guess[name]).max())
        if v > 0.0:
            return v, "start"
        lo, hi = self.bounds.get(name, (-math.inf, math.inf))
        if math.isfinite(lo) and math.isfinite(hi):
            return hi - lo, "bounds"
        s = _natural_scale(name, self.runs[0], guess)
        if not (math.isfinite(s) and s > 0.0):
            raise ValueError(f"{name} starts at 0 without finite bounds, and its materials give it no size "
                             f"({_NATURAL_SCALE_SAID[name]} = {s:g}): give param_scales={{{name!r}: size}} (a step of lr moves "
                             "it by lr times that size), or finite bounds")
        return s, "material"

    def param_scales_record(self) -> dict:
        """``FitResult.param_scales``: of each parameter fitted as itself, its size and its source."""
        return {n: {"size": self.scales[n], "from": self.scale_source[n]} for n in self.params if n in self.scales}

    def to_z(self, p) -> np.ndarray:
        return np.concatenate([np.log(p[n]) if self.spaces[n] == "log" else p[n] / self.scales[n] for n in self.params])

    def from_z(self, z) -> dict[str, np.ndarray]:
        out = {}
        for j, name in enumerate(self.params):
            part = slice(j * self.k, (j + 1) * self.k)
            zz = np.asarray(z[part], dtype=np.float64)
            v = np.exp(zz) if self.spaces[name] == "log" else zz * self.scales[name]
            if name in self.bounds:
                v = np.clip(v, *self.bounds[name])
            if self._start is not None:
                z0, p0 = self._start
                v = np.where(zz == z0[part], p0[part], v)
            out[name] = v
        return out

    def project(self, z) -> np.ndarray:
        return self.to_z(self.from_z(z))

    def z_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = [], []
        for name in self.params:
            a, b = self.bounds.get(name, (-math.inf, math.inf))
            if self.spaces[name] == "log":
                a, b = (math.log(a) if a > 0 else -math.inf), (math.log(b) if b < math.inf else math.inf)
            else:
                a, b = a / self.scales[name], b / self.scales[name]
            lo += [a] * self.k
            hi += [b] * self.k
        return np.array(lo), np.array(hi)

    def grad_z(self, p, grads: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([grads[n] * p[n] if self.spaces[n] == "log" else grads[n] * self.scales[n] for n in self.params])

    def refusal(self, p, cli: bool = False) -> str | None:
        """Why a material would refuse the values ``p``, or None (``cli``: as ``_Run.refusal``).
        An optimiser's step too long for the parameters' range (``exp`` past the floats,
        ``lam`` fitted in linear space stepping below -2 mu / 3) is a failed trial, as a
        rollout that blew up is, and not an error of the fit: it is refused here, before any
        value reaches the model."""
        for r in self.runs:
            why = r.refusal(p, cli)
            if why is not None:
                return why
        return None

    def apply(self, z):
        p = self.from_z(z)
        why = self.refusal(p)
        if why is not None:
            raise RefusedPoint(why)
        for r in self.runs:
            r.apply(p)
        return p

    def loss_roundoff(self) -> np.ndarray:
        """Per optimiser entry, the weighted sum over the experiments of
        ``Rollout.loss_roundoff`` at the last evaluation with a gradient: that of the world the
        entry's material is in, so that a world's values are judged by its own loss (all the
        worlds' where the entry is no material's)."""
        out = np.zeros(len(self.z0))
        for r in self.runs:
            per_world = r.rollout.loss_roundoff()
            if per_world is None:
                continue
            starts = np.asarray(r.model.world_material_start, dtype=np.int64)
            idx = np.asarray(r.idx, dtype=np.int64)
            if len(per_world) == 1 or len(idx) != self.k:
                out += r.weight * float(per_world.sum())
                continue
            worlds = np.searchsorted(starts, idx, side="right") - 1
            out += r.weight * np.tile(per_world[worlds], len(self.params))
        return out

    def value_and_grad(self, z, losses=None, wants=None) -> tuple[float, np.ndarray | None]:
        """The weighted sum of the experiments' losses (or of ``losses``, one per run) and
        its gradient in optimiser space. ``wants(value)``: whether the gradient at that loss
        is read (``_run_lbfgs``'s trials); where not, no backward runs and the gradient is None."""
        if wants is not None and losses is None:
            return self._value_then_grad(z, wants)
        p = self.apply(z)
        total, gz = 0.0, np.zeros(len(z))
        for k, r in enumerate(self.runs):
            loss = r.loss if losses is None else losses[k]
            w = r.weight if losses is None else 1.0
            # The fit's own evaluations fail a diverged trial (the diagnostics' read the fitted
            # point's neighbourhood), before its backward: no optimiser reads a failed trial's
            # gradient, which had been computed all the same.
            value, grads = r.value_and_grad(loss, _check_diverged if losses is None else None)
            total += w * float(value)
            gz += w * self.grad_z(p, r.grads(self.params, grads))
        return total, gz

    def _value_then_grad(self, z, wants) -> tuple[float, np.ndarray | None]:
        """``value_and_grad`` whose backwards run only where ``wants`` the loss the taped
        forwards give: every experiment's forward first (each its own rollout and tape, so the
        backwards after them give the bits they gave each after its own forward)."""
        p = self.apply(z)
        for r in self.runs:
            check = getattr(r.loss, "check_positions", None)
            if check is not None:
                check(r.model.particle_count)
            r.forward()
            _check_diverged(r)
        value = 0.0
        for r in self.runs:
            value += r.weight * float(r.loss.value(r.rollout.observations()))
        if not wants(value):
            return value, None
        total, gz = 0.0, np.zeros(len(z))
        for r in self.runs:
            v, grads = r.rollout.backward(r.loss)
            total += r.weight * float(v)
            gz += r.weight * self.grad_z(p, r.grads(self.params, grads))
        return total, gz

    def value(self, z) -> float:
        """The loss alone (forward passes only, no tape backward)."""
        self.apply(z)
        total = 0.0
        for r in self.runs:
            r.value_forward()
            _check_diverged(r)
            total += r.weight * r.loss.value(r.rollout.observations())
        return total


def _start_candidates(prob: _Problem, samples: int, starts: int, sample_range: float, seed: int) -> list[np.ndarray]:
    """The points a fit starts from, in optimiser space, drawn before any run: with
    ``samples``, the global stage's candidates (the guess and ``samples`` Latin-hypercube
    points of the box; the starts are the best of them), else the guess and ``starts - 1``
    points of the same box."""
    lo, hi = prob.z_bounds()
    span = np.where(np.array([prob.spaces[n] == "log" for n in prob.params for _ in range(prob.k)]),
                    math.log(sample_range), sample_range)
    lo = np.maximum(lo, prob.z0 - span)
    hi = np.minimum(hi, prob.z0 + span)
    rng = np.random.default_rng(seed)
    if samples:
        return [prob.z0] + [lo + u * (hi - lo) for u in latin_hypercube(samples, len(prob.z0), rng)]
    return [prob.z0] + [prob.project(lo + u * (hi - lo)) for u in latin_hypercube(starts - 1, len(prob.z0), rng)]


def _choose_steps(runs: list[_Run], prob: _Problem, candidates) -> list[str]:
    """Give every experiment whose ``dt`` the fit chose (``dt=None``) the smallest stable step
    over ``candidates``, the points its starts (and global stage) begin from; returns the
    lines to log. One step for all the starts, not each start its own: a start's loss is its
    misfit at the targets' step indices, and at another step those are other times and
    another discretisation, so the lowest loss would not tell the best start (and with
    ``worlds`` all the starts run in one model, at one step). The guess's own step, which
    it had been, was past the stable step of every stiffer start (a start at 4 x mu ran at 2 x
    its step, warned and could blow up). A ``dt`` the caller gave is kept; where it is past
    a start's stable step the log says so."""
    said = []
    for r in runs:
        rows = r.model._read_parameters()
        steps = [r.stable_step(prob.from_z(z), rows) for z in candidates]
        least = min(steps)
        if least >= r.dt:
            continue
        if r.exp.dt is None:
            # The guess's own (candidates[0]) from the run's start, not r.dt, a new state's: from a
            # flowed body made elastic the log called the half the stiffest point's, the whole the guess's.
            said.append(f"{r.name}: dt = {least:.4g} s, the stable step of the stiffest point the fit starts from "
                        f"(the guess's is {steps[0]:.4g} s)" if least < steps[0] else
                        f"{r.name}: dt = {least:.4g} s, the guess's stable step from the run's start "
                        f"(Model.stable_dt(state=); a new state's is {r.dt:.4g} s)")
            r.retime(least)
        else:
            said.append(f"{r.name}: dt = {r.dt:.4g} s is above {least:.4g} s, the stable step of the stiffest point "
                        f"the fit starts from: such starts may blow up (failed starts); give dt <= {least:.4g}")
    return said


def starts_stable_steps(models, params, *, materials=None, bounds=None, samples=0, starts=1, sample_range=4.0,
                        seed=0, tie_pressure=None, names=None, param_scales=None) -> list[float]:
    """For each of ``models`` (a joint fit's, the first holding the guess), the smallest
    ``Model.stable_dt()`` over the points ``fit(..., samples, starts, sample_range, seed)``
    starts from (the guess among them), before any run: the step at which a fit of
    ``params`` can run every start. The command line chooses its steps per frame from it.
    ``materials``: one selection per model (None: all); ``names``: how refusals name them."""
    materials = [None] * len(models) if materials is None else materials
    names = names or [f"experiment {k}" if len(models) > 1 else "the experiment" for k in range(len(models))]
    vals = [_Values(m, _material_indices(m, sel), name) for m, sel, name in zip(models, materials, names)]
    for v in vals:
        v.setup_tie(params, tie_pressure)
    prob = _Problem(vals, params, bounds, param_scales)
    candidates = _start_candidates(prob, samples, starts, sample_range, seed)
    out = []
    for v in vals:
        rows = v.model._read_parameters()
        out.append(min(v.stable_step(prob.from_z(z), rows) for z in candidates))
    return out


#: The most samples of a fit's global stage and local starts from them (each a forward run).
MAX_SAMPLES = 10_000
MAX_STARTS = 1_000
#: The most ``iterations`` a fit takes: far above any real fit (the examples converge in tens
#: of evaluations), and each is at least a rollout; 1e22 was taken and estimated at 6.6e18 h.
MAX_ITERATIONS = 100_000
#: The largest step size (``lr``, ``lr_end``): in optimiser space, where a positive
#: parameter is its log, 10 is a factor e^10 = 2.2e4 in one step.
MAX_LR = 10.0
#: ``lr`` where none is given (Adam's step size, L-BFGS's first step).
LR = 0.1
#: ``xtol`` where none is given: the step (in optimiser space) below which a fit has converged.
XTOL = 1e-6


def _count(name: str, value) -> int:
    """An integer >= 0 (an integral float too, as ``int()`` took it before)."""
    try:
        v = int(value)
        ok = not isinstance(value, bool) and v == value and v >= 0
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be an integer >= 0")
    return v


def _step_size(name: str, value) -> float:
    v = checks.positive(name, value)
    if v > MAX_LR:
        raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be in (0, {MAX_LR:g}] (a step in "
                         f"optimiser space, the log of a positive parameter: {MAX_LR:g} is a factor e^{MAX_LR:g})")
    return v


#: What each option that only the draws read does (``_refuse_undrawn``).
_DRAWN_ONLY = {"seed": "it seeds the global stage's draws",
               "sample_range": "it sizes the box the global stage's samples and the extra starts are drawn from"}


def _refuse_undrawn(checked: dict, **given) -> None:
    """Refuse each of ``given`` (``seed``, ``sample_range``: None where not given) where the fit
    draws nothing (``checked``: ``check_options``'s, no samples and one start): refused, not
    ignored, as the command refuses ``--seed`` and ``--sample-range``; the fit ran exactly as
    without it (fit(seed=10**400) and fit(sample_range=8) were taken without a word)."""
    if checked["samples"] or checked["starts"] > 1:
        return
    for name, value in given.items():
        if value is not None:
            raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed without samples or starts > 1: "
                             f"{_DRAWN_ONLY[name]}, and this fit draws nothing")


def check_options(*, params, iterations, lr=None, lr_end=None, clip=None, bounds=None, optimizer="adam", patience=20,
                  samples=0, starts=1, sample_range=4.0, seed=0, noise=None, memory_limit=MEMORY_LIMIT, xtol=XTOL,
                  flag=lambda name: name, bounds_typed: Mapping | None = None,
                  param_scales=None, param_scales_typed: Mapping | None = None) -> dict:
    """``fit``'s options that need no model, checked (as ``fit`` checks them, before any
    rollout): a dict of the validated values. ``flag(name)`` is how a message names an
    option (the command line passes ``--lr`` for ``lr``). ``lr``: ``None`` is ``LR``, and
    one given is refused with ``optimizer = "gauss-newton"``, which never reads it. Bounds
    are checked here for their form (``lo < hi``, a fitted parameter); ``fit`` checks
    ``lo > 0`` of a positive one. ``param_scales`` (``{name: size}``): each a fitted parameter's
    positive, finite size; ``fit`` refuses one of a parameter fitted as its logarithm."""
    if isinstance(params, str):
        params = [p.strip() for p in params.split(",") if p.strip()]
    try:
        params = list(params)
    except TypeError:
        raise ValueError(f"{flag('params')} = {checks.shorten(params)!r} is not allowed: must be a list of parameter "
                         f"names ({', '.join(PARAMETERS)})") from None
    if not params:
        raise ValueError(f"{flag('params')} = [] is not allowed: name at least one parameter")
    for p in params:
        if not isinstance(p, str) or p not in PARAMETERS:  # a 2-D array's rows met 'in' with numpy's 'ambiguous'
            lab = (f"{lab_value_note(p, 'parameter')} (fit {LAB_QUANTITIES[p][0]}: the fitted material's {p} is "
                   f"{LAB_QUANTITIES[p][2]})" if isinstance(p, str) and p in LAB_QUANTITIES else "")
            raise ValueError(f"{flag('params')} entry {checks.shorten(p)!r} is not allowed: must be one of "
                             f"{', '.join(PARAMETERS)}{lab}{material_setting_note(p, 'fitted', flag('params').startswith('--'))}")
    if len(set(params)) != len(params):
        raise ValueError(f"{flag('params')} = {checks.shorten(params)!r} is not allowed: names must be distinct")
    out = {"params": params, "iterations": _count(flag("iterations"), iterations),
           "lr": LR if lr is None else _step_size(flag("lr"), lr),
           "lr_end": None if lr_end is None else _step_size(flag("lr_end"), lr_end),
           "clip": None if clip is None else checks.positive(flag("clip"), clip),
           "optimizer": checks.choice(flag("optimizer"), optimizer, OPTIMIZERS),
           "xtol": checks.positive("xtol", xtol),  # not a command-line option: named as fit's
           "patience": checks.positive_int(flag("patience"), patience),
           "starts": checks.positive_int(flag("starts"), starts, maximum=MAX_STARTS),
           "sample_range": checks.greater_than(flag("sample_range"), sample_range, 1.0, "1"),
           "noise": None if noise is None else checks.noise(flag("noise"), noise),
           "memory_limit": checks.positive(flag("memory_limit"), memory_limit)}
    if out["iterations"] > MAX_ITERATIONS:
        raise ValueError(f"{flag('iterations')} = {out['iterations']} is not allowed: must be at most {MAX_ITERATIONS} "
                         "(each is a rollout at least)")
    if lr is not None and out["optimizer"] == "gauss-newton":
        # Levenberg-Marquardt sizes its steps by its damping and never reads lr: the fit ran
        # as if it had not been given.
        cli = flag("optimizer").startswith("--")
        gn = f"{flag('optimizer')} gauss-newton" if cli else f"{flag('optimizer')} = 'gauss-newton'"
        others = f"{flag('optimizer')} lbfgs or adam" if cli else f"{flag('optimizer')} = 'lbfgs' or 'adam'"
        raise ValueError(f"{flag('lr')} = {checks.shorten(lr)!r} is not allowed with {gn}: its steps are sized by the "
                         f"Levenberg-Marquardt damping, not by a step size; leave {flag('lr')} out, or give {others}")
    if out["optimizer"] in LR_OPTIMIZERS and out["xtol"] >= out["lr"]:
        # Either's first step moves by lr: at or below xtol it counted as converged. Named by
        # lr when xtol is the default: the command line sets lr (--lr) but not xtol.
        # (Both named: the command line chooses between them only once the scene is read.)
        why = f"the first step of Adam and of L-BFGS moves by {flag('lr')}"
        if out["xtol"] == XTOL:
            raise ValueError(f"{flag('lr')} = {checks.shorten(out['lr'])!r} is not allowed with xtol = {out['xtol']:g}: must "
                             f"be > xtol ({why}, and a step below xtol counts as converged)")
        raise ValueError(f"xtol = {checks.shorten(out['xtol'])!r} is not allowed with {flag('lr')} = {out['lr']:g}: must "
                         f"be < {flag('lr')} ({why}, so it would count as converged)")
    out["samples"] = _count(flag("samples"), samples)
    if out["samples"] > MAX_SAMPLES:
        # Each is a forward run, and the hypercube is drawn at once: 1e11 asked for 745 GiB.
        raise ValueError(f"{flag('samples')} = {out['samples']} is not allowed: must be at most {MAX_SAMPLES}")
    if out["samples"] and out["starts"] > out["samples"] + 1:
        # The descents start from the best of the guess and the samples: the rest were dropped.
        raise ValueError(f"{flag('starts')} = {out['starts']} is not allowed with {flag('samples')} = {out['samples']}: "
                         f"the starts are the best of the guess and the samples, at most {out['samples'] + 1}")
    out["seed"] = _count(flag("seed"), seed)
    if bounds is not None and not isinstance(bounds, Mapping):
        raise ValueError(f"{flag('bounds')} = {checks.shorten(bounds)!r} is not allowed: must be a mapping "
                         "{name: (lo, hi)}")
    typed = bounds_typed or {}

    def said(name, lo, hi):
        # The command line's entry as typed ('mu=1e3:1e2'), else as bounds_said writes it.
        return f"{flag('bounds')} {typed[name]}" if name in typed else bounds_said(name, lo, hi, flag)

    for name, rng in (bounds or {}).items():
        if name not in params:
            if name in typed:
                raise ValueError(f"{said(name, 0, 0)} is not allowed: {name} is not fitted ({flag('params')} "
                                 f"{','.join(params)}); give bounds of a fitted parameter")
            raise ValueError(f"{flag('bounds')} for {name!r} are not allowed: {name} is not fitted (params = {params})")
        try:
            lo, hi = (float(v) for v in rng)
        except (TypeError, ValueError):
            raise ValueError(f"{flag('bounds')}[{name!r}] = {checks.shorten(rng)!r} is not allowed: must be (lo, hi) numbers") from None
        if math.isnan(lo) or math.isnan(hi):
            # It said 'need lo < hi' of (nan, 1.0), which reads as a wrong order.
            raise ValueError(f"{said(name, lo, hi)} is not allowed: a bound must be a number, not NaN (an "
                             "open end is -inf or inf)")
        if not lo < hi:
            raise ValueError(f"{said(name, lo, hi)} is not allowed: need lo < hi")
    out["param_scales"] = _check_param_scales(param_scales, params, flag, param_scales_typed or {})
    return out


def _check_param_scales(param_scales, params, flag, typed) -> dict[str, float]:
    """``param_scales`` as ``{name: size}`` of fitted parameters, each size positive and finite;
    ``typed``: the command line's entries as written, by name."""
    if param_scales is None:
        return {}
    if not isinstance(param_scales, Mapping):
        raise ValueError(f"{flag('param_scales')} = {checks.shorten(param_scales)!r} is not allowed: must be a mapping "
                         "{name: size}")
    out = {}
    for name, size in param_scales.items():
        if name not in params:
            given = f"{flag('param_scales')} {typed[name]}" if name in typed else f"{flag('param_scales')} for {name!r}"
            raise ValueError(f"{given} is not allowed: {name} is not fitted ({flag('params')} = "
                             f"{','.join(params)}); give the size of a fitted parameter")
        out[name] = checks.positive(f"{flag('param_scales')}[{name!r}]", size)
    return out


#: What ``fit`` raises on Ctrl-C: a plain ``KeyboardInterrupt`` whose ``result`` is a
#: ``FitResult`` of the evaluations so far, at the best of them (``stopped`` "interrupted";
#: the model holds its values), or None before the first finite one; during the
#: diagnostics, the finished fit without them. The command line writes it before it exits.
#: It was a subclass of ``KeyboardInterrupt``, but Python ends a script on an uncaught
#: interrupt with the SIGINT status (130) only for that exact type: a script stopped in
#: ``fit`` exited 1. The name stays so that ``except FitInterrupted as e: e.result`` still
#: works; it now catches every ``KeyboardInterrupt``, and each one out of ``fit`` has ``result``.
FitInterrupted = KeyboardInterrupt


def _fit_interrupted(result) -> KeyboardInterrupt:
    e = KeyboardInterrupt()
    e.result = result
    return e


def _result_on_interrupt(f):
    """``f`` (``fit``) with ``result`` set (None) on an interrupt raised before its first
    evaluation: ``except FitInterrupted as e: e.result`` catches it too, now that the name is
    ``KeyboardInterrupt`` itself."""

    @functools.wraps(f)
    def wrapper(*args, **kwargs):
        try:
            return f(*args, **kwargs)
        except KeyboardInterrupt as e:
            if not hasattr(e, "result"):
                e.result = None
            raise

    return wrapper


class _Track:
    """One start's descent in ``fit``: its best point and evaluations since the best improved.
    At module level: a class made inside each fit is a reference cycle (its dict, its
    methods), left to the cyclic collector."""

    def __init__(self, index):
        self.index, self.best, self.best_p, self.since_best = index, math.inf, None, 0
        self.patience_spent = False  # stalled by ``patience``, not by its optimiser's own search
        self.entry = None  # its last history entry
        self.kept = None  # the runs at its best point (_Run.kept), one per experiment
        # What its first evaluation observed, and whether a later one observed otherwise
        # (``_tells_apart``): a fit whose observations never move is judged by ``verdict``.
        self.start_z, self.start_obs, self.start_loss, self.moved = None, None, None, False
        # The points whose finite observations were compared with the start's: verdict
        # does not run one of them again as its probe (the zero-gradient check's point).
        self.compared = set()


@_result_on_interrupt
def fit(
    model,
    target=None,
    params: Sequence[str] = ("yield_stress", "flow_rate"),
    *,
    steps: int | None = None,
    dt: float | None = None,
    frames: Sequence[int] | None = None,
    materials=None,
    iterations: int = 50,
    lr: float | None = None,
    lr_end: float | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    param_scales: Mapping[str, float] | None = None,
    clip: float | None = None,
    checkpoint_every: int | str | None = "auto",
    memory_limit: float = MEMORY_LIMIT,
    tie_pressure: bool | None = None,
    initial: Mapping[str, object] | None = None,
    tol: float | None = None,
    xtol: float = XTOL,
    gtol: float = 1e-7,
    patience: int = 20,
    callback: Callable | None = None,
    progress: bool = True,
    dtype=None,
    optimizer: str = "adam",
    max_step: float = 1.0,
    lbfgs_memory: int = 10,
    samples: int = 0,
    starts: int = 1,
    worlds: bool = False,
    sample_range: float | None = None,
    seed: int | None = None,
    diagnostics: bool = True,
    noise: float | None = None,
    fd_step: float = 1e-3,
    log: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit ``params`` of the model's materials so the rollout matches ``target``.

    - ``model``: a ``Model`` (``requires_grad=True``), ``SceneBuilder`` or callable; or a
      list of ``Experiment`` (then ``target`` is None): a joint fit of several experiments
      sharing one material, the sum of their weighted losses.
    - ``steps``/``dt``: the rollout (default ``steps`` = the last target frame, ``dt`` =
      the model's stable step; with ``samples`` or ``starts``, the smallest stable step over
      the points the fit starts from, one step for all: docs/fitting.md). ``frames``: step indices of target positions (a ``Loss``
      carries its own).
    - ``materials``: indices (or body names) of the materials to fit; default all. With a
      per-particle model (``rollout.split_materials``) this fits a field.
    - ``iterations``, ``lr``: optimiser steps and step size (in optimiser space: relative for
      a parameter fitted as its logarithm, times its size for one fitted as itself, ``param_scales``;
      default ``LR`` = 0.1; Adam's step and L-BFGS's first step, refused with
      ``"gauss-newton"``, which never reads it);
      ``lr_end``: decay Adam's step size geometrically to this value at the last iteration.
    - ``bounds``: ``{name: (lo, hi)}`` in the parameter's units: the optimisers hold a value
      on a bound whose gradient points out of the box and step the others alone, so a
      fit whose optimum lies beyond a bound converges to the others' optimum there
      (docs/fitting.md, "Bounds"). ``clip``: gradient norm cap.
    - ``param_scales``: ``{name: size}`` (positive, finite, in the parameter's units) of a parameter
      fitted as itself (one whose initial value is 0 or below; ``lam``, ``hardening``,
      ``pressure_stiffness``, ``viscosity``): a step of ``lr`` moves it by ``lr`` times the
      size. Without one the size is the start's largest magnitude; from 0, the width of
      finite ``bounds``, else the materials' (``mu`` for ``lam`` and ``hardening``, the
      default ``pressure_stiffness``, ``mu`` times the stable step for ``viscosity``):
      docs/fitting.md, "Optimisers". One of a parameter fitted as its logarithm is refused.
    - ``checkpoint_every``: segment length for checkpointed rollouts; ``"auto"``: a full
      tape when it fits in ``memory_limit`` bytes (and in the device's memory), else the
      longest segment that fits (``choose_checkpointing``). A rollout that cannot fit even
      so is refused (``rollout.RolloutMemoryError``) under the experiment's name. A
      Gauss-Newton fit records no tape (every run forward only): its rollouts hold two
      states each and are weighed so, ``checkpoint_every`` and ``memory_limit`` unread.
    - ``initial``: ``Rollout.forward`` keywords (``x0, v0, F0, alpha0, initial_state``),
      checked once at set-up (``rollout.check_initial``; a refused start before any rollout);
      every evaluation starts from the values checked.
    - ``optimizer``: ``"adam"`` (default; ``lr``, ``lr_end``, ``clip``), ``"gauss-newton"``
      (Levenberg-Marquardt on the losses' residual vectors from forward runs only, the
      Jacobian by forward differences of ``GN_STEP``: for least-squares losses with few
      parameters along a curved valley; every loss needs ``residuals``) or ``"lbfgs"``
      (quasi-Newton with a backtracking line search: far fewer evaluations on a smooth
      loss with few parameters; its first step moves by ``lr`` and no step moves a
      parameter by more than ``max_step`` in optimiser space, i.e. a factor ``e`` for
      log-space parameters). ``iterations`` counts gradient evaluations after the first
      (line-search trials included), so both optimisers cost ``iterations + 1`` rollouts;
      at most ``MAX_ITERATIONS`` (100000).
    - Termination (``result.stopped``): ``"converged"`` when an accepted step moves no
      optimiser coordinate by more than ``xtol``, the gradient's largest entry falls
      below ``gtol`` times its initial one, or a rejected L-BFGS trial's slope puts the
      minimum along its direction within ``xtol``; ``"stalled"`` when ``patience`` evaluations
      in a row did not lower the best loss (by 1e-9 relative); ``"iterations"`` at the
      cap; ``"flat"`` when the initial gradient is exactly zero at a loss above 0 (nothing to follow);
      ``"uninformative"`` (never converged, by any optimiser) where no evaluation's observations
      differ from the start's beyond round-off and neither do a forward-only probe's ``lr`` away
      in every value (the target frames precede any motion the values make; docs/fitting.md);

      ``"tol"`` once the loss is below ``tol``; ``"callback"``.
    - Global first stage: ``samples = N > 0`` evaluates the loss alone (forward passes)
      at ``N`` Latin-hypercube points of optimiser space, within a factor ``sample_range``
      (default 4) of the guess (log space; linear ones +-``sample_range`` times their scale) and within
      ``bounds`` where they are narrower, plus the guess; gradient descent then starts from the best
      ``starts`` of them, one after the other, and the lowest loss wins (``seed``: RNG, an
      integer >= 0, default 0). ``seed`` and ``sample_range`` are refused where the fit draws
      nothing (no ``samples``, one start), as ``--seed`` and ``--sample-range`` are.
      Without ``samples``, ``starts = K > 1`` descends from the guess and ``K - 1``
      Latin-hypercube points of the same box.
    - ``worlds``: with several starts, run them at once as the worlds of one model per
      experiment (``builder.replicate_worlds``, ``losses.WorldLoss``): each start keeps its
      own optimiser (Adam or L-BFGS, line search included) and history, and one forward and
      backward pass per round evaluates every start that has not finished. The same
      evaluations as one start after the other, to round-off (``tests/test_fit_worlds.py``),
      with one launch per kernel for all starts. Not with moving tools, host-evaluated
      losses (``SlumpLoss``, ``ReactionForceLoss``) or ``initial``.
    - ``diagnostics``: at the optimum, the Fisher (Gauss-Newton) information of the data
      for observation noise ``noise`` (m; see ``warp_esph.diagnostics``), from central
      differences (step ``fd_step`` in optimiser space) of the residuals (or of taped
      gradients) and a range check: up to ``4 P`` extra runs for ``P`` fitted values (one more where
      the fit's own run at its best point cannot stand in for theirs)
      (``result.diagnostics.evaluations``). ``result.diagnostics`` holds standard
      errors, correlations and warnings about parameters the data do not determine.
    - ``callback(evaluation, loss, params)``: after each evaluation; return ``True`` to
      stop. It must leave the scene and the target as they are: one that changed what the runs
      read (materials, colliders, tools, the start, gravity, the solver's settings) or what they
      are compared against (the target's arrays, weights) is a ``ValueError`` naming what
      changed (``_SceneGuard``). ``log``: called with one-line messages (memory, time per evaluation, stages).
    - ``lbfgs_memory``: the number of past steps L-BFGS keeps (default 10). ``progress``:
      a progress bar on stderr. ``dtype`` and ``tie_pressure``: the module docstring.
    """
    o = check_options(params=params, iterations=iterations, lr=lr, lr_end=lr_end, clip=clip, bounds=bounds,
                      optimizer=optimizer, patience=patience, samples=samples, starts=starts,
                      sample_range=4.0 if sample_range is None else sample_range,
                      seed=0 if seed is None else seed, noise=noise, memory_limit=memory_limit, xtol=xtol,
                      param_scales=param_scales)
    _refuse_undrawn(o, seed=seed, sample_range=sample_range)
    params, iterations, lr, lr_end, clip, optimizer = o["params"], o["iterations"], o["lr"], o["lr_end"], o["clip"], o["optimizer"]
    patience, samples, starts, sample_range, seed = o["patience"], o["samples"], o["starts"], o["sample_range"], o["seed"]
    noise, memory_limit, xtol = o["noise"], o["memory_limit"], o["xtol"]
    if dtype is not None:
        dtype = scalar_type(dtype)
    max_step = checks.positive("max_step", max_step)
    lbfgs_memory = checks.positive_int("lbfgs_memory", lbfgs_memory)
    gtol = checks.non_negative("gtol", gtol)
    # That test passed at the guess whatever the loss, and the fit reported the guess as
    # converged: gtol is a fraction of the initial gradient (xtol against lr: check_options).
    if gtol >= 1.0:
        raise ValueError(f"gtol = {checks.shorten(gtol)!r} is not allowed: must be in [0, 1) (a fraction of the initial "
                         "gradient: at 1 the guess itself counts as converged)")
    if optimizer in ("lbfgs", "gauss-newton") and max_step <= xtol:
        # Every step of theirs is at most max_step: the first one, below xtol, ended the fit as
        # converged (Gauss-Newton at one of its Jacobian's difference points).
        raise ValueError(f"max_step = {checks.shorten(max_step)!r} is not allowed with xtol = {xtol:g}: must be > xtol "
                         f"(no step of {optimizer} is longer than max_step, so the first would count as converged)")
    # A loss is >= 0 and finite where it counts: tol = inf stopped every fit at its guess as
    # converged, and a string failed only after the first rollout.
    tol = None if tol is None else checks.positive("tol", tol)
    worlds = checks.boolean("worlds", worlds)
    # Any value was taken as its truth: diagnostics='no' ran them, progress='no' drew the bar.
    progress = checks.boolean("progress", progress)
    diagnostics = checks.boolean("diagnostics", diagnostics)
    tie_pressure = None if tie_pressure is None else checks.boolean("tie_pressure", tie_pressure)
    # Adam's options, which the other optimisers never read: given with them, they were
    # dropped without a word (a clipped L-BFGS fit ran unclipped).
    for name, value in (("clip", clip), ("lr_end", lr_end)):
        if value is not None and optimizer != "adam":
            raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed with optimizer = {optimizer!r}: it is "
                             "Adam's option (optimizer='adam')")
    if worlds and starts < 2:
        # As the command line's --worlds: one start ran alone on the one-world model.
        raise ValueError(f"worlds = True is not allowed with starts = {starts}: it runs several starts at once as "
                         "worlds of one model; give starts = K > 1")
    # In optimiser space (a factor e^step for a log-space value): below 1e-8 the differences
    # are round-off (0/0 at 1e-17, the Fisher matrix NaN and reported as a conclusion), above
    # 1 they read the loss a factor e away (1.2e6 x mu at 14).
    fd_step = checks.in_range("fd_step", fd_step, 1e-8, 1.0)
    if callback is not None and not callable(callback):
        raise ValueError(f"callback = {checks.shorten(callback)!r} is not allowed: must be callable")
    if log is not None and not callable(log):
        raise ValueError(f"log = {checks.shorten(log)!r} is not allowed: must be callable as log(message)")
    say = log or (lambda message: None)

    if isinstance(model, (list, tuple)) and model and all(isinstance(e, Experiment) for e in model):
        if target is not None:
            raise ValueError("target is not allowed with a list of Experiments: each carries its own")
        exps = list(model)
    else:
        if isinstance(model, (list, tuple)):
            # [] and a list holding something else were refused as 'target is required (or give a
            # list of Experiment)', which the caller had given.
            bad = next((k for k, e in enumerate(model) if not isinstance(e, Experiment)), None)
            if bad is None:
                raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: give a Model and a target, or a non-empty list "
                                 "of Experiment")
            raise ValueError(f"model[{bad}] = {checks.shorten(model[bad])!r} is not allowed: a list of experiments holds "
                             "only Experiment (each its model, loss, steps and dt)")
        if target is None:
            raise ValueError("target is required (or give a list of Experiment)")
        exps = [Experiment(model, target, steps=steps, dt=dt, frames=frames, materials=materials, initial=initial,
                           checkpoint_every=checkpoint_every, noise=noise)]
    for k, e in enumerate(exps):
        # It names the experiment where a body's name does, and a newline or a right-to-left
        # override in it split or reordered those lines, as in a body's.
        if e.name is not None and not isinstance(e.name, str):
            raise ValueError(f"model[{k}].name = {checks.shorten(e.name)!r} is not allowed: must be a string")
        if e.name:
            checks.one_line(f"model[{k}].name", e.name, "it names the experiment in the fit's messages and its history rows")
    # Gauss-Newton takes no gradient: its Jacobian is forward differences and its diagnostics
    # (every loss has residuals) too, so none of its runs records a tape.
    runs = [_Run(e, dtype, memory_limit, e.name or (f"experiment {k}" if len(exps) > 1 else "the experiment"),
                 taped=optimizer != "gauss-newton") for k, e in enumerate(exps)]
    _refuse_unread_noise(runs, noise if len(exps) > 1 else None)
    for r in runs:
        r.setup_tie(params, tie_pressure)
    prob = _Problem(runs, params, bounds, o["param_scales"])
    if optimizer == "gauss-newton":
        from .diagnostics import leaf_terms  # noqa: PLC0415

        lacking = [repr(leaf) for r in runs for leaf in leaf_terms(r.loss) if not hasattr(leaf, "residuals")]
        if lacking:
            raise ValueError(f"optimizer = 'gauss-newton' is not allowed: {lacking[0]} has no residual vector; use lbfgs")
        if worlds:
            raise ValueError("worlds = True is not allowed with optimizer = 'gauss-newton': its starts run one after "
                             "the other (forward runs only)")
    # Every point the fit starts from is drawn before any run: the step is chosen for all of them.
    candidates = _start_candidates(prob, samples, starts, sample_range, seed)
    steps_said = _choose_steps(runs, prob, candidates)
    # The starts' worlds are made (and refused, where they cannot be) before any run and any
    # message, so a refusal is the one thing a fit says.
    track_count = min(starts, samples + 1) if samples else starts
    use_worlds = worlds and track_count > 1
    worlds_problem = _WorldsProblem(runs, prob, track_count, dtype, memory_limit) if use_worlds else None
    for line in steps_said:
        say(line)
    for r in runs:
        if not r.taped:
            say(f"{r.name}: {r.model.particle_count} particles, {r.steps} steps of {r.dt:.4g} s; no tape (Gauss-Newton "
                f"runs forward only): ~{r.memory / 2**20:.1f} MiB of Warp arrays (three states, "
                f"{r.memory / r.model.particle_count:.0f} B per particle, whatever the steps)")
            continue
        mode = f"checkpoint every {r.rollout.segment} steps" if r.rollout.checkpointing else "full tape"
        say(f"{r.name}: {r.model.particle_count} particles, {r.steps} steps of {r.dt:.4g} s; {mode}: "
            f"~{r.memory / 2**20:.1f} MiB of Warp arrays "
            f"({r.memory / (r.model.particle_count * r.steps):.0f} B per particle per step)")
    start = prob.from_z(prob.z0)
    for name in params:
        guess = runs[0].values[name][runs[0].idx]
        if not np.allclose(start[name], guess, rtol=1e-9, atol=0.0):
            # The first evaluation (and the reported initial loss) is not the guess's.
            lo, hi = prob.bounds.get(name, (-math.inf, math.inf))
            say(f"the guess {name} = {', '.join(f'{v:.6g}' for v in guess)} lies outside its bounds "
                f"{lo:g}:{hi:g}: the fit starts at "
                f"{', '.join(f'{v:.6g}' for v in start[name])}")
    history: list[dict] = []
    state = {"bar": None, "stage": "descent", "stop_all": None}

    def record(track, z, value, gz, seconds, note=None):
        """Records one evaluation of ``track``'s start (history, best, callback); raises
        ``_Stop`` where the start ends; returns ``(value, gz, finite)`` for the optimiser.
        With worlds ``seconds`` is the start's share of its round
        (``_WorldsProblem.evaluate``)."""
        p = prob.from_z(z)
        value = float(value)
        # gz None: a forward-only evaluation (Gauss-Newton's residuals).
        finite = math.isfinite(value) and (gz is None or bool(np.isfinite(gz).all()))
        entry = {"iteration": len(history), "stage": state["stage"], "loss": value,
                 "params": {k: [float(x) for x in v] for k, v in p.items()},
                 "grad": None if gz is None else [float(x) for x in gz], "seconds": seconds}
        if use_worlds:
            entry["round_seconds"] = worlds_problem.round_seconds
        if not use_worlds:
            # The guards' particle-steps of this evaluation (the solvers count since built).
            total = _guarded(runs)
            entry["guarded"] = total - state.get("guarded", 0)
            state["guarded"] = total
        if track_count > 1:
            entry["start"] = track.index
        if note:
            entry["note"] = note
        history.append(entry)
        track.entry = entry
        if finite and not use_worlds and not track.moved:
            seen = _observed(runs)
            if track.start_obs is None:
                track.start_z, track.start_obs, track.start_loss = np.array(z, dtype=np.float64), seen, value
            else:
                track.moved = _tells_apart(track.start_obs, seen, runs)
            track.compared.add(tuple(np.asarray(z, dtype=np.float64).tolist()))
        if len(history) == 1 and not use_worlds:
            # At the start, where the guess's curve has the sign a pressing tool gives: a fit
            # to a curve of the opposite sign drives the material soft, where the curve fades
            # and no longer points anywhere (mu 8000 -> 54 Pa, nothing said of the sign).
            state["signs"] = _opposite_signs(runs)
            for said in state["signs"]:
                say(f"warning: {said}")
        if not state.get("timed"):
            state["timed"] = True
            per = "" if not use_worlds else f" for {track_count} worlds at once"
            rounds = (iterations + 1) * (1 if use_worlds else track_count)
            passes = "forward only" if gz is None else "forward + backward"
            say(f"one evaluation ({passes}{per}) took {seconds:.3g} s: "
                f"up to {checks.plural(iterations + 1, 'evaluation')} per start, ~{_duration(seconds * rounds)}")
        # The first finite value is an improvement: inf - 1e-9 * inf is NaN, which had counted
        # the guess itself as a stalled evaluation (patience = 1 stopped every fit there).
        if finite and (track.best == math.inf or value < track.best - 1e-9 * abs(track.best)):
            track.since_best = 0
        else:
            track.since_best += 1
        if finite and value < track.best:
            track.best, track.best_p = value, {k: v.copy() for k, v in p.items()}
            # Every run has just run at z (an evaluation that failed is no improvement).
            track.kept = None if use_worlds else [r.kept for r in runs]
        bar = state["bar"]
        if bar is not None:
            shown = ", ".join(f"{k}={v[0]:.4g}" for k, v in p.items())
            bar.set_postfix_str(f"loss={value:.3e}, {shown}", refresh=False)
            bar.update(1)
        if state["stop_all"] is not None:
            raise _Stop(state["stop_all"])
        if callback is not None:
            light = state["guard"].light()
            stop = callback(len(history) - 1, value, {k: v.copy() for k, v in p.items()})
            state["guard"].check(light, len(history) - 1)
            if stop:
                state["stop_all"] = "callback"
                raise _Stop("callback")
        if tol is not None and finite and value < tol:
            raise _Stop("tol")
        if track.since_best >= patience:
            track.patience_spent = True
            raise _Stop("stalled")
        return value, gz, finite

    def residual_evaluate(track):
        """For Gauss-Newton: the weighted residual vector at z (forward passes only;
        ``sum r^2`` is the loss), recorded like an evaluation (``grad`` None). ``reset``:
        new correspondences (nearest points, tangent planes) for the losses that keep them."""

        def residuals(z, reset=False):
            t0 = time.perf_counter()
            parts, note = [], None
            try:
                prob.apply(z)
                for r in prob.runs:
                    r.value_forward()
                    _check_diverged(r)
                    arrays = r.rollout.observations(numpy=True)
                    terms = r.loss.terms if isinstance(r.loss, SumLoss) else [(1.0, r.loss)]
                    for coef, leaf in terms:
                        if reset or not getattr(leaf, "_counts", True):
                            if hasattr(leaf, "reset_residuals"):
                                leaf.reset_residuals()
                            leaf.value(r.rollout.observations())  # records the residual counts
                        parts.append(math.sqrt(r.weight * coef / leaf.residual_scale()) * leaf.residuals(arrays))
                res = np.concatenate(parts)
            except FloatingPointError as e:
                res = np.full(1, np.inf)
                note = _refused_note(e)
            value = float(res @ res) if np.isfinite(res).all() else math.inf
            _, _, finite = record(track, z, value, None, time.perf_counter() - t0, note)
            return res, finite

        # The losses that choose correspondences at a reset (nearest points, tangent planes):
        # Gauss-Newton's columns put back those of the point they difference from.
        kept = [leaf for r in prob.runs for _, leaf in (r.loss.terms if isinstance(r.loss, SumLoss) else [(1.0, r.loss)])
                if hasattr(leaf, "set_correspondences")]
        if kept:
            residuals.chosen = lambda: [leaf.correspondences() for leaf in kept]
            residuals.use = lambda chosen: [leaf.set_correspondences(c) for leaf, c in zip(kept, chosen)]
        return residuals

    def sequential_evaluate(track):
        def evaluate(z, wants=None):
            t0 = time.perf_counter()
            note = None
            try:
                if wants is None or LBFGS_TRIAL_BACKWARDS != "read":
                    value, gz = prob.value_and_grad(z)
                else:
                    value, gz = prob.value_and_grad(z, wants=wants)
            except FloatingPointError as e:
                value, gz, note = math.inf, np.full(len(z), np.nan), _refused_note(e)
            return record(track, z, value, gz, time.perf_counter() - t0, note)
        return evaluate

    def verdict(stop, track):
        """``stop``, or ``"uninformative"`` where the data do not tell the start from values
        nearby: no evaluation's observations differed from the start's beyond round-off, and
        neither do those of one forward-only probe ``lr`` (``LR`` for Gauss-Newton) away in
        every optimiser coordinate (into the box; not run again where the fit evaluated that
        point already). Asked of a fit that says it converged, and
        of one that stalled or hit the cap after more than one evaluation: Adam's step from a
        gradient at round-off is below ``xtol`` (the dough star's frames before landing,
        float32: "converged" after 1 evaluation), L-BFGS wanders on round-off until the cap."""
        evaluated = sum(1 for h in history if h.get("stage") == "descent" and h.get("start", 0) == track.index)
        if stop == "uninformative":  # Adam's own probe said so (_run_adam)
            track.best, track.best_p, track.kept = track.start_loss, prob.from_z(track.start_z), None
            return stop
        if (track.moved or track.start_obs is None or stop not in ("converged", "tol", "stalled", "iterations")
                or (stop in ("stalled", "iterations") and evaluated < 2)):
            return stop
        size = lr if lr is not None else LR
        moved = None
        for probe in (prob.project(track.start_z + size), prob.project(track.start_z - size)):
            if np.array_equal(probe, track.start_z):
                continue  # on a bound that the box holds it to: the other side
            if tuple(probe.tolist()) in track.compared:
                # Already evaluated (the zero-gradient check's point lr away), its observations
                # compared as it ran and found not to move: running it again tells nothing new.
                moved = False
                break
            t0 = time.perf_counter()
            entry = {"iteration": len(history), "stage": "descent", "loss": math.inf,
                     "params": {k: [float(x) for x in v] for k, v in prob.from_z(probe).items()}, "grad": None}
            try:
                entry["loss"] = float(prob.value(probe))
                moved = _tells_apart(track.start_obs, _observed(runs), runs)
                entry["note"] = "informativeness probe (forward only): the observations " + (
                    "move: the start is told apart" if moved else "do not move beyond round-off")
            except FloatingPointError as e:
                # A point the materials refuse (a linear lam below -2 mu / 3) or whose run blows
                # up says nothing of round-off: the other side is asked.
                entry["note"] = f"informativeness probe: {_refused_note(e) or 'not finite'}"
            entry["seconds"] = time.perf_counter() - t0
            total = _guarded(runs)
            entry["guarded"] = total - state.get("guarded", 0)
            state["guarded"] = total
            if track_count > 1:
                entry["start"] = track.index
            history.append(entry)
            if moved is not None:
                break
        if moved is None:
            return stop  # neither side could run: nothing to say beyond the stop
        if moved:
            return stop
        # The lowest loss of round-off is no fitted value: L-BFGS had reported a viscosity of
        # 44 for a guess of 2 that the data did not tell from it. The start is what stands.
        track.best, track.best_p, track.kept = track.start_loss, prob.from_z(track.start_z), None
        return "uninformative"

    def descend(evaluate, z_start, track):
        try:
            return verdict(_descend(evaluate, z_start, track), track)
        except _FirstPointFailed as e:
            # A start of the global stage or the multi-start box whose first point fails
            # (its rollout blows up, its materials refuse the values) ends alone; at the
            # user's own guess it is an error, with the reason the history noted.
            if np.array_equal(z_start, prob.z0):
                why = track.entry.get("note") if track.entry else None
                if why is not None and why.startswith("diverged: "):
                    raise FloatingPointError(f"the rollout at the initial guess {why}") from None
                raise FloatingPointError(f"{e}: {why}" if why else str(e)) from None
            return "failed"

    def _descend(evaluate, z_start, track):
        def annotate(text):
            # The note goes on this start's last entry (with worlds, history[-1] may be
            # another start's).
            if track.entry is not None:
                why = track.entry.get("note")
                track.entry["note"] = (f"{why}; " if why else "non-finite; ") + text

        try:
            if optimizer == "gauss-newton":
                return _run_gauss_newton(evaluate, prob.project, z_start, iterations, max_step, GN_STEP, xtol,
                                         bounds=prob.z_bounds())
            if optimizer == "adam":
                return _run_adam(evaluate, prob.project, z_start, iterations, lr, lr_end, clip, annotate, xtol, gtol,
                                 bounds=prob.z_bounds(),
                                 told_apart=None if use_worlds else (lambda: track.moved or track.start_obs is None),
                                 loss_roundoff=(lambda: worlds_problem.roundoff[track.index]) if use_worlds
                                 else prob.loss_roundoff)
            return _run_lbfgs(evaluate, prob.project, z_start, iterations, lr, max_step, memory=lbfgs_memory,
                              xtol=xtol, gtol=gtol, bounds=prob.z_bounds())
        except _Stop as e:
            return str(e)

    # ------------------------------------------------------------ global stage
    start_points = candidates
    if samples:
        state["stage"] = "sample"
        cands = candidates
        scored = []
        t0 = time.perf_counter()
        try:
            for z in cands:
                note = None
                t_sample = time.perf_counter()
                try:
                    v = float(prob.value(z))
                except FloatingPointError as e:
                    v, note = math.inf, _refused_note(e)
                # Each sample's own time: every one had recorded 0.0 s.
                history.append({"iteration": len(history), "stage": "sample", "loss": v,
                                "params": {k: [float(x) for x in vv] for k, vv in prob.from_z(z).items()},
                                "grad": None, "seconds": time.perf_counter() - t_sample, **({"note": note} if note else {})})
                scored.append((v if math.isfinite(v) else math.inf, len(scored), z))
        except KeyboardInterrupt:
            raise _fit_interrupted(_interrupted_result(history, runs, params, prob)) from None
        say(f"global stage: {len(cands)} forward-only evaluations in {time.perf_counter() - t0:.3g} s; "
            f"best loss {min(s[0] for s in scored):.4g} (guess {scored[0][0]:.4g})")
        scored.sort(key=lambda s: (s[0], s[1]))
        start_points = [s[2] for s in scored[:starts]]
        state["stage"] = "descent"
    assert len(start_points) == track_count
    if use_worlds:
        say(f"multi-start: {track_count} starts as {track_count} worlds of one model per experiment")
    tracks = [_Track(k) for k in range(track_count)]
    if callback is not None:
        state["guard"] = _SceneGuard(runs)
    state["guarded"] = _guarded(runs)  # the global stage's forward runs counted too
    # The descent's runs keep what the diagnostics read: at the best point they had run the
    # model again, the same inputs and bits, for what the fit had already had in hand.
    diagnosed = diagnostics and not any(isinstance(leaf, WorldLoss) for r in runs for leaf in _leaves(r.loss))
    for r in runs:
        r.keep = diagnosed and not use_worlds

    stops = []
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        from .startup import unread_stream  # noqa: PLC0415

        # (its drawing stops, the fit going on, once stderr's reader has left)
        state["bar"] = tqdm(total=(iterations + 1) * track_count, unit="eval", file=unread_stream(sys.stderr),
                            dynamic_ncols=True, desc=f"fit ({optimizer})")
    try:
        if use_worlds:
            stops = _lockstep(tracks, start_points, descend, worlds_problem, record, lambda: state["stop_all"])
        else:
            for track, z_start in zip(tracks, start_points):
                stop = descend(residual_evaluate(track) if optimizer == "gauss-newton" else sequential_evaluate(track), z_start,
                               track)
                stops.append(stop)
                if stop == "callback":
                    break
    except KeyboardInterrupt:
        raise _fit_interrupted(_interrupted_result(history, runs, params, prob)) from None
    finally:
        if state["bar"] is not None:
            state["bar"].close()
        for r in runs:
            r.keep = False  # the diagnostics' own runs need no copies
    run_best = [(t.best, t.best_p, stop, t.kept, t) for t, stop in zip(tracks, stops)]
    finite_runs = [rb for rb in run_best if rb[1] is not None]
    if not finite_runs:
        raise FloatingPointError("no finite loss was found")
    value, p, stopped, kept, won = min(finite_runs, key=lambda rb: rb[0])
    fitted = [r.finish(p, params) for r in runs]
    result = FitResult(
        params={k: v.copy() for k, v in p.items()},
        materials=fitted[0],
        material_indices=runs[0].idx,
        loss=value,
        initial_loss=history[0]["loss"],
        history=history,
        model=runs[0].model,
        stopped=stopped,
    )
    if stopped == "stalled":
        result.stalled_by = "patience" if won.patience_spent else "search"
    result.models = [r.model for r in runs]
    result.experiment_materials = fitted
    result.flowed_starts = [r.flowed_start() for r in runs]
    result.starts = stops
    result.param_scales = prob.param_scales_record()
    result.evaluations = sum(1 for h in history if h["stage"] == "descent")
    result.step_limit = _step_limit(runs, history)

    if stopped == "flat":
        # The generic reason names the material ('no particle reaches the yield stress'): a
        # target out of every particle's reach (a cloud in mm) was blamed on the yield stress.
        causes = [c for r in runs for leaf in _leaves(r.loss) if (c := leaf.out_of_reach()) is not None]
        result.flat_cause = "; ".join(dict.fromkeys(causes))
    # A worlds model fits W hypotheses at once: one Fisher matrix of their summed loss
    # would describe none of them, so the diagnostics are left to one world at a time.

    # A WorldLoss anywhere in the loss (2 * W, W + a force loss): the diagnostics failed after
    # the fit and lost it.
    worlds = any(isinstance(leaf, WorldLoss) for r in runs for leaf in _leaves(r.loss))
    if diagnostics and worlds:
        say("diagnostics: skipped for a WorldLoss (diagnose each world's fit on its own model)")
    if diagnostics and not worlds:
        from .diagnostics import diagnose_problem  # noqa: PLC0415

        t0 = time.perf_counter()
        try:
            result.diagnostics = diagnose_problem(prob, prob.to_z(p), noise=noise, step=fd_step, kept=kept)
        except KeyboardInterrupt:
            # The fit itself is finished: kept, without its diagnostics.
            for r in runs:
                r.apply(p)
            raise _fit_interrupted(result) from None
        d = result.diagnostics
        say(f"diagnostics ({d.method}): {d.evaluations} evaluations in {time.perf_counter() - t0:.3g} s")
        if not any("points against the model's" in w or "the model's along" in w for w in d.warnings):
            d.warnings.extend(state.get("signs", []))
        if iterations > 0 and not result.converged:
            d.warnings.insert(0, f"the fit did not converge ({stopped}): these errors describe the curvature at its last "
                                 f"point, not the uncertainty of a minimum")
        for r in runs:
            r.apply(p)
    return result


# ------------------------------------------------------------ multi-start over worlds
def _host_terms(loss) -> list:
    """The terms of ``loss`` evaluated on the host (reaction forces, slumps)."""
    own = [loss] if getattr(loss, "_host", False) else []
    return own + [h for _, t in getattr(loss, "terms", ()) for h in _host_terms(t)]


def _has_host_terms(loss) -> bool:
    return bool(_host_terms(loss))


class _WorldsProblem:
    """The experiments of a fit as ``W`` worlds each (``builder.replicate_worlds``): world
    ``w`` of every experiment holds start ``w``'s parameters, and one forward and backward
    pass per experiment evaluates every start (``WorldLoss``: each world's loss and gradient
    are its own)."""

    def __init__(self, runs: list[_Run], prob: _Problem, worlds: int, dtype, memory_limit):
        from .builder import replicate_worlds  # noqa: PLC0415

        self.prob, self.W = prob, worlds
        self.runs = []
        for r in runs:
            if r.initial:
                raise ValueError(f"{r.name}: initial = {sorted(r.initial)} is not allowed with worlds=True: the worlds "
                                 f"start from the model's own initial state (set model.particle_x0 / particle_v0)")
            if isinstance(r.loss, WorldLoss) or r.model.world_count != 1:
                raise ValueError(f"{r.name}: worlds=True is not allowed with a model of worlds or a WorldLoss: it "
                                 f"makes the worlds itself from a one-world model")
            host = _host_terms(r.loss)
            if host:
                # Named by the term (a force curve), not by the sum that holds it.
                raise ValueError(f"{r.name}: worlds=True is not allowed with {type(host[0]).__name__} (a "
                                 f"{'reaction-force' if 'Reaction' in type(host[0]).__name__ else 'host-evaluated'} "
                                 "target): it is evaluated on the host for one model (use worlds=False)")
            model = replicate_worlds(r.model, worlds)
            # checkpoint_every as given: "auto" chooses again for the copies, which need W times
            # the memory; the segment it chose for one world was refused where a shorter fits.
            exp = Experiment(model, WorldLoss(model, r.loss), steps=r.steps, dt=r.dt,
                             checkpoint_every=r.exp.checkpoint_every, weight=r.weight)
            try:
                wr = _Run(exp, dtype, memory_limit, f"{r.name} ({worlds} worlds)")
            except RolloutMemoryError as e:
                raise e.reworded(f"{e}, or fewer starts, or worlds = False (the starts one after another, each in one "
                                 "world's memory)", experiment=r.exp, worlds=worlds) from None
            M = len(r.model.materials)
            wr.idx = [w * M + k for w in range(worlds) for k in r.idx]
            wr.tied = [w * M + k for w in range(worlds) for k in getattr(r, "tied", [])]
            wr.tie = r.tie
            wr.checked = np.tile(r.checked, worlds)  # particles world after world
            self.runs.append(wr)
        self.p = [None] * worlds
        #: Wall-clock seconds of the latest ``evaluate``.
        self.round_seconds = 0.0
        #: Whether each world's last run blew up (diverged, or non-finite).
        self.blew_up = [False] * worlds
        #: Per world, the optimiser entries' ``_Problem.loss_roundoff`` at the world's latest
        #: evaluation with a gradient (``roundoff_read``: the worlds that had one).
        self.roundoff = [np.zeros(len(prob.z0)) for _ in range(worlds)]
        self.roundoff_read: set[int] = set()

    def evaluate(self, batch: dict[int, np.ndarray], wants=None) -> dict[int, tuple[float, np.ndarray | None, float, str | None]]:
        """Loss, optimiser-space gradient, seconds and note (why the materials refused the
        values, or None) of each start in ``batch`` (``{world: z}``). ``wants``: ``{world:
        wants(value) or None}`` as each start's optimiser asked (``_Problem.value_and_grad``);
        where no start of the round reads its gradient, the round runs no backward and every
        gradient is None (``_round``). The other worlds keep
        their last parameters, except where those blew up: then they run the guess. One pass
        evaluates them all: each start's seconds are its share, the round's divided by the
        starts in it (each had been given the whole round's, and a history's seconds added up
        to about W times the fit's); ``round_seconds`` holds the round's."""
        t0 = time.perf_counter()
        prob, W = self.prob, self.W
        refused = {}
        for w, z in batch.items():
            p = prob.from_z(z)
            why = prob.refusal(p)
            if why is None:
                self.p[w] = p
            else:
                # That start's trial fails alone; its world reruns its last values.
                refused[w] = f"refused: {why}"
        for w in range(W):
            if self.p[w] is None or (self.blew_up[w] and (w not in batch or w in refused)):
                # A world whose values no start reads (a start that has finished, a refused trial)
                # runs the guess, which ran at the first round, rather than values that blew up: a
                # failed start's world reran them every later round, 4-5 x a healthy round's time
                # (6.4-7.5 s against 1.5-1.7 s, 3 worlds of 216 particles, 60 steps).
                self.p[w] = prob.from_z(prob.z0)
        guess = prob.from_z(prob.z0)
        while True:
            try:
                values, gz, blew_up = self._round(batch, refused, wants)
                break
            except Collapsed as e:
                # The search stopped the whole round at the worlds it overflowed in: those starts
                # fail (their worlds run the guess) and the round runs again for the others (it had
                # ended the whole multi-start fit). Where a world running the guess overflows, or
                # the particles name no world, every start of the round fails.
                worlds = e.particles_worlds
                hit = [w for w in worlds if not all(np.array_equal(self.p[w][n], guess[n]) for n in prob.params)]
                if not hit or len(hit) < len(worlds):
                    values, gz, blew_up = np.full(W, math.inf), {w: np.full(len(prob.z0), np.nan) for w in batch}, [True] * W
                    for w in batch:
                        refused.setdefault(w, e.world_notes.get(w, str(e)))
                    break
                for w in hit:
                    refused.setdefault(w, e.world_notes[w])
                    self.p[w] = guess
        self.blew_up = blew_up
        for w in refused:
            values[w], gz[w] = math.inf, np.full(len(prob.z0), np.nan)
        self.round_seconds = time.perf_counter() - t0
        seconds = self.round_seconds / len(batch)
        return {w: (float(values[w]), gz[w], seconds, refused.get(w)) for w in batch}

    def _unread(self, batch, refused, wants) -> list[np.ndarray] | None:
        """Each experiment's world values (``WorldLoss.world_values``, read forward-only) where
        no start of ``batch`` reads its gradient at the loss the forwards just gave: each is an
        L-BFGS trial whose ``wants`` says so, refused by its materials, or failed (a loss not
        finite); else None. The loss is summed over the experiments as the round sums it."""
        if LBFGS_TRIAL_BACKWARDS != "read" or wants is None or any(wants.get(w) is None for w in batch if w not in refused):
            return None
        each, values = [], np.zeros(self.W)
        for r in self.runs:
            r.loss.value(r.rollout.observations())
            each.append(np.asarray(r.loss.world_values, dtype=np.float64))
            values += r.weight * each[-1]
        if any(wants[w](float(values[w])) for w in batch if w not in refused and math.isfinite(values[w])):
            return None
        return each

    def _round(self, batch, refused, wants=None):
        """One pass of every world at ``self.p``: ``(values, gz, blew_up)``, each world that blew
        up noted in ``refused``; raises ``Collapsed`` (with ``particles_worlds`` and
        ``world_notes``) where the neighbour search stopped the pass. Every experiment's forward
        runs first (each its own rollout and tape, so a backward after them gives the bits it
        gave after its own forward); the backwards run unless every start of ``batch`` is an
        L-BFGS trial whose ``wants`` says its gradient is not read at the loss the forwards
        give (or is refused): then ``gz`` holds None for each (``LBFGS_TRIAL_BACKWARDS``)."""
        prob, W, k = self.prob, self.W, self.prob.k
        values = np.zeros(W)
        gz = {w: np.zeros(len(prob.z0)) for w in batch}
        blew_up = [False] * W
        try:
            for r in self.runs:
                r.apply({name: np.concatenate([self.p[w][name] for w in range(W)]) for name in prob.params})
                try:
                    r.loss.check_positions(r.model.particle_count)
                    r.forward()
                except Collapsed as e:
                    of = r.model.world_of_particle[e.particles]
                    e.particles_worlds = sorted({int(w) for w in of})
                    e.world_notes = {w: _collapse_note(e.error, e.particles[of == w], int(r.model.world_start[w]))
                                     for w in e.particles_worlds}
                    raise
            unread = self._unread(batch, refused, wants)
            if unread is not None:
                for r, world_values in zip(self.runs, unread):
                    for w in range(W):
                        world = r.model.world_of_particle == w
                        why = _divergence(r.model, r.rollout, world, int(r.model.world_start[w]), checked=r.checked & world)
                        if why is not None or not np.isfinite(world_values[w]):
                            blew_up[w] = True
                        if why is not None and w not in refused:
                            refused[w] = why
                    values += r.weight * world_values
                return values, {w: None for w in batch}, blew_up
            roundoff = np.zeros(W)
            # Every round: Adam reads a start's round-off at each evaluation while it holds an
            # entry as round-off (_run_adam), which is not known here; the cost is one host copy
            # of the frames and their gradient a round.
            for r in self.runs:
                _, grads = r.rollout.backward(r.loss)
                roundoff += r.weight * r.rollout.loss_roundoff()
                world_values = np.asarray(r.loss.world_values, dtype=np.float64)
                g = r.grads(prob.params, grads)
                for w in range(W):  # a world that blew up fails its start alone
                    world = r.model.world_of_particle == w
                    why = _divergence(r.model, r.rollout, world, int(r.model.world_start[w]), checked=r.checked & world)
                    ran = {n: g[n][w * k:(w + 1) * k] for n in prob.params}
                    if why is not None or not (np.isfinite(world_values[w]) and all(np.isfinite(a).all() for a in ran.values())):
                        blew_up[w] = True
                    if why is not None and w not in refused:
                        refused[w] = why
                    if w in batch:
                        gz[w] += r.weight * prob.grad_z(self.p[w], ran)
                values += r.weight * world_values
            for w in batch:
                self.roundoff[w] = np.full(len(prob.z0), roundoff[w])
                self.roundoff_read.add(w)
        except Collapsed:
            raise
        except FloatingPointError:
            values[:] = math.inf
            gz = {w: np.full(len(prob.z0), np.nan) for w in batch}
            blew_up = [True] * W
        return values, gz, blew_up


def _lockstep(tracks, start_points, descend, worlds: _WorldsProblem, record, halted=lambda: None) -> list[str]:
    """Runs one optimiser per start, each in its own thread, in lockstep: every round, each
    start that has not finished asks for one evaluation, and one ``worlds.evaluate`` of all of
    them answers. Only this (the calling) thread launches Warp kernels and records history
    (in start order); the optimiser threads do host arithmetic only. ``halted()``: why the
    whole fit has stopped (a callback's True), or None; then no further round runs. When
    this thread stops answering (an error, Ctrl-C, or an error in any start, which ends the
    lockstep before the next round), every start ends: those waiting for an answer get a
    stop, and those still computing their next point get one when they ask, so the threads
    are joined and the (first) error reaches the caller."""
    import threading  # noqa: PLC0415

    cv = threading.Condition()
    pending: dict[int, np.ndarray] = {}
    asked: dict[int, object] = {}  # each pending start's ``wants``
    answers: dict[int, object] = {}
    active = set(range(len(tracks)))
    stops: list = [None] * len(tracks)
    errors: list = []
    closed = False  # set once the calling thread has stopped answering (an error, Ctrl-C)

    def worker(w):
        def evaluate(z, wants=None):
            # ``wants``: a round's one backward is every world's, so it runs unless no start of
            # the round reads its gradient (``_WorldsProblem._round``).
            with cv:
                if closed:
                    # A start that was between an answer and its next evaluation when the
                    # fit stopped was in neither pending nor the round, so the clean-up did
                    # not answer it: posting now would wait for ever, and the join with it.
                    raise _Stop("callback")
                pending[w] = np.array(z, dtype=np.float64)
                asked[w] = wants
                cv.notify_all()
                while w not in answers:
                    cv.wait()
                answer = answers.pop(w)
            if isinstance(answer, BaseException):
                raise answer
            return answer

        error = None
        try:
            stops[w] = descend(evaluate, start_points[w], tracks[w])
        except BaseException as e:  # noqa: BLE001 (handed to the calling thread)
            error = e
        finally:
            with cv:
                # Under the lock with the discard: the round's wait sees the error as soon as
                # it sees the start gone, and ends the lockstep before another round.
                if error is not None:
                    errors.append(error)
                active.discard(w)
                cv.notify_all()

    threads = [threading.Thread(target=worker, args=(w,), daemon=True) for w in range(len(tracks))]
    for t in threads:
        t.start()
    batch: dict[int, np.ndarray] = {}  # the round being evaluated: its starts wait for answers
    try:
        while True:
            with cv:
                while active and not errors and not active.issubset(pending):
                    cv.wait()
                if not active or errors:
                    # An error in one start ends them all: the others ran on to their end,
                    # full rounds of rollouts, before the error was raised.
                    break
                batch = {w: pending.pop(w) for w in sorted(active)}
                wants = {w: asked.pop(w, None) for w in batch}
            why = halted()
            if why is not None:
                # A callback stopped the fit: the other starts' next round ran and was recorded
                # after it, and could be returned as the result.
                with cv:
                    answers.update({w: _Stop(why) for w in batch})
                    cv.notify_all()
                continue
            results = worlds.evaluate(batch, wants)
            out = {}
            for w in sorted(batch):
                value, gz, seconds, note = results[w]
                try:
                    out[w] = record(tracks[w], batch[w], value, gz, seconds, note)
                except BaseException as e:  # noqa: BLE001 (_Stop ends that start, in its thread)
                    out[w] = e
            with cv:
                answers.update(out)
                batch = {}
                cv.notify_all()
    finally:
        with cv:
            # Threads still waiting (an error here) end at once: those of the round an error
            # or Ctrl-C stopped too, which had left their threads waiting and the join below
            # waiting for them, for ever; those still computing their next point find the
            # fit closed when they ask for it.
            closed = True
            for w in [*pending, *batch]:
                answers.setdefault(w, _Stop("callback"))
            pending.clear()
            cv.notify_all()
        for t in threads:
            t.join()
    if errors:
        raise errors[0]
    return stops


def latin_hypercube(n: int, dims: int, rng) -> np.ndarray:
    """``n`` points in ``[0, 1)^dims``, one in each of the ``n`` slices of every axis."""
    u = (np.arange(n)[:, None] + rng.random((n, dims))) / n
    for d in range(dims):
        u[:, d] = u[rng.permutation(n), d]
    return u


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _refused_note(error: FloatingPointError) -> str | None:
    """The history's note for a trial the materials refused or whose rollout diverged while
    staying finite (``Diverged``); None for a non-finite rollout."""
    if isinstance(error, Diverged):
        return str(error)
    return f"refused: {error}" if isinstance(error, RefusedPoint) else None


def _interrupted_result(history, runs, params, prob):
    finite = [h for h in history if h["loss"] is not None and math.isfinite(h["loss"])]
    if not finite:
        return None
    best = min(finite, key=lambda h: h["loss"])
    p = {k: np.array(v, dtype=np.float64) for k, v in best["params"].items()}
    fitted = [r.finish(p, params) for r in runs]
    result = FitResult(params=p, materials=fitted[0], material_indices=runs[0].idx, loss=best["loss"],
                       initial_loss=history[0]["loss"], history=history, model=runs[0].model, stopped="interrupted")
    result.models = [r.model for r in runs]
    result.experiment_materials = fitted
    result.flowed_starts = [r.flowed_start() for r in runs]
    result.evaluations = sum(1 for h in history if h["stage"] == "descent")
    # Its history's steps were sized as a finished fit's: fit.json says by what.
    result.param_scales = prob.param_scales_record()
    # Its evaluations ran as a finished fit's did: a run past the stable step is as much in
    # doubt when the fit is cut short, and fit.json is written for it all the same.
    result.step_limit = _step_limit(runs, history)
    return result


class _FirstPointFailed(FloatingPointError):
    """An optimiser's first point is not finite: the start cannot begin."""


class _Stop(Exception):
    """Raised inside an evaluation to end the fit (callback, tol or stalled)."""


def _run_adam(evaluate, project, z, iterations, lr, lr_end, clip, annotate, xtol=1e-6, gtol=0.0, bounds=None,
              told_apart=None, loss_roundoff=None) -> str:
    """Adam in optimiser space, each step projected onto the box. Box bounds (``bounds``:
    ``(lo, hi)`` in optimiser space, or None) as L-BFGS holds them: a value on a bound whose
    gradient points outward (``_held``) is held for the step, its moment dropped, and left out
    of ``clip``'s norm and of ``gtol``'s test (with every value held, converged).
    ``told_apart()``: whether any evaluation's observations differed from the start's beyond
    round-off (``_tells_apart``), or None where the caller cannot tell. ``loss_roundoff()``:
    the round-off of the loss at the last evaluation, per entry or one for all
    (``_Problem.loss_roundoff``; None: float64's precision times the loss), from which an
    entry of the first gradient whose step cannot move the loss beyond it is told
    (``_adam_eps``), and held until a later gradient of it exceeds the round-off of the loss
    it is a gradient of, read again at each evaluation (``_adam_eps_release``)."""
    opt = Adam(len(z), lr=lr)
    decay = 1.0 if lr_end is None or iterations <= 1 else (lr_end / lr) ** (1.0 / (iterations - 1))
    good = None
    g0 = None
    round_off = np.zeros(len(z), dtype=bool)  # the entries whose eps holds them (_adam_eps)
    for it in range(iterations + 1):
        value, g, finite = evaluate(z)
        held = _held(z, g, bounds) if finite else None
        if finite and (g0 is None or round_off.any()):
            # This evaluation's, read now (a probe below evaluates elsewhere before eps is set),
            # and at each later one while an entry is held: a held entry is judged against the
            # round-off of the loss its gradient is of. Against the first's, stale once the loss
            # fell, a value the loss read late (a term switched on by another's move, weighing
            # 1e-3 against a start of 4e4) stayed held at its guess for the run.
            roundoff = float(np.finfo(np.float64).eps) * abs(value) if loss_roundoff is None else loss_roundoff()
        if finite and g0 is None:
            if float(np.abs(g).max()) == 0.0:
                return _zero_gradient(evaluate, project, z, value, lr)
            # The free values' gradient, as L-BFGS reads it: a held one's does not fall.
            g0 = float(np.abs(np.where(held, 0.0, g)).max())
            if g0 == 0.0:
                return "converged"  # every value on a bound with the loss falling beyond it: the corner
        if finite and g0 is not None:
            if held.all():
                return "converged"
            if float(np.abs(np.where(held, 0.0, g)).max()) <= gtol * g0:
                return "converged"
        if it == iterations:
            break
        if not finite:
            # The rollout blew up or the gradient is not finite: back to the last good
            # point with half the step size.
            if good is None:
                raise _FirstPointFailed(f"the loss or its gradient is not finite at the initial guess (loss = {value})")
            opt.lr *= 0.5
            annotate(f"back to the last finite point, lr = {opt.lr:g}")
            z = good
            continue
        good = z.copy()
        if held.any():
            g = np.where(held, 0.0, g)
        shrink = 1.0
        if clip is not None:
            norm = float(np.linalg.norm(g))
            if norm > clip:
                shrink = clip / norm
                g = g * shrink
        if it > 0 and round_off.any():
            # A value the first gradient did not read (a yield stress nothing reached) is read
            # once another has moved (particles yield): held for the run, it stayed frozen.
            opt.eps, round_off = _adam_eps_release(opt.eps, round_off, np.abs(g),
                                                   LOSS_ROUNDOFF_UNITS * roundoff * shrink)
        z_new = project(opt.step(z, g, held))
        if float(np.abs(z_new - z).max()) < xtol:
            if it > 0:
                return "converged"
            # A first step moves the largest entry by lr |g| / (|g| + eps), at least lr / 2 >
            # xtol where |g| >= eps: below xtol, Adam's absolute eps swallowed a gradient of a
            # small loss (a weight of 1e-6 on a 27-particle landing, 2 x off: "converged" after 1
            # evaluation). A minimum only where the loss rises a probe away by far more than its
            # slope says; else Adam goes on with eps relative to this gradient.
            minimum = _minimum_by_curvature(evaluate, project, z, value, g, lr)
            if minimum is not None and told_apart is not None and not told_apart():
                # The probe observed what the start did, to round-off: nothing to descend on
                # (the dough star's frames before landing ran Adam to its cap first). Asked
                # before the curvature, which round-off can fake: "converged" then had verdict
                # run this very probe again. A probe that did not run (refused, blown up)
                # observed nothing and says nothing of round-off: Adam goes on.
                return "uninformative"
            if minimum:
                return "converged"
        if it == 0:
            # From here eps is relative to the first gradient, so that the fit's path does not
            # hang on the loss's units: a position loss in m^2 of the landing cube (weight 1,
            # first gradient 1.4e-9) moved the yield stress from 600 Pa to 546 in 8 evaluations
            # where the same loss times 2^20 reached 294 (truth 300). The absolute eps above
            # only tells a first step swallowed whole (a gradient of round-off) from one not.
            # Relative per entry, as Adam's steps are per coordinate: relative to the largest
            # entry, one value's path hung on the others' (a model of two worlds fitted jointly
            # moved each world's yield stress otherwise than its fit alone); an entry whose step
            # the loss reads below its round-off takes one that holds it (_adam_eps).
            # The loss's round-off scaled as clip scaled the gradient it is read against.
            floor = LOSS_ROUNDOFF_UNITS * roundoff * shrink
            first = np.abs(np.where(held, 0.0, g))
            eps = _adam_eps(first, g0, floor)
            round_off = first <= floor
            opt = Adam(len(z), lr=opt.lr, betas=(opt.b1, opt.b2), eps=eps)
            z_new = project(opt.step(z, g, held))
        z = z_new
        opt.lr *= decay
    return "iterations"


#: Adam's eps, relative to each entry of the first gradient (larger for an entry of
#: round-off, ``_adam_eps``; ``_run_adam``): every step after the first evaluation's test of a
#: swallowed step, which reads the absolute 1e-8.
ADAM_EPS = 1e-8

#: An entry of Adam's first gradient whose unit step in the optimiser's space moves the loss
#: by at most this many units of the loss's round-off is round-off (``_adam_eps``): its value
#: times its precision plus what the round-off of the observations it read makes of it
#: (``Rollout.loss_roundoff``; a world's own in a model of worlds).
#: Measured in these units (the landing cube beside a free-falling one,
#: tests/test_fit_informative.py): the falling body's shear modulus 3.5e-5 (float64), 4.5e-3
#: (float32 against a float64 target), 9.2e-4 (float32 against float32); the landing body's
#: yield stress 1.1e12, 966, 2085.
LOSS_ROUNDOFF_UNITS = 1.0


def _adam_eps(first: np.ndarray, g0: float, floor: np.ndarray | float) -> np.ndarray:
    """Adam's eps per value from the first gradient's magnitudes ``first`` (a held value's 0),
    their largest ``g0`` and the loss's round-off ``floor`` (``LOSS_ROUNDOFF_UNITS`` units of
    it): ``ADAM_EPS`` times the entry's own, so that neither the loss's units nor another
    value's gradient change a value's steps; but an entry at or below ``floor`` (0 included),
    whose unit step in the optimiser's space moves the loss by no more than its round-off,
    takes ``floor / ADAM_EPS`` (or ``ADAM_EPS`` times ``g0``, where larger), so that a gradient
    of that size moves it by ``ADAM_EPS`` of a step, until a later gradient of it exceeds
    ``floor`` (``_adam_eps_release``). Per entry alone, Adam's steps are the
    gradient's sign whatever its size: a free-falling body's shear modulus (3.5e-5 units of
    the loss's round-off in float64, 4.5e-3 in float32) went 10 % a step (1000 Pa to 2087 in 8
    evaluations in float64) where the other body's yield stress was being fitted
    (tests/test_fit_informative.py). The floor is the loss's, not a share of the largest
    entry: a world whose loss weighs 1e-4 of another's moves as it does alone
    (tests/test_worlds.py), where such a share in float32 (1.2e-4) held it back.
    ``floor``: one for all entries, or one per entry."""
    at_floor = first <= floor
    return np.where(at_floor, np.maximum(ADAM_EPS * g0, floor / ADAM_EPS), ADAM_EPS * first)


def _adam_eps_release(eps: np.ndarray, round_off: np.ndarray, g: np.ndarray, floor: np.ndarray | float):
    """Adam's eps and its mask of entries still judged round-off (``_adam_eps``), given a later
    gradient's magnitudes ``g`` and the round-off ``floor`` of the loss that gradient is of
    (read at its evaluation): an entry of round-off whose gradient now exceeds ``floor`` takes
    ``ADAM_EPS`` times it, as the first gradient's entries above ``floor`` took theirs, and is
    round-off no longer; one at or below ``floor`` keeps the eps that holds it. ``floor``: one
    for all entries, or one per entry."""
    released = round_off & (g > floor)
    return np.where(released, ADAM_EPS * g, eps), round_off & ~released


#: The share of a probe's rise that its first-order (slope) part may take for the start to
#: count as a minimum (``_minimum_by_curvature``): at a minimum the rise is curvature's alone.
SLOPE_SHARE = 0.01


def _minimum_by_curvature(evaluate, project, z: np.ndarray, value: float, g: np.ndarray, size: float) -> bool | None:
    """Whether ``z``, whose gradient ``g`` is too small for Adam's first step, is a minimum: one
    forward-only evaluation ``size`` away in every optimiser coordinate (into the box) reads a
    loss above ``value`` whose rise the slope ``g`` explains less than ``SLOPE_SHARE`` of. A
    start that made its target has a loss at round-off, and a rise of curvature alone; a guess
    2 x off under a small weight rises by its slope. None where the probe did not run to a
    finite loss (refused by the materials, blown up): it tells nothing."""
    probe = project(z + size)
    if np.array_equal(probe, z):
        probe = project(z - size)
    moved, _, finite = evaluate(probe, lambda loss: False)
    if not finite:
        return None
    rise = moved - value
    return bool(rise > 0.0 and abs(float(g.dot(probe - z))) <= SLOPE_SHARE * rise)


#: Observations (positions at the target frames, tool and collider forces) that differ from
#: the start's by no more than this many units of round-off of their precision, relative to
#: their size, tell nothing apart: rounding alone makes runs differ at a few units (the dough
#: star's frames before it lands, float32: 0.5 unit); a parameter the data read moves them by
#: per cents. The size of positions is the bodies' extent about their centroid, not their
#: distance from the origin (``PLACE_UNITS``).
ROUNDOFF_UNITS = 1000.0

#: Positions' round-off that comes of their coordinates' own magnitude, in units of it: a
#: coordinate is rounded to its own precision (a 10 m coordinate in float32 to 9.5e-7 m, 0.8
#: unit), so two runs differing by round-off differ there by a few units wherever the bodies
#: sit. Read against the largest magnitude with ``ROUNDOFF_UNITS``, the same swelling cube fitted
#: 2000 Pa at the origin and was called uninformative 10 m from it (its 10 % move of mu, 2.3e-5 m,
#: is 19.5 units of 10 m; tests/test_fit_informative.py).
PLACE_UNITS = 8.0


def _observed(runs) -> list[list[tuple[bool, np.ndarray]]]:
    """What each experiment's last forward let its loss read, as float64 host arrays, each
    with whether it holds positions: the positions of every observed frame, then its force
    curves where it has any."""
    from .rollout import COLLIDER_FORCES, FORCES  # noqa: PLC0415

    out = []
    for r in runs:
        obs = r.rollout.observations(numpy=True)
        frames = [np.asarray(obs[f], dtype=np.float64) for f in r.rollout.frames]
        kinds = [(True, np.stack(frames))] if frames else []
        kinds += [(False, np.asarray(obs[k], dtype=np.float64)) for k in (FORCES, COLLIDER_FORCES) if k in obs]
        out.append(kinds)
    return out


def _extent(x: np.ndarray, finite: np.ndarray) -> float:
    """The largest distance along an axis of a finite position from its frame's centroid
    (``x``: frames x particles x 3, ``finite`` its mask)."""
    rows = finite.all(axis=-1, keepdims=True)
    count = rows.sum(axis=1, keepdims=True)
    centre = np.where(rows, x, 0.0).sum(axis=1, keepdims=True) / np.maximum(count, 1)
    away = np.abs(x - centre)[finite & rows.repeat(x.shape[-1], axis=-1)]
    return float(away.max()) if away.size else 0.0


def _tells_apart(a, b, runs) -> bool:
    """Whether two runs' observations (``_observed``) differ anywhere by more than
    ``ROUNDOFF_UNITS`` units of round-off of the experiment's precision, forces against their
    largest finite magnitude, positions against the bodies' extent about their centroid (and
    ``PLACE_UNITS`` units of their largest magnitude, the coordinates' own rounding). The rule
    reads how the observations move with the values (the loss's sensitivity), never the loss's
    value: a start that made its target has a loss at round-off whose observations still move
    a probe away; data taken before any motion the parameters make have observations that do
    not."""
    for r, ka, kb in zip(runs, a, b):
        eps = float(np.finfo(np.float32 if r.model.scalar is wp.float32 else np.float64).eps)
        for (positions, xa), (_, xb) in zip(ka, kb):
            both = np.isfinite(xa) & np.isfinite(xb)
            if not both.any():
                continue
            magnitude = max(float(np.abs(xa[both]).max()), float(np.abs(xb[both]).max()))
            if positions:
                size = max(_extent(xa, both), _extent(xb, both))
                bound = ROUNDOFF_UNITS * eps * size + PLACE_UNITS * eps * magnitude
            else:
                bound = ROUNDOFF_UNITS * eps * magnitude
            if float(np.abs(xa[both] - xb[both]).max()) > bound:
                return True
    return False


def _zero_gradient(evaluate, project, z: np.ndarray, value: float, size: float) -> str:
    """Why a first gradient of exactly zero ends a fit (Adam, L-BFGS). At a loss above 0 the
    loss does not depend on the values there: ``"flat"``. A loss of exactly 0, the least any
    takes, is a guess that made its target (run as given, to the bit): a minimum,
    ``"converged"``, where the loss depends on the values, which one evaluation ``size`` away
    in every coordinate of optimiser space (into the box) asks, forward only; where it reads
    0 too, ``"flat"`` (a drop that stays below the yield stress: the data do not determine it)."""
    if value != 0.0:
        return "flat"
    probe = project(z + size)
    if np.array_equal(probe, z):
        probe = project(z - size)
    moved, _, finite = evaluate(probe, lambda loss: False)
    return "converged" if finite and moved > 0.0 else "flat"


def _minimum_within(g: np.ndarray, g_new: np.ndarray, step: np.ndarray, xtol: float) -> bool:
    """Whether a rejected line-search trial ``z + step`` shows the loss's minimum along
    ``step`` within ``xtol`` of ``z`` (every coordinate): the slope along the step falls at
    ``z`` and rises at the trial, and the secant between the two slopes puts its zero at
    that fraction of the step. L-BFGS's first step has no curvature to size it (it moves by
    ``lr``): from a minimum (a fit started at the values that made its target) every trial
    lay uphill, and halving the step down to ``xtol`` had reported the minimum as stalled,
    or as the iteration cap."""
    down, up = float(g.dot(step)), float(g_new.dot(step))
    if not (down <= 0.0 < up):
        # A trial still sloping down that is no lower: the loss is rough there, not minimal.
        return False
    return (down / (down - up)) * float(np.abs(step).max()) < xtol


#: How many times ``xtol`` the parabola's minimum (``_slope_may_decide``) may lie from the point
#: for a rejected trial's backward to run: the slopes' secant, which ``_minimum_within`` reads,
#: and the parabola through the values agree on a quadratic, and a loss's curvature along a
#: step changes them by a factor, not thousands.
SLOPE_MARGIN = 10.0

#: ``"read"``: an L-BFGS trial's backward runs only where its gradient is read (an accepted
#: trial, or a rejected one whose slope ``_minimum_within`` may decide by); ``"always"``: every
#: trial's, as before (the baseline ``benchmarks.fit_bench --rejected`` times).
LBFGS_TRIAL_BACKWARDS = "read"


def _slope_may_decide(f: float, f_new: float, down: float, step: np.ndarray, xtol: float) -> bool:
    """Whether the slope at a rejected trial ``z + step`` (loss ``f_new``; ``f`` and the slope
    ``down`` along the step at ``z``) may show ``_minimum_within`` a minimum within ``xtol``:
    the parabola through ``f``, ``down`` and ``f_new`` puts its minimum within ``SLOPE_MARGIN``
    times ``xtol`` of ``z``. Its backward is run only then: elsewhere nothing reads the
    trial's gradient (the line search halves the step from ``z``). On a quadratic the slopes'
    secant zero is the parabola's minimum."""
    if not math.isfinite(f_new) or down > 0.0:
        return False  # a failed trial's gradient is read by nothing; a rising start by neither
    curve = f_new - f - down  # the parabola's t^2 coefficient (> (1 - c1) |down| where rejected)
    if not curve > 0.0:
        return True
    return (-down / (2.0 * curve)) * float(np.abs(step).max()) < SLOPE_MARGIN * xtol


def _held(z: np.ndarray, g: np.ndarray, bounds) -> np.ndarray:
    """The coordinates of ``z`` on a bound of the box ``bounds`` (``(lo, hi)`` in optimiser
    space, or None) whose gradient ``g`` points out of it: descent would leave the box there,
    so the optimisers hold them and fit the others (an active set). Projecting such a
    coordinate back onto its bound after every step had left the quasi-Newton direction and
    the Gauss-Newton step computed as if it were free: the free values crept along the valley
    until the iteration cap. "On the bound" to 1e-12 relative, as the diagnostics' ``at_bound``
    reads it: projection maps the bound through ``exp`` and ``log``."""
    if bounds is None:
        return np.zeros(len(z), dtype=bool)
    lo, hi = bounds
    tol = 1e-12 * np.maximum(1.0, np.abs(z))
    at_lo = np.isfinite(lo) & (z <= lo + tol)
    at_hi = np.isfinite(hi) & (z >= hi - tol)
    return (at_lo & (g > 0.0)) | (at_hi & (g < 0.0))


def _two_loop(g: np.ndarray, S, Y, lr: float) -> np.ndarray:
    """``H g`` of L-BFGS's two-loop recursion over the pairs ``S, Y``; without pairs the
    gradient scaled so its largest entry moves by ``lr``."""
    q = g.copy()
    alphas = []
    for s, y in reversed(list(zip(S, Y))):
        a = s.dot(q) / y.dot(s)
        alphas.append(a)
        q -= a * y
    if S:
        q *= S[-1].dot(Y[-1]) / Y[-1].dot(Y[-1])
    else:
        q *= lr / max(float(np.abs(g).max()), 1e-300)
    for (s, y), a in zip(zip(S, Y), reversed(alphas)):
        b = y.dot(q) / y.dot(s)
        q += (a - b) * s
    return q


def _curved(s: np.ndarray, y: np.ndarray) -> bool:
    """Whether a pair carries positive curvature (``s.y > 0`` to round-off), as L-BFGS keeps it."""
    return bool(s.dot(y) > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y))


def _run_lbfgs(evaluate, project, z, iterations, lr, max_step, memory=10, c1=1e-4, xtol=1e-6, gtol=0.0,
               bounds=None) -> str:
    """L-BFGS (two-loop recursion) with a backtracking Armijo line search, in optimiser space.

    Box bounds (``bounds``: ``(lo, hi)`` in optimiser space, or None): the coordinates on a
    bound whose gradient points outward are held there for the step (``_held``) and left out
    of the quasi-Newton direction, whose recursion runs over the free coordinates of the
    pairs (those of no positive curvature there skipped); the other coordinates' trials are
    projected onto the box. ``gtol`` is read on the gradient of the free coordinates, so a fit
    whose optimum lies beyond a bound converges to the optimum of the others with it held.
    Pairs with ``s.y <= 0`` are skipped. A non-finite trial (a blown-up rollout) counts as a
    failed trial.
    """
    f, g, finite = evaluate(z)
    if not finite:
        raise _FirstPointFailed(f"the loss or its gradient is not finite at the initial guess (loss = {f})")
    if float(np.abs(g).max()) == 0.0:
        return _zero_gradient(evaluate, project, z, f, lr)
    held = _held(z, g, bounds)
    # The gradient the free coordinates follow: the held ones' entries point out of the box.
    g0 = float(np.abs(np.where(held, 0.0, g)).max())
    if g0 == 0.0:
        # Every coordinate on a bound with the loss falling beyond it: the corner is the minimum within the box.
        return "converged"
    evals = 0
    S, Y = [], []
    while evals < iterations:
        held = _held(z, g, bounds)
        if float(np.abs(np.where(held, 0.0, g)).max()) <= gtol * g0:
            return "converged"
        if held.any():
            free = ~held
            if not free.any():
                return "converged"
            pairs = [(s[free], y[free]) for s, y in zip(S, Y) if _curved(s[free], y[free])]
            d = np.zeros(len(z))
            d[free] = -_two_loop(g[free], [s for s, _ in pairs], [y for _, y in pairs], lr)
        else:
            d = -_two_loop(g, S, Y, lr)
        gf = np.where(held, 0.0, g) if held.any() else g
        if not g.dot(d) < 0.0:
            S.clear()
            Y.clear()
            d = -gf * (lr / max(float(np.abs(gf).max()), 1e-300))
        big = float(np.abs(d).max())
        if big > max_step:
            d *= max_step / big
        t = 1.0
        while True:
            z_new = project(z + t * d)
            step = z_new - z
            if float(np.abs(step).max()) < xtol:
                # A full quasi-Newton step below the tolerance is convergence; a line
                # search that had to shrink the step that far found no better point
                # along a descent direction: the loss is too rough to make progress.
                return "converged" if t == 1.0 else "stalled"
            down = float(g.dot(step))
            f_new, g_new, finite = evaluate(
                z_new, lambda value, f=f, down=down, step=step: value <= f + c1 * down or _slope_may_decide(
                    f, value, down, step, xtol))
            evals += 1
            if finite and f_new <= f + c1 * g.dot(step):
                break
            if finite and g_new is not None and _minimum_within(g, g_new, step, xtol):
                return "converged"
            if evals >= iterations:
                return "iterations"
            t *= 0.5
        s, y = z_new - z, g_new - g
        if _curved(s, y):
            S.append(s)
            Y.append(y)
            if len(S) > memory:
                S.pop(0)
                Y.pop(0)
        z, f, g = z_new, f_new, g_new
        if float(np.abs(s).max()) < xtol:
            return "converged"
    if float(np.abs(np.where(_held(z, g, bounds), 0.0, g)).max()) <= gtol * g0:
        return "converged"
    return "iterations"


#: Forward-difference step of the Gauss-Newton Jacobian in optimiser space (1 %): large
#: against the loss's roughness (contacts and neighbours switching one particle at a time
#: make it jump at 1e-3), small against the per-cent changes a fit must resolve.
GN_STEP = 1e-2


def _run_gauss_newton(residuals, project, z, iterations, max_step, h, xtol=1e-6, bounds=None) -> str:
    """Levenberg-Marquardt on the residual vector ``r(z)`` (``loss = r . r``), in optimiser
    space, from forward runs only: the Jacobian by forward differences of step ``h`` (one
    run per value), then steps ``-(J^T J + lam diag(J^T J))^-1 J^T r``, with ``lam`` set by
    the gain ratio (actual over predicted decrease; Nielsen's update: a step the linear
    model predicted well lowers ``lam``, a rejected one doubles its growth factor). A least-squares
    loss with few parameters and a curved valley (yield stress against flow rate) is what
    it is for: each step uses the valley's curvature at once, where L-BFGS learns it over
    many steps. ``iterations`` counts runs after the first, Jacobian runs included.

    Box bounds (``bounds``: ``(lo, hi)`` in optimiser space, or None): the values on a bound
    whose gradient ``J^T r`` points outward are held there (``_held``) and the damped normal
    equations solved for the free ones alone, so with one value held the fit becomes a fit of
    the others and converges to their optimum; a Jacobian column's difference steps into the
    box (a step out of it is projected back onto the bound and reads no change). A value held
    at the last Jacobian whose column from then, against the new residuals, still points out
    keeps that column (the step never reads a held value's column; its run is skipped), and
    such columns are run afresh before the fit says it converged: a value the fresh column
    frees is stepped again. A column is kept only while no value has moved more than ``h``
    since it was run: its sign tells the gradient at the point it was run at, and the free
    values moving on change the held value's column (``tests/test_fit_honesty.py``: a column
    of -1 turned to +2 over a step of 3 in the other value, and the value was held for a step
    its fresh column freed it for); within ``h`` of that point the old column differs from a
    fresh one by about as much as the difference it is made of.

    Correspondences (a Chamfer loss's nearest points, a mesh loss's tangent planes) are chosen
    anew at each point the steps reach (``reset``) and kept for its columns. Where
    ``residuals`` has ``chosen()`` (the correspondences it reads now) and ``use(chosen)``, a
    column runs with those of the point it differences from (a rejected trial had chosen its
    own, and the columns run after it, to check a held value, read a row of one pair against
    the other's), and a column is kept only where the correspondences it ran with are the
    point's: another pair's row has another derivative (``tests/test_fit_honesty.py``)."""
    r, finite = residuals(z, reset=True)
    if not finite:
        raise _FirstPointFailed("the loss is not finite at the initial guess")
    chosen, use = getattr(residuals, "chosen", None), getattr(residuals, "use", None)
    at_z = chosen() if chosen is not None else None  # the correspondences r was read with
    f = float(r @ r)
    lam, nu = 1e-3, 2.0
    evals = 0
    n = len(z)
    J = None  # the last Jacobian
    held = np.zeros(n, dtype=bool)
    kept = np.zeros(n, dtype=bool)  # the held values whose column is the last Jacobian's, not z's
    current = False  # whether J is z's already (the kept columns run afresh at z)
    stepped = False  # whether a step was taken: a Jacobian of zeros after one is a minimum reached
    ran_at = np.full((n, n), np.nan)  # row j: the point column j of J was run at
    ran_with = [None] * n  # the correspondences column j of J was run with

    def column(j):
        """The forward difference of the residuals in value ``j`` at ``z`` (one or two runs),
        or None where both sides blew up."""
        nonlocal evals
        if use is not None:
            use(at_z)
        ran_at[j] = z
        ran_with[j] = at_z
        zj = z.copy()
        zj[j] += h if bounds is None or z[j] + h <= bounds[1][j] else -h
        rj, ok = residuals(zj)
        evals += 1
        if not ok:
            zj[j] = z[j] - h if zj[j] > z[j] else z[j] + h  # a blow-up on one side: the other
            rj, ok = residuals(zj)
            evals += 1
            if not ok:
                return None
        return (rj - r) / (zj[j] - z[j])

    def refresh():
        """Runs the kept columns at z; returns False where one blew up on both sides."""
        for j in np.flatnonzero(kept):
            c = column(j)
            if c is None:
                return False
            J[:, j] = c
        kept[:] = False
        return True

    def stop_or_refresh():
        """At a minimum: 'converged' where no column is kept from an earlier z; else the kept
        columns are run afresh (None: go on from them) or the reason that stops the fit."""
        if not kept.any():
            return "converged"
        if evals + int(kept.sum()) > iterations:
            return "iterations"
        return None if refresh() else "stalled"

    while True:
        if not current:
            # The held values whose last column, run within h of z, against these residuals,
            # still points out of the box (a residual vector of the same length).
            if J is not None and J.shape[0] == len(r) and held.any():
                near = (np.abs(z - ran_at).max(axis=1) <= h) & np.array([_same(c, at_z) for c in ran_with])
                kept = held & near & _held(z, J.T @ r, bounds)
            else:
                kept = np.zeros(n, dtype=bool)
            # A Jacobian that the cap has room for runs even where no trial would: its step
            # below xtol ends the fit converged without one (stop_or_refresh counts so too).
            if evals + n - int(kept.sum()) > iterations:
                return "iterations"
            J_new = np.empty((len(r), n))
            for j in range(n):
                if kept[j]:
                    J_new[:, j] = J[:, j]
                    continue
                c = column(j)
                if c is None:
                    return "stalled"
                J_new[:, j] = c
            J = J_new
        current = False
        A, g = J.T @ J, J.T @ r
        if not np.any(A.diagonal() > 0.0):
            # At the start nothing moves the loss; after a step the loss fell to where nothing
            # does, as L-BFGS's gradient of zeros there (gtol) is: a target run at a yield stress
            # above every stress, fitted from below, reached a loss of exactly 0 and was called
            # 'flat' ('stopped at once'), exit 5, where L-BFGS converged.
            return "converged" if stepped else "flat"
        held = _held(z, g, bounds)
        free = ~held
        if not free.any():
            # Every value on a bound with the loss falling beyond it: the corner is the minimum within the box.
            stop = stop_or_refresh()
            if stop is not None:
                return stop
            current = True
            continue
        Af, gf = (A[np.ix_(free, free)], g[free]) if held.any() else (A, g)
        while True:
            D = np.diag(np.maximum(Af.diagonal(), 1e-12 * max(float(Af.diagonal().max()), 1e-300)))
            try:
                dzf = -np.linalg.solve(Af + lam * D, gf)
            except np.linalg.LinAlgError:
                dzf = -gf / max(float(np.abs(gf).max()), 1e-300) * h
            if held.any():
                dz = np.zeros(n)
                dz[free] = dzf
            else:
                dz = dzf
            big = float(np.abs(dz).max())
            if big > max_step:
                dz *= max_step / big
            z_new = project(z + dz)
            step = z_new - z
            if float(np.abs(step).max()) < xtol:
                # No lower loss along the damped steps down to xtol (MINPACK's xtol test):
                # the minimum is found to the resolution asked for, once the held values'
                # columns are z's own.
                stop = stop_or_refresh()
                if stop is not None:
                    return stop
                current = True
                break
            if evals >= iterations:
                return "iterations"
            r_new, ok = residuals(z_new, reset=True)
            evals += 1
            f_new = float(r_new @ r_new) if ok else math.inf
            # Gain ratio: the actual decrease over the one the linear model predicts.
            predicted = -(2.0 * g @ step + step @ A @ step)
            rho = (f - f_new) / predicted if predicted > 0.0 else -1.0
            if f_new < f and rho > 0.0:
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)  # Nielsen's update
                nu = 2.0
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e8:
                return "stalled"
        if current:
            continue
        z, r, f = z_new, r_new, f_new
        stepped = True
        at_z = chosen() if chosen is not None else None
        if float(np.abs(step).max()) < xtol:
            return "converged"


def _full(base: np.ndarray, idx: list[int], v: np.ndarray) -> np.ndarray:
    out = np.array(base, dtype=np.float64)
    out[idx] = v
    return out


# ----------------------------------------------------------------------- targets
@dataclasses.dataclass
class Target:
    """A target read from a file. ``kind``: ``positions`` (``data``: ``(K, n, 3)``),
    ``points`` (a cloud, ``(M, 3)``), ``mesh`` (``(points, triangles)``) or ``forces``
    (the CSV rows of one ``tool``'s reaction force). ``frames``:
    rendered frame index of each position frame (or the frame a cloud/mesh shows; None:
    the last simulated frame). ``fps``: as stored, or None."""

    kind: str
    data: object
    frames: list[int] | None
    fps: float | None
    path: str
    #: The body whose particles ``data`` holds (a run's USD read for one body), or None: all.
    body: str | None = None
    #: ``forces`` targets: the tool whose reaction force ``data`` (CSV rows) holds.
    tool: str | None = None
    #: A run's USD read whole: ``(name, particle count)`` of each body in the file's order, or None.
    bodies: list | None = None
    #: Whether ``frames`` are the file's own (an .npz's 'frames'), not numbered 0..K-1 by default.
    frames_stored: bool = False

    def _check_range(self, model: Model) -> None:
        """Refuse, before any rollout, a coordinate whose square the loss cannot hold in the
        model's precision (``checks.squarable_coordinates``)."""
        data = self.data[0] if self.kind == "mesh" else self.data

        def place(where):
            if self.kind != "positions":
                return f"{'vertex' if self.kind == 'mesh' else 'point'} {where[0]}"
            frame = self.frames[where[0]] if self.frames is not None else where[0]
            # With a body, the file's particles are that body's, numbered from 0 within it.
            of = f" of body {self.body!r}" if self.body is not None else ""
            return f"frame {frame}, particle {where[1]}{of}"

        # A cloud or a mesh is searched in float32 whatever the model's precision (as above).
        precision = model.scalar.__name__ if self.kind == "positions" else "float32"
        if self.kind == "positions":
            data = np.nan_to_num(np.asarray(data, dtype=np.float64), nan=0.0, posinf=np.inf, neginf=-np.inf)  # NaN: missing
        checks.squarable_coordinates(f"target {checks.shown_path(self.path, False)}", data, precision, place)

    def particles(self, model: Model) -> np.ndarray | None:
        """Indices of the model's particles this target observes (None: all)."""
        if self.body is None:
            return None
        names = [b.name for b in model.bodies]
        try:
            from .usd import body_prim_names  # noqa: PLC0415

            prims = body_prim_names(model)
        except ImportError:
            prims = names
        if self.body in names:
            b = model.bodies[names.index(self.body)]
        elif self.body in prims:
            b = model.bodies[prims.index(self.body)]
        else:
            raise ValueError(f"target body {self.body!r} is not allowed: the scene's bodies are {', '.join(names)}")
        return np.arange(b.start, b.start + b.count)

    def _read_as_cloud(self, model: Model) -> bool:
        # One (M, 3) .npy array of another size: a point cloud, not particle positions (a
        # .npz holds 'positions', which are the particles' whatever their number).
        return (self.kind == "positions" and str(self.path).lower().endswith(".npy") and np.asarray(self.data).shape[0] == 1
                and np.asarray(self.data).shape[1] != model.particle_count)

    def check_particle_count(self, model: Model) -> None:
        """Refuse particle positions of another count than the scene's (or ``body``'s): said
        first, as what is wrong with the file, before what its frames can tell (an .npz of one
        frame and no 'frames' was refused as 'only frame 0', never told its count was wrong)."""
        if self.kind != "positions" or self._read_as_cloud(model):
            return
        pos = np.asarray(self.data)
        if self.body is not None:
            count = len(self.particles(model))
            if pos.shape[1] != count:
                raise ValueError(f"target {checks.shown_path(self.path, False)} has {pos.shape[1]} particles of body {self.body!r} per frame, the scene "
                                 f"{count}: use the scene and --scale the run was made with")
        elif pos.shape[1] != model.particle_count:
            raise ValueError(f"target {checks.shown_path(self.path, False)} has {pos.shape[1]} particles per frame, the scene {model.particle_count}: "
                             f"use the scene and --scale the target was made with")

    def _check_start_order(self, model: Model, idx=None) -> None:
        """Refuse positions whose frame 0 holds the scene's initial positions in another order.
        Particles are compared by index (marker i with particle i): a lab's markers numbered
        otherwise than the particles passed, and the fit pulled each particle toward another's
        path. Frame 0 shows it where each of its markers sits on some particle's start (within
        a quarter spacing, closer than any neighbour) but not all on their own."""
        if self.frames is None or 0 not in self.frames:
            return
        from .losses import _nearest_within  # noqa: PLC0415

        first = np.asarray(self.data, dtype=np.float64)[self.frames.index(0)]
        x0 = np.asarray(model.particle_x0, dtype=np.float64)
        if idx is not None:
            x0 = x0[idx]
        seen = np.flatnonzero(np.isfinite(first).all(axis=1))
        if first.shape != x0.shape or not seen.size:
            return
        near = _nearest_within(first[seen], x0, 0.25 * model.spacing)
        if (near < 0).any():
            return  # not the scene's start point for point: nothing said here of the order
        wrong = np.flatnonzero(near != seen)
        if wrong.size:
            i, j = int(seen[wrong[0]]), int(near[wrong[0]])
            of = f" of body {self.body!r}" if self.body is not None else ""
            raise ValueError(f"target {checks.shown_path(self.path, False)} is not allowed: its frame 0 holds the scene's initial positions in "
                             f"another order ({wrong.size} of {seen.size} observed markers on another particle's start; "
                             f"marker {i} on particle {j}'s{of}); particles are compared by index, marker i with particle i: "
                             "reorder the markers to the particles' order")

    def check_tool(self, names: list[str], static: list[str]) -> None:
        """Refuse a force log of a tool that is none of the scene's: ``names`` its tools' and
        pinned sets' names, ``static`` its static colliders' rows (``static_collider_names``);
        the model's, or its builder's before it is built (``warp-esph fit``: before any kernel)."""
        if self.tool not in names + static:
            raise ValueError(f"target {checks.shown_path(self.path, False)} holds the force of tool {self.tool!r}, which is not allowed: the "
                             f"scene's tools are {', '.join(names) or 'none'}, its static colliders "
                             f"{', '.join(static) or 'none'}")

    def _fitted_frames(self) -> list[int]:
        """Indices into ``data`` of the position frames fitted: not frame 0 (the initial state),
        nor a frame whose every marker is missing (NaN: nothing observed), which is left out
        with a warning naming it."""
        keep = [k for k, f in enumerate(self.frames) if f != 0]
        if not keep:
            raise ValueError(f"target {checks.shown_path(self.path, False)} holds only frame 0 (the initial state), which says nothing about the material")
        pos = np.asarray(self.data)
        blank = [k for k in keep if np.isnan(pos[k]).any(axis=1).all()]
        if blank:
            if len(blank) == len(keep):
                raise ValueError(f"target {checks.shown_path(self.path, False)} is not allowed: every position of its frames after frame 0 is NaN "
                                 "(missing); it observes nothing to fit")
            import warnings  # noqa: PLC0415

            warnings.warn(f"target {checks.shown_path(self.path, False)}: frame{'s' if len(blank) > 1 else ''} "
                          f"{', '.join(str(self.frames[k]) for k in blank)} observe{'' if len(blank) > 1 else 's'} no "
                          f"particle (every position NaN, missing) and {'are' if len(blank) > 1 else 'is'} left out of the fit", UserWarning, stacklevel=3)
        return [k for k in keep if k not in blank]

    def loss(self, model: Model, frame_steps: Mapping[int, int], radius: float | None = None, mode: str = "surface",
             force_noise: float | None = None, force_components: str = "xyz", coverage: str = "full",
             surface_offset: float = 0.0) -> Loss:
        """The loss for ``model``: ``frame_steps`` maps each rendered frame to its step;
        ``coverage``: how much of the body a point cloud shows (``ChamferLoss``'s);
        ``surface_offset``: how far outside the particles' centres a point cloud lies (m,
        ``ChamferLoss``'s; a scan of the material's surface: half a spacing);
        ``force_noise``: a force curve's noise (N; None: estimated, ``ReactionForceLoss``);
        ``force_components``: the force log's columns fitted (``ReactionForceLoss``'s
        ``components``). ``coverage = "partial"`` is refused for a target that is no point
        cloud (``_partial_refused``): a mesh's loss had taken it without a word."""
        coverage = checks.choice("coverage", coverage, ChamferLoss.COVERAGES)
        if coverage != "full" and not (self.kind == "points" or self._read_as_cloud(model)):
            raise ValueError(f"coverage (--cloud-coverage) = {checks.shorten(coverage)!r} is not allowed: "
                             f"{_partial_refused(self.path, self.kind)}")
        steps = [frame_steps[f] for f in sorted(frame_steps)]
        if self.kind == "forces":
            from .losses import ReactionForceLoss  # noqa: PLC0415

            from .sim.integrate import static_collider_names  # noqa: PLC0415

            self.check_tool([] if model.tools is None else list(model.tools.names), static_collider_names(model))
            chosen = [f for f in sorted(frame_steps) if f > 0]
            return ReactionForceLoss.from_csv(self.path, self.tool, frame_steps, components=force_components, frames=chosen,
                                              noise=force_noise)
        self.check_particle_count(model)
        self._check_range(model)
        if self.kind == "positions" and self.body is not None:
            idx = self.particles(model)
            pos = np.asarray(self.data)
            self._check_start_order(model, idx)
            keep = self._fitted_frames()
            return PositionLoss({frame_steps[self.frames[k]]: pos[k] for k in keep}, particles=idx)
        if self._read_as_cloud(model):
            self.kind, self.data = "points", _cloud(self.path, np.asarray(self.data)[0])
        if self.kind == "positions":
            pos = np.asarray(self.data)
            if self.bodies is not None:
                # Particles are compared by order: a scene listing the run's bodies in another
                # order (or other bodies of the same total) compared one body's run with another's.
                try:
                    from .usd import body_prim_names  # noqa: PLC0415

                    prims = body_prim_names(model)
                except ImportError:
                    prims = [b.name for b in model.bodies]
                counted = len(self.bodies) == len(model.bodies) and all(
                    count == b.count for (_, count), b in zip(self.bodies, model.bodies))
                # A body the scene names too must sit at its index; a scene that renamed its bodies
                # (its own guess) is matched by the counts.
                where_named = {}
                for k, (b, prim) in enumerate(zip(model.bodies, prims)):
                    where_named.setdefault(b.name, k)
                    where_named.setdefault(prim, k)
                moved = any(name in where_named and where_named[name] != k for k, (name, _) in enumerate(self.bodies))
                same = counted and not moved
                if not same:
                    def listed(bodies):
                        return ", ".join(f"{name} ({count} particles)" for name, count in bodies)

                    raise ValueError(f"target {checks.shown_path(self.path, False)} is not allowed: it holds the bodies {listed(self.bodies)} "
                                     f"in that order, the scene {listed((b.name, b.count) for b in model.bodies)}; particles "
                                     "are compared in order: use the scene the run was made with, or observe one body of the run "
                                     "(--target-body NAME; load_target(path, body=NAME) in Python)")
            self._check_start_order(model)
            keep = self._fitted_frames()
            return PositionLoss({frame_steps[self.frames[k]]: pos[k] for k in keep})
        pinned = pinned_particles(model)
        if self.kind in ("points", "mesh") and pinned is not None and pinned.all():
            # Held, the cloud's particle side was refused at the first evaluation as 'held = every
            # one of the 27 particles', a name the command never gave; the mesh's compared them all.
            raise ValueError(f"target {checks.shown_path(self.path, False)} is not allowed for this model: every one of its "
                             f"{model.particle_count} particles is pinned, which no fitted parameter moves; pin part of "
                             "the body (a clamp's region), not all of it")
        if self.kind == "points":
            r = radius if radius is not None else 3.0 * model.spacing
            if surface_offset >= r:
                raise ValueError(f"surface_offset (--cloud-offset) = {surface_offset:g} m is not allowed: must be below the "
                                 f"search radius (--radius) = {r:g} m (a scanned point is matched within the radius)")
            # Pinned particles (a particle floor's, a clamp's) are held: a scan of the sample need not
            # show them, and no parameter moves them (ChamferLoss's held).
            return ChamferLoss(self.data, radius=r, frames=steps, coverage=coverage, surface_offset=surface_offset,
                               held=None if pinned is None else np.flatnonzero(pinned))
        # A mesh compares each particle with its surface alone: the pinned ones (held, as above)
        # are left out.
        return MeshLoss(self.data, frames=steps, mode=mode, particles=unpinned_particles(model))


_CLOUD_TEXT = (".xyz", ".txt", ".csv", ".pts")


def _partial_refused(path, kind: str) -> str:
    """Why a target of ``kind`` (``Target.kind``, or ``"silhouettes"``) other than a point
    cloud takes no partial coverage, naming ``path``. A mesh target is closed (``load_mesh``
    refuses an open one), so it shows the whole body, and its loss already compares each
    particle with the surface alone: a scan of part of the body is fitted as the cloud of its
    points."""
    said = {"positions": "particle positions, compared one to one", "mesh": "a mesh",
            "forces": "a force curve", "silhouettes": "silhouettes"}.get(kind, kind)
    why = ("; a mesh target is closed (an open one is refused), the whole body's surface: fit a scan of part of "
           "the body as a point cloud of its points" if kind == "mesh" else "")
    return f"the target {checks.shown_path(path, False)} is {said}, not a point cloud{why}; give full for it"


def save_target(path, positions, frames: Sequence[int], fps: float | None = None):
    """Write target positions ``(K, n, 3)`` of rendered ``frames`` to ``.npz`` (or ``.npy``)."""
    positions = np.asarray(checks.host_values("positions", positions), dtype=np.float64)
    if positions.ndim == 2:
        positions = positions[None]
    frames = [int(f) for f in frames]
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[0] != len(frames):
        raise ValueError(f"positions with shape {positions.shape} is not allowed: must be (len(frames) = {len(frames)}, n, 3)")
    path = os.fspath(path)
    if path.lower().endswith(".npy"):
        if frames != list(range(len(frames))):
            raise ValueError("a .npy target holds frames 0..K-1; use .npz to store other frames")
        np.save(path, positions)
        return
    extra = {} if fps is None else {"fps": float(fps)}
    np.savez_compressed(path, positions=positions, frames=np.asarray(frames, dtype=np.int64), **extra)


#: The arrays an ``.npz`` target may hold (``save_target`` writes them); any other is refused, not dropped.
_NPZ_TARGET_KEYS = ("positions", "frames", "fps")


def choose_stored_frames(target: Target, spec, name: str = "frames") -> None:
    """Keep of ``target``, positions whose file stores its frame numbers (an .npz's 'frames'),
    the frames ``spec`` chooses among them, as ``usd.parse_frames`` chooses among a run's
    (``all``, ``last``, ``A:B:STEP``, ``2,4``, a list); a refusal names the spec ``name`` and
    lists the stored frames. Frame 2's positions were fitted at frame 1 where ``1,2,3``
    renumbered the file's 2, 4, 6."""
    from .usd import parse_frames  # noqa: PLC0415

    stored = sorted(target.frames)
    listed = ", ".join(map(str, stored))
    chosen, missing = [], []
    # A list or a range is read as parse_frames reads it; text one part at a time, so that
    # every frame the file does not hold is named.
    parts = str(spec).split(",") if isinstance(spec, str) else [spec]
    for part in parts:
        if isinstance(part, str) and part.strip().isdigit():
            (chosen if int(part) in target.frames else missing).append(int(part))
            continue
        try:
            # In frame order whatever the file's (its 'last' is its largest frame).
            chosen.extend(parse_frames(part, stored, name))
        except ValueError as e:
            raise ValueError(f"{e}; the target {checks.shown_path(target.path, False)} holds frames {listed} (-N counts frame numbers back from "
                             "the last)") from None
    if missing:
        raise ValueError(f"{name} = {checks.shorten(spec)!r} is not allowed: the target {checks.shown_path(target.path, False)} holds frames {listed} "
                         f"(its 'frames'), not {', '.join(map(str, missing))}")
    twice = next((f for k, f in enumerate(chosen) if f in chosen[:k]), None)
    if twice is not None:
        # Fitted twice, the frame weighed twice in the loss ('last,6' named frame 6 once
        # here, while a run's USD target fitted it twice).
        raise ValueError(f"{name} = {checks.shorten(spec)!r} is not allowed: it names frame {twice} twice; name each frame once")
    target.data = np.asarray(target.data)[[target.frames.index(f) for f in chosen]]
    target.frames = chosen


def load_target(path, body: str | None = None, frames=None, tool: str | None = None, frames_name: str = "frames",
                body_name: str = "body", tool_name: str = "tool") -> Target:
    """Read a target file.

    - the ``.usd/.usda/.usdc`` of a previous ``warp-esph run`` (``UsdGeom.Points`` under
      ``/World``): particle positions per rendered frame; ``body`` (a body or prim name)
      keeps one body's particles, ``frames`` (``all``, ``2,4,6``, ``10:60:10``, ...; default
      every frame after the first) chooses frames (a refusal names them ``frames_name``: the
      CLI's ``--target-frames``; ``body`` and ``tool`` likewise ``body_name`` and ``tool_name``). Any other USD file is read as a mesh.

    - ``.npz``: ``positions`` ``(K, n, 3)`` (or ``(n, 3)``), optional ``frames`` (rendered
      frame indices; default 0..K-1) and ``fps``, no other array (a ``times`` is refused, not
      dropped); ``frames`` chooses among a stored ``frames`` as among a run's
      (``choose_stored_frames``), and is refused for a file that stores none. A NaN position (``.npz`` or ``.npy``) is a
      missing marker, left out of the loss (``PositionLoss``), also in a run's USD (another
      program's); a file all NaN is refused.
    - ``.npy``: positions ``(K, n, 3)`` of frames ``0..K-1``, or ``(n, 3)``: the last frame.
    - ``<output>_tools.csv`` of ``warp-esph run`` (a CSV whose header names ``frame, time,
      tool, fx, fy, fz``): the reaction-force curve of ``tool`` (a tool's or a static
      collider's name, ``plane0`` for the ground; default: the only one when the file holds
      one), a ``ReactionForceLoss`` per rendered frame; quoted cells, tabs between the fields
      and ``#`` lines before the header (an instrument's preamble) are read.
    - ``.xyz/.txt/.csv/.pts``: a point cloud, three numbers per line (metres), under an
      optional header row naming the columns ``x``, ``y``, ``z`` (read whatever other columns
      there are; a unit beside them other than ``m`` is refused); a byte-order mark, empty
      rows and a comma after every line are read past, commas or tabs taken for the other
      separator where the first line's numbers say so (semicolons too, but in a ``.csv``); a
      header row may start with ``//``, as CloudCompare's ASCII export writes it
      (``//X,Y,Z,R,G,B``, ``//X;Y;Z``). Without a header, four or more columns
      whose first holds whole numbers in order from 0 or above, counting by 1 (a marker id)
      or by 0 and 1 (a frame number), are refused, asking for a header row. A point
      with a NaN coordinate is one not seen: left out with a warning (every point NaN: refused).
    - anything else ``meshio`` (or ``.usd``) reads: a mesh when it has faces, else a cloud.
    """
    p = os.fspath(path)
    if not p:  # said as nothing: 'target file  does not exist'
        raise ValueError("path = '' is not allowed: must be the path of a target file")
    if os.path.isdir(p):
        raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: it is a folder; give a target file")
    if not os.path.isfile(p):
        raise FileNotFoundError(f"target file {checks.shown_path(p, False)} does not exist{checks.tilde_note(p)}")
    ext = os.path.splitext(p)[1].lower()
    if ext == ".toml":
        # The scene given twice ('fit s.toml --target s.toml') was handed to meshio: "mesh
        # 's.toml' is not allowed: meshio cannot read it (ReadError: Could not deduce ...)".
        raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: it is a scene file (.toml), not a measurement; give the run's USD, "
                         "positions (.npz, .npy), a force log (_tools.csv), a mesh or a point cloud")
    if ext == ".json":
        # Handed to meshio too: a run's force record beside its log was refused as a mesh that
        # 'Could not deduce file format', naming no target the command takes.
        log = p[:-len(".json")] + ".csv" if p.lower().endswith("_tools.json") else None
        # Said to be beside it only where it is: a record copied alone was pointed to a CSV not there.
        gone = "" if log is None or os.path.isfile(log) else ", which is not there (give the run's log as it wrote it)"
        what = (f"a run's force log is its CSV beside it, {checks.shown_path(log, False)} (the same rows){gone}" if log else
                "give the run's USD, positions (.npz, .npy), a force log (_tools.csv), a mesh or a point cloud (a camera "
                "file goes with --cameras, experiments with --experiments)")
        raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: it is a JSON file, not a measurement; {what}")
    if body is not None and ext not in (".usd", ".usda", ".usdc"):
        # It was ignored: every position of the file was the target.
        raise ValueError(f"{body_name} = {checks.shorten(body)!r} is not allowed with the target {checks.shown_path(p, False)}: only the USD of a run holds bodies "
                         "to choose from")
    if ext in (".npz", ".npy"):
        chosen = frames  # the caller's choice among the file's frames ('frames' below is the file's)
        try:
            data = read_arrays(p)
        except Exception as e:  # noqa: BLE001
            raise unreadable_arrays("target", p, e) from None
        frames, fps = None, None
        if ext == ".npz":
            if "positions" not in data:
                raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: a .npz target needs a 'positions' array (has {list(data.keys())})")
            unread = [k for k in data if k not in _NPZ_TARGET_KEYS]
            if unread:
                # Dropped without a word: a lab's 'times' (in ms, or from a clock not at 0) left the
                # entries read as frames 0..K-1 at the scene's rate, whatever the times said.
                timed = [k for k in unread if k.lower() in ("t", "time", "times", "timestamp", "timestamps")]
                how = (f"; {timed[0]!r} is not read: store the frame of each entry as 'frames' (whole indices, frame k "
                       "at k / fps s from time 0 at frame 0) and the rate as 'fps'") if timed else ""
                raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: it holds the array{'s' if len(unread) > 1 else ''} "
                                 f"{', '.join(map(repr, unread))}, which a positions target does not read (allowed: "
                                 f"{', '.join(_NPZ_TARGET_KEYS)}){how}")
            pos = _real_array(p, "positions", data["positions"])
            if "frames" in data:
                given = np.atleast_1d(data["frames"])
                # 1.5 was truncated to frame 1: a frame is a whole index.
                if given.dtype.kind not in "iuf" or given.ndim != 1 or (given.dtype.kind == "f" and (
                        not np.isfinite(given).all() or (given != np.round(given)).any())):
                    raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: its 'frames' must be whole frame indices, "
                                     f"not {checks.shorten(given.tolist())!r}")
                frames = [int(f) for f in given]
            if "fps" in data:
                rate = np.asarray(data["fps"])
                if rate.size != 1 or rate.dtype.kind not in "iuf":
                    raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: its 'fps' must be one number, not an array of shape "
                                     f"{rate.shape} ({rate.dtype})")
                fps = float(rate.reshape(()))
                if not (math.isfinite(fps) and fps > 0.0):
                    # nan was read as the rate ('recorded at nan fps, the other at nan fps'), 0 refused
                    # as 'fps = 0.0', naming no file.
                    raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: its 'fps' = {fps!r} must be a finite number of "
                                     "frames per second > 0")
        else:
            pos = _real_array(p, "positions", data)
        shape = pos.shape
        one_frame = pos.ndim == 2
        if one_frame:
            pos = pos[None]
        # Checked here, with the file's name: an empty or NaN (n, 3) array was refused later as
        # "targets[62]", by the step it was compared at.
        if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] == 0 or pos.shape[1] == 0:
            cloud = " (an (M, 3) .npy of another count than the scene's particles is a point cloud)" if ext == ".npy" else ""
            raise ValueError(f"target {checks.shown_path(p, False)} with shape {shape} is not allowed: positions must be (K, n, 3) or (n, 3) "
                             f"with K, n >= 1{cloud}")
        if np.isinf(pos).any():
            k, i = (int(v) for v in np.argwhere(np.isinf(pos))[0][:2])
            raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: it has an infinite position (frame entry {k}, particle {i}); "
                             "a missing one (an occluded marker) is NaN")
        if np.isnan(pos).all():
            # NaN marks a gap in the data; a file of nothing but gaps observes nothing.
            raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: every position in it is NaN (missing); it observes nothing")
        stored = ext == ".npz" and "frames" in data
        if chosen is not None and not stored:
            # It was ignored: every entry was the target, at frames 0..K-1.
            raise ValueError(f"{frames_name} = {checks.shorten(chosen)!r} is not allowed with the target {checks.shown_path(p, False)}: it chooses among "
                             "the frames a file stores, and this one stores none (no 'frames' array); store the frame of "
                             "each entry as 'frames', or pass the entries wanted")
        if one_frame and frames is None:
            return Target("positions", pos, None, fps, p)  # (n, 3): the last frame
        if frames is None:
            frames = list(range(pos.shape[0]))
        if len(frames) != pos.shape[0] or min(frames) < 0 or len(set(frames)) != len(frames):
            raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: 'frames' must be {pos.shape[0]} distinct indices >= 0")
        target = Target("positions", pos, frames, fps, p, frames_stored=stored)
        if chosen is not None:
            choose_stored_frames(target, chosen, frames_name)
        return target
    if ext == ".csv" and is_tools_csv(p):
        return _forces_target(p, tool, tool_name)
    if ext == ".csv":
        _refuse_other_force_logs(p)
    if ext in _CLOUD_TEXT:
        try:
            pts = _read_cloud_text(p, ext)
        except ValueError as e:  # a header's refusal too: a force log's first row is no header
            hint = ""
            if ext == ".csv":
                with open(p, newline="", encoding=checks.text_encoding(p), errors="replace") as fh:
                    first = fh.readline().split(",")
                if len(first) >= 6 and not _is_number(first[2]) and all(_is_number(c) for c in first[:2] + first[3:6]):
                    # frame, time, tool, fx, fy, fz: a force log whose header row was lost.
                    hint = ("; its first row reads as a force log's (frame, time, tool, fx, fy, fz) without the header "
                            "row a force log starts with: add the line 'frame,time,tool,fx,fy,fz'")
            raise ValueError(f"target {checks.shown_path(p, False)} cannot be read as a point cloud: {str(e).rstrip('.')}{hint}") from None
        return Target("points", _cloud(p, pts), None, None, p)
    if ext in (".usd", ".usda", ".usdc"):
        # Before the run's reader, whose refusals are taken as a damaged file's.
        checks.usd_input(p)
        run = _usd_run_target(p, body, frames, frames_name, body_name)
        if run is not None:
            return run
        if body is not None:
            raise ValueError(f"{body_name} = {checks.shorten(body)!r} is not allowed with the target {checks.shown_path(p, False)}: it is a mesh, not the USD of a "
                             "run, and holds no bodies to choose from")
        from .meshes import load_mesh  # noqa: PLC0415

        try:
            return Target("mesh", load_mesh(p), None, None, p)
        except ValueError as e:
            points = _points_elsewhere(p) if "has no UsdGeom.Mesh prim" in str(e) else []
            if not points:
                raise
            # Particles another program wrote elsewhere (a PointInstancer, Points under a group
            # or another root) were refused as 'not a closed triangle mesh', which they never were.
            raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: it has no mesh, and its points ({', '.join(points[:3])}"
                             f"{', ...' if len(points) > 3 else ''}) are not where a run's particles are read from: "
                             "UsdGeom.Points prims directly under /World, one per body, one time sample per frame") from None
    from .meshes import read_meshio  # noqa: PLC0415

    m = read_meshio(repr(p), p)  # checked or read in a child process: a damaged file cannot hang
    has_faces = any(c.type in ("triangle", "quad", "polygon", "tetra") or c.type.startswith("triangle") for c in m.cells)
    if has_faces:
        from .meshes import load_mesh  # noqa: PLC0415

        return Target("mesh", load_mesh(p), None, None, p)
    return Target("points", _cloud(p, np.asarray(m.points, dtype=np.float64)), None, None, p)


#: Units a point cloud's header may state beside a column name (``x (mm)``, ``x_mm``, ``x [m]``,
#: ``x / mm``: ISO 80000's quantity / unit).
_HEADER_UNIT = r"(?:[\s_]*(?:/\s*)?[\[(]?\s*(m|mm|cm|um|µm|in|inch|ft)\s*[\])]?)?"


def _fields(line: str, sep: str | None) -> list[str]:
    """The cells of a line split at ``sep`` (None: whitespace), quotes and spaces taken off;
    empty cells at the end (a comma after every line, as some exports write) left out."""
    fields = [c.strip().strip('"').strip("'") for c in line.split(sep)]
    while fields and not fields[-1]:
        fields.pop()
    return fields


def _cloud_separator(text: str, ext: str) -> str | None:
    """The separator of a point cloud's first line: the extension's (``,`` for ``.csv``,
    whitespace for ``.xyz/.txt/.pts``) unless the line's numbers are split by another (a
    tab-separated ``.csv``, a comma-separated ``.txt``, which had been refused as a header
    naming no columns x, y, z though its first row is numbers). Semicolons too, but in a
    ``.csv`` (a spreadsheet's of decimal commas, refused there): CloudCompare's ASCII export
    offers them (``//X;Y;Z``), and they were refused as a header naming no x, y, z."""
    usual, others = (",", (None,)) if ext == ".csv" else (None, (",", ";"))
    for sep in (usual, *others):
        fields = _fields(text, sep)
        if fields and all(_is_number(c) for c in fields):
            return sep
    # A header row: split as its commas (or, but in a .csv, semicolons) say.
    return "," if "," in text else ";" if ";" in text and ext != ".csv" else None


def _decimal_commas(line: str, ext: str) -> str | None:
    """Why a line of numbers written with decimal commas is refused, or None where it is not
    one: said of its semicolons too where it has them (a spreadsheet's export in a locale of
    decimal commas), as it is no semicolon-separated cloud of decimal points, which reads."""
    split = _fields(line.replace(";", " "), None)
    commas = [c for c in split if "," in c]
    if not commas or not all(_is_number(c.replace(",", ".")) for c in split):
        return None
    by = "its fields are separated by semicolons and its numbers have" if ";" in line else "its numbers have"
    return (f"{by} decimal commas ({commas[0]!r}); write them with a decimal point (x y z in metres, separated by "
            + ("spaces, tabs or commas)" if ext == ".csv" else "spaces, tabs, commas or semicolons)"))


def _read_cloud_text(path: str, ext: str) -> np.ndarray:
    """The points of a point-cloud text file, ``(M, 3)`` (NaN rows kept: ``_cloud`` leaves
    them out), or a ValueError saying why not, naming a line by its number in the file.

    Blank lines, ``#`` lines and rows of empty cells (a spreadsheet's empty rows) are read
    past, and a first line of one whole number (a ``.pts`` file's point count) where that many
    rows follow (or under a header row: CloudCompare's). A first line that is not all numbers
    is a header row (a ``//`` before it read past: CloudCompare's): it must name columns ``x``,
    ``y`` and ``z`` (any case, in any order, among others; a unit beside them must be ``m``),
    which are then read. Without a header the first three columns are x, y, z; four or more
    columns whose first holds whole numbers in order from 0 or above (0, 1, 2, ... or 1, 2,
    4, ...: a marker's id, counting by 1 but for gaps; 0, 0, 1, 1, ...: a frame number) are
    refused, as it had been read as x."""
    import re  # noqa: PLC0415
    import warnings  # noqa: PLC0415

    with open(path, encoding=checks.text_encoding(path), errors="replace") as fh:
        text = fh.read()
    lines = [(k + 1, line.strip()) for k, line in enumerate(text.splitlines())]
    lines = [(k, line) for k, line in lines if line and not line.startswith("#")]
    if not lines:
        return np.zeros((0, 3))
    first = lines[0][1]
    count, count_at = None, "its first line"
    if len(lines) > 1 and re.fullmatch(r"\d+", first) and len(_fields(lines[1][1], _cloud_separator(lines[1][1], ext))) >= 3:
        # A Leica .pts (CloudCompare's too) starts with its point count: read past, held to the rows.
        count, lines = int(first), lines[1:]
        first = lines[0][1]
    written = first  # as the file has it, for a refusal
    if first.startswith("//") and first[2:].strip():
        # CloudCompare's ASCII export starts its header row with '//' ('//X,Y,Z,R,G,B', its
        # scalar fields' names after them), which named no column x.
        first = first[2:].lstrip()
        lines[0] = (lines[0][0], first)
    if ext == ".csv" and ";" in first and "," not in first:
        raise ValueError("its fields are separated by semicolons (a spreadsheet's export with decimal commas?); a "
                         "point cloud .csv has comma-separated columns x, y, z in metres with decimal points")
    sep = _cloud_separator(first, ext)
    fields = _fields(first, sep)
    cols = None
    if not all(_is_number(c) for c in fields):
        found, units = {}, {}
        for i, f in enumerate(fields):
            m = re.fullmatch(r"([A-Za-z]+?)" + _HEADER_UNIT, f)
            if m and m.group(1).lower() in found:
                # The first was read and the other left without a word: 'x,y,z,x,y,z' (two markers
                # a row) fitted the first marker's points alone.
                axis = m.group(1).lower()
                raise ValueError(f"its header names the column {axis} twice ({fields[found[axis]]!r} in column "
                                 f"{found[axis] + 1}, {f!r} in column {i + 1}); which one to read is not ours to choose: "
                                 "give one point a row, its columns x, y, z named once")
            if m and m.group(1).lower() in ("x", "y", "z"):
                found[m.group(1).lower()] = i
                units[m.group(1).lower()] = (m.group(2) or "m").lower()
        if len(found) < 3:
            commas = _decimal_commas(first, ext)
            if commas is not None:
                raise ValueError(commas)
            raise ValueError(f"its first row {written[:120]!r} is a header that names no columns x, y and z; a point "
                             "cloud's text file holds three numbers per line (x y z, metres), under an optional "
                             "header row naming its columns x, y, z")
        other = sorted({u for u in units.values() if u != "m"})
        if other:
            raise ValueError(f"its header gives the coordinates in {', '.join(other)}; positions are metres: convert "
                             "the file to metres (and its header to x, y, z)")
        cols = (found["x"], found["y"], found["z"])
        # A frame or time column beside them: a cloud's time stamps, or a table over frames.
        # A unit beside 'time' or 't' must be a time's: 'T (degC)' is a thermal scan's temperature.
        stamp = next((i for i, f in enumerate(fields) if re.fullmatch(r"frame\b.*", f.lower()) or re.fullmatch(
            r"(?:time|t)(?:[\s_]*(?:/\s*)?[\[(]?\s*(?:s|ms|us|µs|ns|min|h)\s*[\])]?)?", f.lower())), None)
        lines = lines[1:]
        if count is None and len(lines) > 1 and re.fullmatch(r"\d+", lines[0][1]) and len(
                _fields(lines[1][1], _cloud_separator(lines[1][1], ext))) >= 3:
            # CloudCompare writes its point count under its header row: read past, held to the rows.
            count, count_at, lines = int(lines[0][1]), f"its line {lines[0][0]}, under the header row,", lines[1:]
        if lines:
            sep = _cloud_separator(lines[0][1], ext)  # the numbers' own ('x,y,z' over '0.1 0.2 0.3')
            row = _fields(lines[0][1], sep)
            commas = _decimal_commas(lines[0][1], ext)
            if commas is not None and not all(_is_number(c) for c in row):
                # Under a header ('//X;Y;Z') it had been refused as a cell '1;0' that is no number.
                raise ValueError(commas)
            if stamp is not None and stamp < len(row) and _is_number(row[stamp]):  # a clock time ('12:00:01') is left unread
                cols += (stamp,)
    # A comma after every value, and rows of empty cells (a spreadsheet's empty rows), hold nothing.
    if sep in (",", ";"):  # (a whitespace-separated line was stripped already)
        lines = [(k, line.rstrip(sep + " \t")) for k, line in lines]
        lines = [(k, line) for k, line in lines if line]
    if not lines:
        return np.zeros((0, 3))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pts = np.loadtxt([line for _, line in lines], delimiter=sep, ndmin=2, usecols=cols, quotechar='"',
                             dtype=np.float64)
    except ValueError as e:
        # numpy numbers rows from 0 for a bad number and from 1 for a short row, counting neither
        # the header nor comments: the line is found here, by its number in the file.
        _refuse_cloud_line(lines, sep, cols)
        raise ValueError(str(e).split(";")[0]) from None  # numpy's advice ('use `usecols`') is its API's
    if cols is not None and len(cols) == 4:
        stamps, pts = pts[:, 3], pts[:, :3]
        # A NaN stamp is a time not recorded, no repeat of another row's: distinct stamps with
        # one NaN among them had been refused as a table over frames.
        stamped = stamps[np.isfinite(stamps)]
        distinct = np.unique(stamped)
        by_frame = fields[cols[3]].lower().startswith("frame")
        if 1 < len(distinct) and (len(distinct) < len(stamped) or by_frame):
            # Several points share each value: frames of markers, which one cloud would merge;
            # and a cloud is one frame's: a frame per row is a marker tracked over frames (a
            # scanner stamps its points with times, each its own).
            unstamped = f" (and {len(stamps) - len(stamped)} of no value)" if len(stamped) < len(stamps) else ""
            raise ValueError(f"its column {fields[cols[3]]!r} holds {len(distinct)} different values over {len(stamped)} "
                             f"rows{unstamped}: a table of positions over frames, which one cloud would merge; give "
                             "positions per frame as an .npz ('positions' (K, n, 3), 'frames'), or one frame's points as "
                             "a cloud"
                             + ("" if by_frame else
                                # Not told apart from a table by the stamps' counts or order: a line
                                # scanner's profiles hold one count of points each, in one order, as
                                # frames of markers do, and a tracker's table leaves out a marker not seen.
                                f"; a scan whose points share a time stamp (one pulse's returns, one profile's points) is "
                                f"read as one cloud with the column {fields[cols[3]]!r} left out of the file, or with "
                                "its header cell renamed 'scan_time', which is read past as any column other than "
                                "x, y, z is"))
    if count is not None and count != len(pts):
        why = "a file cut short?" if len(pts) < count else "points added after the count was written?"
        raise ValueError(f"{count_at} says it holds {count} points, and {len(pts)} follow ({why})")
    width = pts.shape[1]
    if cols is None and width >= 4 and len(pts) >= 2:
        ids, step = pts[:, 0], np.diff(pts[:, 0])
        # Whole numbers in order, not all one (a flat scan at x = 0 is a cloud), from 0 or
        # above, rows counted by 1 (a dropped marker's gap aside) or frames one after another:
        # an index column, no coordinate in metres. A scan of whole coordinates sorted by x
        # (centred on 0, or at a spacing of 2 or more) is read as the x it is.
        counts = (step >= 1.0).all() and 2 * np.count_nonzero(step == 1.0) >= len(step)
        frames = (step >= 0.0).all() and np.isin(step, (0.0, 1.0)).all()
        if (ids == np.round(ids)).all() and ids[0] >= 0.0 and (step > 0.0).any() and (counts or frames):
            header = ("add a header row naming them (e.g. 'id,x,y,z'; 'x,y,z,...' if the first column is x)")
            if counts:
                what = f"numbers its rows in order ({ids[0]:.0f}, {ids[1]:.0f}, ..., {ids[-1]:.0f}: a marker or point id?)"
            else:
                what = (f"holds whole numbers in order, some repeated ({ids[0]:.0f} to {ids[-1]:.0f}: a frame number "
                        "of a table of frames?)")
                header = ("a table of markers per frame is no point cloud: give positions per frame as an .npz "
                          "('positions' (K, n, 3), 'frames'); else " + header)
            raise ValueError(f"its first column {what} beside {width - 1} more columns, and a cloud without a header "
                             f"row is read as x, y, z from its first three columns: {header}")
    return pts


def _refuse_cloud_line(lines, sep, cols) -> None:
    """Raise a ValueError naming the first line of ``lines`` (``(line number, text)``) that
    holds another number of columns than the first, or a cell of ``cols`` (None: every
    cell) that is no number."""
    width, first = None, None
    for k, line in lines:
        f = _fields(line, sep)
        if width is None:
            width, first = len(f), k
        if len(f) != width:
            raise ValueError(f"line {k} has {len(f)} columns, line {first} has {width}; every line of a point "
                             "cloud holds the same number of columns")
        for c, cell in enumerate(f):
            if not _is_number(cell) and (cols is None or c in cols):
                # A spreadsheet's or a tracker's mark of a value not measured: said how a gap is written.
                gap = "; a point not seen is a row of nan (or no row)" if cell.lower() in (
                    "", "na", "n/a", "-", "null", "none", "missing") else ""
                raise ValueError(f"line {k}, column {c + 1}: {cell!r} is not a number{gap}" if cell else
                                 f"line {k}, column {c + 1} is empty{gap}")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


#: Column names of a lab's force or time log that are no point cloud's.
_FORCE_LOG_NAMES = ("frame", "time", "tool", "fx", "fy", "fz", "force", "load", "t")


def _refuse_other_force_logs(p: str) -> None:
    """Refuse, by what is wrong with it, a CSV that is a force log in another layout than
    ``<output>_tools.csv``'s: such files had been read as point clouds and refused as
    'cannot be read as a point cloud: could not convert string ...', which they never were."""
    import re  # noqa: PLC0415

    from .losses import TOOLS_CSV_COLUMNS, tools_csv_header, tools_log_head  # noqa: PLC0415

    with open(p, newline="", encoding=checks.text_encoding(p), errors="replace") as fh:
        line = tools_log_head(fh)[0].rstrip("\r\n")  # the header below a preamble's '#' lines, as the log reads it
    if line.startswith("//"):  # CloudCompare's header row ('//X,Y,Z,Time'): a cloud's, as _read_cloud_text reads it
        line = line[2:]
    names = [re.sub(r"\s*[\[(].*$", "", c.strip().strip('"')).strip().lower() for c in re.split(r"[,;\t]", line)]
    if not any(n in _FORCE_LOG_NAMES for n in names):
        return
    axes = {m.group(1).lower() for c in re.split(r"[,;\t]", line)
            if (m := re.fullmatch(r"([A-Za-z]+?)" + _HEADER_UNIT, c.strip().strip('"')))}
    if {"x", "y", "z"} <= axes and not {"fx", "fy", "fz", "force", "load"} & set(names):
        return  # a cloud's header with a time stamp or frame column beside x, y, z: read as a cloud
    need = (f"a reaction-force log needs the columns {', '.join(TOOLS_CSV_COLUMNS)}, comma-separated (or tab-separated; "
            "times in s, forces in N, numbers with a decimal point), one row per frame and tool")
    if ";" in line and "," not in line and "\t" not in line:
        # A spreadsheet in a locale of decimal commas writes ';' between fields. Tabs are read
        # (losses.tools_log_delimiter): they had been refused as if they meant decimal commas.
        raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: its fields are separated by semicolons (a spreadsheet's "
                         f"export with decimal commas?); {need}")
    header = tools_csv_header(p) or []
    missing = [c for c in TOOLS_CSV_COLUMNS if c not in header]
    extra = ""
    if "frame" in missing and "time" not in missing:
        # A lab's log by time alone: the fit compares frame k's window mean at k / fps.
        extra = ("; a log by time alone is not resampled: average its samples over each frame's interval "
                 "((k - 1) / fps, k / fps] and number the rows by frame k")
    forces = [c for c in ("fx", "fy", "fz") if c not in missing]
    twice = [c for c in forces if header.count(c) > 1]
    if twice:
        # 'frame,time,tool,fy,fy,fz': a mislabelled column, not a load cell of fewer axes.
        extra += f"; it names {', '.join(twice)} more than once (a mislabelled column?): name each column once"
    elif forces and len(forces) < 3:
        # A single-axis load cell's log (frame, time, tool, fy): the refusal named what it
        # lacked, not that such a log is fitted with zeros in the other columns left unfitted.
        unmeasured = [c for c in ("fx", "fy", "fz") if c in missing]
        axes = "".join(c[1] for c in forces)
        extra += (f"; a load cell that measures {axes} alone: write 0 in {', '.join(unmeasured)} and give "
                  f"--force-components {axes} (the zeros are then not fitted as measured forces)")
    raise ValueError(f"target {checks.shown_path(p, False)} is not allowed: {need}; it lacks {', '.join(missing)} (its header: "
                     f"{line.strip()[:120]!r}){extra}")


def _points_elsewhere(path: str) -> list[str]:
    """The paths of a USD file's Points and PointInstancer prims (a file that ``UsdFrames`` found
    no run's particles in holds none directly under /World)."""
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    from .usd import open_layer_checked  # noqa: PLC0415

    stage = Usd.Stage.Open(open_layer_checked(path))
    return [str(q.GetPath()) for q in stage.Traverse() if q.IsA(UsdGeom.Points) or q.IsA(UsdGeom.PointInstancer)]


def _cloud(path: str, pts: np.ndarray) -> np.ndarray:
    """The first three columns of ``pts``, one or more rows, every point finite; else refused
    by the file's name (an empty .obj or .stl raised IndexError; a cloud of (x, y) pairs or
    a NaN point was named by the step it was compared at)."""
    if pts.ndim != 2 or pts.shape[0] == 0 or pts.shape[1] < 3:
        shape = "no points" if pts.size == 0 else f"points of shape {pts.shape}"
        # A force log of '#' lines alone (an instrument's export cut after its preamble) was told
        # of points alone, as if it had been taken for a cloud by its name.
        log = ("; nor is it a force log, which needs a header naming frame, time, tool, fx, fy, fz" if pts.size == 0
               and str(path).lower().endswith(".csv") else "")
        raise ValueError(f"target {checks.shown_path(path, False)} is not allowed as a point cloud: it holds {shape}; it needs one or more points "
                         f"of three coordinates (x y z){log}")
    pts = pts[:, :3]
    bad = np.flatnonzero(np.isinf(pts).any(axis=1))
    if bad.size:
        raise ValueError(f"target {checks.shown_path(path, False)} is not allowed as a point cloud: point {bad[0]} is {pts[bad[0]].tolist()}; "
                         "a coordinate must be finite, or NaN for a missing point")
    # A cloud is unordered: a NaN row can only be a point not seen (as a NaN marker of a
    # position target is one), and had been refused as if the file were damaged.
    missing = np.isnan(pts).any(axis=1)
    if missing.all():
        raise ValueError(f"target {checks.shown_path(path, False)} is not allowed as a point cloud: every point has a NaN coordinate (missing); "
                         "it observes nothing")
    if missing.any():
        import warnings  # noqa: PLC0415

        warnings.warn(f"target {checks.shown_path(path, False)}: {int(missing.sum())} of its {len(pts)} points have a NaN coordinate (missing) and "
                      f"are left out ({int((~missing).sum())} points)", stacklevel=2)
        pts = pts[~missing]
    from .losses import unique_points  # noqa: PLC0415

    pts, repeats = unique_points(np.asarray(pts, dtype=np.float64))
    if repeats:
        import warnings  # noqa: PLC0415

        warnings.warn(f"target {checks.shown_path(path, False)}: {repeats} of its {len(pts) + repeats} points repeat an earlier point exactly; "
                      f"each point is counted once ({len(pts)} points)", stacklevel=2)
    return pts


def _real_array(path: str, name: str, a) -> np.ndarray:
    """``a`` as float64 where it holds real numbers; complex values (numpy dropped their
    imaginary parts with a warning) and text are refused by the file's name."""
    a = np.asarray(a)
    if a.dtype.kind not in "iuf":
        raise ValueError(f"target {checks.shown_path(path, False)} is not allowed: its {name} must be real numbers, not {a.dtype} values")
    return a.astype(np.float64)


def unreadable_arrays(what: str, path: str, exc: BaseException) -> ValueError:
    """'<what> <path> cannot be read: <why> (a damaged or foreign file?)' for an .npz or .npy
    file whose reading (``read_arrays``) raised ``exc``, said in words, not by its class."""
    # numpy reads bytes that are no array file as pickled data and advises loading them
    # unsafely: not the advice to give about a damaged or foreign file.
    # (numpy's words, not the path an OSError's str() holds: '/data/pickles/t.npz' unreadable
    # was 'not a numpy .npz/.npy file', not 'Permission denied')
    pickled = isinstance(exc, ValueError) and "allow_pickle" in str(exc)
    why = "not a numpy .npz/.npy file" if pickled else checks.read_reason(exc)
    return ValueError(f"{what} {checks.shown_path(path, False)} cannot be read: {why} (a damaged or foreign file?)")


def read_arrays(path: str):
    """The arrays of an ``.npz`` file as a dict (every one read now: a damaged zip fails on
    access, not on open), or the array of an ``.npy`` file; the file is closed whatever
    happens (np.load leaves its handle open when the zip is damaged: a ResourceWarning)."""
    with open(path, "rb") as fh:
        data = np.load(fh, allow_pickle=False)
        if isinstance(data, np.lib.npyio.NpzFile):
            with data:
                return {k: data[k] for k in data.files}
        return data


def _forces_target(path: str, tool: str | None, tool_name: str = "tool") -> Target:
    """The reaction-force curve of one tool from a ``<output>_tools.csv``."""
    rows = read_tools_csv(path)
    names = list(dict.fromkeys(r["tool"] for r in rows))
    if tool is None:
        if len(names) > 1:
            raise ValueError(f"{tool_name} is required: {checks.shown_path(path, False)} holds the forces of tools and static colliders "
                             f"{', '.join(names)}")
        tool = names[0]
    if tool not in names:
        raise ValueError(f"{tool_name} = {checks.shorten(tool)!r} is not allowed: {checks.shown_path(path, False)} holds the forces of {', '.join(names)}")
    mine = [r for r in rows if r["tool"] == tool]
    frames = sorted(r["frame"] for r in mine if r["frame"] > 0)
    if not frames:
        raise ValueError(f"target {checks.shown_path(path, False)} holds only frame 0 of tool {tool!r}, which has no force yet")
    fps = None
    _refuse_shifted_or_repeated_times(path, tool, mine)
    if any(r["time"] != 0.0 for r in mine):
        # The rate from the last frame (the most digits), and every row held to it: frame k is
        # fitted at k / fps, so a row whose time says otherwise (times out of order, a clock
        # that did not start at 0, a log sampled unevenly) was compared at another time than
        # it was measured, and only the first row's time was ever read.
        last = max(mine, key=lambda r: r["frame"])
        fps = last["frame"] / last["time"] if last["time"] > 0 else None
        for r in sorted(mine, key=lambda r: r["row"]):
            if fps is None or abs(r["time"] * fps - r["frame"]) > 0.1:
                expected = "a time > 0" if fps is None else f"frame / fps = {r['frame']} / {fps:g} = {r['frame'] / fps:.6g} s"
                raise ValueError(f"{checks.shown_path(path, False)}, row {r['row']} (frame {r['frame']}, tool {tool!r}): time = {r['time']!r} is "
                                 f"not allowed: must be {expected} (the rate its last frame, {last['frame']}, gives; "
                                 "frame k is fitted at k / fps, so rows are one frame period apart from time 0)")
    return Target("forces", mine, frames, fps, path, tool=tool)


def _refuse_shifted_or_repeated_times(path: str, tool: str, rows: list[dict]) -> None:
    """Refuse a force log's ``rows`` (one tool's) where two frames give one time, or where
    every time is ``frame / fps`` plus one offset (a lab clock that did not start at 0): each
    had been refused at a row that was right, or as off a rate that no one measured (the
    last row's time over its frame), which said nothing of the cause."""
    by_frame = sorted(rows, key=lambda r: r["frame"])
    for a, b in zip(by_frame, by_frame[1:]):
        if a["time"] == b["time"] and any(r["time"] != 0.0 for r in rows):
            raise ValueError(f"{checks.shown_path(path, False)}, rows {a['row']} and {b['row']} (frames {a['frame']} and {b['frame']} of tool "
                             f"{tool!r}) are not allowed: both give time = {a['time']!r} s; each frame's row is one frame "
                             "period after the one before (frame k at k / fps)")
    first, last = by_frame[0], by_frame[-1]
    if last["frame"] == first["frame"] or last["time"] == first["time"]:
        return
    fps = (last["frame"] - first["frame"]) / (last["time"] - first["time"])
    offset = first["time"] - first["frame"] / fps
    if not (fps > 0.0 and abs(offset * fps) > 0.1):
        return  # time 0 at frame 0 (or no steady rate at all: said row by row after this)
    if all(abs((r["time"] - offset) * fps - r["frame"]) <= 0.1 for r in rows):
        cure = f"{'subtract' if offset > 0 else 'add'} {abs(offset):g} s {'from' if offset > 0 else 'to'} the time column"
        raise ValueError(f"{checks.shown_path(path, False)} is not allowed: its times for tool {tool!r} start at {first['time']:g} s (row "
                         f"{first['row']}, frame {first['frame']}), {abs(offset):g} s {'after' if offset > 0 else 'before'} "
                         f"frame / fps; frame k is fitted at k / fps from time 0 at frame 0, so {cure} (or, where the "
                         "frames are what is off, number the rows so that time 0 is frame 0)")


def _usd_run_target(path: str, body, frames, frames_name: str = "frames", body_name: str = "body") -> Target | None:
    """Positions from a ``warp-esph run`` USD file, or None when the file is not one."""
    try:
        from .render import UsdFrames, parse_frames  # noqa: PLC0415
    except ImportError:
        return None
    from .usd import NotAnOutput  # noqa: PLC0415

    try:
        data = UsdFrames(path)
    except NotAnOutput:
        return None  # no particles: a mesh file
    except ValueError as e:  # it does not open: a damaged file, not a mesh to try next
        raise ValueError(f"{e} (a damaged or foreign file?)") from None
    names = [n for n, _ in data.bodies]
    # A body is named as the scene names it (the prim name is a cleaned copy, '_1' added where two
    # clean alike): 'a_b' picked the prim of body 'a b' here and body 'a_b''s particles in the
    # loss (Target.particles), comparing one body's run with another's.
    given = [prim.GetCustomDataByKey("warp_esph:body_name") for _, prim in data.bodies]
    given = [g if isinstance(g, str) and g else n for g, n in zip(given, names)]
    if body is not None:
        if body in given:
            index = given.index(body)
        elif body in names:
            index = names.index(body)
        else:
            raise ValueError(f"{body_name} = {checks.shorten(body)!r} is not allowed: {checks.shown_path(path, False)} holds bodies {', '.join(given)}")
        body = given[index]
    chosen = parse_frames(frames, data.frames, frames_name) if frames is not None else [f for f in data.frames if f != data.frames[0]]
    if not chosen:
        raise ValueError(f"target {checks.shown_path(path, False)} holds only frame {data.frames[0]}, which says nothing about the material")
    observed = [(given[k], k) for k in range(len(data.bodies)) if body is None or k == index]
    pos = []
    counts = None
    for f in chosen:
        missing = next((name for name, k in observed if not data.has_sample(k, f)), None)
        if missing is not None:
            # USD answers between samples with the nearest one held, or interpolated: a body of
            # another program's file whose samples stopped (or skipped a frame) was fitted as
            # standing still there, or moving on a straight line, which nothing measured.
            raise ValueError(f"target {checks.shown_path(path, False)} is not allowed: body {missing!r} has no sample at frame {f} (the file's "
                             "frames are those of any body); a run's file holds every body at every frame")
        # In metres and world coordinates (UsdFrames.arrays), as render and export read them
        # and a mesh target is read (meshes.load_mesh).
        a = data.arrays(f)
        pts = a["points"].astype(np.float64)
        if body is not None:
            pts = pts[a["body"] == index]
        here = np.bincount(np.asarray(a["body"], dtype=np.int64), minlength=len(given)).tolist()
        if counts is None:
            counts, first = here, f
        elif here != counts and (body is None or here[index] != counts[index]):
            # Particles are compared by index: another program's file whose particle count
            # changes from frame to frame (or an empty sample) failed in numpy's stack,
            # 'all input arrays must have the same shape', naming neither file nor frame.
            k = index if body is not None else next(k for k in range(len(given)) if here[k] != counts[k])
            raise ValueError(f"target {checks.shown_path(path, False)} is not allowed: body {given[k]!r} has {counts[k]} particles at frame {first} "
                             f"and {here[k]} at frame {f}; a run's particles are the same in every frame")
        bad = np.flatnonzero(np.isinf(pts).any(axis=1))
        if bad.size:
            # Refused here, by file and frame: it was named 'targets at step 34', by the step it
            # was compared at. NaN is a missing marker (another program's gap, an occluded one),
            # left out of the loss as an .npz target's is; it was refused here as 'not finite'.
            raise ValueError(f"target {checks.shown_path(path, False)} is not allowed: at frame {f}, {bad.size} of its {len(pts)} positions are infinite "
                             f"(first: particle {bad[0]}{'' if body is None else f' of body {body!r}'}, "
                             f"{pts[bad[0]].tolist()}); a missing one (an occluded marker) is NaN")
        pos.append(pts)
    bodies = None if body is not None else list(zip(given, counts))
    # A rate the file does not author is USD's fallback (24), not a recorded one: it overrode
    # the scene's rate and refused --fps as "recorded at 24 fps".
    fps = data.fps if data.fps_authored else None
    return Target("positions", np.stack(pos), list(chosen), fps, path, body=body, bodies=bodies)


def write_fitted_usd(model: Model, path, frames: int, fps: float, dt: float, progress: bool = False) -> str | None:
    """Simulate ``model`` (with its current parameters) and write it to USD; None without usd support."""
    try:
        from .usd import UsdWriter  # noqa: PLC0415
    except ImportError:
        return None
    from .simulate import simulate  # noqa: PLC0415

    writer = UsdWriter(path, model, fps)
    simulate(model, frames, fps=fps, dt=dt, writer=writer, progress=progress)
    return writer.path
