"""``simulate``: run a model for a number of rendered frames, optionally writing USD.

Frame 0 is the initial state; frame ``k`` is the state after ``k * substeps`` steps of
``dt``, ``substeps * dt = 1 / fps``. After every frame, before it is written, the
positions and velocities are checked: a non-finite value, or a blow-up that stays finite
(``DivergenceMonitor``: speeds, kinetic energy or distances no motion of the scene can
reach), stops the run with a ``SimulationError`` that names the step, the particle and
its body, after the writer has kept every finished frame.
"""

from __future__ import annotations

import inspect
import math
import sys
import time
import warnings

import numpy as np

from . import checks, tools
from .model import CORRECTED_INCREMENTAL_STEP, Model, State
from .sim.neighbors import NeighborOverflow
from .sim.solver import Solver

__all__ = [
    "simulate", "resolve_timestep", "adaptive_timestep", "check_start_speed", "SimulationError", "DivergenceMonitor", "AUTO",
    "MAX_STEPS_PER_FRAME", "MAX_STEPS",
]

#: The most frames a second ``resolve_timestep`` takes: shorter frames would need steps near
#: or below what float32 resolves in time.
MAX_FPS = 1.0e6
#: Most steps one frame may take. The stiffest useful material at a fine spacing (steel,
#: c_P ~ 6 km/s, at 5 mm) needs about 1e5 at 30 fps; more is a mistake that would run for
#: days (``--dt 1e-300`` asks for 3e298).
MAX_STEPS_PER_FRAME = 10**6
#: Most steps one run may take (1e10 steps of the smallest scene take about a month here).
MAX_STEPS = 10**10
#: The largest frame index ``simulate`` numbers (``start_frame + frames``): a USD time code is a
#: double, which holds every integer only up to 2**53.
MAX_FRAME_INDEX = 2**53

#: ``dt = AUTO`` (``"auto"``) asks ``simulate`` for an adaptive (CFL) time step.
AUTO = "auto"
#: A run whose deformation fits the guards of paper §4 skipped (too few same-body neighbours,
#: or a neighbourhood too flat for a 3-D fit: ``Solver.guard_counts()``' ``few_neighbors`` and
#: ``ill_conditioned``) in at least this share of its particle-steps warns (``skipped_fits``):
#: where they are skipped the material does not deform as itself. Measured over whole runs:
#: none in dough_drop, rubber_bounce, clay_on_sphere, three_cylinders at scale 0.3-0.35, 0.6 %
#: in the star at scale 1 (its tips and its landing), 1.5-5 % in coarse runs of Fig. 3, 6
#: and 5, 8.4 % in the star at scale 0.5 (two layers thick), 100 % in a body one layer thick.
SKIPPED_FIT_SHARE = 0.05


class StepRefusal(ValueError):
    """A refused time step or step count (``resolve_timestep``, ``check_step_count``; a start
    or a tool faster than a spacing a step, ``check_start_speed``, ``ToolSet.check_speed``; the
    adaptive step too short for the material, ``adaptive_timestep``): its message is ``reason``
    and then ``advice``, a Python caller's (naming ``dt=``, ``fps=``); ``reason`` lets a caller
    with other options (a sweep, ``warp-esph run``) give its own advice instead, ``advice``
    telling which refusal it is (``START_ADVICE``, ``ADAPTIVE_ADVICE``, ``ADAPTIVE_FALL_ADVICE``,
    ``ADAPTIVE_VISCOUS_ADVICE``, ``ADAPTIVE_HOURGLASS_ADVICE``, ``ADAPTIVE_FIELD_ADVICE``, ``STABLE_ADVICE``,
    ``STABLE_HOURGLASS_ADVICE``, ``STABLE_FIELD_ADVICE``, ``STABLE_REPULSION_ADVICE``, ``ADAPTIVE_REPULSION_ADVICE``,
    ``tools.TOO_FAST_ADVICE``). ``detail``: the reason without the refused value's name
    ('frames = ... is not allowed: ', 'the stable step ... is not allowed: '), for a caller that
    refuses its own option by name (default: ``reason``)."""

    def __init__(self, reason: str, advice: str = "", detail: str | None = None):
        super().__init__(reason + advice)
        self.reason = reason
        self.advice = advice
        self.detail = reason if detail is None else detail


def divergence_advice(model: Model, hourglass: float | None, dt: str = "dt=", solver: Solver | None = None,
                      since: int = 0, step: float | None = None, state: State | None = None) -> str:
    """The advice of ``simulate``'s divergence (``SimulationError``) of ``model`` at the stable
    step of the hourglass control ``hourglass`` (``Model.stable_dt``); ``dt``: how the caller
    names the step (``warp-esph run``: ``--dt``, and then its options for the fit). Where a
    compression field's limit sets the stable step, it says so: the field's spring is bounded,
    but a body it crushes is stiffer than the rest state the limit assumes (docs/method.md §8),
    so the run may blow up below it, and softer material settings do not help. Where
    ``solver`` runs the rest-configuration model from ``state`` (``Solver.runs_rest``: the
    state the diverging step wrote, which says what that step ran; None: a new state) and
    counted inverted fits, it says that: a body crushed or folded through itself, where a
    smaller step, a stiffer material or the incremental composition (which follows the
    neighbours as a body parts) may run on. Before an inverted rest fit's energy was continued through det = 0 no
    smaller step mended it (a soft cantilever hanging under its own weight diverged at 0.299 s
    at the stable step and at 0.293 s at half of it; it now holds); since, a St.
    Venant-Kirchhoff block released from twice its size, stiffer at that strain than the
    stable step assumes, blows up at the stable step and runs on at a quarter of it. ``since``:
    the solver's inverted count when the run began (an earlier run's are not this one's);
    ``step``: the run's step, above the stable one a blow-up inverts the fits too, and a
    smaller step is the cure."""
    asked = None if solver is None else solver.asked_fit
    stable = model.stable_dt(hourglass=hourglass, fit=asked, state=state)
    inverted = rest_inversions(solver, state) - since if solver is not None and rest_inversions(solver, state) else 0
    if inverted > 0 and (step is None or step <= stable * (1.0 + 1e-6)):
        fit = ("--solver-fit curvature_corrected --hourglass 0.05" if dt == "--dt" else
               "fit='curvature_corrected' with hourglass=0.05 (SceneBuilder or Solver)")
        return (f"the rest-configuration model's fit inverted in {inverted} particle-steps: a body crushed or folded "
                f"through itself, whose strain may be stiffer than the stable limit ({stable:.3g} s) assumes; try a "
                f"smaller {dt}, a stiffer material, or {fit}, the incremental composition, which follows the "
                f"neighbours as a body parts")
    if _repulsion_cause(model, 0.3, hourglass, asked, state) is not None:
        # Checked before the fields: where the repulsion's limit is the shorter, a weaker field
        # (or a softer material) leaves the step as it is.
        which = model._repulsion_limit(0.3)[1]
        return (f"try a smaller {dt} (stable limit {stable:.3g} s, set by {model._repulsion_words(which)} at contact) "
                f"or a smaller pair_repulsion or pressure_stiffness")
    if _field_cause(model, 0.3, hourglass, asked, state) is not None:
        _, k, which = model._field_limit(0.3)
        return (f"try a smaller {dt} (stable limit {stable:.3g} s, set by {model._field_words(which)} at net strength "
                f"k = {k:g} 1/s^2; a body it crushes is stiffer than that limit allows for, docs/method.md §8) or a weaker field")
    return f"try a smaller {dt} (stable limit {stable:.3g} s) or stiffer-to-softer material settings"


def rest_inversions(solver: Solver, state: State | None = None) -> int:
    """The particle-steps whose rest fit inverted (``Solver.guard_counts()["inverted"]``) where
    ``solver`` runs the rest-configuration model from ``state`` now (``Solver.runs_rest``; the
    state a run's last step wrote: what that step ran; None: a new state); 0 otherwise (the
    incremental composition counts its own inverted fits there)."""
    return solver.guard_counts()["inverted"] if solver.runs_rest(state) else 0


#: The advice of ``check_start_speed``'s refusal at a fixed dt, and of ``adaptive_timestep``'s
#: where the material's own step needs too many steps a frame (a Python caller's names).
START_ADVICE = f"; give a smaller velocity (or angular_velocity), a smaller dt=, or dt={AUTO!r} (the adaptive step)"
ADAPTIVE_ADVICE = "; use a softer material, a larger spacing or a higher fps="
#: ``adaptive_timestep``'s where the viscous limit sets the stable step (stiffness leaves it as it is).
ADAPTIVE_VISCOUS_ADVICE = "; use a less viscous material, a larger spacing or a higher fps="
#: ``adaptive_timestep``'s where the hourglass control's limit is shorter than the wave limit
#: (its springs, of strength ``Solver(hourglass=)``, are what shortens the step).
ADAPTIVE_HOURGLASS_ADVICE = ("; use a smaller hourglass control strength (Solver(hourglass=) or SceneBuilder(hourglass=)), a "
                             "larger spacing or a higher fps=")
#: ``resolve_timestep``'s where the stable step needs more than ``MAX_STEPS_PER_FRAME`` steps a
#: frame; ``STABLE_HOURGLASS_ADVICE`` where the hourglass control's limit is what shortens it.
STABLE_ADVICE = ": use softer materials, a larger spacing, a higher fps, or give dt= or substeps="
#: ``resolve_timestep``'s and ``adaptive_timestep``'s where a force field's limit is what
#: shortens the stable step (its strength sets it; neither the material nor the spacing does).
STABLE_FIELD_ADVICE = (": use a weaker compression field (SceneBuilder.add_compression_field's strength), a higher fps, "
                       "or give dt= or substeps=")
ADAPTIVE_FIELD_ADVICE = "; use a weaker compression field (SceneBuilder.add_compression_field's strength) or a higher fps="
STABLE_HOURGLASS_ADVICE = (": use a smaller hourglass control strength (Solver(hourglass=) or SceneBuilder(hourglass=)), "
                           "a larger spacing, a higher fps, or give dt= or substeps=")
#: ``resolve_timestep``'s and ``adaptive_timestep``'s where the pair repulsion's limit
#: (``Material.pair_repulsion``) is what shortens the stable step: its strength sets it.
STABLE_REPULSION_ADVICE = (": use a smaller pair repulsion (Material.pair_repulsion) or pressure stiffness, a larger spacing, "
                           "a higher fps, or give dt= or substeps=")
ADAPTIVE_REPULSION_ADVICE = ("; use a smaller pair repulsion (Material.pair_repulsion) or pressure stiffness, a larger "
                             "spacing or a higher fps=")
#: ``adaptive_timestep``'s where gravity's gain over a frame, ``|g| / fps``, is the largest speed
#: the step resolves (a softer material hardly lengthens it).
ADAPTIVE_FALL_ADVICE = "; use a higher fps= (gravity adds up to |g| / fps to a speed within a frame) or a larger spacing"


class SimulationError(checks.Rebuilt, RuntimeError):
    """The simulation produced a non-finite position or velocity, or blew up while staying
    finite (``DivergenceMonitor``), or a ``tools.Scripted`` motion moved a tool more than a
    spacing in a step (``ToolSet.check_scripted_step``), or the neighbour search found a row
    past ``MAX_CANDIDATES`` (``sim.neighbors.NeighborOverflow``, kept as ``__cause__``: a
    body crushed together, or a blow-up).

    ``step``: the number of steps taken when it was detected (counted from the start of
    the run; the bad value arose in one of the steps of the last frame). ``particle``:
    the first bad particle's index (``None`` where a tool's motion stopped the run);
    ``body``: its body's name; ``frame``: the frame whose check found it. ``reason`` and
    ``advice``: the message without and its advice, a Python caller's (a divergence's 'try a
    smaller dt= ...', ``divergence_advice``; a far mesh tool's, ``far_mesh_advice``; '' where
    there is none), as ``StepRefusal`` has them for a caller
    (``warp-esph run``) that names its own options.
    """

    def __init__(self, message: str, *, step: int, particle: int | None, body: str | None = None, frame: int | None = None,
                 advice: str = ""):
        super().__init__(message + advice)
        self.reason = message
        self.advice = advice
        self.step = step
        self.particle = particle
        self.body = body
        self.frame = frame


def exempt_bodies(exempt, names: list[str]) -> tuple[str, ...]:
    """``monitor_exempt`` (``simulate``'s, a fit's ``Experiment``'s) as a tuple, refused unless
    it lists body names of ``names``, the model's."""
    refused = f"monitor_exempt = {checks.shorten(exempt)!r} is not allowed: must be a list of body names ({names})"
    if isinstance(exempt, str) or not hasattr(exempt, "__iter__"):  # 5 ended in a TypeError, "ab" in 'a', 'b'
        raise ValueError(refused)
    try:
        given, exempt = exempt, tuple(exempt)
    except TypeError:  # a 0-d numpy array has __iter__ and said numpy's 'iteration over a 0-d array'
        raise ValueError(refused) from None
    if not all(isinstance(name, str) for name in exempt):
        # A 2-D array's rows met 'in' with numpy's 'truth value of an array ... is ambiguous'.
        raise ValueError(refused)
    for name in exempt:
        if name not in names:
            raise ValueError(f"monitor_exempt = {checks.shorten(given)!r} is not allowed: {name!r} is not a body of the "
                             f"model ({names})")
    return exempt


