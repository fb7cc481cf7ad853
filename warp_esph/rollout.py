"""Differentiable rollouts of any length, with optional segment checkpointing.

``Rollout(model, steps, dt, frames=[...], checkpoint_every=None)`` runs ``steps`` solver
steps from the model's initial state and records the positions at ``frames`` (step
indices in ``[0, steps]``). ``backward`` takes the gradient of a loss with respect to
those positions (or a loss object from ``warp_esph.losses``) and returns the gradients
with respect to every per-material parameter array of the model (``mu, lam,
yield_stress, flow_rate, hardening, pressure_stiffness, viscosity``) and to the initial
state (``x0, v0, F0, alpha0``)::

    model = builder.finalize(dtype=wp.float64, requires_grad=True)
    rollout = Rollout(model, steps=200, dt=1e-3, frames=[100, 200], checkpoint_every=50)
    positions = rollout.forward()                  # (2, n, 3) numpy
    value, grads = rollout.backward(loss)          # loss: a warp_esph.losses.Loss
    grads["yield_stress"], grads["v0"]             # per material, per particle

Memory
------
Without checkpointing (``checkpoint_every=None``) the forward pass is recorded on one
``wp.Tape`` with one ``State`` per step: memory grows with ``steps`` (about 0.95 kB
per particle per step in float64, see ``docs/fitting.md``); ``forward(taped=False)``, for a
loss value alone, runs the same steps unrecorded between two states (as the checkpointed
forward does); a rollout made with ``taped=False`` runs every forward so and is weighed for
it: two untaped states, whatever ``steps``, where a tape holds ``steps + 1`` taped states.
With ``checkpoint_every=S``
the forward pass runs untaped, keeping only the state fields (``x, v, F, alpha``) at the
start of every segment of ``S`` steps; ``backward`` re-runs each segment on a fresh tape,
last segment first, seeds its end state with the adjoint that the later segment left at
its start, and adds its parameter gradients into separate buffers before
``tape.zero()`` (which also zeroes the model's parameter ``.grad``; docs/method.md, Warp pitfall 6).
Memory is then ``steps / S`` light checkpoints plus ``S + 1`` taped states; time is one
extra forward pass. The re-run is bitwise identical to the first, so the checkpointed
gradient equals the full-tape one up to the order of floating-point sums (tested to
1e-9 relative in float64).

Per-particle parameters
-----------------------
The model design is one material per particle index: ``split_materials(model)`` returns
a copy of a model in which every particle (of the chosen bodies) has its own material
index, so each material parameter array becomes a per-particle field whose gradient
``backward`` returns particle by particle.

Reaction forces
---------------
A model with tools (``warp_esph.tools``) also has the reaction force of every tool in every
step recorded by ``forward`` (``step_forces()``: ``(steps, tools, 3)``, row ``k`` the force
during step ``k``, i.e. ``state[k + 1].reaction_force``). A loss may observe them
(``warp_esph.losses.ReactionForceLoss``): ``observations()`` hands the losses the frame
positions and, under the key ``FORCES``, the step forces; ``backward`` seeds the
gradient a loss returns under that key into each step's ``reaction_force`` adjoint (on the
full tape or in each re-run segment), so the gradient flows through the contact response
that produced the force.

The static colliders (``SceneBuilder.add_ground``, ``add_plane``, ``add_sphere_collider``,
``add_box_collider``) report theirs the same way, under their own keys: every step's
``state.collider_force`` rows (``step_collider_forces()``: ``(steps, rows, 3)``, names
``COLLIDER_NAMES``: ``plane<k>``, ``sphere<k>``, ``box<k>``, ``Solver.collider_reactions``)
under ``COLLIDER_FORCES``, whose gradient ``backward`` seeds into each step's
``collider_force`` adjoint.

The gradient with respect to ``x0`` holds the SPH rest density fixed (it is a constant
of the model, computed once from the model's own initial positions), and so the rest
configuration of the rest model that ``fit="auto"`` runs for purely elastic scenes
(``Model.auto_runs_rest``): there an ``x0`` off ``particle_x0`` starts a strained body.
"""

import contextlib
import dataclasses
import functools
import math
import types
from collections.abc import Mapping, Sequence

import numpy as np
import warp as wp

from . import checks
from ._types import type_set
from .model import Model, State, flowed_by_hardening, precision_problem
from .sim.solver import GUARD_NAMES, Solver, representable_dt, resolvable_dt
from .simulate import DivergenceMonitor, SimulationError, energy_growth

__all__ = ["Rollout", "split_materials", "PARAMETERS", "STATE_GRADIENTS", "FORCES", "TOOL_NAMES", "COLLIDER_FORCES",
           "COLLIDER_NAMES", "NonFiniteRollout", "DivergedRollout", "RolloutMemoryError"]

#: The per-material parameter arrays of a ``Model`` whose gradients ``backward`` returns.
PARAMETERS = Model.MATERIAL_FIELDS
#: The initial-state gradients ``backward`` returns, by key.
STATE_GRADIENTS = {"x0": "x", "v0": "v", "F0": "F", "alpha0": "alpha"}
#: Key of the step reaction forces (``(steps * tools,)`` vec3, row ``k * tools + c``) in
#: ``Rollout.observations()`` and of their gradient in what a loss returns.
FORCES = "reaction_force"
#: Key of the tool names in ``Rollout.observations()``.
TOOL_NAMES = "tool_names"
#: Key of the static colliders' step reaction forces (``(steps * rows,)`` vec3, row ``k * rows
#: + c``, ``Solver.collider_reactions``' order) in ``Rollout.observations()`` and of their
#: gradient in what a loss returns.
COLLIDER_FORCES = "collider_force"
#: Key of the static colliders' row names in ``Rollout.observations()``.
COLLIDER_NAMES = "collider_names"


@functools.cache
def _kernels(scalar):
    T = type_set(scalar)
    vec3 = T.vec3

    @wp.kernel(enable_backward=False, module="unique")
    def add_vec3(src: wp.array(dtype=vec3), dst: wp.array(dtype=vec3)):
        i = wp.tid()
        dst[i] = dst[i] + src[i]

    return types.SimpleNamespace(add_vec3=add_vec3)


def _differentiable_solver(model: Model) -> Solver:
    """A solver whose untaped steps run the same kernels as its taped ones (the fused ones
    where ``Solver.fast_under_tape``, the differentiable ones otherwise)."""
    solver = Solver(model)
    if not solver.fast_under_tape():
        solver.fused = False
    return solver


class NonFiniteRollout(SimulationError, FloatingPointError):
    """``Rollout.forward``'s run holds a non-finite position or velocity: it blew up (a ``dt``
    above ``Model.stable_dt()``, a parameter far out). Also a ``FloatingPointError``, so
    ``except FloatingPointError`` catches it as it catches ``fit``'s failed trials.

    ``step``: the first state (steps taken) found non-finite: exact without checkpointing;
    with ``checkpoint_every`` the first checked one (a checkpoint, a frame or the last state)
    after ``last_finite``, the last checkpoint found finite. ``particle``, ``body``: the first
    non-finite particle of that state and its body's name; ``frame``: None."""

    def __init__(self, message: str, *, step: int, particle: int, body: str, last_finite: int):
        super().__init__(message, step=step, particle=particle, body=body)
        self.last_finite = last_finite


class DivergedRollout(SimulationError, FloatingPointError):
    """A run that blew up while staying finite: its last state is past
    ``simulate.DivergenceMonitor``'s bounds from its initial state, or its kinetic +
    gravitational energy grew past ``simulate.energy_growth``'s limit (``Rollout.bounds_hit``,
    the test ``fit`` fails its trials on; ``simulate`` stops on the bounds, ``sweep`` fails a
    sample on the energy growth). Raised by the torch bridge,
    whose caller's optimiser would otherwise take a loss of positions 1e5 m out as a result;
    ``step``: the rollout's steps (the last state is what is checked), ``particle``, ``body``:
    the particle farthest past its bound and its body's name."""


def _first_non_finite(*arrays) -> int | None:
    """The first particle index at which any of the ``(n, 3)`` arrays is not finite, or None."""
    bad = np.zeros(len(arrays[0]), dtype=bool)
    for a in arrays:
        bad |= ~np.isfinite(a.reshape(len(a), -1)).all(axis=1)
    return int(np.argmax(bad)) if bad.any() else None


class _Checkpoint:
    """The state fields of one ``State`` (what a segment needs to restart), without grads."""

    def __init__(self, model: Model):
        n, T, dev = model.particle_count, model.types, model.device
        self.x = wp.zeros(n, dtype=T.vec3, device=dev)
        self.v = wp.zeros(n, dtype=T.vec3, device=dev)
        self.F = wp.zeros(n, dtype=T.mat33, device=dev)
        self.alpha = wp.zeros(n, dtype=T.scalar, device=dev)
        self.F_p = wp.zeros(n, dtype=T.mat33, device=dev)
        self.F_lo = wp.zeros(n, dtype=T.mat33, device=dev)
        self.x_lo = wp.zeros(n, dtype=T.vec3, device=dev)
        self.F_image = wp.zeros(n, dtype=T.mat33, device=dev)
        self.alpha_image = wp.zeros(n, dtype=T.scalar, device=dev)
        self.time = 0.0
        self.rest_model = None
        self.flowed = None

    def save(self, state):
        for name in State.STATE_FIELDS:
            wp.copy(getattr(self, name), getattr(state, name))
        self.time = state.time
        self.rest_model = state.rest_model
        self.flowed = state.flowed

    @property
    def nbytes(self) -> int:
        return sum(getattr(self, k).capacity for k in State.STATE_FIELDS)


def _zero_state_grads(state: State):
    for name in State.STATE_FIELDS:
        g = getattr(state, name).grad
        if g is not None:  # F_p has none without a comparison model
            g.zero_()


def state_nbytes(state: State) -> int:
    """Bytes held by a ``State``'s arrays and their gradients."""
    total = 0
    for value in vars(state).values():
        if isinstance(value, wp.array):
            total += value.capacity
            if value.grad is not None:
                total += value.grad.capacity
    return total