class DivergenceMonitor:
    """Catches a run that has blown up, to non-finite values or while staying finite, from
    what the scene can do.

    Made from the model and the run's first state; ``check(x, v, t)`` (``t``: seconds since
    that state) returns ``None`` or ``(what, particle)``: a non-finite position or velocity
    (of ``particles``, the exempt bodies' too) is a blow-up whatever the bounds below (also
    where they do not run); the bounds read the particles checked, the exempt bodies left
    out. Three bounds, each a generous multiple of what the physics allows:

    - speed: no particle can move faster than its initial speed, plus the fall from the
      highest particle to the lowest floor (``sqrt(2 g H)``; ``g t`` where nothing stops a
      fall), plus the fastest p-wave speed (an elastic rebound), plus what the force fields
      can have given it by ``t`` (``sqrt(strength) R``, a harmonic field over the radius of
      the particles it acts on): each particle's own bound counts the fields that have come
      on by then (one switched off since leaves its speed behind; one off before the state
      left it in the state's own), and of those the fields
      acting on its body, or any body's where bodies interact (SPH pressure passes a field's
      speed on to the bodies its body strikes; ``bodies_interact=False`` keeps each body to
      its own fields); ``SPEED_FACTOR`` times that is a blow-up.
    - energy: with no work done on the bodies, the kinetic energy is at most the initial
      one plus the elastic energy stored at the start (``_stored_energy_bound``, from F's
      singular values: a prestrained ``F0`` recoils; given the solver, of the deformation
      its first step sees, on the rest model the rest fit of the start positions, which a
      body scaled from its rest shape holds with ``F = I``) plus the potential
      energy released since (``sum m g (h_0 - h)``) plus what the force fields held when they
      came on (``0.5 k sum m r^2``, ``r`` the distance from the field's axis; for a field
      switched on later, ``r`` up to the farthest start plus the diagonal plus the distance
      the speed bound covers until it comes on, which its ``sqrt(k) R`` counts too; a field acting
      only on particles not checked, an exempt body's, counts its energy as its speed, for the
      checked ones that body may strike); kinetic energy
      plus the potential energy of the fields acting now beyond ``ENERGY_FACTOR`` times that,
      plus a floor ``0.5 M (0.1 c_P)^2`` (the strain a rest-configuration body's positions
      may hold), is a blow-up.

    The wave speeds and energies read the parameters the model runs now (a fit's trial
    writes them without changing ``model.materials``) of the particles checked.
    - reach: a particle farther from the scene's box (particles and colliders) than
      ``REACH_FACTOR`` times (its diagonal + the speed bound x ``t``) is a blow-up; so is
      one farther than ``FAR_FACTOR`` times (the diagonal + the speed bound less its p-wave
      term, plus the speed the stored elastic energy can give the lightest particle, x
      ``t``), which holds at any stiffness (the p-wave speed of a trial at mu 1e30 Pa let
      particles 1.5e8 m from a 6 cm block pass).

    Moving tools and pinned sets (``model.tools``) do work on the bodies: their fastest
    point, ``|v| + |omega| (D + |v| t)`` over their motions (``D`` the diagonal of the box
    of the particles, colliders and the tools' poses), joins the speed bound and the kinetic
    energy of every particle moving that fast joins the energy bound; the potential energy
    the bodies gain (lifted by a tool) is the tools' work and takes nothing off it, and the
    work the tools did (``check``'s ``work``, ``ToolWork``: height, speed and elastic energy
    they gave alike) joins it, or where that is not known the most height they can have given
    (``lift_given``), held as height or fallen back as speed.

    A repelling field (``strength < 0``) can add energy without bound, and a scripted motion
    (``tools.Scripted``) has no speed known beforehand: then only the non-finite check runs.
    """

    SPEED_FACTOR = 10.0
    ENERGY_FACTOR = 10.0
    REACH_FACTOR = 10.0
    #: The reach that holds at any stiffness: a particle farther out than this many times the
    #: scene's size plus what the energy given to the bodies can carry it is a blow-up (its
    #: concentration in one particle of the N sharing it is sqrt(N) times their speed at most).
    FAR_FACTOR = 1000.0
    #: An upward-facing plane (its normal within ~8 degrees of up) is a floor that ends a fall.
    FLOOR_COSINE = 0.99

    def __init__(self, model: Model, state: State, exempt=(), particles=None, solver=None):
        """``particles``: a boolean mask of the particles to check (one world of a model of
        worlds, whose bounds are that world's own), None: all but ``exempt``'s. ``solver``: the
        solver whose steps run from ``state``; the elastic energy stored at the start is that of
        the deformation its first step sees (``Solver.start_deformation``: on the rest model,
        the rest fit of the start positions), None: of the stored ``F``."""
        names = [b.name for b in model.bodies]
        exempt = exempt_bodies(exempt, names)
        #: Particles the non-finite check reads: all (of ``particles``), the exempt bodies' too.
        self.finite = np.ones(model.particle_count, dtype=bool) if particles is None else np.asarray(particles, dtype=bool)
        #: Particles the bounds read: all but those of the exempt bodies (a scene showing a method fail).
        self.keep = ~np.isin(model.particle_body_np, [names.index(n) for n in exempt]) & self.finite
        x0 = state.x.numpy().astype(np.float64)[self.keep]
        v0 = state.v.numpy().astype(np.float64)[self.keep]
        self.mass = model.particle_mass.numpy().astype(np.float64)[self.keep]
        self.index = np.flatnonzero(self.keep)
        motions = [] if model.tools is None else [c.motion for c in model.tools.colliders] + [p.motion for p in model.tools.pins]
        driven = [_driven_motion(m) for m in motions]
        self.enabled = (all(f.strength >= 0.0 for f in model.force_fields) and self.keep.any()
                        and np.isfinite(x0).all() and np.isfinite(v0).all() and all(d is not None for d in driven))
        g = np.array(model.gravity, dtype=np.float64)
        self.g = float(np.linalg.norm(g))
        self.up = -g / self.g if self.g > 0.0 else np.array([0.0, 1.0, 0.0])
        self.h0 = x0 @ self.up
        planes, spheres, boxes = model.static_colliders()  # as they run: a ground moved in place is where it is
        floors = [p.offset / float(np.dot(p.normal, self.up)) for p in planes
                  if float(np.dot(p.normal, self.up)) >= self.FLOOR_COSINE * float(np.linalg.norm(p.normal))]
        self.fall_height = float(self.h0.max() - min(floors + [float(self.h0.min())])) if floors else None
        if not self.keep.any():
            return
        lo, hi = x0.min(axis=0), x0.max(axis=0)
        for sph in spheres:
            lo, hi = np.minimum(lo, np.subtract(sph.center, sph.radius)), np.maximum(hi, np.add(sph.center, sph.radius))
        for box in boxes:
            lo, hi = np.minimum(lo, np.subtract(box.center, box.half_extents)), np.maximum(hi, np.add(box.center, box.half_extents))
        self.lo, self.hi = lo, hi
        poses = [p for d in driven if d is not None for p in d[2]]
        if poses:  # the tools' poses widen only the box their rotations sweep, not the reach check's
            lo, hi = np.minimum(lo, np.min(poses, axis=0)), np.maximum(hi, np.max(poses, axis=0))
        self.diagonal = float(np.linalg.norm(hi - lo)) + 2.0 * model.support_radius
        self.v_tools = max((d[0] for d in driven if d is not None), default=0.0)
        self.w_tools = max((d[1] for d in driven if d is not None), default=0.0)
        #: (tool, the highest of the positions its motion names along up, its reach) of each moving
        #: tool: what it can lift the bodies to (``lift_given``)
        self.lifters = [(k, max((float(np.dot(p, self.up)) for p in d[2]), default=-np.inf), model.tools.reach(k))
                        for k, d in enumerate(driven) if d is not None and (d[0] > 0.0 or d[1] > 0.0)]
        self.tools = model.tools
        self.extent = float(self.h0.max() - self.h0.min()) + 2.0 * model.support_radius
        self.v0 = float(np.sqrt((v0 * v0).sum(axis=1).max()))
        # From the model's parameter arrays, which a fit or Rollout.set_parameters changes
        # without changing model.materials (a trial 3000 x stiffer read the guess's speed).
        p = model.parameter_values()
        self.wave = _wave_speed(model, p, self.keep)  # of the particles checked
        # On the rest model the first step replaces the stored F by the rest fit of the
        # positions: a 4x4x4 block scaled by 1.1 from its rest shape with F = I was stopped as
        # a blow-up (0.21 J against 0.11 J) while it rang with the energy it started with.
        F = state.F.numpy() if solver is None else solver.start_deformation(state)
        self.e_elastic = _stored_energy_bound(model, p, F, self.keep) + _repulsion_energy(model, p, state.x.numpy(), self.keep)
        # The fastest the stored elastic energy can throw the lightest particle checked.
        self.recoil = math.sqrt(2.0 * self.e_elastic / float(self.mass.min())) if self.mass.min() > 0.0 else 0.0
        self.ke0 = 0.5 * float((self.mass * (v0 * v0).sum(axis=1)).sum())
        self.e_floor = _energy_floor(float(self.mass.sum()), self.wave)
        self.t0 = float(state.time)
        #: (t_on, speed it can give, which particles checked may get it) of each attracting field
        self.field_speeds = []
        self.fields = []  # (field, its particles among those checked, the energy it gives at most)
        if not self.enabled:  # a repelling field's sqrt(k) is not real (it ended in 'math domain error')
            return
        # Each field's potential energy 0.5 k m r^2 (r its horizontal distance from the centre)
        # is part of the scene's energy: at most what it held when it came on is released, and
        # while it acts a particle thrown out far holds more than that (a dough box under k = 1e6
        # at 0.66 x its stable step ran with particles 42 m out of a 0.2 m box, inside the bound
        # of 0.5 k M (r + D)^2 given once, far beyond the 0.5 k sum m r0^2 it started with).
        # Where a field comes on later the particles may have moved by then as fast as the
        # scene allows (with the fields on before it): a body drifting at 1 m/s into a field
        # switched on at 2 s, 2 m out, was stopped as a blow-up where r0 + D was taken.
        body = model.particle_body_np[self.keep]
        # Each field's speed counted for every particle loosened the bound of those it never
        # reaches (another body's, or all of them before it came on) by sqrt(k) R.
        world = model.world_of_particle[self.keep]
        for f in sorted(model.force_fields, key=lambda f: f.t_on):
            later = max(f.t_on - self.t0, 0.0)
            r = np.linalg.norm((x0 - np.asarray(f.center))[:, [0, 2]], axis=1)
            on = np.ones(len(body), dtype=bool) if f.body < 0 else body == f.body
            # Where bodies interact, the bodies of the worlds its body is in (a world's bodies
            # never touch another's); an exempt body it acts on may push the checked ones, and
            # the farthest of those then stands for it.
            acting = model.particle_body_np == f.body if f.body >= 0 else np.ones(model.particle_count, dtype=bool)
            felt = np.isin(world, model.world_of_particle[acting]) if model.bodies_interact else on
            source = on if on.any() else np.ones(len(body), dtype=bool)
            # One off by the start gave its speed before it, in the state's own (v0): counted
            # again, a run resumed from a state after it was allowed sqrt(k) R more.
            if felt.any() and f.t_off > self.t0:
                travel = float(self.speed_bounds(later)[source].max()) * later
                self.field_speeds.append((f.t_on, math.sqrt(f.strength) * (r[source].max() + self.diagonal + travel), felt))
            if f.t_off <= self.t0:
                continue
            if on.any():
                m_on, r_on = self.mass[on], r[on]
            elif felt.any():
                # It acts on particles left unchecked (an exempt body) that may strike the checked
                # ones: its energy joins their budget as its speed joins their bound. Left out,
                # a body pulled by its field into a checked one at rest was stopped as a blow-up
                # (1.1 J of kinetic energy against a floor of 0.1 J, the field's 1.7 J uncounted).
                src = acting & ~self.keep & np.isin(model.world_of_particle, world[felt])
                if not src.any():
                    continue
                m_on = model.particle_mass.numpy().astype(np.float64)[src]
                r_on = np.linalg.norm((state.x.numpy().astype(np.float64)[src] - np.asarray(f.center))[:, [0, 2]], axis=1)
            else:
                continue
            if f.active(self.t0):
                given = 0.5 * f.strength * float((m_on * r_on * r_on).sum())
            else:
                given = 0.5 * f.strength * (r_on.max() + self.diagonal + travel) ** 2 * float(m_on.sum())
            self.fields.append((f, on, given))

    def lift_given(self, t: float) -> float:
        """The most potential energy (J) the moving tools can have given the particles checked
        by ``t`` seconds since the monitor's state: each lifted to the highest a tool's reach got
        (its named positions, its pose then and now), plus the bodies' height above it."""
        if not self.lifters or self.g == 0.0:
            return 0.0
        top = -np.inf
        for k, named, reach in self.lifters:
            now = max(float(np.dot(self.tools.pose_at(k, s)[0], self.up)) for s in (self.t0, self.t0 + t))
            top = max(top, max(named, now) + reach)
        return _lift_energy(self.g, self.mass, self.h0, top, self.extent)

    def driven_speed(self, t: float) -> float:
        """The fastest point of a moving tool or pinned set by time ``t`` (0 without them)."""
        return self.v_tools + self.w_tools * (self.diagonal + self.v_tools * t)

    def field_energy(self, x: np.ndarray, t: float) -> tuple[np.ndarray, float]:
        """``(potential, given)`` at ``t`` seconds since the monitor's state, of the particles
        checked at positions ``x``: each one's potential energy (J) in the fields acting now,
        and the most the fields switched on by then can have given (J; each one's potential
        energy when it came on)."""
        potential, given = np.zeros(len(x)), 0.0
        now = self.t0 + t
        for f, on, e in self.fields:
            if f.t_on <= now:
                given += e
            if f.active(now):
                r2 = ((x[on] - np.asarray(f.center))[:, [0, 2]] ** 2).sum(axis=1)
                potential[on] += 0.5 * f.strength * self.mass[on] * r2
        return potential, given

    def field_speed(self, t: float) -> np.ndarray:
        """Per particle checked, the most speed (m/s) the fields can have given it by ``t``
        seconds since the monitor's state: those on by then that act on its body (or on any,
        where bodies interact)."""
        speed = np.zeros(len(self.mass))
        for t_on, given, felt in self.field_speeds:
            if t_on <= self.t0 + t:
                speed[felt] += given
        return speed

    def speed_bounds(self, t: float) -> np.ndarray:
        """Per particle checked, the speed bound (m/s, before ``SPEED_FACTOR``) at ``t``."""
        fall = self.g * t if self.fall_height is None else min(self.g * t, math.sqrt(2.0 * self.g * self.fall_height))
        return self.v0 + fall + self.wave + self.driven_speed(t) + self.field_speed(t)

    def speed_bound(self, t: float) -> float:
        """The largest of ``speed_bounds(t)``."""
        return float(self.speed_bounds(t).max())

    def check(self, x: np.ndarray, v: np.ndarray, t: float, work: float | None = None):
        """``None``, or ``(why, particle)``: a non-finite position or velocity (whatever bounds
        run: a NaN passes every comparison, and a caller reading this alone, a fit's trial, took
        a NaN run as no blow-up), the exempt bodies' too (an exempt body is left out of the
        bounds alone: a non-finite value is no blow-up a scene shows but a lost state, which
        spreads to what it meets; ``simulate`` stops on it), else the first bound exceeded.
        ``work``: the work (J) the tools and pinned sets did on the bodies since the monitor's
        state (``ToolWork``), counted in place of ``lift_given``; None: not known."""
        bad = ~(np.isfinite(x[self.finite]).all(axis=1) & np.isfinite(v[self.finite]).all(axis=1))
        if bad.any():
            p = int(np.flatnonzero(self.finite)[int(np.argmax(bad))])
            return f"non-finite position or velocity (particle {p} is the first of {int(bad.sum())} bad particles)", p
        if not self.enabled:
            return None
        # A blown-up speed past 1e154 m/s squares to inf in float64, which is past every bound
        # and reported as such: numpy's overflow warning would only add noise to that report.
        with np.errstate(over="ignore"):
            return self._check(x, v, t, work)

    def _check(self, x: np.ndarray, v: np.ndarray, t: float, work: float | None = None):
        if not self.keep.all():
            x, v = x[self.keep], v[self.keep]
        x = x.astype(np.float64, copy=False)
        v = v.astype(np.float64, copy=False)
        speed2 = (v * v).sum(axis=1)
        bounds = self.speed_bounds(t)
        limit = self.SPEED_FACTOR * bounds
        # The speed farthest past its particle's own bound (a bound of 0: at rest at the start,
        # no wave speed, nothing falling yet, any speed is past it).
        ratio = np.divide(speed2, limit * limit, out=np.where(speed2 > 0.0, np.inf, 0.0), where=limit > 0.0)
        p = int(np.argmax(ratio))
        if speed2[p] > limit[p] * limit[p]:
            parts = ("fall + p-wave + initial speed" + (" + the fields' sqrt(k) R" if self.field_speed(t)[p] > 0.0 else "")
                     + (" + the tools' speed" if self.driven_speed(t) > 0.0 else ""))
            return (f"speed {math.sqrt(speed2[p]):.3g} m/s, more than {self.SPEED_FACTOR:g} x the {bounds[p]:.3g} m/s "
                    f"the scene can produce ({parts})"), int(self.index[p])
        ke = 0.5 * self.mass * speed2
        released = float((self.mass * self.g * (self.h0 - x @ self.up)).sum())
        driven = 0.5 * float(self.mass.sum()) * self.driven_speed(t) ** 2
        if driven > 0.0:
            # The potential energy a moving tool lifts the bodies by is its work, not a debit: a
            # blob a rising floor carried up had its budget fall to 0 J, and was a blow-up at
            # the tool's own speed. Held or fallen back (as speed): a block a keyframed platform
            # lifted 4 m and let fall was stopped in its fall when only the height held counted.
            # Where the run counted the tools' work (their reactions along their motion) that is
            # what they gave, elastic energy they pressed into a body and it gave back as speed
            # too (a rubber block a plate pressed 47 % and slid off was stopped in its spring-back).
            released = max(released, 0.0) + (self.lift_given(t) if work is None else max(float(work), 0.0))
        potential, given = self.field_energy(x, t)
        budget = max(self.ke0 + self.e_elastic + released + given + driven, 0.0)
        limit = self.ENERGY_FACTOR * budget + self.e_floor
        held = ke + potential
        energy = float(held.sum())
        if energy > limit:
            fields = "gravity's, and all the fields held when they came on" if self.fields else ""
            work_done = "" if work is None else f" (the tools' work on the bodies, {float(work):.3g} J, with it)"
            what = (f"and potential energy released{f' ({fields})' if fields else ''}{work_done}, and every particle at the "
                    "tools' speed" if driven > 0.0 else f"and potential energy released ({fields + '; ' if fields else ''}no work is done on the bodies)")
            kind = "kinetic energy and the fields' potential energy" if potential.any() else "kinetic energy"
            # The particle holding the most: one thrown far out may be at rest there.
            return (f"{kind} {energy:.3g} J, more than the {limit:.3g} J the scene can give: {self.ENERGY_FACTOR:g} "
                    f"x the {budget:.3g} J of initial kinetic and elastic energy {what}, plus a floor of {self.e_floor:.3g} J "
                    f"(0.5 M (0.1 c_P)^2)"), int(self.index[np.argmax(held)])
        outside = np.maximum(np.maximum(self.lo - x, x - self.hi), 0.0)
        d2 = (outside * outside).sum(axis=1)
        reach = self.REACH_FACTOR * (self.diagonal + bounds * t)
        # The speed bound's p-wave term grows with the stiffness a trial runs (sqrt(mu / rho)):
        # at mu 1e25 Pa it let a 6 cm block's particles 1.5 km out in one step (1.5e8 m at 1e30),
        # a blow-up. No stiffness moves a particle farther than the energy it is given: the
        # start's speeds, the fall, the fields', the tools' and the elastic energy stored at the
        # start (its recoil) bound the distance whatever the wave speed.
        far = self.FAR_FACTOR * (self.diagonal + (bounds - self.wave + self.recoil) * t)
        for limit, words in ((reach, f"{self.REACH_FACTOR:g} x its size plus the speed bound x time"),
                             (far, f"{self.FAR_FACTOR:g} x its size plus the distance its start's speed, the fall, "
                                  "the fields, the tools and the stored elastic energy can give, at any stiffness")):
            p = int(np.argmax(d2 / (limit * limit)))
            if d2[p] > limit[p] * limit[p]:
                return (f"a particle {math.sqrt(d2[p]):.3g} m outside the scene, more than {limit[p]:.3g} m "
                        f"({words})"), int(self.index[p])
        return None


#: A run whose kinetic + gravitational energy grew by more than this many times the scene's
#: energy scale has blown up (see ``energy_growth``).
BLOWUP_FACTOR = 10.0


def _wave_speed(model: Model, p: dict, keep: np.ndarray) -> float:
    """The fastest p-wave speed (m/s) among the materials of the particles ``keep``, at the
    parameters ``p`` the model runs now (``Model.parameter_values``)."""
    return float(model.wave_speeds(p)[np.unique(model.particle_material_np[keep])].max())


def _lift_energy(g: float, mass: np.ndarray, heights: np.ndarray, top: float, size: float) -> float:
    """The most gravitational energy (J) a moving tool whose reach got to the height ``top``
    (m along ``-gravity``) can have given particles of ``mass`` at ``heights``: each lifted to
    ``top`` plus the bodies' ``size`` above it (a body resting on the tool reaches that far
    over it), none lowered. ``DivergenceMonitor.lift_given`` and ``energy_growth`` read at
    the end of a run share it."""
    return g * float((mass * np.maximum(top + size - heights, 0.0)).sum())


def _energy_floor(mass: float, wave: float) -> float:
    """``0.5 M (0.1 c_P)^2`` (J): the kinetic energy a rest-configuration body of mass ``M``
    may hold without having blown up (the strain its positions may hold, and round-off),
    which a scene whose energy scale is 0 J, at rest without gravity, needs."""
    return 0.5 * mass * (0.1 * wave) ** 2


def energy_growth(model: Model, x0: np.ndarray, v0: np.ndarray, x: np.ndarray, v: np.ndarray, *, t0: float = 0.0,
                  dt: float | None = None, steps: int | None = None, particles=None,
                  stored: float = 0.0, scripted_seen: dict | None = None, work: float | None = None,
                  solver=None, state: State | None = None) -> tuple[str, int] | None:
    """``(why, particle)`` where a run from positions and velocities ``x0, v0`` (at time
    ``t0``) to ``x, v`` has blown up without a non-finite value, else ``None``: the one test of
    energy growth that ``simulate`` (at every frame), ``sweep``'s samples, ``fit``'s evaluations
    and the torch bridge share (``Rollout.bounds_hit`` runs it after ``DivergenceMonitor``'s
    bounds); ``particle`` is the
    one holding the most kinetic energy.

    Without force fields and moving tools nothing does work on the bodies but gravity (colliders
    are at rest, pressure and elastic forces are internal, viscosity and plasticity dissipate),
    so kinetic plus gravitational energy cannot grow: at the end it is at most its
    initial value plus the elastic energy stored at the start (``stored``, J; zero at rest),
    which it only takes from. An explicit step above the stable limit makes it grow without
    bound while the guards keep every value finite, and may stay inside the monitor's bounds
    (which allow a floor of ``0.5 M (0.1 c_P)^2``, the strain a rest-configuration body may
    hold). Growth beyond ``BLOWUP_FACTOR`` times the scale ``KE0 + M |g| L + stored`` (``L``
    the initial bounding-box diagonal plus the spacing), plus the monitor's floor ``0.5 M
    (0.1 c_P)^2``, is taken as a blow-up: without gravity or a start speed the scale is 0 J,
    and a body at rest, moved by round-off alone, was a blow-up.

    A tool or pinned set of known speed (``Velocity``, ``Keyframes``) is left to the monitor,
    which counts its work. A ``Scripted`` one has no speed known beforehand, and the monitor
    runs only its non-finite check: here its fastest point over the poses of the run's
    ``steps`` steps of ``dt`` from ``t0`` joins the scale as ``0.5 M v^2``, and the height it
    lifts the bodies by is its work, not growth: read here at the end alone, up to each
    particle lifted to its highest position plus its reach and the bodies' size (``simulate``,
    reading every frame, counts the tools' work instead, ``work``). ``work``: the work (J) the
    tools and pinned sets did on the bodies since ``x0, v0`` (``ToolWork``, which ``simulate``
    leaves in ``solver.tool_work_done``), taken off the growth in place of the heights and the
    scripted speed: a tool's push stored as elastic energy and given back as speed counts too.
    ``scripted_seen``: the scripted motions as the
    run's own steps evaluated them (``{k: (linear speed, angular speed, lowest, highest
    position)}``, the fastest over the steps, ``simulate``'s record of
    ``ToolSet.scripted_step_motion``), read in place of calling the poses again (``dt`` and
    ``steps`` are then not needed). ``particles``: a boolean mask of the particles read (one
    world of a model of worlds, the bodies not exempt), None: all. ``solver``: the ``Solver``
    that ran the steps, whose stable step (its fit and hourglass strength, ``Solver.stable_dt``)
    the message quotes; None: ``Model.stable_dt()``, a ``Solver(model)``'s. ``state``: the run's
    start, whose stable step it is (``Model.stable_dt(state=)``: a flowed body made elastic keeps
    half the wave limit); None: a new state's.
    """
    hit = _grown(model, x0, v0, x, v, t0=t0, dt=dt, steps=steps, particles=particles, stored=stored,
                 scripted_seen=scripted_seen, work=work)
    if hit is None:
        return None
    stable = model.stable_dt(state=state) if solver is None else solver.stable_dt(state=state)
    return (f"the simulation blew up: {hit[0]}; the time step is likely above the stable limit {stable:.3g} s",
            hit[1])