#: What a taped ``State`` holds besides its arrays' bytes (``state_nbytes``): the Python objects
#: of its some sixty arrays and gradients, 64.2-64.9 kB at 8 and 512 particles (measured with
#: ``tracemalloc``). Host memory, on a GPU too; so are the overheads below.
STATE_OVERHEAD = 64 * 1024
#: The tape's record of one taped step of a plain scene besides its state, and the step's own
#: records of its launches (``sim/replay.py``, kept with its ``state_out``; their argument
#: structs are built at the second run). Per launch, not per particle: a kept record is 5.2-5.5
#: kB whatever the particles (8 to 1000) and precision, and a step keeps one per kernel it
#: launches, taped and adjoint. On the ground a taped step holds 132.6-133.4 kB with its state
#: (36 and 256 particles, float32 and float64; ``tracemalloc`` after two forwards and
#: backwards, the difference of 16 and 4 steps; 74.2-74.8 kB before the records were kept):
#: 69.4 kB besides the state's 64, taken with a 15 % margin. What a scene adds to a step is
#: ``STEP_FEATURE_OVERHEADS``' (``tape_step_overhead``); static colliders, worlds and a
#: material's viscosity add nothing measurable (a taped step runs the SPH terms anyway).
TAPE_STEP_OVERHEAD = 80 * 1024
#: What a taped step holds besides ``TAPE_STEP_OVERHEAD`` for each feature of the scene (or of
#: the solver's choice of fit), measured as it (the step's total less the same scene's without
#: the feature; 36 and 256 particles, float32 and float64) and taken with a 10-20 % margin:
#:
#: - ``tools``: a tool set, whatever its tools (moving planes, boxes, spheres, capsules, meshes,
#:   keyframed, scripted, held still) and pinned sets: its samples' arrays each taped
#:   ``state_out`` keeps (``ToolSet.integrate``), the states' pose and reaction arrays and the
#:   pose launch's records: 49.9-50.7 kB a step for one to three tools, pins alone, or two
#:   worlds (a box tool plus the ground's images and a field: 234.8 kB a step, which the single
#:   208 kB of before left out).
#: - ``images``: the ground's images, their constitutive and hardening updates and reaction:
#:   41.9 kB.
#: - ``field``: each force field: 3.5 kB on the ground, 7.9-8.2 kB with the images (its
#:   reaction out of the floor besides).
#: - ``ghost_floor``: the ghosts' stencils, fit and hand-over (its pinned floor counts as
#:   ``tools``): 43.6 kB.
#: - ``comparison``: a comparison deformation model (``"rest"``: 10.6 kB, ``"additive"``: 6.6).
#: - ``curved``: the curvature-corrected fit: 15.4 kB (with the hourglass control 19.7; the
#:   rest-configuration model that ``fit="auto"`` runs for an elastic scene, both, 14.2).
#: - ``hourglass``: the hourglass control: 5.0 kB.
STEP_FEATURE_OVERHEADS = {"tools": 56 * 1024, "images": 48 * 1024, "field": 10 * 1024, "ghost_floor": 48 * 1024,
                          "comparison": 12 * 1024, "curved": 18 * 1024, "hourglass": 6 * 1024}
#: An untaped ``State``'s Python objects (the start's copy, a forward's two states): 42.7-43.2 kB.
UNTAPED_STATE_OVERHEAD = 48 * 1024
#: A checkpoint's Python objects: 16.8-17.0 kB at 8 and 512 particles.
CHECKPOINT_OVERHEAD = 20 * 1024
#: What a rollout's run holds besides, whatever its size: the replayed launches' records of
#: its states, and garbage the collector frees in its own time (0.1-1.8 MB beyond the
#: overheads above, measured at 8 and 64 particles and 50-3000 steps; an untaped run's did
#: not grow from 2000 to 20000 steps).
ROLLOUT_OVERHEAD = 2 * 1024 * 1024
#: Positions' worth of Warp arrays per observed step (``frames``): the rollout's copy, the
#: loss's target, its copy of the positions and their gradient, and the gradient handed back
#: (``fit.memory_estimate``; a ``PositionLoss``'s, measured).
FRAME_BUFFERS = 5


def tape_step_overhead(model: Model, fit: str | None = None, hourglass: float | None = None) -> int:
    """The host bytes a taped step of ``model`` holds besides its state's (``STATE_OVERHEAD``):
    ``TAPE_STEP_OVERHEAD`` and ``STEP_FEATURE_OVERHEADS``' terms for what the scene has, and for
    the fit and hourglass control a ``Solver(model, fit=fit, hourglass=hourglass)`` runs now
    (``Model.solver_choice``). A single figure for every scene left out a tool set's objects:
    a box tool with the ground's images and a field held 234.8 kB a step against 208 taken,
    and a ghost floor 227.1, while it over-counted a plain scene's 133 by half. A fit whose
    parameters turn a flowing scene elastic under ``fit="auto"`` runs the curvature-corrected
    fit from then on, which this choice at its start does not count: an elastic scene's step
    holds 147.4 kB against the 144 taken for a flowing one's (its own estimate is 168)."""
    terms = STEP_FEATURE_OVERHEADS
    total = TAPE_STEP_OVERHEAD
    if model.tools is not None:
        total += terms["tools"]
    if model.image_plane is not None:
        total += terms["images"]
    total += len(model.force_fields) * terms["field"]
    if model.ghost_floor is not None:
        total += terms["ghost_floor"]
    if model.uses_comparison_models:
        total += terms["comparison"]
    chosen, strength = model.solver_choice(fit, hourglass)
    if chosen == "curvature_corrected":
        total += terms["curved"]
    if strength > 0.0:
        total += terms["hourglass"]
    return total


class RolloutMemoryError(checks.Rebuilt, ValueError):
    """A rollout refused because it could not fit in memory (``_check_rollout_memory``). Its
    message names ``steps`` and ``checkpoint_every``, a Python caller's; a caller with other
    names for them (``fit``'s ``checkpoint_every="auto"``, ``warp-esph fit``'s options) words
    its own from ``reason`` (what would not fit: 'the rollout would need about 7.2 GiB, more
    than the 1 GiB available'), ``device``, ``steps``, ``segment`` (the refused one, None: a full
    tape), ``least`` (the segment that needs the least memory), ``least_gib`` (what that
    would need) and ``least_fits``. ``experiment``: the ``fit.Experiment`` refused, where a
    fit refused it (else None; None where pickled, as a worker process sends it back);
    ``worlds``: the copies of its scene a fit's ``worlds=True`` ran it as (else None)."""

    LOCAL = ("experiment",)

    def __init__(self, message: str, *, reason: str, device: str, steps: int, segment: int | None, least: int,
                 least_gib: float, least_fits: bool, experiment=None, worlds: int | None = None, taped: bool = True):
        super().__init__(message)
        self.reason, self.device, self.steps, self.segment = reason, device, steps, segment
        self.least, self.least_gib, self.least_fits = least, least_gib, least_fits
        self.experiment, self.worlds = experiment, worlds
        #: False: a ``Rollout(taped=False)`` was refused, which records no tape (its least is
        #: no checkpointing: ``least`` is ``steps``), so only fewer steps fit.
        self.taped = taped

    def reworded(self, message: str, experiment=None, worlds: int | None = None) -> "RolloutMemoryError":
        """The same refusal under another message (and the experiment refused, its worlds)."""
        return RolloutMemoryError(message, reason=self.reason, device=self.device, steps=self.steps,
                                  segment=self.segment, least=self.least, least_gib=self.least_gib,
                                  least_fits=self.least_fits,
                                  experiment=self.experiment if experiment is None else experiment,
                                  worlds=self.worlds if worlds is None else worlds, taped=self.taped)


class _RolloutMemory:
    """What a rollout of ``steps`` steps of ``model`` would hold (``need``) against the memory
    it has (``overrun``): on a GPU its arrays against the GPU's memory and the taped states'
    own overhead against the host's, on the CPU both against the host's. ``taped=False``: a
    rollout whose runs record no tape (``Rollout(taped=False)``): two untaped states hold it,
    whatever the segment. ``solver``: the one the rollout runs (None: the model's choice), whose
    fit and hourglass control weigh in a taped step's host memory (``tape_step_overhead``)."""

    def __init__(self, model: Model, steps: int, sizes=None, taped: bool = True, frames: int = 1,
                 solver: Solver | None = None):
        from .builder import _device_memory  # noqa: PLC0415
        from .fit import _state_bytes  # noqa: PLC0415 (fit imports this module)

        self.model, self.steps, self.taped, self.frames = model, steps, taped, frames
        self.have = _device_memory(model.device)
        self.cpu = model.device.is_cpu
        self.host = None if self.cpu or self.have is None else _device_memory(wp.get_device("cpu"))
        self.sizes = _state_bytes(model) if sizes is None else sizes
        #: A taped step's host bytes besides its state's: its tape's and launches' records,
        #: and what the scene's features (tools, images, ...) add to them.
        self.tape_step = tape_step_overhead(model, *(solver._asked if solver is not None else (None, None)))
        self.rows = len(getattr(model.tools, "row_names", ())) + model.world_count * (
            len(model.planes) + len(model.spheres) + len(model.boxes))

    def need(self, segment: int | None) -> tuple[int, int]:
        """``(bytes on the device, bytes of the host's besides)`` of the rollout with ``segment``."""
        from .fit import memory_estimate  # noqa: PLC0415

        steps = self.steps
        checkpoints = 0
        if not self.taped:
            segment = None
            taped, untaped = 0, 3  # the start's copy and the two states an untaped forward steps between
        elif segment is not None and segment < steps:
            taped, untaped, checkpoints = segment, 3, math.ceil(steps / segment)
        else:
            taped, untaped = steps, 1
        arrays = (memory_estimate(self.model, steps, segment, self.sizes, taped=self.taped, frames=self.frames)
                  + steps * self.rows * 3 * np.dtype(self.model.types.np_dtype).itemsize)  # the per-step force rows
        # The start's copy and a checkpointed run's two untaped states, the tape's records and the
        # checkpoints' objects had been left out: 0.3-0.9 x what 8 particles held (measured).
        # No share for cyclic garbage: a dropped tape is freed at once (its recorded adjoints
        # hold it weakly), where each segment's had been left to the collector (1.20 x).
        own = ((taped + 1 if taped else 0) * STATE_OVERHEAD + taped * self.tape_step
               + untaped * UNTAPED_STATE_OVERHEAD + checkpoints * CHECKPOINT_OVERHEAD + ROLLOUT_OVERHEAD)
        return (arrays + own, 0) if self.cpu else (arrays, own)

    def overrun(self, segment: int | None) -> int:
        """0 where the rollout with ``segment`` fits (or the memory is not known), 1 where it
        overruns the device's memory, 2 the host's (a GPU's run of few particles and many steps:
        12 GB of arrays and 64 GB of the host's, weighed together against a 24 GB GPU, refused
        a run that fits)."""
        if self.have is None:
            return 0
        d, h = self.need(segment)
        return 1 if d > self.have else 2 if self.host is not None and h > self.host else 0

    def least(self) -> int:
        """The segment that needs the least memory. ``sqrt(steps)`` was taken for it, which is
        the least where a taped state weighs what a checkpoint does; a taped state (its
        arrays, its own 64 kB and the tape's records of its step) outweighs a checkpoint several
        times, and the least lies below: for 8 particles and 1e5 steps 122 steps need 41.5 MiB,
        316 need 59.7 MiB (sqrt(steps) had a rollout that fit at the least refused 'even at the
        least'). On a GPU, of the memory it
        overruns most (the device's or the host's). Untaped: ``steps``, no checkpoints (its
        forward keeps none)."""
        if not self.taped:
            return self.steps
        have, host, steps = self.have, self.host, self.steps
        checkpoint = self.sizes[2] + (CHECKPOINT_OVERHEAD if self.cpu else 0)

        def worst(segment, smooth=False):
            d, h = self.need(segment)
            if smooth and segment < steps:  # ceil(steps / S) checkpoints taken as steps / S
                d -= (math.ceil(steps / segment) - steps / segment) * checkpoint
            if have is None or have <= 0:
                return d + h
            return max(d / have, h / host if host else 0.0)

        # The ceil(steps / S) checkpoints make the need wander by up to a checkpoint about its
        # smooth part (S + 1 taped states and steps / S checkpoints), which has one minimum; a
        # search of the need itself stopped in a dip beside the least (3545 for 611178402 steps
        # of 8 particles, 272 bytes above 3548's). The least lies where the smooth part is
        # within a checkpoint of its minimum: found by a search of the smooth part, then every
        # segment where the smooth part is below the best need seen.
        lo, hi = 1, max(steps - 1, 1)
        while hi - lo > 2:
            m1, m2 = lo + (hi - lo) // 3, hi - (hi - lo) // 3
            if worst(m1, True) < worst(m2, True):
                hi = m2
            else:
                lo = m1
        centre = min(range(lo, hi + 1), key=lambda s: worst(s, True))
        best, best_need = steps, worst(steps)  # a full tape
        for direction in (-1, 1):
            s = centre if direction < 0 else centre + 1
            while 1 <= s < steps and worst(s, True) <= best_need:
                need = worst(s)
                if need < best_need or (need == best_need and s < best):
                    best, best_need = s, need
                s += direction
        return best

    def reason(self, segment: int | None) -> str:
        """What would not fit of the rollout with ``segment`` (which overruns)."""
        where = self.overrun(segment)
        what = ("the rollout would need about {:.3g} GiB" if where == 1 else
                "the rollout's taped states would need about {:.3g} GiB of the host's memory besides their arrays on "
                "the device")
        return (f"{what.format(self.need(segment)[where - 1] / 2**30)}, more than the "
                f"{(self.have if where == 1 else self.host) / 2**30:.3g} GiB available")