def _grown(model: Model, x0, v0, x, v, *, t0, dt, steps, particles, stored, scripted_seen,
           memo: dict | None = None, work: float | None = None) -> tuple[str, int] | None:
    """``energy_growth``'s test: ``(what grew, particle)`` without its words around it, which
    ``simulate`` puts in its own divergence message (step, frame, time, advice). ``memo``:
    ``simulate``'s record across its frames (a dict, empty at the start; ``x0, v0, particles``
    and ``stored`` the same at every frame): what the start gives (its particles' masses, its
    kinetic energy, its size) is read from the device and summed once. ``work``: the work (J)
    the tools and pinned sets did on the bodies since ``x0, v0`` (``ToolWork``; ``simulate``
    always counts it), which is what they gave, in place of the height and the scripted speed
    that bound it where it is not known: a tool's push stored as elastic energy and given back
    as speed counts too."""
    if getattr(model, "force_fields", None):
        return None
    memo = {} if memo is None else memo
    if "keep" not in memo:
        keep = np.ones(model.particle_count, dtype=bool) if particles is None else np.asarray(particles, dtype=bool)
        all_kept = bool(keep.all())
        x0k, v0k = np.asarray(x0, dtype=np.float64)[keep], np.asarray(v0, dtype=np.float64)[keep]
        m = model.particle_mass.numpy().astype(np.float64)[keep]
        memo.update(keep=keep, all=all_kept, x0=x0k, m=m, ke0=0.5 * float((m * (v0k * v0k).sum(axis=1)).sum()),
                    size=(float(np.linalg.norm(x0k.max(axis=0) - x0k.min(axis=0))) + model.spacing) if len(m) else 0.0)
    keep = memo["keep"]
    if not keep.any():
        return None
    x0, m = memo["x0"], memo["m"]
    x1 = np.asarray(x, dtype=np.float64) if memo["all"] else np.asarray(x, dtype=np.float64)[keep]
    v1 = np.asarray(v, dtype=np.float64) if memo["all"] else np.asarray(v, dtype=np.float64)[keep]
    moving = _tools_move(model)
    reached = _scripted_speed(model, x0, x1, t0, dt, steps, scripted_seen) if moving else (0.0, None)
    if reached is None:
        return None  # the monitor's energy bound counts the tools' work
    scripted, top = reached
    g = np.asarray(model.gravity, dtype=np.float64)
    # A blown-up speed past 1e154 m/s squares to inf, which is past the limit as it should be.
    with np.errstate(over="ignore", invalid="ignore"):
        ke = 0.5 * m * (v1 * v1).sum(axis=1)
        kinetic = float(ke.sum()) - memo["ke0"]
        lifted = float(-(m * ((x1 - x0) @ g)).sum())
    if moving and work is not None:
        scripted = 0.0
        grew = kinetic + lifted - max(float(work), 0.0)
    elif moving:
        # Without the work, the most height it can have given, held or fallen back as speed (a
        # body a scripted platform lifted 4 m and let fall was stopped in its fall when only the
        # height it still held counted): each particle lifted to the tools' highest reach plus
        # the bodies' size above it.
        raised = max(lifted, 0.0)
        if top is not None and np.linalg.norm(g) > 0.0:
            up = -g / np.linalg.norm(g)
            raised = max(raised, _lift_energy(float(np.linalg.norm(g)), m, x0 @ up, top, memo["size"]))
        grew = kinetic + lifted - raised
    else:
        grew = kinetic + lifted
    scale = (memo["ke0"] + float(m.sum()) * float(np.linalg.norm(g)) * memo["size"]
             + 0.5 * float(m.sum()) * scripted ** 2 + max(float(stored), 0.0))
    if not grew > BLOWUP_FACTOR * scale:
        return None  # inside the limit without the floor (>= 0), whose wave speeds cost a frame as much again
    floor = _energy_floor(float(m.sum()), _wave_speed(model, model.parameter_values(), keep))
    if grew > BLOWUP_FACTOR * scale + floor:
        does = (f"less the tools' work on the bodies, {float(work):.4g} J" if moving and work is not None
                else f"with every particle at a scripted tool's fastest {scripted:.3g} m/s" if scripted > 0.0
                else "nothing does work on the bodies")
        return (f"kinetic + gravitational energy grew by {grew:.4g} J, more than "
                f"{BLOWUP_FACTOR:g} x the scene's energy scale {scale:.4g} J plus a floor of {floor:.3g} J "
                f"(0.5 M (0.1 c_P)^2) ({does})"), int(np.flatnonzero(keep)[int(np.argmax(ke))])
    return None


def _scripted_speed(model: Model, x0: np.ndarray, x: np.ndarray, t0: float, dt, steps, seen=None) -> tuple | None:
    """``(speed, top)``: the fastest point (m/s) of the moving tools and pinned sets of
    ``model`` over a run of ``steps`` steps of ``dt`` from ``t0`` (particles from ``x0`` to
    ``x``) where one is ``Scripted`` (its poses read at each step's time, as the run read them;
    ``seen``: as the run's steps evaluated them, ``energy_growth``'s ``scripted_seen``), and the
    highest a Scripted one reached (m along ``-gravity``: its highest position plus its reach;
    None without gravity), else None: every motion's speed is known and the monitor bounds the
    energy with it."""
    motions = [c.motion for c in model.tools.colliders] + [p.motion for p in model.tools.pins]
    if not any(isinstance(mo, tools.Scripted) for mo in motions):
        return None
    if seen is None and (dt is None or steps is None):
        raise ValueError(f"dt = {dt!r}, steps = {checks.shorten(steps)!r} is not allowed: a scene with a Scripted tool or pinned set "
                         "needs the run's step (s) and step count to be checked for a blow-up")
    xs = np.concatenate([x0, x])
    lo, hi = xs.min(axis=0), xs.max(axis=0)
    speeds = []
    g = np.asarray(model.gravity, dtype=np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0.0 else None
    top = None
    for k, mo in enumerate(motions):
        if isinstance(mo, tools.Scripted) and seen is not None:
            lin, ang, *at = seen.get(k, (0.0, 0.0))
        elif isinstance(mo, tools.Scripted):
            times = float(t0) + dt * np.arange(steps + 1)
            poses = [mo.pose(t) for t in times]
            at = np.array([p for p, _ in poses], dtype=np.float64)
            q = np.array([q for _, q in poses], dtype=np.float64)
            lin = float((np.linalg.norm(np.diff(at, axis=0), axis=1) / dt).max()) if steps else 0.0
            cos = np.clip(np.abs((q[1:] * q[:-1]).sum(axis=1)), 0.0, 1.0)
            ang = float((2.0 * np.arccos(cos) / dt).max()) if steps else 0.0
        else:
            lin, ang, at = _driven_motion(mo)
        if len(at):
            lo, hi = np.minimum(lo, np.min(at, axis=0)), np.maximum(hi, np.max(at, axis=0))
            if isinstance(mo, tools.Scripted) and up is not None:
                # The highest corner of the box of its positions (seen's two corners, or the poses).
                high = float(np.maximum(np.min(at, axis=0) * up, np.max(at, axis=0) * up).sum())
                top = max(top if top is not None else -np.inf, high + model.tools._scripted_reach(k))
        speeds.append((lin, ang))
    # A turning tool's fastest point that can touch a particle: its angular speed times the
    # farthest a particle or a pose lies from another.
    reach = float(np.linalg.norm(hi - lo)) + 2.0 * model.support_radius
    return max(lin + ang * reach for lin, ang in speeds), top


def _tools_move(model: Model) -> bool:
    """Whether a tool or pinned set of ``model`` moves (a scripted motion may): it does work on
    the bodies, which the divergence monitor counts where the motion's speed is known, and
    ``energy_growth`` counts for a scripted one (a blob a rising floor lifted 1.2 m was a blow-up
    in every sample)."""
    if getattr(model, "tools", None) is None:
        return False
    motions = [c.motion for c in model.tools.colliders] + [p.motion for p in model.tools.pins]
    driven = [_driven_motion(mo) for mo in motions]
    return any(d is None or d[0] > 0.0 or d[1] > 0.0 for d in driven)


def _stored_energy_bound(model: Model, p: dict, F: np.ndarray, keep: np.ndarray) -> float:
    """An upper bound (J) of the elastic energy the particles ``keep`` hold at deformation
    gradients ``F`` (a prestrained ``F0``, a resumed state): its recoil is no blow-up.

    Per particle ``2 (mu + 3/2 max(lam, 0) + 3/2 rho k_p) sum_i max((s_i - 1)^2,
    ((s_i^2 - 1) / 2)^2) V`` over F's singular values ``s``: rotation-free (``|F - I|^2``
    read a body turned by 90 degrees as 4 units of strain and so let a blow-up of a resumed
    tumbling body pass), at least each model's energy (the linear model's in ``s - 1``, St.
    Venant-Kirchhoff's in Green's strain, the hyperelastic one's twice that; the smallest
    ``s`` signed by det F, so a mirrored F counts its inversion), and with lam
    < 0 (down to -2 mu / 3) the shear energy still counted."""
    if not keep.any():
        return 0.0
    density = np.array([m.density for m in model.materials], dtype=np.float64)
    stiffness = p["mu"] + 1.5 * np.maximum(p["lam"], 0.0) + 1.5 * density * p["pressure_stiffness"]
    F = F.astype(np.float64)[keep]
    finite = np.isfinite(F).all(axis=(1, 2))  # a NaN F (numpy's SVD fails on it) is the non-finite check's
    s = np.ones((len(F), 3))
    s[finite] = np.linalg.svd(F[finite], compute_uv=False)
    # Signed, as the energies read them: a mirrored F (an inverted rest fit, which the rest
    # model takes) holds the energy of its negative singular value, where |s| read none.
    s[finite, 2] *= np.sign(np.linalg.det(F[finite]))
    strain = np.maximum((s - 1.0) ** 2, (0.5 * (s * s - 1.0)) ** 2).sum(axis=1)
    volume = model.particle_volume.numpy().astype(np.float64)[keep]
    return float(2.0 * (stiffness[model.particle_material_np[keep]] * strain * volume).sum())


def _repulsion_energy(model: Model, p: dict, x: np.ndarray, keep: np.ndarray) -> float:
    """The pair repulsion's energy (J) ``sum s (1 - r/r0)^3`` over the pairs within ``r0``
    at positions ``x`` with a particle of ``keep``, of one neighbour group (``pressure.pair_repulsion_force``,
    ``pair_repulsion_strength``): a start holding it gives it back as speed, no blow-up
    (two particles 0.1 dx apart at c = 2 hold 8.2 mJ; the floor was 0.36 mJ). 0 where no
    material has ``pair_repulsion > 0``."""
    from .sim.pressure import PAIR_REPULSION_RANGE  # noqa: PLC0415 (model data first, kernels on demand)

    c = np.array([m.pair_repulsion for m in model.materials], dtype=np.float64)
    if not (c > 0.0).any() or not keep.any():
        return 0.0
    r0 = PAIR_REPULSION_RANGE * model.support_radius
    x = np.asarray(x, dtype=np.float64)
    ok = np.isfinite(x).all(axis=1)  # a NaN position is the non-finite check's
    idx = np.flatnonzero(ok)
    cell = np.floor(x[idx] / r0).astype(np.int64)
    cell -= cell.min(axis=0) - 1
    span = cell.max(axis=0) + 2
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    first, second = [], []
    # Pairs within r0 share a cell of side r0 or touch it: each of the 27 offsets, by search.
    for off in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T:
        k = ((cell[:, 0] + off[0]) * span[1] + cell[:, 1] + off[1]) * span[2] + cell[:, 2] + off[2]
        lo = np.searchsorted(sorted_key, k, "left")
        n = np.searchsorted(sorted_key, k, "right") - lo
        a = np.repeat(np.arange(len(idx)), n)
        b = order[np.repeat(lo, n) + np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)]
        first.append(a[a < b])
        second.append(b[a < b])
    i, j = idx[np.concatenate(first)], idx[np.concatenate(second)]
    r = np.linalg.norm(x[i] - x[j], axis=1)
    near = (r < r0) & (keep[i] | keep[j])
    if model.neighbor_group is not None:  # other worlds (or bodies that do not interact) never meet
        group = model.neighbor_group.numpy()
        near &= group[i] == group[j]
    i, j, r = i[near], j[near], r[near]
    mat = model.particle_material_np
    ck = c * np.asarray(p["pressure_stiffness"], dtype=np.float64)
    mass = model.particle_mass.numpy().astype(np.float64)
    s = 0.5 * (ck[mat[i]] + ck[mat[j]]) * np.sqrt(mass[i] * mass[j])
    return float((s * (1.0 - r / r0) ** 3).sum())


def _driven_motion(motion):
    """``(linear speed, angular speed, poses)`` of a tool's or pinned set's motion
    (``tools.Velocity``, ``tools.Keyframes``): the fastest over its motion, and the positions
    it passes through that it names; None for a scripted one, whose speed is not known."""
    if isinstance(motion, tools.Velocity):
        poses = [] if motion.position is None else [np.asarray(motion.position, dtype=np.float64)]
        return float(np.linalg.norm(motion.velocity)), float(np.linalg.norm(motion.angular_velocity)), poses
    if isinstance(motion, tools.Keyframes):
        t = np.asarray(motion.times, dtype=np.float64)
        p = np.asarray(motion.positions, dtype=np.float64).reshape(len(t), 3)
        dt = np.diff(t)
        lin = float((np.linalg.norm(np.diff(p, axis=0), axis=1) / dt).max()) if len(t) > 1 else 0.0
        ang = 0.0
        if motion.orientations is not None and len(t) > 1:
            q = np.asarray(motion.orientations, dtype=np.float64).reshape(len(t), 4)
            cos = np.clip(np.abs((q[1:] * q[:-1]).sum(axis=1)), 0.0, 1.0)
            ang = float((2.0 * np.arccos(cos) / dt).max())
        return lin, ang, list(p)
    return None


def _steps_a_frame(frame_dt: float, stable: float) -> tuple[float, int]:
    """``(ratio, n)``: the steps of ``stable`` a frame of ``frame_dt`` takes, and the whole
    number of steps no longer than ``stable`` that fill it (0 where the ratio is above
    ``MAX_STEPS_PER_FRAME`` or not a number, which the caller refuses). The default step, each
    world's step alone (``_warn_worlds_step``), the adaptive step and ``warp-esph fit``'s
    stiffest start are this one count: computed apart, the warning could name a world as
    differing where only the rounding differed. The ratio is shaved by 1e-12 so that a frame a
    whole number of stable steps long, to round-off, is that many steps and not one more."""
    ratio = frame_dt / stable * (1.0 - 1e-12)
    return ratio, (max(1, math.ceil(ratio)) if ratio <= MAX_STEPS_PER_FRAME else 0)


def _warn_worlds_step(model: Model, courant: float, hourglass, frame_dt: float, n: int, flag, fit=None,
                      state: State | None = None) -> None:
    """Warn where the step of a model of worlds (the stiffest world's) is not what a world runs
    alone: a soft world beside a stiff one ran 14 steps a frame where alone it runs 1, and ended
    2.8e-4 m off its separate run in 3 frames (float64, measured), unsaid. ``fit``: the one ``n``
    was counted for (``resolve_timestep``'s), ``state`` the start it was counted from."""
    # Counted with the model's fit, identical worlds under a solver asked for the corrected
    # incremental fit (half the step) were each told they run half the count alone.
    alone = [_steps_a_frame(frame_dt, s)[1] for s in model.world_stable_dts(courant, hourglass, fit, state)]
    other = [w for w, k in enumerate(alone) if k != n]
    if other:
        # Each world beside its own count: listed apart ('[0, 2] ... 31, 50', the counts sorted
        # and merged) they did not say which world runs which.
        first, *rest = other
        each = ", ".join([f"world {first}: {alone[first]} step{'s' if alone[first] != 1 else ''} a frame"]
                         + [f"world {w}: {alone[w]}" for w in rest])
        warnings.warn(f"the step {frame_dt / n:.3g} s ({n} a frame) is the stiffest world's; alone, a world runs its "
                      f"own ({each}); give {flag('dt')}= (the same to their separate runs) to compare the worlds with "
                      "separate runs", RuntimeWarning, stacklevel=3)


def check_fps(name: str, fps) -> float:
    """``fps`` as a float, refused (ValueError naming ``name``) unless a positive rate whose
    frames can be stepped: at most ``MAX_FPS``, and with a frame ``1 / fps`` a float holds."""
    fps = checks.positive(name, fps)
    if fps > MAX_FPS:
        # 1e300 frames a second ran with dt = 1e-300 s, 0 in float32, and exited 0.
        raise ValueError(f"{name} = {checks.shorten(fps)!r} is not allowed: must be at most {MAX_FPS:g} (frames of a microsecond and longer)")
    if not math.isfinite(1.0 / fps):
        # 5e-324 frames a second: a frame of inf s, refused as needing 'inf steps' or with the
        # advice 'use dt >= inf s'.
        raise ValueError(f"{name} = {checks.shorten(fps)!r} is not allowed: it is too small to step, a frame (1/fps) being longer "
                         f"than a float holds; must be above {1.0 / sys.float_info.max:.3g}")
    return fps


def resolve_timestep(model: Model, fps: float = 30.0, substeps: int | None = None, dt: float | None = None,
                     hourglass: float | None = None, flag=None, limit: float | None = None,
                     fit: str | None = None, state: State | None = None) -> tuple[int, float]:
    """``(substeps, dt)`` with ``substeps * dt = 1 / fps``.

    Give at most one of ``substeps`` and ``dt``. With neither, ``dt`` is the model's
    stable step (``model.stable_dt(hourglass=hourglass)``: None, the model's hourglass
    control) rounded down so that a whole number of steps fills a frame. A given ``dt`` must divide ``1 / fps`` into a whole number of steps
    (to 1e-6 relative). ``flag(name)``: how a refusal names ``fps``, ``dt`` or ``substeps``
    (the CLI's ``--dt`` where the value is the option's). ``limit``: a shorter bound than the
    model's own stable step where neither is given (``warp-esph fit``'s stiffest start,
    ``fit.starts_stable_steps``). ``fit``: the solver's asked fit (``Model.stable_dt``'s; None:
    the model's); ``state``: the run's start (``Model.stable_dt``'s; None: a new state).
    """
    flag = flag or (lambda name: name)
    fps = check_fps(flag("fps"), fps)
    frame_dt = 1.0 / fps
    if substeps is not None and dt is not None:
        raise ValueError(f"{flag('substeps')} = {substeps!r} and {flag('dt')} = {dt!r} are not allowed together: give one of them (or neither)")
    if substeps is not None:
        n = checks.positive_int(flag("substeps"), substeps, maximum=MAX_STEPS_PER_FRAME)
        return n, frame_dt / n
    if dt is None:
        courant = 0.3  # stable_dt's own
        stable = model.stable_dt(courant, hourglass=hourglass, fit=fit, state=state)
        if limit is not None:
            stable = min(stable, limit)
        ratio, n = _steps_a_frame(frame_dt, stable)
        if not n:
            stiff = max(model.materials, key=lambda m: m.p_wave_speed)
            needs = (f"more than {MAX_STEPS_PER_FRAME:.0e}; the stiffest material (p-wave speed {stiff.p_wave_speed:.3g} "
                     f"m/s) or the most viscous one needs it")
            advice = STABLE_ADVICE
            control = _hourglass_cause(model, courant, hourglass, fit, state)
            field = _field_cause(model, courant, hourglass, fit, state)
            viscous = _viscous_limit(model, courant)
            repulsion = _repulsion_cause(model, courant, hourglass, fit, state)
            if not (viscous is not None and viscous[0] <= stable * (1.0 + 1e-9)):
                if repulsion is not None:
                    # A stiff pair repulsion shortened it: the stiffest material's wave speed was
                    # blamed, which leaves the repulsion's limit as it is.
                    needs = f"more than {MAX_STEPS_PER_FRAME:.0e}; the pair repulsion sets it ({repulsion})"
                    advice = STABLE_REPULSION_ADVICE
                elif field is not None:
                    # A field's spring shortened it (strength 1e15 1/s^2: 4e-8 s): the stiffest
                    # material was blamed, and softer ones advised, which leave its limit as it is.
                    needs = f"more than {MAX_STEPS_PER_FRAME:.0e}; a compression field sets it ({field})"
                    advice = STABLE_FIELD_ADVICE
                elif control is not None:
                    # The control's springs shortened it (Solver(hourglass=1000) on a stiff box: 5 x
                    # the wave limit): the stiffest material was blamed, and softer ones advised,
                    # where a smaller strength lengthens the step the most.
                    needs = f"more than {MAX_STEPS_PER_FRAME:.0e}; the hourglass control sets it ({control})"
                    advice = STABLE_HOURGLASS_ADVICE
            raise StepRefusal(
                f"the stable step {stable:.3g} s is not allowed: a frame (1/fps = {frame_dt:.6g} s) would take {ratio:.3g} steps, "
                f"{needs}", advice,
                detail=f"a frame (1/fps = {frame_dt:.6g} s) would take {ratio:.3g} steps of the stable step {stable:.3g} s, {needs}"
            )
        if model.world_count > 1 and limit is None:
            _warn_worlds_step(model, courant, hourglass, frame_dt, n, flag, fit, state)
        return n, frame_dt / n
    dt = checks.positive(flag("dt"), dt)
    ratio = frame_dt / dt
    if not ratio <= MAX_STEPS_PER_FRAME:
        raise ValueError(
            f"{flag('dt')} = {checks.shorten(dt)!r} is not allowed: a frame (1/fps = {frame_dt:.6g} s) would take {ratio:.3g} steps, "
            f"more than {MAX_STEPS_PER_FRAME:.0e}; use {flag('dt')} >= {frame_dt / MAX_STEPS_PER_FRAME:.3g} s"
        )
    n = round(ratio)
    if n < 1 or abs(ratio - n) > 1e-6 * ratio:
        lo = max(1, math.floor(ratio))
        # Written as it is given: an option as typed on the command line ('--dt 0.000694'), a
        # parameter or key as assigned ('dt = 0.000694').
        give = f"{flag('dt')} " if flag("dt").startswith("--") else f"{flag('dt')} = "
        hint = (f"{give}{frame_dt / lo:.6g}" if n < 1 else
                f"{give}{frame_dt / math.ceil(ratio):.6g} or {frame_dt / lo:.6g}")
        raise ValueError(
            f"{flag('dt')} = {checks.shorten(dt)!r} is not allowed: a frame (1/fps = {frame_dt:.6g} s) must be a whole number of steps, "
            f"but 1/fps / dt = {ratio:.6g}; use e.g. {hint}, or leave {flag('dt')} out (the stable step, rounded to fill a frame)"
        )
    return n, frame_dt / n


def scene_dt_refusal(what: str, dt: float, fps: float, rate: str, give: str, other_rates: bool = True) -> ValueError:
    """The refusal of a scene's own step ``dt`` (``what``: how it is named, "fig1's dt") that
    does not fill a frame at a rate the scene did not set (``rate``: what set it, "--fps = 30"),
    advising the caller's way to give a step (``give``: "--dt") and, with ``other_rates`` (a rate
    the caller may change, not one its data were recorded at), the rates the step fills:
    ``resolve_timestep``'s own line named a bare ``dt`` nobody had typed, and advised leaving it
    out, which a built-in scene's step cannot be."""
    frame_dt = 1.0 / fps
    ratio = frame_dt / dt
    counts = sorted({max(1, math.floor(ratio)), max(1, math.ceil(ratio))}, reverse=True)
    steps = " or ".join(f"{frame_dt / n:.6g}" for n in counts)
    rates = " or ".join(f"{1.0 / (dt * n):.6g}" for n in counts)
    return ValueError(f"{rate} is not allowed with {what} = {dt:.6g} s: a frame (1/fps = {frame_dt:.6g} s) must be a whole "
                      f"number of steps, but 1/fps / dt = {ratio:.6g}; give {give} {steps} with it"
                      + (f", or a rate the step fills ({rates} fps)" if other_rates else ""))


def skipped_fits(counts: dict) -> int:
    """The particle-steps whose deformation fit the guards of paper §4 skipped, of a
    ``Solver.guard_counts()`` (its two guards' counts are of different particle-steps)."""
    return int(counts["few_neighbors"]) + int(counts["ill_conditioned"])


def coarse_bodies(model, by_body: dict, steps: int) -> list[tuple[str, float]]:
    """``(name, share)`` of each body whose fits were skipped in ``SKIPPED_FIT_SHARE`` or more of
    its own particle-steps (``by_body``: ``Solver.skipped_fits()`` over ``steps`` steps), the
    largest share first: the bodies a run's warning and ``warp-esph run``'s summary name."""
    out = []
    for b in model.bodies:
        total = b.count * steps
        if total > 0 and by_body.get(b.name, 0) >= SKIPPED_FIT_SHARE * total:
            out.append((b.name, by_body[b.name] / total))
    return sorted(out, key=lambda item: -item[1])


def shown_bodies(bodies: list[tuple[str, float]]) -> str:
    """``coarse_bodies`` as the warning and the summary show them: 'star' 8.4 %, ..."""
    return ", ".join(f"{name!r} {100.0 * share:.3g} %" for name, share in bodies)


def skipped_fit_warning(skipped: int, particle_steps: int, larger: str = "a smaller spacing",
                        bodies: list[tuple[str, float]] | None = None) -> str | None:
    """The warning of a run whose fits were skipped in ``skipped`` of its ``particle_steps``,
    or None below ``SKIPPED_FIT_SHARE`` (a guard acting on a few particles briefly, as at a
    landing, says nothing). ``larger``: how the caller makes the bodies finer; ``bodies``: the
    bodies that skipped as much of their own (``coarse_bodies``), named."""
    if particle_steps <= 0 or skipped < SKIPPED_FIT_SHARE * particle_steps:
        return None
    named = f"; by body, of its own particle-steps: {shown_bodies(bodies)}" if bodies else ""
    return (f"the deformation fit was skipped in {100.0 * skipped / particle_steps:.3g} % of the run's particle-steps "
            f"({skipped} of {particle_steps}) by the guards of paper §4 (too few neighbours, or too flat a "
            f"neighbourhood){named}: there the bodies are too coarse for the fit (parts one or two particle layers "
            f"across) and did not deform as their material; give them more particle layers ({larger})")


def check_step_count(frames: int, substeps: int) -> None:
    """Refuse a run of more than ``MAX_STEPS`` steps before it starts."""
    if frames * substeps > MAX_STEPS:
        total = frames * substeps
        shown = f"{total:.3g}" if total < 1e300 else "more than 1e300"  # (10**400 overflowed the formatting)
        detail = f"at {substeps} steps per frame the run would take {shown} steps, more than {MAX_STEPS:.0e}"
        raise StepRefusal(f"frames = {checks.shorten(frames)!r} is not allowed: {detail}", "; give fewer frames=, or a larger dt= (fewer substeps=)",
                          detail=detail)