def _check_rollout_memory(model: Model, steps: int, segment: int | None, checkpoint_every,
                          memory: _RolloutMemory | None = None) -> None:
    """Refuse, before anything is allocated, a rollout whose taped states and per-step force rows
    could not fit in the device's memory (``RolloutMemoryError``): ``Rollout(model, 10**6, dt)``
    of 8 particles allocated a million taped states (about 72 GiB) at its first forward, minutes
    on, until the machine killed it, where a checkpointed one needs kilobytes. On a GPU the
    arrays are weighed against its memory and the states' own overhead against the host's.
    ``memory``'s ``taped`` says which runs are weighed (``Rollout(taped=False)``: two states)."""
    m = _RolloutMemory(model, steps) if memory is None else memory
    where = m.overrun(segment)
    if not where:
        return
    if not m.taped:
        # Two states already: no segment needs less, only fewer steps (their force rows) do.
        reason = m.reason(segment)
        raise RolloutMemoryError(f"steps = {steps} is not allowed with taped = False on {model.device}: {reason}; give "
                                 "fewer steps", reason=reason, device=str(model.device), steps=steps, segment=None,
                                 least=steps, least_gib=m.need(None)[where - 1] / 2**30, least_fits=False, taped=False)
    least = m.least()
    least_where = m.overrun(least)
    # Where the least fits, what it needs of the memory the refused one overran.
    least_gib = m.need(least)[(least_where or where) - 1] / 2**30
    if not least_where:
        fix = f"give checkpoint_every ({least} needs the least, about {least_gib:.3g} GiB) or fewer steps"
    elif segment == least:
        fix = "give fewer steps"
    else:
        fix = f"give fewer steps (with checkpoint_every = {least}, the least, it would need about {least_gib:.3g} GiB)"
    reason = m.reason(segment)
    raise RolloutMemoryError(f"steps = {steps} is not allowed with checkpoint_every = {checkpoint_every!r} on "
                             f"{model.device}: {reason}; {fix}", reason=reason, device=str(model.device), steps=steps,
                             segment=segment, least=least, least_gib=least_gib, least_fits=not least_where)


def _step_indices(frames) -> list[int]:
    """``Rollout``'s ``frames`` as integers: whole numbers only (1.7 was truncated to step 1,
    '2' and True taken as steps), one level deep, each named where it is not one."""
    if isinstance(frames, (str, bytes, Mapping)) or not hasattr(frames, "__len__") and not np.isscalar(frames):
        raise ValueError(f"frames = {checks.shorten(frames)!r} is not allowed: must be step indices (a list of integers)")
    out = []
    for f in (np.asarray(frames).ravel().tolist() if isinstance(frames, np.ndarray) else
              [frames] if np.isscalar(frames) else list(frames)):
        if isinstance(f, (float, np.floating)) and math.isfinite(f) and float(f).is_integer():
            f = int(f)  # a whole number held as a float (np.arange(...) * 1.0)
        if isinstance(f, bool) or not isinstance(f, (int, np.integer)):
            raise ValueError(f"frames entry {checks.shorten(f)!r} is not allowed: must be an integer step index")
        out.append(int(f))
    return out


#: The tools' differentiable arrays (``tools.ToolSet``) whose gradients ``Rollout.backward``
#: sums over its passes and leaves on them.
TOOL_GRADIENTS = ("friction", "static_friction", "keyframe_times", "keyframe_positions", "keyframe_orientations",
                  "velocity", "angular_velocity")


#: The shape of one particle's entry of each initial field (``Rollout.forward``'s keywords).
_INITIAL_SHAPES = {"x0": (3,), "v0": (3,), "F0": (3, 3), "alpha0": ()}
#: The fields one particle's entry of which is taken for every particle: all but ``x0``,
#: which would put every particle at one point (refused below).
_BROADCAST = {"v0": "one velocity for every particle", "F0": "one for every particle",
              "alpha0": "one number for every particle"}


def initial_shapes(name: str, n: int) -> str:
    """The shapes ``check_initial`` takes for field ``name`` of ``n`` particles, as its
    messages say them."""
    full = (n, *_INITIAL_SHAPES[name])
    return f"{full}, or {_INITIAL_SHAPES[name]}: {_BROADCAST[name]}" if name in _BROADCAST else f"{full}"


def check_initial(model: Model, name: str, value) -> np.ndarray:
    """``value`` of the initial field ``name`` (``x0``, ``v0``, ``F0``, ``alpha0``) as an
    ``(n, ...)`` array of ``model``'s precision, or a ``ValueError`` naming it: not numbers,
    another shape, a non-finite value, one the model's precision cannot hold (checked as given,
    before the cast; an ``x0`` so far out that it does not resolve a hundredth of the spacing,
    as ``SceneBuilder`` refuses), an ``F0`` with ``det F <= 0``, a negative
    ``alpha0``, or ``x0`` with two particles that see each other at one place
    (``checks.coincident_points``, as ``SceneBuilder`` refuses them: all at one point, the
    step returned the start moved only by gravity). ``v0``, ``F0`` and ``alpha0`` may be one
    particle's entry (a ``(3,)`` velocity, a ``(3, 3)`` matrix, one number), taken for every
    particle, and then refused as that one value (``the one F0 given for every particle has
    det F = 0``), not as particle 0's; ``x0`` is one position per particle."""
    shape = _INITIAL_SHAPES[name]
    n = model.particle_count
    if isinstance(value, wp.array):
        value = value.numpy()
    value = checks.host_values(name, value)
    checks.real_numbers(name, value, f"must be numbers of shape {initial_shapes(name, n)}")
    try:
        v = np.asarray(value, dtype=np.float64)
    except checks.ARRAY_ERRORS:
        raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be numbers of shape "
                         f"{initial_shapes(name, n)}") from None
    one = None  # the one entry given for every particle, which its refusals name (not "particle 0")
    if name in _BROADCAST and (v.shape == shape or (name == "alpha0" and v.size == 1)):
        one = v.reshape(shape)
        v = np.broadcast_to(one, (n, *shape)).copy()
        shown = np.asarray(value, dtype=np.float64).reshape(shape).tolist()  # as given, not rounded to the model's precision
        given = f"{name} = {checks.shorten(shown)!r} is not allowed: the one {name} given for every particle"
    if not np.isfinite(v).all():  # a NaN start ran to NaN positions, returned as a result
        if one is not None:
            raise ValueError(f"{given} has non-finite values")
        raise ValueError(f"{name} is not allowed: it has non-finite values (first at index "
                         f"{int(np.argmax(~np.isfinite(v).reshape(v.shape[0] if v.ndim else 1, -1).all(axis=1)))})")
    if v.shape != (n, *shape):
        raise ValueError(f"{name} with shape {v.shape} is not allowed: must be {initial_shapes(name, n)}")
    # Checked as given, before the cast to the model's precision: a float64 v0 of 1e39 m/s
    # was refused as 'non-finite values' in float32, and x0 of 6e37 m ran into the
    # neighbour search's OverflowError.
    T = model.scalar.__name__
    big = float(np.abs(v).max()) if v.size else 0.0
    why = precision_problem(big, model.scalar) if big > 1.0 else None
    if why is not None:
        if one is not None:
            raise ValueError(f"{given} exceeds {T}: {why}")
        raise ValueError(f"{name} is not allowed in {T}: its largest value {big:g} {why}")
    if name == "x0" and v.size:
        # As SceneBuilder refuses a scene so far out that the precision does not resolve the
        # spacing (the lattice falls onto fewer points, every fit ill-conditioned).
        i = int(np.argmax(np.abs(v).max(axis=1)))
        eps = float(np.finfo(model.types.np_dtype).eps)
        if big * eps > 1e-2 * model.spacing:
            raise ValueError(f"x0 is not allowed in {T}: particle {i} lies {big:.3g} m from the origin, where {T} "
                             f"resolves {big * eps:.2g} m, more than a hundredth of the spacing {model.spacing:g}; move "
                             f"the start nearer the origin or use dtype=float64")
    v = v.astype(model.types.np_dtype)
    # An F that is no deformation (det <= 0: zero, or a reflection) and a negative
    # accumulated plastic strain ran without a word.
    if name == "F0" and not (np.linalg.det(v.astype(np.float64)) > 0.0).all():
        bad = int(np.argmax(~(np.linalg.det(v.astype(np.float64)) > 0.0)))
        det = f"det F = {np.linalg.det(v[bad].astype(np.float64)):.3g}, and a deformation gradient has det F > 0"
        if one is not None:
            raise ValueError(f"{given} has {det}")
        raise ValueError(f"F0 is not allowed: particle {bad} has {det}")
    if name == "alpha0" and (v < 0).any():
        if one is not None:
            raise ValueError(f"{given} is negative; the accumulated plastic strain is >= 0")
        raise ValueError(f"alpha0 is not allowed: particle {int(np.argmax(v < 0))} has {float(v[v < 0][0]):g}; "
                         "the accumulated plastic strain is >= 0")
    if name == "x0":
        # In the model's precision: two places float64 tells apart may be one in float32.
        # Worlds share space by design, and so may bodies that do not interact
        # (``bodies_interact=False``): each group is checked alone.
        if model.bodies_interact:
            groups = [(int(model.world_start[w]), int(model.world_start[w + 1])) for w in range(model.world_count)]
        else:
            groups = [(b.start, b.start + b.count) for b in model.bodies]
        count = 0
        for lo, hi in groups:
            count, i = checks.coincident_points(v[lo:hi].astype(np.float64), model.spacing)
            if count:
                i += lo
                break
        if count:
            raise ValueError(f"x0 is not allowed: {count} particles coincide with another (first: particle {i} at "
                             f"{np.round(v[i].astype(np.float64), 6).tolist()}); each particle needs a place of its "
                             "own, as SceneBuilder requires")
    return v