def adaptive_timestep(model: Model, state: State, fps: float = 30.0, courant: float = 0.3,
                      hourglass: float | None = None, until: float | None = None,
                      fit: str | None = None) -> tuple[int, float]:
    """``(substeps, dt)`` for the next frame of ``state``, ``substeps * dt = 1 / fps``.

    The CFL limit of docs/method.md §8 with the signal speed measured now: a disturbance
    travels at the p-wave speed relative to the material, which itself moves, so

        dt <= C dx / (c_P + v_max + |g| / fps)

    where ``v_max`` is the largest particle speed of ``state`` (or of a tool's points over the
    frame, ``ToolSet.fastest``: a tool gives the particles it meets its speed) and ``|g| / fps`` bounds
    what gravity adds to it within the frame; and ``dt`` is at most ``Model.stable_dt`` (its
    viscous limit, with the limits of the force fields and of the hourglass control of strength
    ``hourglass``; None: the model's; of the fit ``fit``, half the wave limit where the step runs
    the corrected fit on the incremental composition). The speed term is not halved there: it
    is the shorter only where ``v_max + |g| / fps > c_P``, below that half already, and halving
    it changed no energy reading (docs/physics.md, "The biweight's incremental composition
    (measured)"). A body at rest gets ``stable_dt`` (to the gravity term); one in
    flight or hit hard gets smaller steps. Rounded down to a whole number of steps per frame.
    ``until``: take the tools' speeds up to that time instead of over the next frame (a run
    checks its whole span before its first step).
    """
    fps = checks.positive("fps", fps)
    courant = checks.courant(courant)
    frame_dt = 1.0 / fps
    stable = model.stable_dt(courant, hourglass=hourglass, fit=fit, state=state)
    c = float(np.max(model.wave_speeds()))
    v = state.v.numpy().astype(np.float64)
    v_max = float(np.sqrt((v * v).sum(axis=1)).max()) if len(v) else 0.0
    if not math.isfinite(v_max):
        v_max = 0.0  # the divergence check after the frame reports it
    who = "a particle speed"
    if model.tools is not None:
        # A tool gives the particles it meets its own speed: the step must follow it too (a
        # box at 3 spacings a step flattened a resting block into a sheet).
        ts = model.tools
        for k, speed, when in ts.fastest(state.time, state.time + frame_dt if until is None else until):
            if speed > v_max:
                v_max = speed
                who = f"{ts._owner(k)}: its {type(ts.motions[k]).__name__} motion's speed (from t = {when:.4g} s)"
    g = float(np.linalg.norm(model.gravity))
    dt = min(stable, courant * model.spacing / (c + v_max + g * frame_dt))
    ratio, n = _steps_a_frame(frame_dt, dt)
    if not n:
        # A start at 1e37 m/s asked for a step of 6e-40 s, below what float32 holds, and was
        # refused as a bad dt the user never gave.
        fastest = courant * model.spacing * fps * MAX_STEPS_PER_FRAME - c - g * frame_dt
        if fastest > 0.0 and v_max > fastest:
            raise ValueError(
                f"{who} of {v_max:.3g} m/s is not allowed with the adaptive step: it would take {ratio:.3g} "
                f"steps a frame, more than {MAX_STEPS_PER_FRAME:.0e} (dt = C dx / (c_P + v_max + |g| / fps)), so at most "
                f"{fastest:.3g} m/s at this spacing and fps"
            )
        # Not the speed: the material's own step (a body at rest was told its speed of 0 m/s was too
        # much), or gravity's term, which a long frame makes the largest: at 0.01 fps it was called
        # 'its stable step, 1.52e-05 s' of a model whose stable step is 200 times that.
        fall = g * frame_dt
        advice = ADAPTIVE_FALL_ADVICE if fall > c + v_max else ADAPTIVE_ADVICE
        if dt == stable:
            which = f"its stable step, {dt:.3g} s (wave speed c_P = {c:.3g} m/s at spacing {model.spacing:g} m)"
            control = _hourglass_cause(model, courant, hourglass, fit, state)
            if control is not None:
                # The control's springs shortened it (Solver(hourglass=1000) on a stiff box: 5 x
                # the wave limit): c_P alone was cited, and a softer material advised, where a
                # smaller strength lengthens the step the most.
                which = f"its stable step, {dt:.3g} s ({control})"
                advice = ADAPTIVE_HOURGLASS_ADVICE
            field = _field_cause(model, courant, hourglass, fit, state)
            if field is not None:
                # A field's spring shortened it: the wave speed was cited, and a softer material
                # or a larger spacing advised, which leave its limit as it is.
                which = f"its stable step, {dt:.3g} s ({field})"
                advice = ADAPTIVE_FIELD_ADVICE
            repulsion = _repulsion_cause(model, courant, hourglass, fit, state)
            if repulsion is not None:
                which = f"its stable step, {dt:.3g} s ({repulsion})"
                advice = ADAPTIVE_REPULSION_ADVICE
            viscous = _viscous_limit(model, courant)
            if viscous is not None and viscous[0] <= stable * (1.0 + 1e-9):
                # The viscous limit set it: the wave speed was cited, and a softer material
                # advised, which leaves that limit as it is.
                which = (f"its stable step, {dt:.3g} s (the viscous limit (C / 12) rho0 h^2 / eta of material "
                         f"{viscous[1]}, viscosity eta = {viscous[2]:.3g} Pa s at support radius h = "
                         f"{model.support_radius:g} m)")
                advice = ADAPTIVE_VISCOUS_ADVICE
        else:
            which = (f"its step C dx / (c_P + v_max + |g| / fps) = {dt:.3g} s (c_P = {c:.3g} m/s, v_max = {v_max:.3g} m/s, "
                     f"|g| / fps = {fall:.3g} m/s, at spacing {model.spacing:g} m; the stable step is {stable:.3g} s)")
        raise StepRefusal(
            f"the adaptive step is not allowed for this model at {fps:g} fps: {which}, would take {ratio:.3g} steps a "
            f"frame, more than {MAX_STEPS_PER_FRAME:.0e}", advice
        )
    return n, frame_dt / n


def _wave_limit(model: Model, courant: float, fit: str | None, state: State | None = None) -> tuple[float, str, float]:
    """``(wave, words, c_P)``: ``stable_dt``'s wave limit for the fit ``fit`` (None: the model's)
    and how the refusals write it: ``C dx / c_P``, x ``CORRECTED_INCREMENTAL_STEP`` where the step
    runs the corrected incremental fit (from ``state``, None: a new state; a flowed body made
    elastic keeps it). Against the whole one, a control between it and the half was said to set
    the step, and a smaller strength advised, which leaves it as it is."""
    c = float(np.max(model.wave_speeds()))
    wave = courant * model.spacing / c
    if model.corrected_incremental(fit, state):
        return CORRECTED_INCREMENTAL_STEP * wave, f"{CORRECTED_INCREMENTAL_STEP:g} C dx / c_P", c
    return wave, "C dx / c_P", c


def _hourglass_cause(model: Model, courant: float, hourglass: float | None, fit: str | None = None,
                     state: State | None = None) -> str | None:
    """Where the hourglass control's limit (``Model._hourglass_limit``, strength ``hourglass``;
    None: the model's) is at most the wave limit (``_wave_limit``, for the fit ``fit`` from
    ``state``), so that it is what shortens ``stable_dt``: the refusals' words for it, naming
    both limits; else None."""
    control, strength = model._hourglass_limit(courant, hourglass)
    wave, words, c = _wave_limit(model, courant, fit, state)
    if not control <= wave:
        return None
    return (f"the hourglass control's limit at strength c = {strength:g}, {control:.3g} s, with the wave limit "
            f"{words} = {wave:.3g} s, c_P = {c:.3g} m/s at spacing {model.spacing:g} m")


def _field_cause(model: Model, courant: float, hourglass: float | None, fit: str | None = None,
                 state: State | None = None) -> str | None:
    """Where the force fields' limit (``Model._field_limit``) is at most both the wave limit
    (``_wave_limit``, for the fit ``fit``) and the hourglass control's (strength ``hourglass``;
    None: the model's), and the viscous limit is not shorter than ``stable_dt``, so that the
    field is what shortens it: the refusals' words for it, naming the fields, their net strength
    and both limits; else None."""
    limit, k, which = model._field_limit(courant)
    wave, words, c = _wave_limit(model, courant, fit, state)
    if not (limit <= wave and limit <= model._hourglass_limit(courant, hourglass)[0]):
        return None
    viscous = _viscous_limit(model, courant)
    if viscous is not None and viscous[0] <= model.stable_dt(courant, hourglass=hourglass, fit=fit, state=state) * (1.0 + 1e-9):
        # The viscous limit set the step: a divergence was put on the field, and a weaker one
        # advised, which leaves the step as it is.
        return None
    return (f"the limit of {model._field_words(which)} at net strength "
            f"k = {k:g} 1/s^2, (C / 0.3) 2 / (1.5 sqrt(k)) = {limit:.3g} s, with the wave limit {words} = {wave:.3g} s, "
            f"c_P = {c:.3g} m/s at spacing {model.spacing:g} m")


def _repulsion_cause(model: Model, courant: float, hourglass: float | None, fit: str | None = None,
                     state: State | None = None) -> str | None:
    """Where the pair repulsion's limit (``Model._repulsion_limit``) is at most the wave limit
    (``_wave_limit``, for the fit ``fit``), the hourglass control's (strength ``hourglass``;
    None: the model's) and the force fields', and the viscous limit is not shorter than
    ``stable_dt``, so that it is what shortens it: the refusals' words for it, naming the
    materials, their strengths and both limits; else None."""
    limit, which = model._repulsion_limit(courant)
    wave, words, c = _wave_limit(model, courant, fit, state)
    if not (limit <= wave and limit <= model._hourglass_limit(courant, hourglass)[0] and limit <= model._field_limit(courant)[0]):
        return None
    viscous = _viscous_limit(model, courant)
    if viscous is not None and viscous[0] <= model.stable_dt(courant, hourglass=hourglass, fit=fit, state=state) * (1.0 + 1e-9):
        return None  # the viscous limit set the step (as _field_cause)
    return (f"the limit of {model._repulsion_words(which)} at contact, (C / 0.3) 2 / (1.5 omega) = {limit:.3g} s, "
            f"with the wave limit {words} = {wave:.3g} s, c_P = {c:.3g} m/s at spacing {model.spacing:g} m")


def _viscous_limit(model: Model, courant: float):
    """``Model.stable_dt``'s viscous limit ``(C / 12) rho0 h^2 / eta`` at its most viscous
    material, as ``(limit, material index, eta)``; None where no material is viscous."""
    eta = np.asarray(model.parameter_values()["viscosity"], dtype=np.float64)
    rho = np.array([m.density for m in model.materials], dtype=np.float64)
    if not (eta > 0.0).any():
        return None
    limits = np.where(eta > 0.0, courant / 12.0 * rho * model.support_radius**2 / np.where(eta > 0.0, eta, 1.0), np.inf)
    k = int(np.argmin(limits))
    return float(limits[k]), k, float(eta[k])


def check_start_speed(model: Model, state: State, fps: float, dt, hourglass: float | None = None,
                      until: float | None = None) -> None:
    """Refuse a start whose fastest particle the step cannot follow, before any step.

    With a fixed ``dt`` a particle may move at most one spacing in a step (``|v| dt <= dx``,
    the CFL condition of the motion itself; docs/method.md §8): farther, it passes its
    neighbours and the colliders between two looks at them. A body started at 1e37 m/s
    (3e38 fits float32) left its neighbourhood in the first step; every fit then failed its
    guard and the run "passed", because the divergence monitor's bounds grow with the
    initial speed. ``dt = AUTO``: the adaptive step follows the speed, so it is the step
    count of the first frame that is bounded (``adaptive_timestep``); ``until`` (read only
    with ``dt = AUTO``): with it, the tools' speeds up to that time (a run's end) count too,
    so that one call checks a run's whole span (it was checked again, by a second call,
    before the same first step). With a fixed ``dt`` it has no effect: only the particles'
    start is checked here, and the tools' speeds over the run by ``ToolSet.check_speed``,
    which ``simulate`` and ``warp-esph run`` call beside this."""
    v = state.v.numpy().astype(np.float64)
    if not len(v):
        return
    if isinstance(dt, str):
        speed = np.sqrt((v * v).sum(axis=1))
        p = int(np.argmax(speed))
        index = int(model.particle_body_np[p])
        try:
            adaptive_timestep(model, state, fps, hourglass=hourglass, until=until)
        except ValueError as e:
            if not str(e).startswith("a particle speed"):
                raise  # a tool's, which names it, or the material's own step
            raise _body_error(f"initial velocity of body {model.bodies[index].name!r} (particle {p}): {e}", index) from None
        return
    check_particle_speed(model, v, dt)


def check_particle_speed(model: Model, v: np.ndarray, dt: float) -> None:
    """``check_start_speed`` at a fixed ``dt`` of the velocities ``v`` (n, 3): a
    ``StepRefusal`` (``START_ADVICE``) naming the fastest particle and its body where it
    moves more than one spacing in a step (``fit`` checks its starts with it)."""
    v = np.asarray(v, dtype=np.float64)
    if not len(v):
        return
    speed = np.sqrt((v * v).sum(axis=1))
    p = int(np.argmax(speed))
    index = int(model.particle_body_np[p])
    body = model.bodies[index].name
    limit = model.spacing / dt
    if not speed[p] <= limit:
        raise _body_error(
            f"initial velocity of body {body!r}: a speed of {speed[p]:.3g} m/s (particle {p}) is not allowed at "
            f"dt = {dt:.4g} s: a step may carry a particle at most one spacing ({model.spacing:g} m), |v| dt <= dx, "
            f"so at most {limit:.3g} m/s", index, START_ADVICE)


def _body_error(message: str, index: int, advice: str | None = None) -> ValueError:
    """A ``ValueError`` about body ``index`` (``body_index``: the CLI names the scene file's
    table of that body by it); with ``advice``, a ``StepRefusal`` of ``message`` and it."""
    error = ValueError(message) if advice is None else StepRefusal(message, advice)
    error.body_index = index
    return error


def _check_run_start(model: Model, state: State, frames: int, fps: float, dt, hourglass: float | None = None,
                     start_frame: int = 0) -> tuple:
    """The checks of a run before its first step: the start's speed (``check_start_speed``;
    a resumed run's, ``start_frame > 0``, was checked when its run began) and the tools'
    speeds up to the run's end. Returns what was checked, for ``simulate(_checked=)``:
    ``warp-esph run`` checks before it opens its output, and each check ran again in
    ``simulate`` (the tools' motions sampled at every step time twice)."""
    end = state.time + frames / fps
    if start_frame == 0:
        # With the adaptive step this call also takes the tools' speeds to the run's end.
        check_start_speed(model, state, fps, dt, hourglass=hourglass, until=end)
    if model.tools is not None:
        if isinstance(dt, str):  # it follows the tools' speed, but at most MAX_STEPS_PER_FRAME steps a frame
            if start_frame != 0:
                adaptive_timestep(model, state, fps, hourglass=hourglass, until=end)
        else:
            model.tools.check_speed(dt, state.time, end)
    return model, float(state.time), frames, fps, dt, hourglass, start_frame


def _frame_count(frames) -> int:
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        # Shortened: a negative int past 4300 digits made repr() raise Python's own digit-limit
        # error from this message, naming no parameter.
        raise ValueError(f"frames = {checks.shorten(frames)!r} is not allowed: must be an integer >= 1")
    return int(frames)


class _PlainBar:
    """A minimal stand-in for tqdm (used only where tqdm is not installed)."""

    def __init__(self, total: int, desc: str):
        from .startup import unread_stream  # noqa: PLC0415

        self.total, self.desc, self.n, self.postfix = total, desc, 0, ""
        self.stream = unread_stream(sys.stderr)

    def set_postfix_str(self, text: str, refresh: bool = True):
        self.postfix = text

    def update(self, n: int = 1):
        self.n += n
        print(f"\r{self.desc}: {self.n}/{self.total} frames, {self.postfix}", end="", file=self.stream, flush=True)

    def close(self):
        print(file=self.stream, flush=True)


def _progress_bar(total: int, desc: str):
    """A bar on stderr that stops drawing, the work going on, once stderr's reader has left."""
    from .startup import unread_stream  # noqa: PLC0415

    try:
        from tqdm import tqdm  # noqa: PLC0415 (only when a bar is wanted)
    except ModuleNotFoundError:
        return _PlainBar(total, desc)
    return tqdm(total=total, unit="frame", file=unread_stream(sys.stderr), dynamic_ncols=True, leave=True, desc=desc)


def _overflow_error(model: Model, e: NeighborOverflow, step: int, frame: int, t: float, dt: float) -> SimulationError:
    """The ``SimulationError`` of a step the neighbour search stopped (``NeighborOverflow``),
    naming the step, frame and time as a divergence's does: the search's own message named
    none, and a long run said only that a body had collapsed somewhere in it."""
    p = int(e.particles[0]) if len(e.particles) else None
    body = None if p is None else model.bodies[int(model.particle_body_np[p])].name
    at = "" if p is None else f" (particle {p} of body {body!r} is the first past it)"
    return SimulationError(f"the simulation stopped in step {step} (frame {frame}, t = {t:.4g} s, dt = {dt:.4g} s): "
                           f"the neighbour search found that {e}{at}", step=step, particle=p, body=body, frame=frame)


def _first_bad(model: Model, state: State, monitor: DivergenceMonitor | None = None, t: float = 0.0,
               work: float | None = None):
    """``None`` or ``(what went wrong, first bad particle)``: a non-finite position or
    velocity, else a bound of ``monitor`` exceeded."""
    x = state.x.numpy()
    v = state.v.numpy()
    bad = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
    if bad.any():
        p = int(np.argmax(bad))
        return f"non-finite position or velocity (particle {p} is the first of {int(bad.sum())} bad particles)", p
    if monitor is not None:
        return monitor.check(x, v, t, work)
    return None


def _far_mesh_tools(model: Model) -> list:
    """The mesh tools some of whose points lie where float32 does not resolve half the
    contact's margin (``builder._float32_resolves_margin``), and that move in a known way
    (not ``tools.Scripted``, whose whole mesh ``finalize`` judged): ``finalize`` judged them
    where the particles can meet them from their start, but the particles go farther (a block
    thrown or sliding across a wide floor, one on a conveyor carried far along it, one a
    pinned set drags), so ``_far_mesh_contact`` looks where they are at each frame."""
    from .builder import _float32_resolves_margin  # noqa: PLC0415 (builder imports this module's users)
    import warp as wp  # noqa: PLC0415

    out = []
    for k, c in enumerate(model.tools.colliders if model.tools is not None else ()):
        if c.kind != "mesh" or isinstance(c.motion, tools.Scripted) or c.mesh_points is None or not len(c.mesh_points):
            continue
        pts = np.asarray(c.mesh_points, dtype=np.float64)
        if not _float32_resolves_margin(float(np.abs(pts).max()), model.spacing):
            faces = None
            if model.scalar is wp.float32:
                # Each face's bounds and farthest coordinate, once a run: the frame's check built
                # the (faces, 3, 3) vertex array of the whole mesh anew every frame.
                tri = pts[np.asarray(c.mesh_triangles)]
                faces = (tri.min(axis=1), tri.max(axis=1), np.abs(tri).max(axis=(1, 2)))
            out.append((k, c.name, pts.min(axis=0), pts.max(axis=0), faces))
    return out


def _far_mesh_contact(model: Model, state: State, far: list):
    """``None`` or ``(what, particle)``: particles at a mesh tool of ``far`` (within two
    spacings of its bounds, in its frame) where float32 does not resolve half the contact's
    margin: in float64 at their own place in the tool's frame, in float32 at the vertices of
    the faces near them (the model computes the contact point from them). Measured: a small
    box mesh met 100 m from its origin put particles inside it in 128 of 3000 steps."""
    from .builder import _float32_resolves_margin, _margin_unresolved  # noqa: PLC0415

    x = state.x.numpy().astype(np.float64)
    grow = 2.0 * model.spacing
    import warp as wp  # noqa: PLC0415

    f32 = model.scalar is wp.float32
    for k, name, lo, hi, faces in far:
        p, q = model.tools.pose_at(k, float(state.time))
        qx, qy, qz, qw = (float(v) for v in q / np.linalg.norm(q))
        rot = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
                        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
                        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])
        y = (x - p) @ rot  # the tool's frame: R^T (x - p), row by row
        near = np.flatnonzero(((y >= lo - grow) & (y <= hi + grow)).all(axis=1))
        if not len(near):
            continue
        yn = y[near]
        if f32:
            tri_lo, tri_hi, tri_reach = faces
            box_lo, box_hi = yn.min(axis=0) - grow, yn.max(axis=0) + grow
            met = ((tri_hi >= box_lo) & (tri_lo <= box_hi)).all(axis=1)
            reach = float(tri_reach[met].max()) if met.any() else 0.0
        else:
            reach = float(np.abs(yn).max())
        if not _float32_resolves_margin(reach, model.spacing):
            p_far = int(near[int(np.argmax(np.abs(yn).max(axis=1)))])
            where = ("the faces they are at reach", "(the model's contact and Warp's mesh queries)") if f32 else \
                ("they are at it", "(Warp's mesh queries)")
            return (f"the particles met mesh tool {name!r} far from its origin ({where[0]} {reach:.3g} m from it), where "
                    f"float32 {where[1]} {_margin_unresolved(reach, model.spacing)}"), p_far
    return None


def far_mesh_advice(f32: bool, dtype: str = "dtype=float64") -> str:
    """The advice of ``simulate``'s stop at a mesh tool beyond float32's resolution
    (``_far_mesh_contact``), for a model of float32 or not; ``dtype``: how the caller names
    the precision (``warp-esph run``: ``--dtype float64``)."""
    return ("model the mesh about where they meet it (its points less that place, the place added to position)"
            + (f", split its faces there into smaller ones, use {dtype}," if f32 else "") + " or use a larger spacing")


def _body_layout(model: Model) -> list[tuple[str, int]]:
    return [(b.name, b.count) for b in model.bodies]


def _growth_origin(model: Model, current: State, monitor, origin: State | None, exempt, solver: Solver,
                   work_known: bool = True):
    """``(x0, v0, t0, stored elastic energy, from the origin)`` of the state ``simulate`` judges
    its energy growth from (``energy_growth``), copied (the run's states are reused), or None
    where the monitor is off. A resumed run's is the run's own initial state (``origin``), as
    the monitor's, so each frame is judged as the uninterrupted run judged it; beside a
    ``Scripted`` tool whose work before this call is not known (``work_known``: a checkpoint
    written before ``State.tool_work`` was kept) it is the state this call starts from: the
    work the tool did before, uncounted, would read as growth."""
    if monitor is None or not monitor.keep.any():
        return None
    motions = [] if model.tools is None else model.tools.motions
    if origin is None or (not work_known and any(isinstance(mo, tools.Scripted) for mo in motions)):
        start = current
        stored = getattr(monitor, "e_elastic", 0.0) if origin is None else \
            DivergenceMonitor(model, current, exempt, solver=solver).e_elastic
    else:
        start, stored = origin, getattr(monitor, "e_elastic", 0.0)
    return (start.x.numpy().astype(np.float64), start.v.numpy().astype(np.float64), float(start.time), stored,
            start is origin)


def _work_given(state: State | None) -> float | None:
    """The work (J) the tools did on the bodies before ``state`` since the run's start, as
    ``simulate`` left it on the state (``State.tool_work``; a loaded checkpoint's), or None
    where it is not known (a state no ``simulate`` counted; a checkpoint written before)."""
    w = None if state is None else getattr(state, "tool_work", None)
    if w is None:
        return None
    if isinstance(w, bool) or not isinstance(w, (int, float, np.integer, np.floating)) or not math.isfinite(float(w)):
        raise ValueError(f"state.tool_work = {checks.shorten(w)!r} is not allowed: must be a finite number of joules "
                         "(the tools' work since the run's start) or None (not known)")
    return float(w)


def _record_scripted(seen: dict, step: dict) -> None:
    """Fold one step's ``ToolSet.scripted_step_motion`` into ``seen``: each Scripted motion's
    fastest linear and angular speed and the box of its positions (``energy_growth``'s
    ``scripted_seen``)."""
    for k, (lin, ang, p0, p1) in step.items():
        old = seen.get(k)
        lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
        if old is not None:
            lin, ang, lo, hi = max(lin, old[0]), max(ang, old[1]), np.minimum(lo, old[2]), np.maximum(hi, old[3])
        seen[k] = (lin, ang, lo, hi)