class Rollout:
    """A differentiable run of ``steps`` steps of ``dt`` observing positions at ``frames``.
    ``steps``, ``frames``, the checkpoint segments and ``taped`` are fixed once made (setting
    one is refused), as are ``model`` and ``solver``; ``dt`` (checked when set), the model's
    gravity and the solver's settings may be set between runs (``run_settings``; not between a
    forward and its backward).

    - ``model``: finalized with ``requires_grad=True`` (float64 to validate gradients).
    - ``frames``: step indices in ``[0, steps]`` whose positions ``forward`` returns and
      whose position gradients ``backward`` takes, in that order; default ``[steps]``. Increasing,
      each once (a set is taken sorted).
    - ``checkpoint_every``: ``None`` records the whole run on one tape; an integer ``S``
      keeps only segment starts every ``S`` steps and re-runs segments in ``backward``. A
      rollout whose taped states would not fit in the device's memory is refused here.
    - ``solver``: a ``Solver`` of ``model`` (default: a new one). It and its hash grid are
      kept for the rollout's lifetime. Its fused fast path (``solver.fused``) is switched
      off unless ``solver.fast_under_tape()`` (then a taped step runs the fused kernels too),
      so an untaped forward step is the step that a tape records. Set ``hand_adjoints``
      before passing it. A forward after ``model.particle_x0`` changed has it take the rest
      configuration (its rest model's and hourglass control's) as it is now, as a new rollout's
      solver does: the start is the new ``particle_x0``.
    - ``taped``: False for a rollout run for loss values alone (a Gauss-Newton fit's): every
      ``forward`` runs as ``forward(taped=False)`` (a ``forward(taped=True)`` and ``backward``
      are refused), and its memory is weighed as what those runs hold, two untaped states and
      the force rows, not ``steps + 1`` taped states: a run whose tape would not fit is not
      refused. Not with ``checkpoint_every`` (it keeps no checkpoints).
    """

    #: Set once, by ``__init__``: the taped states, frame slots, force rows, segments and memory
    #: check were made for them, and for the model and solver (``dt``, read by each step, may
    #: be set between runs).
    _FIXED = ("steps", "frames", "segment", "checkpointing", "segments", "taped", "model", "solver")

    def __setattr__(self, name, value):
        # A steps or frames set after __init__ was taken without a word and ran half of it:
        # frames = (3,) on a rollout of frames (2, 3) still returned both; steps = 5 ran five
        # steps and returned the third's positions. Another model or solver ran on states,
        # counters and a hash grid made for the first.
        if name in self._FIXED and name in self.__dict__:
            raise ValueError(f"Rollout.{name} = {checks.shorten(value)!r} is not allowed: this rollout's states, frame "
                             f"slots and force rows were made for {name} = {checks.shorten(getattr(self, name))!r}; make a "
                             "new Rollout")
        super().__setattr__(name, value)

    @property
    def dt(self) -> float:
        """The step (s) every run takes. Checked when set (``ValueError`` unless positive,
        representable in the model's precision and short enough for it to resolve a step's
        fall, ``sim.solver.resolvable_dt``); a step above ``Model.stable_dt`` is warned of
        by the solver's step, as any run's. Set it between runs, not between a forward and its
        backward (``backward`` refuses that run)."""
        return self._dt

    @dt.setter
    def dt(self, value):
        # Any value was taken (0, -1, NaN, a string) and refused only by the next step, or by
        # repr as a format error.
        self._dt = resolvable_dt(self.model, representable_dt(self.model.scalar, value))

    def __init__(self, model: Model, steps: int, dt: float, frames: Sequence[int] | None = None,
                 checkpoint_every: int | None = None, solver: Solver | None = None, taped: bool = True):
        if not isinstance(model, Model):
            raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph.Model")
        if not model.requires_grad:
            raise ValueError("model is not allowed: it was finalized without requires_grad=True, so its "
                             "parameter arrays have no gradients; use builder.finalize(requires_grad=True)")
        self.model = model
        self.steps = checks.positive_int("steps", steps)
        self.dt = dt
        if frames is None:
            frames = [self.steps]
        unordered = isinstance(frames, (set, frozenset))
        frames = _step_indices(frames)
        if unordered:
            frames = sorted(frames)
        if not frames:
            raise ValueError("frames = [] is not allowed: give at least one step index")
        bad = [f for f in frames if not 0 <= f <= self.steps]
        if bad:
            raise ValueError(f"frames = {bad!r} are not allowed: step indices must be in [0, steps = {self.steps}]")
        if any(a >= b for a, b in zip(frames, frames[1:])):
            # They were sorted and made unique without a word: frames=[300, 100] returned step 100's
            # positions first and took backward's [g300, g100] as [g100, g300], a gradient of
            # another loss; [2, 2] returned one frame.
            raise ValueError(f"frames = {checks.shorten(frames)!r} is not allowed: give increasing step indices, each once "
                             f"(forward returns their positions, and backward takes their gradients, in that order)")
        self.frames = tuple(frames)
        if checkpoint_every is None:
            self.segment = self.steps
        else:
            self.segment = min(checks.positive_int("checkpoint_every", checkpoint_every), self.steps)
        self.checkpointing = self.segment < self.steps
        if not isinstance(taped, bool):
            raise ValueError(f"taped = {checks.shorten(taped)!r} is not allowed: must be True or False")
        if not taped and checkpoint_every is not None:
            raise ValueError(f"checkpoint_every = {checks.shorten(checkpoint_every)!r} is not allowed with taped = False: an untaped "
                             "rollout keeps no checkpoints (nothing goes back through it); give checkpoint_every = None")
        #: Whether this rollout's runs may record a tape (``taped=False``: loss values alone).
        self.taped = taped
        if solver is not None and (not isinstance(solver, Solver) or solver.model is not model):
            raise ValueError("solver is not allowed: it must be a warp_esph.Solver built for this model")
        _check_rollout_memory(model, self.steps, self.segment if self.checkpointing else None, checkpoint_every,
                              _RolloutMemory(model, self.steps, taped=taped, frames=len(self.frames), solver=solver))
        if solver is None:
            solver = _differentiable_solver(model)
        # The untaped forward of a checkpointed rollout must compute exactly what the
        # taped re-run of ``backward`` records: the fused kernels only where a tape runs them too.
        if getattr(solver, "fused", False) and not solver.fast_under_tape():
            solver.fused = False
        self.solver = solver
        self.solver.check_dt(self.dt)
        self._k = _kernels(model.scalar)
        T, n, dev = model.types, model.particle_count, model.device
        #: Positions at each frame after ``forward`` (Warp arrays, no gradients).
        self.frame_positions = [wp.zeros(n, dtype=T.vec3, device=dev) for _ in self.frames]
        self._frame_slot = {f: k for k, f in enumerate(self.frames)}
        tools = getattr(model, "tools", None)
        # With worlds one row per world and tool, named "w<w>/<name>" (tools.ToolSet.row_names).
        self.tool_names = [] if tools is None else list(tools.row_names)
        #: Every step's reaction force of every tool after ``forward`` (no gradients).
        self.forces = (wp.zeros(self.steps * len(self.tool_names), dtype=T.vec3, device=dev)
                       if self.tool_names else None)
        from .sim.integrate import static_collider_names  # noqa: PLC0415

        #: The static colliders' row names (``Solver.collider_reactions``), and every step's
        #: force of each after ``forward`` (no gradients; None without static colliders).
        self.collider_names = static_collider_names(model)
        self.collider_forces = (wp.zeros(self.steps * len(self.collider_names), dtype=T.vec3, device=dev)
                                if self.collider_names else None)
        # (start step, number of steps) of each segment.
        self.segments = [(s, min(self.segment, self.steps - s)) for s in range(0, self.steps, self.segment)]
        self._initial = model._scratch_state()  # each forward's start is loaded into it (_load_initial)
        self._states: list[State] | None = None  # taped states: whole run, or one segment
        self._final: State | None = None  # the latest forward's last state (final_state)
        self._pair: list[State] | None = None  # untaped ping-pong pair (checkpointed or taped=False forward)
        self._checkpoints: list[_Checkpoint] = []
        self._tape: wp.Tape | None = None
        self._forward_done = False
        self._scripted_poses = None  # the Scripted poses the latest forward evaluated (_scripted_log)
        self._force_grads = None
        self._collider_grads = None
        #: Incremented by every ``forward``: lets callers (the torch wrapper) tell runs apart.
        self.forward_count = 0
        # The solver's guard counters as the latest forward began (a copy on the device, so the
        # forward waits for nothing), and the particle-steps each guard held in its forwards.
        self._counts_before = wp.zeros_like(self.solver.scratch.counters)
        self._forward_guards = np.zeros(self._counts_before.shape[0], dtype=np.int64)
        self._last_guards = np.zeros_like(self._forward_guards)
        #: Each world's loss term at the last ``backward`` with a ``losses.WorldLoss`` (else None).
        self.world_values = None
        # The observations, the loss's gradient with respect to them and its value at the last
        # backward given a loss (loss_roundoff), else None.
        self._read = None

    # ----------------------------------------------------------------- set-up
    def set_parameters(self, values: Mapping[str, object]):
        """Assign per-material parameter arrays (``{name: array of n_materials}``); the solver
        follows them at its next step (whether SPH runs, the stable ``dt``)."""
        self._set_parameters(values)

    def _set_parameters(self, values: Mapping[str, object], current: dict[str, np.ndarray] | None = None
                        ) -> dict[str, np.ndarray]:
        """``set_parameters``, given ``current`` (``get_parameters``' answer, as the arrays hold
        now; default: read here); returns every parameter's values as the arrays then hold
        them. An array whose values are unchanged is not written: the torch bridge sets every
        value it is given at each forward, and restores the model's after a backward."""
        m = self.model
        if not isinstance(values, Mapping):
            raise ValueError(f"values = {checks.shorten(values)!r} is not allowed: must be a mapping "
                             "{parameter name: one value per material}")
        new = {}
        for name, value in values.items():
            if name not in PARAMETERS:
                raise ValueError(f"parameter {checks.shorten(name)!r} is not allowed: must be one of {', '.join(PARAMETERS)}")
            arr = getattr(m, name)
            value = checks.host_values(name, value)
            try:
                if np.asarray(value).dtype.kind not in "iuf":  # True read as 1 Pa, "5" as 5 Pa
                    raise TypeError
                v = np.asarray(value, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be numbers, one per "
                                 "material") from None
            if v.size == 1 and arr.shape[0] > 1:
                v = np.full(arr.shape[0], v[0], dtype=v.dtype)
            if v.shape[0] != arr.shape[0]:
                raise ValueError(f"{name} has {v.shape[0]} values, the model {arr.shape[0]} materials")
            if not (np.isfinite(v) | ((v == np.inf) if name == "yield_stress" else False)).all():
                # yield_stress = inf is an elastic material's (a torch backward restoring every
                # parameter of one failed on it)
                raise ValueError(f"{name} = {checks.shorten(v)!r} is not allowed: values must be finite"
                                 + (" (or inf: no yield)" if name == "yield_stress" else ""))
            # Checked as given: 1e39 Pa cast to float32 first was refused as inf ('values must be
            # finite'), and 1e-50 became 0 without a word.
            for k, one in enumerate(v.tolist()):
                why = precision_problem(one, m.scalar)
                if why is not None:
                    raise ValueError(f"{name} = {one:g} (material {k}) is not allowed in {m.scalar.__name__}: {why}")
            new[name] = v.astype(m.types.np_dtype)
        current = self.get_parameters() if current is None else current
        after = {**current, **new}
        # Each material's checks, now that the values are given (a negative mu was refused
        # only at the next step, as "the model's parameter arrays").
        m._check_parameter_values(np.stack([after[f] for f in m.MATERIAL_FIELDS]), "values")
        for name, v in new.items():
            if not np.array_equal(v, current[name]):
                getattr(m, name).assign(v)
        return after

    def get_parameters(self) -> dict[str, np.ndarray]:
        """The per-material parameter arrays' values, ``{name: array of n_materials}`` (copies),
        read in one transfer (``Model._read_parameters``; one per array had each wait for the
        device)."""
        rows = self.model._read_parameters()
        return {name: rows[k] for k, name in enumerate(self.model.MATERIAL_FIELDS)}

    def _load_initial(self, initial_state, given: Mapping[str, np.ndarray]):
        """``given``: the starts ``check_initial`` answered, by name."""
        init = self._initial
        m = self.model
        if initial_state is not None:
            if not isinstance(initial_state, State) or initial_state.particle_count != m.particle_count:
                raise ValueError("initial_state is not allowed: it must be a warp_esph.State of this model")
            checks.same_state(m, "initial_state", initial_state)  # its precision and device too
            init.assign(initial_state)
        else:
            m.check_start(velocities="v0" not in given)  # a given v0 replaces particle_v0
            init.x.assign(m.particle_x0)
            init.v.assign(m.particle_v0)
            eye = np.tile(np.eye(3, dtype=m.types.np_dtype), (m.particle_count, 1, 1))
            init.F.assign(eye)
            init.F_lo.zero_()
            init.x_lo.zero_()
            init.F_p.assign(eye)
            init.alpha.zero_()
            # The floor images' own F and hardening too (a new state's I and 0): kept, a forward
            # after one from an initial_state started from that state's images (0.25 mm off in
            # 5 steps of a block pressed onto them).
            init.F_image.assign(eye)
            init.alpha_image.zero_()
            init.time = 0.0
            init.rest_model = None
            init.flowed = False
        for name, v in given.items():
            getattr(init, STATE_GRADIENTS[name]).assign(v)
            if name in ("x0", "F0"):
                getattr(init, STATE_GRADIENTS[name] + "_lo").zero_()  # the whole value is given
        if "F0" in given:
            # A given F is the body's strain: the rest model takes it over as it takes over an
            # incremental step's (State.rest_model False: F_p = F0^-1 G(x0)). As a new state's it
            # set only the first step's stress, the next F being the rest fit of the positions:
            # a block released from a 20 % stretch kept 2 % of its recoil's kinetic energy.
            init.rest_model = False
        if "alpha0" in given:
            # A given hardening says whether the body has flowed, read here on the host: where it
            # has, the first step of every forward need not read alpha back from the device (a
            # False is read there again, as any state's: State.has_flowed).
            init.flowed = flowed_by_hardening(given["alpha0"])

    def _taped_states(self, count: int) -> list[State]:
        m, solver = self.model, self.solver
        # Whether this rollout's solver may run the rest model now: its own fit, not the model's
        # (Model.state asks the model's, so a Solver(fit="auto") on a model built with another
        # fit was given states whose F_p had no gradient).
        rest = m.uses_comparison_models or (solver._auto and m.auto_runs_rest(solver._asked[0]))
        if self._states is not None and self._states[0].F_p.grad is None and rest:
            # Made while the model could flow, so without F_p's gradient (Model.state), which a
            # step handing F over to the rest model now needs (Solver.step refused it, telling
            # the caller to make states that only the rollout makes).
            self._states = None
        if self._states is None or len(self._states) < count:
            self._states = [m._scratch_state(requires_grad=True) for _ in range(count)]
            if rest:
                for state in self._states:
                    state.F_p.requires_grad = True
        return self._states

    # ---------------------------------------------------------------- forward
    def forward(self, x0=None, v0=None, *, F0=None, alpha0=None, initial_state: State | None = None,
                check: bool = True, taped: bool | None = None) -> np.ndarray:
        """Run the rollout; returns the positions at ``frames`` as an ``(frames, n, 3)`` array.

        A run that blew up to a non-finite position (at a frame, or in the last state) or
        velocity (in the last state) raises ``NonFiniteRollout`` (a ``SimulationError`` and a
        ``FloatingPointError``) naming the first non-finite step, particle and body and the
        stable step: its NaN positions were returned as a result, and a loss of them went on
        as NaN. The run stays readable (``positions()``, ``final_state()``); ``check=False``
        returns it as it is (``fit`` does, and fails such a trial itself). Only non-finite
        values are caught: a run that blew up while staying finite (particles far away) is
        returned as a result; ``simulate.DivergenceMonitor``'s bounds and
        ``simulate.energy_growth`` catch it (``bounds_hit``: ``fit`` fails its trials on them,
        the torch bridge raises ``DivergedRollout``). The check reads the last state's
        velocities (and its positions where ``steps`` is not a frame) once per forward.

        The initial state is the model's (``particle_x0``, ``particle_v0``, F = I, alpha =
        0, the floor images' too, whatever an earlier forward started from), or ``initial_state``'s fields, with ``x0, v0, F0, alpha0`` overriding: ``x0``
        ``(n, 3)``; ``v0`` ``(n, 3)`` or one ``(3,)`` velocity for every particle; ``F0``
        ``(n, 3, 3)`` or one ``(3, 3)``; ``alpha0`` ``(n,)`` or one number. Their gradients
        (``backward``) are per particle whichever was given (sum them for a shared value).
        A given ``F0`` is the body's strain on the rest model too (``Model.auto_runs_rest``: the
        start is handed over as an incremental step's, ``State.rest_model`` False, unless an
        ``alpha0`` > 0 says the body has flowed: then the incremental composition runs,
        ``State.flowed``); without it the rest model starts from the fit of the positions.

        ``taped=False`` runs for a loss value alone: the same steps, in the same bits, with no
        tape recorded, between two states as the checkpointed forward runs (a Gauss-Newton
        fit of 125 particles, all its runs so, in 0.73 of the time: docs/performance.md,
        "Loss-only fit evaluations without a tape"); a ``backward`` then needs a taped
        ``forward`` first. With ``checkpoint_every`` the forward records no tape either way
        (``backward`` re-runs the segments on tapes). None (the default): the rollout's own
        ``taped``, True unless it was made with ``taped=False``.
        """
        given = {name: check_initial(self.model, name, value) for name, value in
                 (("x0", x0), ("v0", v0), ("F0", F0), ("alpha0", alpha0)) if value is not None}
        if not isinstance(check, bool):
            raise ValueError(f"check = {checks.shorten(check)!r} is not allowed: must be True or False")
        if taped is None:
            taped = self.taped
        elif not isinstance(taped, bool):
            raise ValueError(f"taped = {checks.shorten(taped)!r} is not allowed: must be True or False (or None: the rollout's own)")
        return self._forward_checked(given, initial_state, check, taped)

    def _forward_checked(self, given: Mapping[str, np.ndarray], initial_state: State | None = None,
                         check: bool = True, taped: bool = True) -> np.ndarray:
        """``forward`` from starts ``check_initial`` has answered (``{name: its array}``), not
        checked again: the torch bridge checks each start once, before it sets the parameters,
        and re-runs a forward for its backward from the same arrays (x0's check of coincident
        particles took 17 ms at 64k particles, up to three times an iteration)."""
        if taped and not self.taped:
            # Its memory was weighed for untaped runs: a tape of every step may not fit.
            raise ValueError("taped = True is not allowed: this rollout was made with taped = False (its memory weighed "
                             "for runs without a tape); make it with taped = True to run taped")
        # Its start is particle_x0 as it is now, so its rest configuration too, as a new
        # rollout's (Solver._take_rest_configuration).
        self.solver._take_rest_configuration()
        self._load_initial(initial_state, given)
        self._tape = None
        counters = self.solver.scratch.counters
        wp.copy(self._counts_before, counters)
        with self._scripted_log() as log:
            self._run(taped)
        # A checkpointed backward re-runs every step and its solver counts them again (work
        # done); the run's own counts are the forward's, taken here (a fit's history gave a
        # checkpointed fit twice the guarded particle-steps of the same fit on a full tape).
        self._last_guards = counters.numpy().astype(np.int64) - self._counts_before.numpy()
        self._forward_guards += self._last_guards
        # The Scripted tools' poses this forward evaluated (``{(tool, t): (position, quaternion)}``;
        # None without Scripted tools), against which a re-run is checked.
        self._scripted_poses = log
        self._forward_done = True
        self._forward_inputs = self._inputs()
        self.forward_count += 1
        out = self.positions()
        if check:
            self._check_finite(out)
        return out

    @contextlib.contextmanager
    def _scripted_log(self):
        """Inside, the Scripted tools' poses evaluated are logged (``ToolSet._pose_log``); yields
        the log, or None where the model has no Scripted tool."""
        tools = self.model.tools
        if tools is None or not tools._scripted:
            yield None
            return
        held, log = tools._pose_log, {}
        tools._pose_log = log
        try:
            yield log
        finally:
            tools._pose_log = held

    def _check_scripted(self, log, then, who: str = "backward()", since: str = "forward()"):
        """Refuse (``RuntimeError``) a re-run whose Scripted poses ``log`` are not those ``then``
        of the run it re-runs: a Scripted motion is called again by a checkpointed backward and
        by the torch bridge's re-run of a forward, and one changed since (a closure's speed)
        gave the gradient of another trajectory without a word."""
        if log is None or then is None:
            return
        for (k, t), pose in sorted(log.items(), key=lambda item: (item[0][1], item[0][0])):  # the earliest named
            was = then.get((k, t))
            if was != pose:
                old = "none" if was is None else f"position {list(was[0])}, quaternion {list(was[1])}"
                raise RuntimeError(
                    f"{who} is not allowed: the Scripted motion of {self.model.tools._owner(k)} gives position "
                    f"{list(pose[0])}, quaternion {list(pose[1])} at t = {t:g} s, where {since} had {old}; it must give "
                    "the same pose when asked again at the same t (set it back, or run the forward again)")

    def _run(self, taped: bool):
        """The steps of ``_forward_checked`` from the loaded initial state."""
        tools_ = self.model.tools
        # The work the tools do on the bodies over the run (bounds_hit), per reaction row.
        self._work = None if tools_ is None else wp.zeros(len(tools_.row_names), dtype=wp.float64, device=self.model.device)
        if self.checkpointing or not taped:
            # A loss value alone needs no tape: the same steps, unrecorded, on the two states the
            # checkpointed forward steps between (the very bits a taped run gives; a step between
            # the same two states also repacks fewer launch arguments, docs/performance.md).
            prior = getattr(self.solver, "tool_work", None)
            self.solver.tool_work = self._work  # untaped steps add their work as they go
            try:
                self._forward_untaped()
            finally:
                self.solver.tool_work = prior
        else:
            states = self._taped_states(self.steps + 1)
            states[0].assign(self._initial)
            tape = wp.Tape()
            with tape, self.solver.caller_checks():
                for k in range(self.steps):
                    self.solver.step(states[k], states[k + 1], self.dt)
            self._tape = tape
            for f, out in zip(self.frames, self.frame_positions):
                wp.copy(out, states[f].x)
            for k in range(self.steps):
                self._store_forces(k, states[k + 1])
                if self._work is not None:  # each step's state holds its reactions and tool motion, off the tape
                    tools_.launch_work(states[k + 1], self._work)
            self._final = states[self.steps]

    def first_non_finite(self, particles=None, positions: np.ndarray | None = None) -> tuple[int, int, int] | None:
        """``(step, particle, last_finite)`` of the latest forward's first non-finite position
        or velocity among ``particles`` (a boolean mask; None: all), or None where the frames
        and the last state are finite there. ``step``: the first state (steps taken) found
        non-finite, exact with a full tape; otherwise the first checked one (a checkpoint, a
        frame or the last state) after ``last_finite``, the last full state found finite.
        ``positions``: the frames' positions where the caller has read them already."""
        if positions is None:
            positions = self.positions()
        keep = slice(None) if particles is None else np.asarray(particles, dtype=bool)

        def first(*arrays):
            # The mask's own first: a model of worlds fails the world that blew up alone.
            if particles is None:
                return _first_non_finite(*arrays)
            p = _first_non_finite(*(a[keep] for a in arrays))
            return None if p is None else int(np.flatnonzero(keep)[p])

        final = self._final
        last = [final.v.numpy()]
        if self.steps not in self._frame_slot:
            last.append(final.x.numpy())
        if np.isfinite(positions[:, keep]).all() and all(np.isfinite(a[keep]).all() for a in last):
            return None
        # The failure path only: find the first non-finite state among those kept.
        known = []  # (steps taken, its first non-finite particle or None, whether x and v were read)
        if self._tape is not None:  # a full tape keeps every state
            for k in range(1, self.steps + 1):
                p = first(self._states[k].x.numpy(), self._states[k].v.numpy())
                known.append((k, p, True))
                if p is not None:
                    break
        else:
            known += [(start, first(ck.x.numpy(), ck.v.numpy()), True)
                      for (start, _), ck in zip(self.segments, self._checkpoints)]
            known += [(f, first(positions[j]), False) for j, f in enumerate(self.frames)]
            known.append((self.steps, first(*last, positions[-1]) if self.steps in self._frame_slot
                          else first(*last), True))
        step, p = min((k, p) for k, p, _ in known if p is not None)
        last_finite = max([0] + [k for k, p, full in known if p is None and full and k < step])
        return step, p, last_finite

    def bounds_hit(self, checked=None) -> tuple[str, int] | None:
        """``(why, particle)`` where the last state of the latest forward is past
        ``simulate.DivergenceMonitor``'s bounds from the run's initial state, or its kinetic +
        gravitational energy grew past ``simulate.energy_growth``'s limit (the test ``sweep``
        fails its samples on; the stored elastic energy the monitor finds at the start counts
        as energy the run may release), among the particles of the boolean mask ``checked``
        (None: all), else None: a blow-up that stayed finite. ``fit`` fails its trials on it;
        the torch bridge raises on it. It reads the initial and last states once (no step's), and
        the work the tools did over the latest forward (``simulate.ToolWork``'s sum, made by its
        steps), which both tests count as the energy the tools gave."""
        monitor = DivergenceMonitor(self.model, self._initial, particles=checked, solver=self.solver)
        final = self.final_state()
        x, v = final.x.numpy(), final.v.numpy()
        work = self._work_done(checked)
        hit = monitor.check(x, v, self.steps * self.dt, work)
        if hit is not None:
            return hit
        # A Scripted tool turns the bounds off: a box beside one, 5 x past its stable step, was
        # a fit's trial and a torch result at 1e35 J, where a sweep failed the same run.
        init = self._initial
        return energy_growth(self.model, init.x.numpy(), init.v.numpy(), x, v, t0=float(init.time), dt=self.dt,
                             steps=self.steps, particles=checked, stored=getattr(monitor, "e_elastic", 0.0), work=work,
                             solver=self.solver, state=init)

    def _work_done(self, checked=None) -> float | None:
        """The work (J) the tools and pinned sets did in the latest forward on the worlds of the
        particles ``checked`` (None: all), or None where it was not counted."""
        work = getattr(self, "_work", None)
        if work is None:
            return None
        rows = work.numpy()
        if checked is not None and self.model.world_count > 1:
            worlds = np.unique(self.model.world_of_particle[np.asarray(checked, dtype=bool)])
            rows = rows[np.isin(np.arange(len(rows)) // self.model.tools.count, worlds)]
        return float(rows.sum())

    def _check_bounds(self):
        """Raise ``DivergedRollout`` where ``bounds_hit`` finds the last state blown up."""
        hit = self.bounds_hit()
        if hit is None:
            return
        why, p = hit
        m = self.model
        body = m.bodies[int(m.particle_body_np[p])].name
        stable, named, advice = self._stable_advice()
        raise DivergedRollout(
            f"the rollout blew up while staying finite: {why} (particle {p} of body {body!r}, after step {self.steps} "
            f"of {self.steps}), at dt = {self.dt:.4g} s ({named} = {stable:.3g} s); {advice}",
            step=self.steps, particle=p, body=body)

    def _stable_advice(self) -> tuple[float, str, str]:
        """The blow-up messages' stable step, of the latest forward's start (``_initial``), how
        they name it and their advice. From a flowed body made elastic (``keeps_incremental``)
        it is half the one of a new state: quoted without the start, a dt between the two was
        said to be within it, and the start blamed."""
        stable = self.solver.stable_dt(state=self._initial)
        named = "Model.stable_dt()" if stable == self.solver.stable_dt() else "Model.stable_dt(state=) of its start"
        # Within the stable step a smaller dt is no cure: the cause is the start (a speed or
        # stretch past the precision's range) or the parameters, and the advice sent users to dt.
        advice = (f"use a smaller dt (at most {named}) or check the parameters (a stiffness far above the "
                  "materials' makes the stable step smaller)" if self.dt > stable else
                  "dt is within it, so check the start (x0, v0, F0, alpha0) and the parameters")
        return stable, named, advice

    def _check_finite(self, positions: np.ndarray):
        """Raise ``NonFiniteRollout`` where the frame ``positions`` or the last state's
        positions or velocities are not finite."""
        bad = self.first_non_finite(positions=positions)
        if bad is None:
            return
        step, p, last_finite = bad
        m = self.model
        body = m.bodies[int(m.particle_body_np[p])].name
        where = f"particle {p} of body {body!r}" + (f" (world {int(m.world_of_particle[p])})" if m.world_count > 1 else "")
        # A rollout made with taped=False refuses forward(taped=True): the advice names one that runs.
        kept = (f"checkpoint_every={self.segment} keeps only the states at its segment starts and frames: run with "
                "checkpoint_every=None to find the first step" if self.checkpointing else
                "forward(taped=False) keeps only the frames and the last state: run forward() taped to find the first step"
                if self.taped else
                "a rollout made with taped=False keeps only the frames and the last state: run a Rollout of these steps "
                "made with taped=True to find the first step")
        when = (f"after step {step} of {self.steps}" if step - last_finite <= 1 else
                f"after step {step} of {self.steps} (finite after step {last_finite}; {kept})")
        stable, named, advice = self._stable_advice()
        raise NonFiniteRollout(
            f"the rollout blew up: {where} has a non-finite position or velocity {when}, at dt = {self.dt:.4g} s "
            f"({named} = {stable:.3g} s); {advice}; forward(check=False) returns such a run as it is",
            step=step, particle=p, body=body, last_finite=last_finite)

    def _inputs(self) -> tuple:
        """What ``backward`` reads from the model besides the taped states: the parameter
        arrays, the materials, the tools' differentiable arrays, and the run's settings
        (``run_settings``)."""
        return (self.model._read_parameters(), tuple(self.model.materials),  # a copy already
                {name: a.numpy().copy() for name, a in self._tool_arrays().items()}, self.run_settings())

    def run_settings(self) -> dict:
        """What a run of this rollout reads besides the parameters, materials, tools and start:
        ``dt``, the model's ``gravity`` and the solver's settings (``checkpoint.solver_settings``:
        the fit, hourglass strength, contact ramp, neighbourhood guards, the yield test's pressure,
        fused kernels, rest model), as a run now would take them."""
        from .checkpoint import solver_settings  # noqa: PLC0415 (checkpoint imports the model, as this module)

        return {"dt": self.dt, "gravity": tuple(self.model.gravity), **solver_settings(self.solver)}

    def _check_inputs_unchanged(self):
        # The tape re-reads the arrays, and a checkpointed backward re-runs the segments with
        # them: values written after forward gave the gradient of another point with the value
        # of this one, without a word (3x the shear modulus: the yield stress's gradient 37 % off).
        # A checkpointed backward re-runs its segments at the dt, gravity and solver settings it
        # finds: set since the forward, they gave the gradient of another run (dt doubled: the
        # shear modulus's gradient 5.1 times its own), without a word.
        rows, materials, tools, settings = self._forward_inputs
        now_rows, now_materials, now_tools, now_settings = self._inputs()
        changed = [name for k, name in enumerate(PARAMETERS) if not np.array_equal(rows[k], now_rows[k])]
        changed += [f"materials[{k}]" for k, (a, b) in enumerate(zip(materials, now_materials)) if a != b]
        changed += [f"tools.{name}" for name in tools if not np.array_equal(tools[name], now_tools[name])]
        changed += [f"{name} ({settings[name]!r}, now {now_settings[name]!r})" for name in settings
                    if settings[name] != now_settings[name]]
        if changed:
            raise RuntimeError(f"backward() is not allowed: {', '.join(changed)} changed since forward(); run forward() "
                               "again with the new values first")

    def _forward_untaped(self):
        """The forward of a checkpointed rollout (its segment starts saved) or of
        ``forward(taped=False)``, stepping between two states without a tape."""
        if self._pair is None:
            self._pair = [self.model._scratch_state() for _ in range(2)]
        if self.checkpointing and len(self._checkpoints) != len(self.segments):
            self._checkpoints = [_Checkpoint(self.model) for _ in self.segments]
        cur, nxt = self._pair
        cur.assign(self._initial)
        seg = 0
        for k in range(self.steps + 1):
            if self.checkpointing and seg < len(self.segments) and self.segments[seg][0] == k:
                self._checkpoints[seg].save(cur)
                seg += 1
            if k in self._frame_slot:
                wp.copy(self.frame_positions[self._frame_slot[k]], cur.x)
            if k < self.steps:
                with self.solver.caller_checks():
                    self.solver.step(cur, nxt, self.dt)
                self._store_forces(k, nxt)
                cur, nxt = nxt, cur
        self._final = cur

    def _store_forces(self, k: int, state):
        if self.forces is not None:
            n = len(self.tool_names)
            wp.copy(self.forces, state.reaction_force, dest_offset=k * n, src_offset=0, count=n)
        if self.collider_forces is not None:
            n = len(self.collider_names)
            wp.copy(self.collider_forces, state.collider_force, dest_offset=k * n, src_offset=0, count=n)

    def guard_counts(self, last: bool = True) -> dict[str, int]:
        """The particle-steps each guard of the solver held (``Solver.guard_counts``' keys) in
        the latest ``forward`` (``last=False``: in every forward since the rollout was made).
        The steps a checkpointed ``backward`` re-runs are not counted again, as the solver's
        own counts, a count of work, do: a run's counts are the same whatever its checkpoints."""
        last = checks.boolean("last", last)
        counts = self._last_guards if last else self._forward_guards
        return dict(zip(GUARD_NAMES, (int(c) for c in counts)))

    def step_forces(self) -> np.ndarray:
        """Reaction force of every tool in every step of the last ``forward``, ``(steps, tools, 3)``
        (row ``k``: the step from ``k`` to ``k + 1``; see ``warp_esph.tools``)."""
        if self.forces is None:
            raise ValueError("step_forces is not allowed: the model has no tools, so nothing reports a reaction force")
        return self.forces.numpy().astype(np.float64).reshape(self.steps, len(self.tool_names), 3)

    def step_collider_forces(self) -> np.ndarray:
        """Force of every static collider in every step of the last ``forward``, ``(steps, rows,
        3)`` (row ``k``: the step from ``k`` to ``k + 1``; columns ``collider_names``)."""
        if self.collider_forces is None:
            raise ValueError("step_collider_forces is not allowed: the model has no static colliders (ground, planes, "
                             "spheres, boxes)")
        return self.collider_forces.numpy().astype(np.float64).reshape(self.steps, len(self.collider_names), 3)

    def final_state(self) -> State:
        """The state after the last step of the latest ``forward`` (the rollout's own: valid
        until the next ``forward``; read it, do not step from it)."""
        if not self._forward_done or self._final is None:
            raise ValueError("final_state is not allowed before forward(): there is no run to read")
        return self._final

    def observations(self, numpy: bool = False) -> dict:
        """What a loss may observe after ``forward``: ``{step: positions}`` at ``frames``, and
        with tools ``FORCES`` (every step's reaction forces, flat, see ``FORCES``) and
        ``TOOL_NAMES``, with static colliders ``COLLIDER_FORCES`` and ``COLLIDER_NAMES``.
        ``numpy=True``: numpy arrays instead of Warp arrays."""
        out = {f: (a.numpy() if numpy else a) for f, a in zip(self.frames, self.frame_positions)}
        if self.forces is not None:
            out[FORCES] = self.forces.numpy() if numpy else self.forces
            out[TOOL_NAMES] = list(self.tool_names)
        if self.collider_forces is not None:
            out[COLLIDER_FORCES] = self.collider_forces.numpy() if numpy else self.collider_forces
            out[COLLIDER_NAMES] = list(self.collider_names)
        return out

    def loss_roundoff(self) -> np.ndarray | None:
        """Per world, the round-off of the loss of the last ``backward`` given a loss: its
        value's (the model's precision times it; each world its own term where a
        ``losses.WorldLoss`` gives them, the rest counted in every world) plus, to first order,
        how far it moves where every observation it read moves by one unit of its own
        round-off (``sum |dL/do| |o|`` times the precision). A loss of positions reads their
        round-off more than its own: a free-falling body's shear modulus in float32 moved the
        loss by 127 units of its value's round-off and by 0.0045 of this one (the landing
        body's yield stress beside it by 966; tests/test_fit_informative.py). Forces are
        counted in every world. None where the backward was given gradients, not a loss."""
        if self._read is None:
            return None
        observed, grads, value = self._read
        m = self.model
        starts = np.asarray(m.world_start, dtype=np.int64)
        out = np.zeros(len(starts) - 1)
        shared = 0.0
        for key, g in grads.items():
            if key not in observed or g is None:
                continue
            g = np.asarray(g.numpy() if hasattr(g, "numpy") else g, dtype=np.float64)
            o = observed[key]
            o = np.asarray(o.numpy() if hasattr(o, "numpy") else o, dtype=np.float64)
            if g.size != o.size:
                continue  # no entry-by-entry pairing to read
            if isinstance(key, (int, np.integer)) and g.shape == o.shape and g.shape[0] == m.particle_count:
                read = (np.abs(g) * np.abs(o)).reshape(g.shape[0], -1).sum(axis=1)
                per_particle = np.concatenate([[0.0], np.cumsum(read)])
                out += per_particle[starts[1:]] - per_particle[starts[:-1]]
            else:
                # Forces: a loss's gradient of them may come in another shape (per frame and
                # tool) than the flat record, entry for entry.
                shared += float(np.sum(np.abs(g.ravel()) * np.abs(o.ravel())))
        value = float(value)
        if self.world_values is not None and len(self.world_values) == len(out):
            terms = np.abs(np.asarray(self.world_values, dtype=np.float64))
            out += terms
            shared += abs(value - float(np.sum(self.world_values)))
        else:
            shared += abs(value)
        return float(np.finfo(m.types.np_dtype).eps) * (out + shared)

    def positions(self) -> np.ndarray:
        """Positions at ``frames`` of the last ``forward``, ``(frames, n, 3)``."""
        return np.stack([a.numpy() for a in self.frame_positions])

    # --------------------------------------------------------------- backward
    def _frame_gradients(self, grads) -> dict[int, wp.array]:
        """Normalise the incoming position gradients to ``{frame: wp.array(vec3)}``."""
        m = self.model
        T = m.types
        shape = (m.particle_count, 3)
        if isinstance(grads, Mapping):
            items = list(grads.items())
        else:
            grads = checks.host_values("grads", grads)
            if isinstance(grads, np.ndarray) and grads.ndim == 2 and len(self.frames) == 1:
                grads = [grads]
            grads = list(grads)
            if len(grads) != len(self.frames):
                raise ValueError(f"{len(grads)} frame gradients given, the rollout observes {len(self.frames)} frames")
            items = list(zip(self.frames, grads))
        out = {}
        for f, g in items:
            if f not in self._frame_slot:
                raise ValueError(f"gradient for step {f!r} is not allowed: the rollout observes steps {list(self.frames)}")
            if g is None:
                continue
            if isinstance(g, wp.array):
                if g.dtype == T.vec3 and g.shape == (m.particle_count,) and g.device == m.device:
                    out[f] = g
                    continue
                g = g.numpy()
            g = checks.host_values(f"gradient for step {f}", g)
            checks.real_numbers(f"gradient for step {f}", g, f"must be numbers of shape {shape}")
            a = np.asarray(g, dtype=T.np_dtype)
            if a.shape != shape:
                raise ValueError(f"gradient for step {f} with shape {a.shape} is not allowed: must be {shape}")
            if not np.isfinite(a).all():  # NaN gradients came back as a result
                raise ValueError(f"gradient for step {f} is not allowed: it has non-finite values")
            out[f] = wp.array(a, dtype=T.vec3, device=m.device)
        return out

    def _force_gradients(self, g, names=None, what="reaction-force", lacks="tools") -> np.ndarray | None:
        """The gradient with respect to every step's reaction forces as ``(steps, rows, 3)``
        (the tools', or with ``names`` the static colliders')."""
        if g is None:
            return None
        names = self.tool_names if names is None else names
        if not names:
            raise ValueError(f"a {what} gradient is not allowed: the model has no {lacks}")
        if isinstance(g, wp.array):
            g = g.numpy()
        a = np.asarray(g, dtype=self.model.types.np_dtype)
        shape = (self.steps, len(names), 3)
        if a.size != int(np.prod(shape)):
            raise ValueError(f"{what} gradient with shape {a.shape} is not allowed: must be {shape}")
        return a.reshape(shape)

    def _seed_forces(self, state, k: int):
        """Seed the adjoint of the reaction forces of step ``k`` (the one ``state`` ends)."""
        if self._force_grads is not None:
            state.reaction_force.grad.assign(self._force_grads[k])
        if self._collider_grads is not None:
            state.collider_force.grad.assign(self._collider_grads[k])

    def _tool_arrays(self) -> dict[str, wp.array]:
        """The tools' differentiable arrays (``tools.ToolSet``) that keep gradients."""
        tools = self.model.tools
        arrays = {name: getattr(tools, name, None) for name in TOOL_GRADIENTS} if tools is not None else {}
        return {name: a for name, a in arrays.items() if a is not None and a.grad is not None}

    def _zero_parameter_grads(self):
        for name in PARAMETERS:
            getattr(self.model, name).grad.zero_()
        for a in self._tool_arrays().values():
            a.grad.zero_()

    def _add_parameter_grads(self, acc: dict[str, np.ndarray]):
        for name in PARAMETERS:
            acc[name] += getattr(self.model, name).grad.numpy()
        for name, a in self._tool_arrays().items():
            self._tool_acc[name] = self._tool_acc.get(name, 0.0) + a.grad.numpy()

    def backward(self, grads) -> tuple[float | None, dict[str, np.ndarray]]:
        """Gradients of a loss through the last ``forward``.

        ``grads``: a ``warp_esph.losses.Loss`` (evaluated on the frame positions), or the
        gradient of the loss with respect to the positions at ``frames``: a sequence (one
        ``(n, 3)`` array per frame, ``None`` to skip one), an ``(frames, n, 3)`` array, or
        ``{step: (n, 3) array}``.

        Returns ``(loss value or None, gradients)``; gradients are numpy arrays keyed by
        parameter name (one value per material) and ``x0, v0, F0, alpha0`` (per particle).
        The gradients of the tools' parameters (``TOOL_GRADIENTS``) are left on the arrays of
        ``model.tools`` (``model.tools.motion_gradient(name)``, ``model.tools.friction.grad``).
        The model's parameter values, materials and tool parameters, and the run's settings
        (``run_settings``: ``dt``, gravity, the solver's) must not change between ``forward``
        and ``backward`` (a ``RuntimeError`` names what did).
        """
        if not self.taped:
            raise RuntimeError("backward() is not allowed: this rollout was made with taped = False, for loss values "
                               "alone; make it with taped = True to take gradients")
        if not self._forward_done:
            raise RuntimeError("backward() before forward(): run forward() first")
        if self._tape is None and not self.checkpointing:
            raise RuntimeError("backward() is not allowed after forward(taped=False): that run recorded no tape to go "
                               "back through; run forward() (taped=True) first")
        self._check_inputs_unchanged()
        if grads is None or isinstance(grads, (str, bytes, int, float)):
            raise ValueError(f"grads = {checks.shorten(grads)!r} is not allowed: give a warp_esph.losses.Loss or the "
                             "loss's gradients with respect to the positions at the rollout's frames")
        value = None
        self.world_values = None
        self._read = None
        if hasattr(grads, "value_and_grad"):
            from .losses import WorldLoss, _leaves  # noqa: PLC0415

            loss = grads
            worlds = list({id(leaf): leaf for leaf in _leaves(loss) if isinstance(leaf, WorldLoss)}.values())
            for leaf in worlds:
                if not np.array_equal(leaf.world_start, self.model.world_start):
                    # Another model's worlds of the same particle total ran and gave its values.
                    raise ValueError(f"loss {leaf!r} is not allowed: it was made for a model of worlds starting at "
                                     f"particles {leaf.world_start.tolist()}, this one's start at "
                                     f"{np.asarray(self.model.world_start).tolist()}")
            observed = self.observations()
            value, grads = loss.value_and_grad(observed)
            # Each world's terms, also where the WorldLoss is a term of a sum (it read None there).
            parts = [leaf.world_values for leaf in worlds if leaf.world_values is not None]
            self.world_values = sum(parts[1:], parts[0]) if parts else None
            self._read = (observed, grads, value)
        force_grads = collider_grads = None
        if isinstance(grads, Mapping) and (FORCES in grads or COLLIDER_FORCES in grads):
            grads = dict(grads)
            force_grads = self._force_gradients(grads.pop(FORCES, None))
            collider_grads = self._force_gradients(grads.pop(COLLIDER_FORCES, None), self.collider_names,
                                                   "static-collider force", "static colliders")
        frame_grads = self._frame_gradients(grads)
        self._force_grads = force_grads
        self._collider_grads = collider_grads
        acc = {name: np.zeros(getattr(self.model, name).shape[0], dtype=self.model.types.np_dtype) for name in PARAMETERS}
        self._tool_acc = {}
        if self.checkpointing:
            with self._scripted_log() as log:
                adj = self._backward_checkpointed(frame_grads, acc)
            self._check_scripted(log, self._scripted_poses)
        else:
            adj = self._backward_full(frame_grads, acc)
        # The tools' gradients stay on their arrays (ToolSet.motion_gradient reads them): the
        # tape's zeroing after each pass had left them 0.
        for name, a in self._tool_arrays().items():
            a.grad.assign(self._tool_acc[name])
        result = dict(acc)
        result.update(adj)
        return value, result

    def per_world(self, gradients: Mapping[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
        """``backward``'s gradients split by world (``SceneBuilder.finalize(worlds=W)``):
        one dict per world, with that world's entries of every parameter array (its
        materials, ``model.world_materials(w)``) and of the initial-state gradients (its
        particles). Worlds never interact, so with a ``losses.WorldLoss`` these are the
        gradients of each world's own loss."""
        if not isinstance(gradients, Mapping):
            raise ValueError(f"gradients = {checks.shorten(gradients)!r} is not allowed: must be backward's gradients "
                             "(a mapping {name: array})")
        parts = {key: self.model.per_world(value, "materials" if key in PARAMETERS else "particles")
                 for key, value in gradients.items()}
        return [{key: p[w] for key, p in parts.items()} for w in range(self.model.world_count)]

    def _seed(self, arr: wp.array, g: wp.array):
        wp.launch(self._k.add_vec3, arr.shape[0], [g], [arr.grad], device=self.model.device, record_tape=False)

    def _backward_full(self, frame_grads, acc):
        states = self._states
        tape = self._tape
        tape.zero()
        for s in states[: self.steps + 1]:
            _zero_state_grads(s)
        self._zero_parameter_grads()
        for f, g in frame_grads.items():
            self._seed(states[f].x, g)
        for k in range(self.steps):
            self._seed_forces(states[k + 1], k)
        tape.backward()
        self._add_parameter_grads(acc)
        adj = {key: getattr(states[0], name).grad.numpy().copy() for key, name in STATE_GRADIENTS.items()}
        tape.zero()
        _zero_state_grads(states[0])
        return adj

    def _backward_checkpointed(self, frame_grads, acc):
        states = self._taped_states(self.segment + 1)
        adj: dict[str, wp.array] | None = None  # adjoint of the current segment's end state
        for (start, length), ck in reversed(list(zip(self.segments, self._checkpoints))):
            seg = states[: length + 1]
            for s in seg:
                _zero_state_grads(s)
            seg[0].assign(ck)
            tape = wp.Tape()
            with tape, self.solver.caller_checks():
                for k in range(length):
                    self.solver.step(seg[k], seg[k + 1], self.dt)
            end = seg[length]
            if adj is not None:
                for name, g in adj.items():
                    wp.copy(getattr(end, name).grad, g)
            for f, g in frame_grads.items():
                if start < f <= start + length:
                    self._seed(seg[f - start].x, g)
            for j in range(length):
                self._seed_forces(seg[j + 1], start + j)
            self._zero_parameter_grads()
            tape.backward()
            # docs/method.md, Warp pitfall 6: tape.zero() zeroes the parameter grads too: keep them first.
            self._add_parameter_grads(acc)
            adj = {name: wp.clone(getattr(seg[0], name).grad) for name in State.STATE_FIELDS
                   if getattr(seg[0], name).grad is not None}
            tape.zero()
            del tape
        if 0 in frame_grads:
            self._seed_plain(adj["x"], frame_grads[0])
        for s in states:
            _zero_state_grads(s)
        self._zero_parameter_grads()
        return {key: adj[name].numpy().copy() for key, name in STATE_GRADIENTS.items()}

    def _seed_plain(self, arr: wp.array, g: wp.array):
        wp.launch(self._k.add_vec3, arr.shape[0], [g], [arr], device=self.model.device, record_tape=False)

    # ------------------------------------------------------------- utilities
    def value_and_grad(self, loss, **initial) -> tuple[float, dict[str, np.ndarray]]:
        """``forward(**initial)`` then ``backward(loss)``: the loss value and its gradients."""
        check = getattr(loss, "check_positions", None)
        if check is not None:  # a loss of the wrong size was refused only after the forward pass
            check(self.model.particle_count)
        self.forward(**initial)
        value, grads = self.backward(loss)
        return value, grads

    def memory_bytes(self) -> dict[str, int]:
        """Bytes held by the rollout's Warp arrays: taped states, untaped ones (the start's copy
        and a forward's two), checkpoints, frame buffers."""
        taped = sum(state_nbytes(s) for s in (self._states or []))
        untaped = sum(state_nbytes(s) for s in (self._initial, *(self._pair or [])))
        ck = sum(c.nbytes for c in self._checkpoints)
        frames = sum(a.capacity for a in self.frame_positions)
        return {"taped_states": taped, "untaped_states": untaped, "checkpoints": ck, "frames": frames,
                "total": taped + untaped + ck + frames}

    def release(self):
        """Free the taped states and checkpoints (they are re-allocated when needed)."""
        self._states = None
        self._pair = None
        self._checkpoints = []
        self._tape = None
        self._final = None
        self._forward_done = False

    def __repr__(self):
        mode = f"checkpoint_every={self.segment}" if self.checkpointing else "full tape" if self.taped else "untaped"
        return f"Rollout({self.model.particle_count} particles, {self.steps} steps of {self.dt:g} s, frames={list(self.frames)}, {mode})"


def split_materials(model: Model, bodies: Sequence[int | str] | None = None) -> Model:
    """A copy of ``model`` in which every particle of ``bodies`` (default: all) has its own material.

    Each material parameter array then holds one value per such particle (a per-particle
    field; other bodies keep their shared materials, renumbered after them). The copy
    has the same precision, device and ``requires_grad`` as ``model`` and starts from its
    ``particle_x0`` / ``particle_v0``.
    """
    if not isinstance(model, Model):
        raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph.Model")
    names = [b.name for b in model.bodies]
    if isinstance(bodies, (str, int, np.integer)) and not isinstance(bodies, bool):
        # One body, as fit's materials= takes it: a name was split into its letters
        # ("body 'b' is not allowed"), an index was a TypeError.
        bodies = [bodies]
    if bodies is not None and (isinstance(bodies, (bytes, Mapping)) or not hasattr(bodies, "__iter__")):
        raise ValueError(f"bodies = {checks.shorten(bodies)!r} is not allowed: give body names or indices "
                         f"(the model's bodies are {', '.join(names)})")
    if bodies is None:
        chosen = set(range(len(model.bodies)))
    else:
        chosen = set()
        for b in bodies:
            if isinstance(b, str):
                if b not in names:
                    raise ValueError(f"body {b!r} is not allowed: the model's bodies are {', '.join(names)}")
                chosen.add(names.index(b))
            elif isinstance(b, (int, np.integer)) and 0 <= int(b) < len(names):
                chosen.add(int(b))
            else:
                raise ValueError(f"body {b!r} is not allowed: give a body name or an index in [0, {len(names) - 1}]")
    old = model.particle_material_np
    body_of = model.particle_body_np
    materials = []
    source = []  # the model's material each new material copies
    new_index = np.empty(model.particle_count, dtype=np.int32)
    # An elastic particle floor keeps its one material (a wall's, never fitted).
    walls = sorted({b.floor_material for b in model.bodies if b.floor_material >= 0})
    per_particle = np.isin(body_of, sorted(chosen)) & ~np.isin(old, walls)
    wall_index = {}
    world_material_start = [0]
    # World by world, so each world's materials stay contiguous (``Model.world_materials``).
    for w in range(model.world_count):
        s = model.world_particles(w)
        idx = np.arange(s.start, s.stop)
        for i in idx[per_particle[idx]]:
            new_index[i] = len(materials)
            materials.append(model.materials[old[i]])
            source.append(int(old[i]))
        shared = {}
        for i in idx[~per_particle[idx]]:
            k = int(old[i])
            if k not in shared:
                shared[k] = len(materials)
                materials.append(model.materials[k])
                source.append(k)
            new_index[i] = shared[k]
        wall_index.update({k: v for k, v in shared.items() if k in walls})
        world_material_start.append(len(materials))
    new_bodies = [dataclasses.replace(b, material=int(new_index[b.start]), floor_material=wall_index.get(b.floor_material, -1))
                  for b in model.bodies]
    out = Model(
        positions=model.particle_x0.copy(),
        velocities=model.particle_v0.copy(),
        particle_material=new_index,
        particle_body=body_of.copy(),
        materials=materials,
        bodies=new_bodies,
        **model.settings(),
        requires_grad=model.requires_grad,
        particle_world=model.world_of_particle.copy(),
        world_material_start=world_material_start,
    )
    out.force_fields = list(model.force_fields)
    # The solver's scene-wide options and the tools, as replicate_worlds keeps them: a split
    # model must run as its source does.
    out._fit, out.contact_ramp, out.hourglass = model._fit, model.contact_ramp, model.hourglass
    if model.tools is not None:
        from .tools import ToolSet  # noqa: PLC0415 (tools imports the solver's modules)

        src = model.tools
        pin = src.pin.numpy()
        first = len(src.colliders)
        world_pins = [[np.flatnonzero(pin[model.world_particles(w)] == first + j) for j in range(len(src.pins))]
                      for w in range(model.world_count)]
        out.tools = ToolSet(out, src.colliders, src.pins, world_pins=world_pins)
        # Their parameters too (a fit may have moved them from the colliders' values).
        for name in ("friction", "static_friction", "keyframe_positions", "keyframe_orientations", "velocity",
                     "angular_velocity"):
            wp.copy(getattr(out.tools, name), getattr(src, name))
    # Copy the rest density, masses and volumes rather than recompute them, so the split model
    # runs identically (a mass written after the build ran in the model and not in its split).
    for name in ("particle_rest_density", "particle_mass", "particle_volume"):
        wp.copy(getattr(out, name), getattr(model, name))
    # Copy the parameter values too (they may differ from model.materials after a fit).
    for name in PARAMETERS:
        vals = getattr(model, name).numpy()
        getattr(out, name).assign(vals[np.asarray(source, dtype=np.int64)])
    return out