class ToolWork:
    """The work (J) a run's tools and pinned sets do on the bodies, summed on the device as
    the solver's steps go (``ToolSet.integrate``: each reaction row's force along its tool's
    displacement plus its torque along its rotation) and read once per frame: the energy they
    give, as height, speed or elastic energy, which the blow-up tests allow.
    ``solver.tool_work`` holds it while the run lasts (``close`` gives back what it held)."""

    def __init__(self, model: Model, solver: Solver, particles=None):
        import warp as wp  # noqa: PLC0415

        self.solver = solver
        self.prior = getattr(solver, "tool_work", None)
        tools_ = model.tools
        rows = len(tools_.row_names)
        self.rows = np.ones(rows, dtype=bool)
        if particles is not None and model.world_count > 1:
            # Row w * count + k is world w's: only the worlds of the particles checked.
            worlds = np.unique(model.world_of_particle[np.asarray(particles, dtype=bool)])
            self.rows = np.isin(np.arange(rows) // tools_.count, worlds)
        solver.tool_work = wp.zeros(rows, dtype=wp.float64, device=model.device)

    def read(self) -> float:
        return float(self.solver.tool_work.numpy()[self.rows].sum())

    def close(self) -> None:
        # The run's total stays readable (a sweep judges its sample's end with it).
        self.solver.tool_work_done = self.read()
        self.solver.tool_work = self.prior


def _takes_keyword(record, solver, **keyword) -> bool:
    """Whether a writer's ``record_solver`` takes ``(solver, frame=...)`` (or ``state=``), not
    the solver alone. Bound (and passed) by keyword: bound positionally, a
    ``record_solver(self, solver, *, frame=None)`` did not take it and was told the solver at
    the start only."""
    try:
        inspect.signature(record).bind(solver, **keyword)
    except TypeError:
        return False
    except ValueError:  # no signature to read (a built-in): the documented protocol
        return True
    return True


def simulate(
    model: Model,
    frames: int,
    fps: float = 30,
    substeps: int | None = None,
    dt: float | None = None,
    writer=None,
    progress: bool = True,
    solver: Solver | None = None,
    state: State | None = None,
    callback=None,
    *,
    start_frame: int = 0,
    monitor: bool = True,
    monitor_exempt=(),
    monitor_origin: State | None = None,
    _checked: tuple | None = None,
    _finer: str = "a smaller spacing",
) -> State:
    """Simulate ``frames`` frames at ``fps``; returns the final state.

    - ``substeps`` / ``dt``: at most one; see ``resolve_timestep``. ``dt="auto"``: an
      adaptive (CFL) step, chosen anew for each frame by ``adaptive_timestep`` (whole
      steps per frame, never above ``model.stable_dt()`` with the hourglass control the
      frame's steps run: ``solver.hourglass`` as a callback left it, or an automatic
      solver's choice from the materials as they are then).
    - ``writer``: anything with ``write_frame(frame_index, state)`` (e.g. ``UsdWriter``); one
      with ``record_solver(solver, frame=None, state=None)`` is told the solver at the start
      and before each frame, the frame passed by keyword (``frame=``, so a keyword-only
      ``frame`` takes it too; what it runs, ``UsdWriter.record_solver``), and the state it
      writes next (``state=``: the start, then the state the frame's last step wrote, whose
      ``Solver.record(state)`` says what ran); one whose ``record_solver`` takes the solver
      alone (or no ``frame`` keyword), at the start only; one without ``state`` reads the
      solver alone (``Solver.record()``: what a step from a new state runs).
      Frame ``start_frame`` (the initial state) is written first, then one frame per
      rendered frame. The writer is closed when the run ends, also when it fails.
    - ``solver``: a ``Solver`` of ``model`` (default: a new one; pass your own to read
      its ``guard_counts()`` afterwards; a run whose deformation fits the guards skipped in
      ``SKIPPED_FIT_SHARE`` or more of its particle-steps warns, RuntimeWarning). ``state``: the initial state (default: the
      model's initial configuration); it is copied, not modified.
    - ``callback(frame_index, state)``: called after each frame is written.
    - ``progress``: a tqdm bar on stderr (frames, particles, steps per second).
    - ``start_frame``: index of the initial frame (resuming a run); frames are numbered
      ``start_frame .. start_frame + frames``, at most ``MAX_FRAME_INDEX`` (2**53: a frame's
      USD time code is a double).

    - ``monitor``: stop a run that blows up but stays finite (``DivergenceMonitor``'s bounds,
      then ``energy_growth`` from the monitor's state, at every frame, the tools' work counted;
      beside a ``Scripted`` tool its speed read from the poses the steps evaluated);
      ``False`` keeps only the check for non-finite values (and refuses ``monitor_exempt``
      and ``monitor_origin``, which only the monitor reads). ``monitor_exempt``: names of
      bodies its bounds leave out (``Scene.diverges``: a body a scene shows blowing up); a
      non-finite position or velocity in them still stops the run, as ``fit`` fails the trial.
      ``monitor_origin``: the state of frame 0 whose bounds the monitor keeps, the time
      counted from it (a resumed run: the run's initial state, so that each frame is judged
      as the uninterrupted run judged it; default: the state this call starts from). With it,
      ``state.tool_work`` (a loaded checkpoint's: the tools' work from the run's start to the
      checkpoint) is added to the work this call's steps do; where it is None (a checkpoint
      written before it was kept) the bounds read the height the tools can have given in its
      place, and beside a ``Scripted`` tool ``energy_growth`` judges from this call's start.
      The states handed to ``writer`` and ``callback`` and the one returned carry the work
      since the monitor's state (``State.tool_work``; None where the monitor is off or the
      scene has no tools), which
      ``save_state`` keeps.

    Two states are swapped, so nothing is allocated per step. Raises ``SimulationError``
    when a position or velocity becomes non-finite, the monitor finds a blow-up (its bounds, or
    kinetic + gravitational energy grown past ``energy_growth``'s limit), or a step
    moved a ``tools.Scripted`` tool more than a spacing (checked from the poses each step
    evaluates, with a fixed ``dt`` and with ``dt="auto"`` alike: the function may read what
    ``callback`` sets, so it is never called ahead of the run), or the neighbour search
    stopped a step (``NeighborOverflow``, a collapsed or blown-up body: the message names the
    step, frame and time); the frame that shows it is not written.
    """
    try:
        if not isinstance(model, Model):
            raise ValueError(f"model = {checks.shorten(model)!r} is not allowed: must be a warp_esph.Model")
        frames = _frame_count(frames)
        if isinstance(start_frame, bool) or not isinstance(start_frame, (int, np.integer)) or start_frame < 0:
            raise ValueError(f"start_frame = {checks.shorten(start_frame)!r} is not allowed: must be an integer >= 0")
        start_frame = int(start_frame)
        if start_frame + frames > MAX_FRAME_INDEX:
            # A frame's USD time code is a double: past 2**53 two frames got one time code, the
            # later written over the earlier without a word (10**400 raised OverflowError).
            raise ValueError(f"start_frame = {checks.shorten(start_frame)!r} is not allowed with frames = {frames}: the "
                             f"last frame's index, start_frame + frames, must be at most 2**53 = {MAX_FRAME_INDEX} (a "
                             "frame's USD time code is a double, which holds every integer only up to it)")
        monitor = checks.boolean("monitor", monitor)
        if not monitor:
            # Read by the monitor alone: with it off they were taken and ignored without a word.
            if exempt_bodies(monitor_exempt, [b.name for b in model.bodies]):
                raise ValueError(f"monitor_exempt = {checks.shorten(monitor_exempt)!r} is not allowed with monitor = False: "
                                 "it names the bodies the divergence monitor's bounds leave out, and the monitor is off")
            if monitor_origin is not None:
                raise ValueError("monitor_origin is not allowed with monitor = False: it is the state whose bounds the "
                                 "divergence monitor keeps, and the monitor is off")
        progress = checks.boolean("progress", progress)  # 'no' drew the bar
        fps = checks.positive("fps", fps)
        # The stable step follows the control the solver runs (a given solver's own).
        hourglass = solver.hourglass if isinstance(solver, Solver) else None
        fit = solver.asked_fit if isinstance(solver, Solver) else None
        adaptive = isinstance(dt, str)
        if adaptive:
            if dt != AUTO:
                raise ValueError(f"dt = {checks.shorten(dt)!r} is not allowed: must be a number of seconds or {AUTO!r}")
            if substeps is not None:
                raise ValueError(f"substeps = {substeps!r} and dt = {AUTO!r} are not allowed together: the adaptive step chooses the substeps")
            # From the start given: a flowed body made elastic keeps the corrected incremental fit.
            n_sub, dt = 1, model.stable_dt(hourglass=hourglass, fit=fit, state=state)
        else:
            n_sub, dt = resolve_timestep(model, fps, substeps, dt, hourglass=hourglass, fit=fit, state=state)
            check_step_count(frames, n_sub)
        if writer is not None:
            if not callable(getattr(writer, "write_frame", None)):
                raise ValueError(f"writer = {checks.shorten(writer)!r} is not allowed: it must have a write_frame(frame_index, state) method")
            wmodel = getattr(writer, "model", None)
            if isinstance(wmodel, Model) and _body_layout(wmodel) != _body_layout(model):
                # A UsdWriter holds its model's bodies and their particle counts.
                raise ValueError(f"writer is not allowed: it was opened for another model (bodies "
                                 f"{_body_layout(wmodel)}, this one {_body_layout(model)}); open it with this model")
            wfps = getattr(writer, "fps", None)
            if wfps is not None and not math.isclose(float(wfps), fps, rel_tol=1e-9):
                raise ValueError(f"fps = {fps:g} is not allowed: the writer was opened with fps = {float(wfps):g}")
        if callback is not None and not callable(callback):
            raise ValueError(f"callback = {checks.shorten(callback)!r} is not allowed: must be callable as callback(frame_index, state)")
        if solver is None:
            solver = Solver(model)
        elif not isinstance(solver, Solver) or solver.model is not model:
            raise ValueError("solver is not allowed: it must be a warp_esph.Solver built for this model")
        solver.check_dt(dt, state)  # warns once here, before the progress bar, if dt is above the stable limit
        record = getattr(writer, "record_solver", None)
        # A writer's record_solver(solver) of the earlier protocol (told the solver at the
        # start only) met a TypeError at the first frame once the frame was passed.
        solver_frames = callable(record) and _takes_keyword(record, solver, frame=0)

        # A given start replaces the model's: its particle_v0 is not read (nor refused).
        current = model.state(requires_grad=False) if state is None else model._scratch_state()
        if state is not None:
            checks.same_state(model, "state", state)
            # By the name the caller gave it: the step's check named state_in.time, and a string
            # failed adding the run's length to it.
            checks.number("state.time", state.time)
            current.assign(state)
        # The run's own copy is this solver's run from its start: a checkpoint of the start frame
        # (a callback's) recorded the settings of the solver that wrote the given state, and a
        # resume with this run's own was refused (State.written_by).
        current.written_by = solver._weak_self
        # What the first step runs from this start: a body that flowed is not handed over to the
        # rest model (Solver._runs_rest), which a record of the parameters alone named. Later
        # frames' records read the state the frame's last step wrote, which says what it ran.
        told = {"state": current} if callable(record) and _takes_keyword(record, solver, state=current) else {}
        if callable(record):
            # Which model writes the frames: fit="auto" resolves by the material values, and a
            # callback that changes them can switch it (recorded per frame, from the first).
            record(solver, **told)
        initial = _first_bad(model, current)
        if initial is not None:
            raise ValueError(f"state is not allowed: it has a {initial[0]}")
        run = (frames, fps, AUTO if adaptive else dt, hourglass, start_frame)
        # _checked: the caller's _check_run_start of this very run (warp-esph run's, made
        # before it opened its output); anything else is checked here.
        if _checked is None or _checked[0] is not model or _checked[1:] != (float(current.time), *run):
            _check_run_start(model, current, *run)
        spare = model._scratch_state()
        if monitor_origin is not None:
            checks.same_state(model, "monitor_origin", monitor_origin)
        # A resumed run's bounds taken from its checkpoint's state were laxer (the energy it
        # had gained counted as initial energy): it wrote a frame the uninterrupted run refused.
        monitor = DivergenceMonitor(model, current if monitor_origin is None else monitor_origin,
                                    monitor_exempt, solver=solver) if monitor else None
        t_origin = 0 if monitor_origin is None else start_frame  # frames from the monitor's state to this call's
        # The tools' work from the monitor's state to this call's (J; None: not known). A resumed
        # run's is what its first run had counted by the checkpoint (State.tool_work, which
        # save_state keeps): without it the resumed bounds read the height the tools can have
        # given alone, and stopped a rubber block a keyframed plate had pressed, in its
        # spring-back, which the uninterrupted run let pass.
        work_before = 0.0 if monitor_origin is None else _work_given(state)
        current.tool_work = work_before
        # energy_growth, the test a sweep, a fit and the torch bridge fail a run on, at each frame
        # beside the bounds: beside a Scripted tool the bounds are off, and a box 4.6 x past its
        # stable step ran to its end and returned particles 20 m out as a success.
        growth = _growth_origin(model, current, monitor, monitor_origin, monitor_exempt, solver,
                                work_known=work_before is not None)
        seen = {}  # the Scripted motions as this run's steps evaluated them
        memo = {}  # the start's part of the energy check, summed once, and the most height the tools gave
        work = ToolWork(model, solver, monitor.keep) if monitor is not None and model.tools is not None else None

        # A solver's counts run on from its earlier runs: theirs are not this run's inversions.
        inverted0 = solver.guard_counts()["inverted"]
        skipped0 = skipped_fits(solver.guard_counts())
        by_body0 = solver.skipped_fits()
        far_meshes = _far_mesh_tools(model)
        bar = _progress_bar(frames, f"{model.particle_count} particles") if progress else None
        try:
            if writer is not None:
                if solver_frames:
                    writer.record_solver(solver, frame=start_frame, **told)
                writer.write_frame(start_frame, current)
            if callback is not None:
                callback(start_frame, current)
            steps = 0
            scripted = model.tools is not None
            t0 = time.perf_counter()
            for k in range(1, frames + 1):
                if adaptive:
                    try:
                        # The control as the frame's steps will run it: a callback may have set
                        # solver.hourglass (or the materials an automatic solver chooses it from);
                        # the strength read at the start had stepped a control set to 1000 from
                        # 0.05 at 4 x its stable step, which blew up.
                        n_sub, dt = adaptive_timestep(model, current, fps, hourglass=solver.next_hourglass(),
                                                      fit=solver.asked_fit)
                    except ValueError as e:  # the start was checked: a speed the step cannot follow came in the run
                        p = int(np.argmax((current.v.numpy().astype(np.float64) ** 2).sum(axis=1)))
                        body = model.bodies[int(model.particle_body_np[p])].name
                        raise SimulationError(f"the simulation ran away before frame {start_frame + k}: {e}", step=steps,
                                              particle=p, body=body, frame=start_frame + k) from None
                for i in range(n_sub):
                    try:
                        with solver.caller_checks():  # the monitor reads each frame
                            solver.step(current, spare, dt)
                    except NeighborOverflow as e:
                        raise _overflow_error(model, e, steps + i + 1 if adaptive else start_frame * n_sub + steps + i + 1,
                                              start_frame + k, float(current.time) + dt, dt) from e
                    current, spare = spare, current
                    if scripted:
                        if growth is not None:
                            _record_scripted(seen, model.tools.scripted_step_motion(dt))
                        try:
                            model.tools.check_scripted_step(dt)
                        except ValueError as e:  # its poses are known only as the steps evaluate them
                            step = steps + i + 1 if adaptive else start_frame * n_sub + steps + i + 1
                            # Its advice apart, as a divergence's: it names dt=, which a sweep's row
                            # (the command's table too) leaves out.
                            refused = isinstance(e, StepRefusal)
                            raise SimulationError(f"the simulation stopped in step {step}, in frame {start_frame + k}: "
                                                  f"{e.reason if refused else e}", step=step, particle=None,
                                                  frame=start_frame + k, advice=e.advice if refused else "") from None
                steps += n_sub
                frame = start_frame + k
                done = None if work is None else work.read()
                # Since the monitor's state: a resumed run's adds what its first run had counted.
                total = None if done is None or work_before is None else work_before + done
                current.tool_work = total
                bad = _first_bad(model, current, monitor, (t_origin + k) / fps,  # simulated time since the monitor's state
                                 work=total)
                if bad is None and growth is not None:
                    x0, v0, t_start, stored, from_origin = growth
                    # Judged from this call's start (a Scripted tool's run resumed without the work
                    # before it), the work of this call's steps alone.
                    bad = _grown(model, x0, v0, current.x.numpy(), current.v.numpy(), t0=t_start, dt=None, steps=None,
                                 particles=monitor.keep, stored=stored, scripted_seen=seen, memo=memo,
                                 work=total if from_origin else done)
                if bad is not None:
                    what, p = bad
                    body = model.bodies[int(model.particle_body_np[p])].name
                    step = steps if adaptive else start_frame * n_sub + steps
                    raise SimulationError(
                        f"the simulation diverged after step {step} (frame {frame}, t = {frame / fps:.4g} s, "
                        f"dt = {dt:.4g} s): {what}, at particle {p} of body {body!r}", step=step, particle=p, body=body,
                        frame=frame, advice="; " + divergence_advice(model, solver.hourglass, solver=solver,
                                                                     since=inverted0, step=dt, state=current),
                    )
                met = _far_mesh_contact(model, current, far_meshes) if far_meshes else None
                if met is not None:
                    import warp as wp  # noqa: PLC0415

                    what, p = met
                    body = model.bodies[int(model.particle_body_np[p])].name
                    step = steps if adaptive else start_frame * n_sub + steps
                    raise SimulationError(f"the simulation stopped after step {step} (frame {frame}, t = {frame / fps:.4g} "
                                          f"s): {what}", step=step, particle=p, body=body, frame=frame,
                                          advice=f"; {far_mesh_advice(model.scalar is wp.float32)}")
                if writer is not None:
                    if solver_frames:
                        writer.record_solver(solver, frame=frame, **({"state": current} if told else {}))
                    writer.write_frame(frame, current)
                if callback is not None:
                    callback(frame, current)
                if bar is not None:
                    elapsed = max(time.perf_counter() - t0, 1e-9)
                    bar.set_postfix_str(f"{steps / elapsed:.0f} steps/s, dt={dt:.3g}s", refresh=False)
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
            if work is not None:
                work.close()
        by_body = {k: v - by_body0.get(k, 0) for k, v in solver.skipped_fits().items()}
        note = skipped_fit_warning(skipped_fits(solver.guard_counts()) - skipped0, model.particle_count * steps,
                                   _finer, coarse_bodies(model, by_body, steps))
        if note is not None:
            warnings.warn(note, RuntimeWarning, stacklevel=2)
        return current
    finally:
        if writer is not None and callable(getattr(writer, "close", None)):
            writer.close()
