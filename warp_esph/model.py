"""``Model`` (what does not change during a run) and ``State`` (what a step advances).

A ``State`` also holds the arrays the step that produced it computed on the way
(neighbour lists, densities, stresses, forces). With one state per step under a
``wp.Tape``, each step's intermediates then stay untouched until the backward pass
reads them (docs/method.md, Warp pitfalls 3-4); with two states swapped in a plain forward run,
nothing is allocated inside the step.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import operator
from collections.abc import Sequence

import numpy as np
import warp as wp

from . import checks, tools
from ._types import type_set
from .sim.fields import CompressionField
from .sim.fields import precision_problem as field_precision_problem
from .sim.colliders import CONTACT_RAMP, CONTINUOUS_CONTACT_RAMP, INSTANT_CONTACT_RAMP, Box, Plane, Sphere
from .material import (BINGHAM_MODELS, DEFORMATION_IDS, ELASTIC_FORCE_IDS, LAB_QUANTITIES, LAME_FORMULAS, MODEL_IDS, PRESSURE_FORCE_IDS,
                       Material, SPIKY_DENSITY_FORCES, lab_given, p_wave_speed, young_given)
from .sim import ghost_floor, integrate
from .sim.replay import Launches, pointer_key
from .sim.smoothing import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS
from .sim import materials as material_struct


#: The incremental fits a ``Solver`` offers (docs/method.md §2): the paper's affine one,
#: the curvature-corrected one (``sim/curvature.py``), and ``"auto"``, which picks between
#: them by the materials (``Model.solver_choice``). ``Model.fit`` picks a model's.
FITS = ("auto", "linear", "curvature_corrected")
#: ``Model.fit`` of a new model.
DEFAULT_FIT = "auto"
#: Strength ``c`` of the hourglass control (``sim/hourglass.py``) that ``fit="auto"`` runs with
#: the curvature-corrected fit when no strength is chosen (docs/physics.md, "The default:
#: the fit by material"): the static residual penalty of that strength lifted every
#: zero-energy mode of a free lattice cube above 0.03 (docs/physics.md, "Where the surface
#: noise comes from"), and the control moves the 6-thick beam by 0.1 % (measured).
AUTO_HOURGLASS = 0.05
#: The contact laws by name (scene files' ``[solver] contact``, the CLI's ``--contact``):
#: name -> ``Model.contact_ramp``.
CONTACTS = {"instant": INSTANT_CONTACT_RAMP, "continuous": CONTINUOUS_CONTACT_RAMP}
#: The largest ``Model.contact_ramp``: a touchdown spread over more than ten steps' drift lets
#: a particle sink that far into a collider (1e300 let every particle fall through).
MAX_CONTACT_RAMP = 10.0
#: How far below its own explicit limit ``2 / sqrt(k)`` ``Model.stable_dt`` keeps a force
#: field's step at ``C = 0.3``: the margin the wave limit was measured to have at least
#: (docs/method.md §8), which the hourglass control's limit keeps too.
FIELD_MARGIN = 1.5
#: The fraction of the wave limit ``Model.stable_dt`` keeps where the step runs the
#: curvature-corrected fit with the incremental composition ``F <- dF F`` (not the rest model):
#: under compression a mode of that fit's step potential stiffens (``det A~ / det A`` 0.21-0.24)
#: until ``omega dt`` rose from 0.64 at rest to 2.13 at the full step, past symplectic Euler's 2.
#: Measured: the large breathing 6^3 cube (biweight) ran away at 1.0 x (1279 x its energy in
#: 6.7 periods), bounded at 0.5 x (1.23 x over 10); an elastic 4^3 box dropped on the imaged
#: ground gained at 1.0 x (11.1 J in the 3rd second against 0.169 J in the 1st), not at 0.5 x
#: (docs/physics.md, "The biweight's incremental composition (measured)").
CORRECTED_INCREMENTAL_STEP = 0.5


#: The deviatoric singular-value spread ``|dev sigma|`` a plastic material's squared flow stress
#: leaves room for in the model's precision (``modulus_precision_problem``).
FLOW_DEVIATOR_ROOM = 100.0


def precision_problem(value: float, scalar, cli: bool = False) -> str | None:
    """What is allowed, where the finite ``value`` does not hold in ``scalar`` (it would become
    inf, or 0), or None. ``cli``: the advice names the command's ``--dtype`` too
    (``wider_precision``)."""
    info = np.finfo(np.float32 if scalar is wp.float32 else np.float64)
    tiny, big = float(info.tiny), float(info.max)
    if math.isfinite(value) and abs(value) > big:
        return f"must be at most {big:.3g}; {wider_precision(scalar, 'a smaller value', cli)}"
    if value != 0.0 and abs(value) < tiny:
        return f"must be 0 or at least {tiny:.3g} in size; {wider_precision(scalar, 'a larger value', cli)}"
    return None


def wider_precision(scalar, instead: str, cli: bool = False) -> str:
    """The advice of a refusal for the precision: float64 where a float32 model was asked for,
    else ``instead`` alone (a float64 model was told to use dtype=float64)."""
    if scalar is wp.float32:
        return f"use dtype=float64{' (--dtype float64)' if cli else ''} or {instead}"
    return f"use {instead}"


def modulus_precision_problem(material: Material, scalar, cli: bool = False) -> tuple[str, float, str] | None:
    """``(field, value, what is allowed)`` where the p-wave modulus ``lam + 2 mu + density
    pressure_stiffness`` of ``material`` (each value holding in ``scalar``) does not, or None: in
    float32 mu = 3e38 holds but the modulus the step computes overflowed, and the rollout ran to
    NaN (stable_dt 7.7e-21 s). The field named is the one of the largest term, so the value
    that made the modulus too big is the one named (``mu`` alone named ``mu = 1000`` where
    ``pressure_stiffness = 4e35`` was given)."""
    big = float(np.finfo(np.float32 if scalar is wp.float32 else np.float64).max)
    with np.errstate(over="ignore"):
        terms = {"lam": np.float64(material.lam), "mu": 2.0 * np.float64(material.mu),
                 "density" if material.density > material.pressure_stiffness else "pressure_stiffness":
                     np.float64(material.density) * material.pressure_stiffness}
        modulus = float(sum(terms.values()))
    if math.isfinite(modulus) and modulus > big:
        field = max(terms, key=lambda k: terms[k])
        return (field, float(getattr(material, field)),
                f"with it the p-wave modulus lam + 2 mu + density pressure_stiffness = {modulus:.3g} Pa must be at most "
                f"{big:.3g}; {wider_precision(scalar, 'smaller values', cli)}")
    # The pressure pair force multiplies a pressure by two densities (sim/pressure.py): where
    # their product underflowed to 0 the force was 0 / 0, NaN positions in the first steps at
    # half the stable step (float32 from 4e-23 kg/m^3 down, float64 from 2e-162, measured);
    # where the pressure at a strain of 1, density pressure_stiffness, times it overflowed, NaN
    # in a squeezed block (float32 density 1e18, float64 1e155, default pressure_stiffness).
    tiny = float(np.finfo(np.float32 if scalar is wp.float32 else np.float64).tiny)
    if material.density < math.sqrt(tiny):
        return ("density", float(material.density),
                f"the pressure force multiplies two densities, so it must be at least {math.sqrt(tiny):.3g} (their "
                f"product below the smallest {scalar.__name__} is 0, and the force 0 / 0); "
                f"{wider_precision(scalar, 'a larger value', cli)}")
    density, pressure = float(material.density), float(material.density) * float(material.pressure_stiffness)
    if pressure > 0.0 and math.log(pressure) + 2.0 * math.log(density) > math.log(big):
        if pressure <= math.sqrt(big):  # the density is what is out of range
            return ("density", density,
                    f"the pressure force multiplies its pressure, up to density pressure_stiffness = {pressure:.3g} Pa, "
                    f"by two densities, so it must be at most sqrt({big:.3g} / {pressure:.3g} Pa) = "
                    f"{math.sqrt(big / pressure):.3g}; {wider_precision(scalar, 'a smaller value', cli)}")
        # The pressure is: named by the value given, lam or mu where the stiffness is K / (4 density).
        field = (("lam" if material.lam >= 2.0 * material.mu / 3.0 else "mu")
                 if material.has_default_pressure_stiffness else "pressure_stiffness")
        default = " (pressure_stiffness by default, from lam and mu)" if material.has_default_pressure_stiffness else ""
        return (field, float(getattr(material, field)),
                f"the pressure force multiplies its pressure, up to density pressure_stiffness = {pressure:.3g} Pa"
                f"{default}, by two densities of {density:.3g} kg/m^3, so that pressure must be at most "
                f"{big:.3g} / density^2 = {big / density ** 2:.3g} Pa; {wider_precision(scalar, 'smaller values', cli)}")
    # The flow rule compares squares, 4 mu^2 |dev sigma|^2 against the yield stress's
    # (plasticity.flow_fraction): past the precision's range the square was inf, the rate NaN,
    # and every flow removed the whole deviatoric strain in one step whatever the flow rate
    # (float32, mu = 1e19, measured). Room is left for |dev sigma| up to FLOW_DEVIATOR_ROOM.
    limit = math.sqrt(big) / (2.0 * FLOW_DEVIATOR_ROOM)
    if material.plastic and material.mu > limit:
        return ("mu", float(material.mu),
                f"with a yield stress and a flow rate it must be at most {limit:.3g}: the flow rule squares the "
                f"deviatoric stress, 2 mu times the singular values' deviator (room left for a deviator of norm "
                f"{FLOW_DEVIATOR_ROOM:g}); "
                f"{wider_precision(scalar, 'a smaller value', cli)}")
    return None


def material_precision_problem(material: Material, scalar, cli: bool = False) -> tuple[str, float, str] | None:
    """``(name, value, what is allowed)`` of the first parameter of ``material`` that does not
    hold in ``scalar``, or None (``check_material_precision``); last, the p-wave modulus they
    make, reported on the field of its largest term (``modulus_precision_problem``). ``name``
    is ``Material.<field>``, or ``E`` (``value`` the E given) for a ``mu`` or ``lam`` derived
    from the E and nu given (``_named_as_given``). ``cli``: the advice names ``--dtype`` too."""
    # pair_repulsion is no fitted field but is cast as one: 1e39 was inf in float32, 1e-50 was 0.
    for name in (*Model.MATERIAL_FIELDS, "density", "pair_repulsion"):
        v = getattr(material, name)
        why = precision_problem(v, scalar, cli)
        if why is not None and name == "pressure_stiffness" and material.has_default_pressure_stiffness:
            # No one gave it: density = 1e-300 was refused as "pressure_stiffness = 7.67e+303
            # ... or a smaller value", a value derived from the density, which a smaller one raises.
            # Below the precision's smallest (density = 1e300: 1.5e-295) it was refused as above
            # its largest, named by the modulus, with the advice of a smaller one.
            info = np.finfo(np.float32 if scalar is wp.float32 else np.float64)
            modulus = "mu" if material.mu >= material.lam else "lam"
            if abs(v) > float(info.max):
                source = "density" if material.density < 0.25 else modulus
                bound, fix = f"at most {float(info.max):.3g}", ("larger density" if source == "density" else "smaller modulus")
            else:
                # The one further from a solid's (1000 kg/m^3, 1e5 Pa), in decades.
                source = ("density" if abs(math.log10(material.density / 1e3)) >= abs(math.log10(getattr(material, modulus) / 1e5))
                          else modulus)
                bound, fix = f"at least {float(info.tiny):.3g}", ("smaller density" if source == "density" else "larger modulus")
            return _named_as_given(material, source, float(getattr(material, source)), (
                f"the pressure_stiffness it gives by default, K / (4 density) = {v:.3g}, must be {bound} in "
                f"{scalar.__name__}; give pressure_stiffness, or a {fix}"))
        if why is not None:
            return _named_as_given(material, name, v, why)
    problem = modulus_precision_problem(material, scalar, cli)
    return None if problem is None else _named_as_given(material, *problem)


def _named_as_given(material: Material, name: str, value: float, why: str) -> tuple[str, float, str]:
    """The problem of a modulus derived from the ``E`` and ``nu`` given (``young_given``) as
    theirs: ``("E", E, ...)``; field names stay prefixed ``Material.``, ``E`` is no field."""
    if name == "yield_stress" and name in lab_given(material):
        # A lab's yield stress (Material.from_rheology's, a scene file's), which grows with it as
        # the advice says; a flow rate falls as its plastic viscosity grows, and stays named so.
        given, v = lab_given(material)[name]
        return given, v, f"it gives {LAB_QUANTITIES[given][1]} = {value:g}: {why}"
    young = young_given(material)
    if young is None or name not in LAME_FORMULAS:
        return f"Material.{name}", value, why
    E, nu = young
    return "E", E, f"with nu = {nu!r} it gives {name} = {LAME_FORMULAS[name]} = {value:g}: {why}"


def check_pressure_forces(materials: Sequence[Material], images: bool = False) -> None:
    """Refuse ``pressure_force = "isotropic"`` beside another pressure force in one model: a pair
    between the two would carry the pair material's pressure on one side only (the isotropic
    particle applies its own through its moments, not along its pairs), and no force for such a
    pair is defined (docs/method.md §6); nor with floor images (``images``), whose pressure is a
    pair force of the floor's mirror images. Here, where the materials are given, so that no
    kernel has run (docs/errors.md)."""
    forces = [m.pressure_force for m in materials]
    if "isotropic" in forces and any(f != "isotropic" for f in forces):
        iso = forces.index("isotropic")
        other = next(k for k, f in enumerate(forces) if f != "isotropic")
        raise ValueError(f"Material.pressure_force = 'isotropic' (material {iso}) is not allowed beside "
                         f"pressure_force = {forces[other]!r} (material {other}) in one model: make every material "
                         "'isotropic' or none (Model.set_materials changes them together)")
    if images and "isotropic" in forces:
        raise ValueError(f"Material.pressure_force = 'isotropic' (material {forces.index('isotropic')}) is not allowed "
                         "with floor images (add_ground(images=True)): their pressure is a pair force of the floor's "
                         "mirror images; use a particle or ghost floor or a collider")


def check_shear_cap(materials: Sequence[Material], shear_cap: float) -> None:
    """Refuse the Tresca ground (``add_ground(shear_cap=K)``, ``K > 0``) under a material
    without a shear yield stress ``tau_y`` for it to hold up to: ``Material.shear_yield_stress``
    exists for the Bingham models with incremental deformation, and an infinite
    ``yield_stress`` (an elastic material) would make the hold a wall without a limit.
    Here, where the materials are given, so that no kernel has run."""
    if not shear_cap > 0.0:
        return
    for k, m in enumerate(materials):
        if m.model not in BINGHAM_MODELS or m.deformation != "incremental" or not math.isfinite(m.yield_stress):
            raise ValueError(
                f"add_ground(shear_cap = {shear_cap!r}) is not allowed with material {k} (model = {m.model!r}, "
                f"deformation = {m.deformation!r}, yield_stress = {m.yield_stress!r}): the ground holds its base up to "
                f"shear_cap times the material's shear yield stress yield_stress / sqrt(2), which exists for a finite "
                f"yield_stress of model {' or '.join(map(repr, BINGHAM_MODELS))} with deformation 'incremental'; give "
                "such a material, or a ground without shear_cap (its friction grips instead)")


def check_material_precision(material: Material, scalar, where: str = "", cli: bool = False) -> None:
    """Every parameter of ``material`` holds in ``scalar``: 1e300 Pa cast to float32 became
    inf, 1e-300 Pa became 0 (a modulus of nothing, NaN by the third step), without a word.
    ``where`` follows the field in the message (``" (material 0)"``); ``cli``: the advice
    names ``--dtype`` too (a table the command writes)."""
    problem = material_precision_problem(material, scalar, cli)
    if problem is not None:
        name, v, why = problem
        raise ValueError(f"{name} = {v:g}{where} is not allowed in {scalar.__name__}: {why}")


def flowed_by_hardening(alpha) -> bool:
    """Whether a body of hardening ``alpha`` (host values: a state's, a checkpoint's, a given
    ``alpha0``) has flowed: ``alpha`` > 0 somewhere. The one test of it, so that a state, a
    checkpoint and a fit's start cannot disagree on which body keeps the incremental
    composition (``State.has_flowed``)."""
    return bool(np.any(np.asarray(alpha) > 0.0))


def keeps_incremental(state: "State", flowed: bool | None = None) -> bool:
    """Whether a step from ``state`` keeps the incremental composition whatever the parameters
    allow: an incremental step wrote it (``State.rest_model`` False) and its body has flowed
    (``State.has_flowed``), so its rest neighbourhoods no longer describe it and it is never
    handed over to the rest model (``Solver._runs_rest``). Not a function of the parameters:
    ``Solver.runs_rest`` is ``rest_model and not keeps_incremental(state)``, and a record made
    later at other values (fit.json's ``solver``) combines the two alike; ``Model.stable_dt(state=)``
    halves the step of such a state (``corrected_incremental``). Reads ``alpha`` back only where
    ``rest_model`` is False and ``flowed`` is not True (``State.has_flowed``); ``flowed``: its
    answer where the caller has read it already (the step, for its path and its check alike)."""
    return state.rest_model is False and (state.has_flowed() if flowed is None else flowed)


def check_contact_ramp(name: str, value) -> float:
    """A contact ramp: a number in [0, ``MAX_CONTACT_RAMP``] (0: the instant law; 1: the continuous one)."""
    v = checks.non_negative(name, value)
    if not v <= MAX_CONTACT_RAMP:
        raise ValueError(f"{name} = {checks.shorten(value)!r} is not allowed: must be at most {MAX_CONTACT_RAMP:g} "
                         "(0: the whole inward velocity removed; 1: the continuous contact)")
    return v


@dataclasses.dataclass(frozen=True)
class Body:
    """A contiguous range of particles made of one material."""

    name: str
    start: int
    count: int
    material: int
    kind: str
    #: The world it belongs to (``SceneBuilder.finalize(worlds=W)``; 0 without worlds).
    world: int = 0
    #: The material of its elastic particle floor (``add_particle_floor(elastic=True)``), a
    #: wall's, which a fit leaves as built; -1: none.
    floor_material: int = -1
    #: How many of its last particles are a ghost floor (``add_particle_floor(ghost=True)``,
    #: ``sim/ghost_floor.py``; 0: none), the height of that floor's wall plane (m), and whether
    #: the wall lets the material slide (``slip=True``) rather than holding it (no slip).
    ghost_floor: int = 0
    ghost_plane: float = 0.0
    ghost_slip: bool = False


class Unpicklable:
    """Refuses pickle (and ``copy.deepcopy`` where the class has no ``__deepcopy__``) in one
    line naming what carries the object instead (``UNPICKLABLE``): pickle's own error came
    from deep inside Warp's device (``Can't pickle local object 'CDLL.__init__.<locals>._FuncPtr'``),
    naming neither the object nor a way out. A shallow ``copy.copy`` stays what it was."""

    UNPICKLABLE = ""
    #: The name it is refused by (None: ``warp_esph.<class name>``).
    UNPICKLABLE_NAME = None

    def __reduce_ex__(self, protocol):
        copies = "" if hasattr(type(self), "__deepcopy__") else " or deep-copied"
        name = self.UNPICKLABLE_NAME or f"warp_esph.{type(self).__name__}"
        raise TypeError(f"a {name} cannot be pickled{copies}: {self.UNPICKLABLE}")

    def __copy__(self):
        twin = object.__new__(type(self))
        twin.__dict__.update(self.__dict__)
        return twin


class State(Unpicklable):
    """Positions ``x``, velocities ``v``, elastic deformation gradient ``F`` (docs/method.md: the only
    deformation state stored) and hardening accumulator ``alpha`` of every particle; with
    ``add_ground(images=True)`` also ``F_image`` and ``alpha_image``, the elastic F and the
    hardening of each particle's floor image."""

    UNPICKLABLE = ("it holds Warp arrays on its device and the Model that made it; write it to a checkpoint with "
                   "warp_esph.checkpoint.save_state(path, model, state, step=, frame=) and read it back with "
                   "load_state(path, model) (copy.deepcopy(state) copies it within this process)")

    def __init__(self, model: "Model", requires_grad: bool, start_velocities: bool = True):
        n, K, dev = model.particle_count, model.max_neighbors, model.device
        T = model.types
        # The model this state is of: a checkpoint is filed under its model's fingerprint, so
        # ``save_state`` refuses a state of another scene that merely has as many particles.
        # Held, not weakly: a state of a model built again and dropped (``finalize()`` twice)
        # is still told to be of the same scene.
        self._model = model
        # And that model's bodies and rest positions as they are now (``checks.same_state``):
        # a model edited since (``calibrate.jitter_model``) no longer describes this state's
        # scene, and one built again from the same builder still does.
        self._made_of = model.scene_snapshot()
        model.check_start(velocities=start_velocities)
        self.x = wp.array(model.particle_x0, dtype=T.vec3, device=dev, requires_grad=requires_grad)
        # The positions' round-off (warp_esph/sim/roundoff.py), as F_lo for F below.
        self.x_lo = wp.zeros(n, dtype=T.vec3, device=dev)
        self.v = (wp.array(model.particle_v0, dtype=T.vec3, device=dev, requires_grad=requires_grad) if start_velocities
                  else wp.zeros(n, dtype=T.vec3, device=dev, requires_grad=requires_grad))
        self.F = wp.array(np.tile(np.eye(3, dtype=T.np_dtype), (n, 1, 1)), dtype=T.mat33, device=dev, requires_grad=requires_grad)
        # F's round-off, F + F_lo being the stored gradient to about twice the precision:
        # the per-step changes of F near rest are a few units in F's last place, and
        # rounding them away every step makes a pile at yield creep (docs/physics.md, the
        # float32 creep floor; warp_esph/sim/roundoff.py). Not differentiated (it is below
        # F's round-off; the adjoints treat F + F_lo as F). A state edited by hand keeps its
        # round-off arrays: an error of half a unit in the last place of the old value
        # (save_state files x + x_lo split again where that exceeds the new value's last place).
        self.F_lo = wp.zeros(n, dtype=T.mat33, device=dev)
        self.alpha = wp.zeros(n, dtype=T.scalar, device=dev, requires_grad=requires_grad)
        # The plastic F_p of the rest-configuration comparison model (docs/method.md §7; I elsewhere).
        # The additive model's strain needs no field of its own: F holds I + eps there.
        # Its gradient only where a comparison model reads it, or fit="auto" runs the rest model
        # (Model.auto_runs_rest; a taped hand-over to it needs F_p's gradient): a taped step's memory.
        self.F_p = wp.array(np.tile(np.eye(3, dtype=T.np_dtype), (n, 1, 1)), dtype=T.mat33, device=dev,
                            requires_grad=requires_grad and (model.uses_comparison_models or model.auto_runs_rest()))
        # Each floor image's own elastic F (``SceneBuilder.add_ground(images=True)``): the image
        # of a particle near the plane is a floor particle at rest over the step whose energy
        # works on its own fit, so its F is stored as a particle's is, or that work would have
        # no stored counterpart (docs/physics.md, "The floor images' energy is not stored").
        # I in a new state (an undeformed floor; set it with F when F is set by hand), kept while
        # the image has no particle within the support; unread without an image plane.
        images = model.image_plane is not None
        self.F_image = wp.array(np.tile(np.eye(3, dtype=T.np_dtype), (n, 1, 1)), dtype=T.mat33, device=dev,
                                requires_grad=requires_grad and images)
        # And its own hardening, advanced by its own flow as a floor particle's is (0 in a new
        # state; set it with alpha when alpha is set by hand; its particle's where the share
        # below is 0, as F_image with F).
        self.alpha_image = wp.zeros(n, dtype=T.scalar, device=dev, requires_grad=requires_grad and images)
        #: Simulated time (s) of this state: the step that writes it sets ``time_in + dt``.
        self.time = 0.0
        #: Whether the step that wrote this state ran the rest-configuration model in place of the
        #: incremental composition (None: no step wrote it); the record of what ran, which the
        #: solver does not keep (``Solver.record(state)``, ``Solver.runs_rest``). A rest step
        #: after an incremental one hands the stored ``F`` over (``comparison.rest_handover``),
        #: unless the body has flowed (``flowed``).
        self.rest_model = None
        #: Whether the body has flowed (``alpha`` > 0 somewhere; it never decreases): True, False,
        #: or None where no step or load has read it. A step keeps the incremental composition for
        #: a flowed state in place of handing it over to the rest model (``Solver.step``), and
        #: carries True on. Only True is taken as it stands (``has_flowed``): a step never lowers
        #: ``alpha``, and a body that flowed stays so. False is what the writer found, which an
        #: ``alpha`` set by hand since (``state.alpha.assign(...)``) makes stale, so a hand-over
        #: reads ``alpha`` back for a state of False or None (once: the rest steps after it carry
        #: their own flag and are no hand-over).
        self.flowed = None
        #: A weak reference to the solver whose step wrote this state, or whose ``simulate`` run it
        #: starts (None: neither): save_state without solver= records that solver's settings while
        #: it exists, so a resume with another hourglass strength (one set by hand,
        #: Solver.hourglass) is refused, not run.
        self.written_by = None
        #: The work (J) the moving tools and pinned sets did on the bodies from the run's start
        #: to this state, as ``simulate`` counted it (``ToolWork``) and ``save_state`` keeps it;
        #: None where not known (a state a step wrote outside ``simulate``, a new one). A resumed
        #: ``simulate`` (``monitor_origin``) adds it to the work its own steps do, so its blow-up
        #: bounds count the work done before the checkpoint as the uninterrupted run did.
        self.tool_work = None
        # Written by the step that produced this state.
        self.neighbors = wp.zeros((n, K), dtype=wp.int32, device=dev)
        # The selection's squared distances: scratch of the search, allocated only when asked
        # for (the solver keeps its own), so a taped step does not hold K scalars per particle.
        self._neighbor_d2 = None
        self._d2_spec = ((n, K), T.scalar, dev)
        self.neighbor_count = wp.zeros(n, dtype=wp.int32, device=dev)
        self.guard = wp.zeros(n, dtype=wp.int32, device=dev)
        #: The SPH (poly6) density of every particle, whatever its pressure force: the volumes
        #: ``m / rho`` of the viscous force, what diagnostics and exports read.
        self.density = wp.zeros(n, dtype=T.scalar, device=dev, requires_grad=requires_grad)
        #: The density the pressure of an ``energy_spiky`` material reads, each material's own
        #: (docs/method.md §6: the spiky sum there, the poly6 sum elsewhere), written by the step
        #: where the model has such a material (``Model.separate_pressure_density``); None
        #: otherwise (the pressure reads ``density``; ``pressure.pressure_density``).
        self.pressure_density = (wp.zeros(n, dtype=T.scalar, device=dev, requires_grad=requires_grad)
                                 if model.separate_pressure_density else None)
        self.F_flowed = wp.zeros(n, dtype=T.mat33, device=dev, requires_grad=requires_grad)
        self.F_flowed_lo = wp.zeros(n, dtype=T.mat33, device=dev)
        self.stress = wp.zeros(n, dtype=T.mat33, device=dev, requires_grad=requires_grad)
        self.F_inv = wp.zeros(n, dtype=T.mat33, device=dev, requires_grad=requires_grad)
        self.force = wp.zeros(n, dtype=T.vec3, device=dev, requires_grad=requires_grad)
        # The images' plastic flow and stress, written by the step (with an image plane only).
        self.F_image_flowed = wp.zeros(n, dtype=T.mat33, device=dev, requires_grad=requires_grad) if images else None
        self.alpha_image_flowed = wp.zeros(n, dtype=T.scalar, device=dev, requires_grad=requires_grad) if images else None
        self.image_stress = wp.zeros(n, dtype=T.mat33, device=dev, requires_grad=requires_grad) if images else None
        #: How much of each image's state is its own rather than its particle's
        #: (``deformation.floor_image_share``, written by the fit's update: 1 for images at
        #: rest and for moving ones whose particle is within ``h`` of the plane, else 0; 0
        #: without images).
        self.image_share = wp.zeros(n, dtype=T.scalar, device=dev, requires_grad=requires_grad and images)
        tools.allocate_state(model, self, requires_grad)
        integrate.allocate_state(model, self, requires_grad)
        ghost_floor.allocate_state(model, self, requires_grad)

    @property
    def neighbor_d2(self) -> wp.array:
        """Squared distances of the neighbour selection (``NeighborSearch.build``'s scratch)."""
        if self._neighbor_d2 is None:
            shape, dtype, dev = self._d2_spec
            self._neighbor_d2 = wp.zeros(shape, dtype=dtype, device=dev)
        return self._neighbor_d2

    #: The arrays that define the simulation state (what a checkpoint must hold).
    STATE_FIELDS = ("x", "v", "F", "alpha", "F_p", "x_lo", "F_lo", "F_image", "alpha_image")
    #: Fields a checkpoint written before the comparison models (``F_p``), the compensated
    #: state (``x_lo``, ``F_lo``) or the images' own F and hardening (``F_image``,
    #: ``alpha_image``) lacks (then: initial values, I and 0; the images' their particles').
    OPTIONAL_FIELDS = ("F_p", "x_lo", "F_lo", "F_image", "alpha_image")
    #: What the step that produced a state reported of the tools and static colliders (their
    #: reaction force and torque, written with its frame): ``assign`` and checkpoints carry
    #: them where both sides have them, so a resumed run writes its first frame as the
    #: uninterrupted run did (they were zero there).
    STEP_REPORTS = ("reaction_force", "reaction_torque", "collider_force", "collider_torque")

    #: What every step writes on its ``state_out`` besides arrays: none of it is what
    #: ``checks.same_state`` checks, so setting it keeps that check's memo (cleared by these
    #: too, the full check ran twice a step, docs/performance.md).
    BOOKKEEPING = frozenset(("time", "rest_model", "flowed", "written_by", "tool_work"))

    def __deepcopy__(self, memo):
        # Its own arrays (wp.clone: warp's arrays refuse deepcopy, 'ctypes objects containing
        # pointers cannot be pickled'), of the same model and the same record of its scene.
        # The memo of checks is not copied: it names the arrays by id.
        for shared in ("_model", "_made_of", "_d2_spec"):  # read-only, and holding warp's devices
            if shared in self.__dict__:
                memo[id(self.__dict__[shared])] = self.__dict__[shared]
        twin = object.__new__(type(self))
        memo[id(self)] = twin
        for name, value in self.__dict__.items():
            if name in ("_checked_for", "_arrays"):
                continue
            if isinstance(value, wp.array):
                if id(value) not in memo:
                    memo[id(value)] = wp.clone(value)
                twin.__dict__[name] = memo[id(value)]
            else:
                twin.__dict__[name] = copy.deepcopy(value, memo)
        return twin

    def __setattr__(self, name, value):
        # A replaced array may not fit the model any more: ``checks.same_state`` checks again.
        if name not in self.BOOKKEEPING:
            self.__dict__.pop("_checked_for", None)
            self.__dict__.pop("_arrays", None)
        object.__setattr__(self, name, value)

    def has_flowed(self) -> bool:
        """Whether the body has flowed: True where ``flowed`` is True, else ``alpha`` > 0
        somewhere, read back from the device (not cached: a step only reads its ``state_in``).
        A ``flowed`` of False is not trusted: the step that wrote it would hand a body whose
        ``alpha`` was set by hand since to the rest model, whose rest neighbourhoods no longer
        describe it."""
        return True if self.flowed else flowed_by_hardening(self.alpha.numpy())

    def assign(self, other: "State"):
        """Copy ``other``'s state fields (and time) into this state, and the reactions the
        step that produced it reported (``STEP_REPORTS``) where both have them alike."""
        for name in self.STATE_FIELDS:
            a, b = getattr(self, name), getattr(other, name, None)
            if not isinstance(b, wp.array):  # a State, or anything holding its fields (rollout checkpoints)
                raise ValueError(f"other = {checks.shorten(other)!r} is not allowed: must be a warp_esph.State (its {name} is {b!r})")
            if a.shape != b.shape or a.dtype is not b.dtype:
                raise ValueError(
                    f"other is not allowed: its {name} is {b.shape} {getattr(b.dtype, '__name__', b.dtype)}, this state's "
                    f"{a.shape} {getattr(a.dtype, '__name__', a.dtype)} (a state of another model?)"
                )
        for name in self.STATE_FIELDS:
            wp.copy(getattr(self, name), getattr(other, name))
        for name in self.STEP_REPORTS:
            a, b = getattr(self, name, None), getattr(other, name, None)
            if isinstance(a, wp.array) and isinstance(b, wp.array) and a.shape == b.shape and a.dtype is b.dtype:
                wp.copy(a, b)
        self.time = getattr(other, "time", 0.0)
        self.rest_model = getattr(other, "rest_model", None)
        self.flowed = getattr(other, "flowed", None)
        self.written_by = getattr(other, "written_by", None)
        self.tool_work = getattr(other, "tool_work", None)

    @property
    def particle_count(self) -> int:
        """The number of particles this state holds (every world's, with worlds)."""
        return self.x.shape[0]


#: The least depth below the plane of a floor image (``deformation.floor_image``), in
#: spacings: half a spacing, where a floor of particles has its top layer.
IMAGE_MIN_DEPTH = 0.5

#: The static colliders' arrays that ``Model.check_colliders`` judges, in the order the
#: step's one read brings them: each with the list of the model's colliders its rows are and
#: the numbers of a row.
COLLIDER_FIELDS = (("plane_friction", "planes", 1), ("plane_offset", "planes", 1), ("plane_normal", "planes", 3),
                   ("sphere_friction", "spheres", 1), ("sphere_radius", "spheres", 1), ("sphere_center", "spheres", 3),
                   ("box_friction", "boxes", 1), ("box_half", "boxes", 3), ("box_center", "boxes", 3))
#: The field of ``Plane``, ``Sphere`` or ``Box`` each of ``COLLIDER_FIELDS`` holds
#: (``Model.static_colliders``).
COLLIDER_ATTRIBUTES = {"plane_friction": "friction", "plane_offset": "offset", "plane_normal": "normal",
                       "sphere_friction": "friction", "sphere_radius": "radius", "sphere_center": "center",
                       "box_friction": "friction", "box_half": "half_extents", "box_center": "center"}

#: The per-particle and per-material arrays that ``Model.check_particles`` judges: each with
#: what its rows are and whether it holds integers (else the model's scalars).
PARTICLE_FIELDS = (("particle_material", "particles", True), ("particle_mass", "particles", False),
                   ("particle_volume", "particles", False), ("material_model", "materials", True),
                   ("material_deformation", "materials", True), ("material_elastic_force", "materials", True),
                   ("material_pressure_force", "materials", True), ("clamp_pressure", "materials", True),
                   ("pair_repulsion", "materials", False))
#: The per-particle arrays a caller may replace by any array-like of one row per particle
#: (``Model._particle_rows`` converts it): the start's, numpy arrays of shape ``(n, 3)``, and
#: those the kernels index, warp arrays of ``n`` real numbers or integers.
PARTICLE_ROWS = {"particle_x0": "start", "particle_v0": "start", "particle_mass": "reals", "particle_volume": "reals",
                 "particle_material": "integers"}
#: The material code arrays of ``PARTICLE_FIELDS``: each with the ``Material`` field it codes
#: and the codes (``clamp_pressure``: 1 for True).
MATERIAL_CODES = (("material_model", "model", MODEL_IDS), ("material_deformation", "deformation", DEFORMATION_IDS),
                  ("material_elastic_force", "elastic_force", ELASTIC_FORCE_IDS),
                  ("material_pressure_force", "pressure_force", PRESSURE_FORCE_IDS),
                  ("clamp_pressure", "clamp_pressure", {False: 0, True: 1}))

#: The kernels' ``images`` argument (``Model.image_args``): no image plane; images at rest over
#: each step in the fits (a rough floor, the ground's ``friction > 0``); images that move with
#: their particles over the step (a frictionless floor, ``friction = 0``;
#: ``deformation.partner_displacement``; docs/physics.md, "The imaged ground is rough whatever
#: its friction").
IMAGES_NONE, IMAGES_AT_REST, IMAGES_MOVING = 0, 1, 2


class MaterialList(list):
    """``Model.materials``: the materials the model's parameter arrays were built from, which
    ``set_material`` changes together. Not to be changed in place: the list alone changed and the
    arrays the kernels read did not (``model.materials[0] = Material.preset("rubber", mu=1e3)``
    stepped at the old modulus, the list and ``stable_dt`` saying 1e3); each change is refused,
    naming ``set_material``. A copy is a list of the same class (``copy``, ``deepcopy``)."""

    ADVICE = ("the kernels read the parameter arrays built from the materials, which this list only records (a "
              "material written into it ran at the old values)")

    def __setitem__(self, index, value):
        raise ValueError(f"model.materials[{checks.shorten(index)!r}] = {checks.shorten(value)!r} is not allowed: "
                         f"{self.ADVICE}; change a material with model.set_material({checks.shorten(index)!r}, material)")

    def _refused(name):  # noqa: N805 (makes the class's methods)
        def refuse(self, *args, **kwargs):
            raise ValueError(f"model.materials.{name}(...) is not allowed: {self.ADVICE}, and the particles' materials "
                             "are set when the model is built; change a material with model.set_material(index, "
                             "material), or finalize a model with other materials")
        return refuse

    __delitem__, __iadd__, __imul__ = _refused("__delitem__"), _refused("__iadd__"), _refused("__imul__")
    append, extend, insert, pop = _refused("append"), _refused("extend"), _refused("insert"), _refused("pop")
    remove, clear, sort, reverse = _refused("remove"), _refused("clear"), _refused("sort"), _refused("reverse")
    del _refused

    def __reduce_ex__(self, protocol):
        return type(self), (list(self),)  # made whole: pickle's default appends the items one by one


class Model(Unpicklable):
    """Particles, materials, bodies and colliders of a scene; built by ``SceneBuilder.finalize``."""

    UNPICKLABLE = ("it holds Warp arrays on its device; pickle the SceneBuilder that made it (or keep its scene "
                   "file) and finalize it again, which makes the same scene (its checkpoints resume there)")

    def __init__(
        self,
        *,
        positions: np.ndarray,
        velocities: np.ndarray,
        particle_material: np.ndarray,
        particle_body: np.ndarray,
        materials: list[Material],
        bodies: list[Body],
        spacing: float,
        support_radius: float,
        gravity: tuple[float, float, float],
        planes: list[Plane],
        spheres: list[Sphere],
        boxes: list[Box],
        max_neighbors: int,
        device,
        scalar,
        requires_grad: bool,
        bodies_interact: bool = True,
        particle_world: np.ndarray | None = None,
        world_material_start: Sequence[int] | None = None,
        fit_weight: str = DEFAULT_FIT_WEIGHT,
    ):
        self.device = wp.get_device(device)
        self.types = type_set(scalar)
        self.scalar = scalar
        #: The step's launches on this model, replayed (``sim/replay.py``).
        self.launches = Launches()
        self.requires_grad = bool(requires_grad)
        self._spacing = float(spacing)
        self._support_radius = float(support_radius)
        #: The weights of the incremental fit and the sums that share them
        #: (``smoothing.FIT_WEIGHTS``: ``"biweight"``, the default; ``"poly6"``, the paper's eq. 7;
        #: ``SceneBuilder(fit_weight=)``, docs/physics.md, "The fit's weight").
        self.fit_weight = checks.choice("fit_weight", fit_weight, FIT_WEIGHTS)
        self.max_neighbors = int(max_neighbors)
        #: Whether neighbour lists (so SPH pressure and viscosity) reach into other bodies.
        self.bodies_interact = bool(bodies_interact)
        self._gravity = tuple(float(g) for g in gravity)
        self.materials = MaterialList(materials)
        self._material_struct = None  # material_arrays' struct and what it was built from
        self._rest_material_struct = None  # the same with every deformation code "rest" (material_arrays(rest=True))
        self._rest_codes = None
        self._stable_dt = None  # stable_dt's last answer and what it was computed from
        self._row_answers = {}  # _answer's last answer to each question, with the parameter rows' bytes it read
        self._parameter_stage = None  # _read_parameters's one buffer (allocated on first use)
        # Whether _read_parameters copies into it on the device and reads that (a GPU's), or
        # reads the arrays through views (the CPU's).
        self._staged_reads = not self.device.is_cpu
        self._parameter_views = None  # on the CPU, _read_parameters's views of the arrays, with their key
        self._held_parameters = None  # _read_parameters's answer inside _parameters_read_once
        self._held_bytes = None  # their bytes (_parameters_key), where they are a read's
        self._image_args = None  # image_args' list, made once: the plane and spacing are fixed
        self._image_reaction_rows = None  # integrate.launch_floor_image_reaction's row arguments, made once
        self._static_collider_struct = None  # sim.integrate.static_collider_struct's (key, struct, arrays)
        self._static_collider_adjoint = None  # sim.integrate.static_collider_adjoint's (struct, its adjoint, its arrays' gradients)
        self._spare_reaction_rows = None  # sim.integrate.spare_reaction_rows' (force, torque)
        self.bodies = list(bodies)
        self.planes, self.spheres, self.boxes = list(planes), list(spheres), list(boxes)
        self.contact_ramp = CONTACT_RAMP
        self._fit = None  # the default (``fit``), until one is chosen
        self.hourglass = None  # by the fit (``solver_choice``), until one is chosen
        self.particle_count = int(positions.shape[0])
        npf = self.types.np_dtype
        self.particle_x0 = np.ascontiguousarray(positions, dtype=npf)
        self.particle_v0 = np.ascontiguousarray(velocities, dtype=npf)
        self.particle_material_np = np.ascontiguousarray(particle_material, dtype=np.int32)
        self.particle_body_np = np.ascontiguousarray(particle_body, dtype=np.int32)

        dev = self.device
        self.particle_material = wp.array(self.particle_material_np, dtype=wp.int32, device=dev)
        self.particle_body = wp.array(self.particle_body_np, dtype=wp.int32, device=dev)

        # Worlds: independent copies (or different scenes) in one model, particles and
        # materials world after world; neighbour lists never cross them.
        if particle_world is None:
            particle_world = np.zeros(self.particle_count, dtype=np.int32)
        #: World of each particle (numpy int32, non-decreasing).
        self.world_of_particle = np.ascontiguousarray(particle_world, dtype=np.int32)
        #: Number of worlds.
        self.world_count = int(self.world_of_particle.max()) + 1 if self.particle_count else 1
        #: Particles of world ``w``: ``world_start[w]:world_start[w + 1]``.
        self.world_start = np.searchsorted(self.world_of_particle, np.arange(self.world_count + 1)).astype(np.int64)
        if world_material_start is None:
            world_material_start = (0, len(materials))
        #: Materials of world ``w``: ``world_material_start[w]:world_material_start[w + 1]``
        #: (the entries of every per-material array, and of its gradient, that are world ``w``'s).
        self.world_material_start = np.asarray(world_material_start, dtype=np.int64)
        self._check_worlds()
        self.particle_world = wp.array(self.world_of_particle, dtype=wp.int32, device=dev)
        if self.world_count > 1 and self.bodies_interact:
            #: Ids whose particles never appear in each other's neighbour lists (``None``: all
            #: may): the world with worlds; the body without body interaction.
            self.neighbor_group = self.particle_world
        elif not self.bodies_interact:
            self.neighbor_group = self.particle_body
        else:
            self.neighbor_group = None
        # Lattice volume dx^3 per particle: V_i = m_i / rho0 (docs/method.md §5; the kernel is
        # evaluated in reference space, so the rest volume is the right one).
        volume = np.full(self.particle_count, self.spacing**3, dtype=npf)
        density = np.array([m.density for m in materials], dtype=npf)[self.particle_material_np]
        ghosts = [(b.start + b.count - b.ghost_floor, b.start + b.count, b.ghost_plane, b.ghost_slip)
                  for b in bodies if b.ghost_floor > 0]
        # The volume that weighs each particle's elastic energy: none for a ghost floor's
        # (sim/ghost_floor.py), whose mass still enters the SPH density.
        energy_volume = volume.copy()
        for a, b, _, _ in ghosts:
            energy_volume[a:b] = 0.0
        self.particle_volume = wp.array(energy_volume, dtype=scalar, device=dev)
        self.particle_mass = wp.array(volume * density, dtype=scalar, device=dev)
        self.particle_rest_density = wp.zeros(self.particle_count, dtype=scalar, device=dev)

        # Per-material parameters; differentiable when requires_grad.
        self.mu = self._material_array("mu")
        self.lam = self._material_array("lam")
        self.yield_stress = self._material_array("yield_stress")
        self.flow_rate = self._material_array("flow_rate")
        self.hardening = self._material_array("hardening")
        self.pressure_stiffness = self._material_array("pressure_stiffness")
        self.viscosity = self._material_array("viscosity")
        self.material_model = wp.array([MODEL_IDS[m.model] for m in materials], dtype=wp.int32, device=dev)
        self.clamp_pressure = wp.array([int(m.clamp_pressure) for m in materials], dtype=wp.int32, device=dev)
        # Not differentiated (not in MATERIAL_FIELDS): no gradient array.
        self.pair_repulsion = wp.array([m.pair_repulsion for m in materials], dtype=scalar, device=dev)
        self.material_deformation = wp.array(
            [DEFORMATION_IDS[m.deformation] for m in materials], dtype=wp.int32, device=dev
        )
        self.material_elastic_force = wp.array(
            [ELASTIC_FORCE_IDS[m.elastic_force] for m in materials], dtype=wp.int32, device=dev
        )
        check_pressure_forces(materials)
        self.material_pressure_force = wp.array(
            [PRESSURE_FORCE_IDS[m.pressure_force] for m in materials], dtype=wp.int32, device=dev
        )
        #: External force fields (``fields.CompressionField``), set by the builder. A caller may
        #: append more (or replace the list) after ``finalize``: ``stable_dt``, so each step
        #: before its first launch, refuses what ``finalize`` refuses (``_check_force_fields``).
        self.force_fields: list = []
        self._checked_fields: list = []  # the fields _check_force_fields last passed
        #: Moving colliders and pinned sets (``tools.ToolSet``), set by the builder; None: none.
        self.tools = None
        # Rest positions and initial neighbour lists of the rest-configuration model
        # (``rest_neighbors()`` builds them once).
        self.rest_x = None
        self._rest_from = None  # the particle_x0 they were built from (_drop_stale_rest)
        self._snapshot = None  # the last scene_snapshot(), shared by the states made while it holds
        self.rest_nbr = None
        self.rest_count = None
        #: The neighbourhood guard (``neighbors.GUARD_*``) of each particle's rest neighbourhood,
        #: with the default thresholds (6 neighbours, ``cond(A) <= 20``); ``rest_neighbors()`` fills it
        #: (a solver's own thresholds: ``rest_guard_for``).
        self.rest_guard = None
        # The same with a solver's other thresholds (rest_guard_for), keyed by them.
        self._rest_guards = {}
        # The rest neighbourhoods' fixed moments (rest_moments), keyed by the fit and its weight.
        self._rest_moments = {}

        V, S = self.types.vec3, scalar
        self.plane_normal = self._collider_array([p.normal for p in planes], V)
        self.plane_offset = self._collider_array([p.offset for p in planes], S)
        self.plane_friction = self._collider_array([p.friction for p in planes], S)
        self.sphere_center = self._collider_array([s.center for s in spheres], V)
        self.sphere_radius = self._collider_array([s.radius for s in spheres], S)
        self.sphere_friction = self._collider_array([s.friction for s in spheres], S)
        self.box_center = self._collider_array([b.center for b in boxes], V)
        self.box_half = self._collider_array([b.half_extents for b in boxes], V)
        self.box_friction = self._collider_array([b.friction for b in boxes], S)
        imaged = [p for p in planes if getattr(p, "images", False)]
        #: ``(normal, offset)`` of the plane whose mirror images enter the fits (a rough floor,
        #: ``SceneBuilder.add_ground(images=True)``); None: none.
        self.image_plane = (tuple(imaged[0].normal), float(imaged[0].offset)) if imaged else None
        #: How the images move over a step (``IMAGES_*``): with their particles on a frictionless
        #: imaged ground, else at rest.
        self.image_motion = (IMAGES_NONE if not imaged else IMAGES_MOVING if imaged[0].friction == 0.0
                             else IMAGES_AT_REST)
        # The imaged plane's row of the plane arrays, and every collider array's values as built
        # (check_colliders).
        self._image_row = next((k for k, p in enumerate(planes) if getattr(p, "images", False)), None)
        # The fields of the kinds of collider the model has: a kind it has none of passes a row
        # the kernels never read, and reading it cost every step of a scene on the ground alone.
        self._collider_fields = [f for f in COLLIDER_FIELDS if getattr(self, f[1])]
        self._collider_lists = (list(self.planes), list(self.spheres), list(self.boxes))  # as built
        self._collider_getter = operator.attrgetter(*(f[0] for f in self._collider_fields)) if self._collider_fields else None
        self._collider_flat = None  # _collider_arrays' answer, with the arrays it was made of
        self._collider_view_list = None
        self._collider_stage = None
        self._collider_read = None  # their values as the last staged read of the parameter arrays found them
        self._particle_getter = operator.attrgetter(*(f[0] for f in PARTICLE_FIELDS))
        self._particle_held = None  # _particle_arrays' (arrays, their views on the CPU)
        self._particles_checked = None  # the bytes check_particles last passed
        self._collider_built = self._collider_values()
        self._colliders_checked = self._collider_built.tobytes()  # the values check_colliders last passed
        check_pressure_forces(materials, self.image_plane is not None)
        self._shear_cap = float(imaged[0].shear_cap) if imaged else 0.0
        check_shear_cap(materials, self._shear_cap)
        #: The ghost floors, no-slip or slip (``sim.ghost_floor.GhostFloor``); None: none.
        self.ghost_floor = ghost_floor.build(self, ghosts)

    def _collider_arrays(self) -> list:
        """The arrays of ``COLLIDER_FIELDS`` of the model's kinds of collider as it holds them now, each refused
        (``ValueError``) where it is not one the kernels were made for: an array replaced by
        another of other rows, type or device; a collider added to (or taken from) the model's
        lists after the build, for which no kernel and no row of the arrays was made (a plane
        appended ran its contact on the arrays' memory past their end: NaN positions in one step),
        or one replaced in them (the kernels ran the old one's arrays, and what reads the list, the
        divergence check's floor, the reaction rows' reference points, a checkpoint's
        fingerprint, the new one)."""
        lists = (self.planes, self.spheres, self.boxes)
        if lists != self._collider_lists:  # each element compared by identity first: no cost in a step
            self._refuse_collider_lists(lists)
        fields = self._collider_fields
        if not fields:
            return []
        now = self._collider_getter(self)  # a tuple: a kind has three fields
        held = self._collider_flat
        if held is not None and all(map(operator.is_, held[0], now)):
            return held[1]
        arrays = []
        for (name, kind, width), a in zip(fields, now):
            self._check_kernel_array(name, a, len(getattr(self, kind)), self.scalar if width == 1 else self.types.vec3)
            arrays.append(a if width == 1 else a.view(self.scalar).flatten())
        # Kept while the arrays are the same ones: every step asks.
        self._collider_flat = (now, arrays)
        return arrays

    def _refuse_collider_lists(self, lists) -> None:
        """``_collider_arrays``' refusal of collider lists not as built (``ValueError``)."""
        for kind, one, now, built in zip(("planes", "spheres", "boxes"), ("plane", "sphere", "box"), lists,
                                         self._collider_lists):
            if len(now) != len(built):
                raise ValueError(f"model.{kind} = a list of {len(now)} is not allowed: the model was built with {len(built)}, "
                                 f"and finalize made the step's kernels and the collider arrays for them; add the collider "
                                 f"with the builder and build the scene again")
            k = next((k for k, (a, b) in enumerate(zip(now, built)) if a != b), None)
            if k is not None:
                names = [name for name, of, _ in COLLIDER_FIELDS if of == kind]
                raise ValueError(f"model.{kind}[{k}] = {now[k]!r} is not allowed: the step's kernels run the collider arrays "
                                 f"finalize made from the one built, {built[k]!r}, which the list only records; change a "
                                 f"{one} by writing its values into model.{', '.join(names[1:])} and {names[0]} "
                                 f"(.assign(...)), or build the scene again")

    def _check_kernel_array(self, name: str, a, rows: int, dtype) -> None:
        """Refuse (``ValueError``) ``model.<name>`` replaced by an array the step's kernels were not
        made for: not a warp array of ``rows`` entries of ``dtype`` on the model's device."""
        if not isinstance(a, wp.array) or a.shape != (rows,) or a.dtype != dtype or a.device != self.device:
            shown = (f"a warp array of shape {a.shape}, dtype {wp.types.type_repr(a.dtype)} on {a.device}"
                     if isinstance(a, wp.array) else f"a {type(a).__name__}")
            raise ValueError(f"model.{name} = {shown} is not allowed: the step's kernels were made for a warp array of "
                             f"shape ({rows},), dtype {wp.types.type_repr(dtype)} on {self.device}; write the values "
                             f"into the array it was (model.{name}.assign(...))")

    def _collider_views(self) -> list[np.ndarray]:
        """On the CPU, views of the memory of ``_collider_arrays`` (kept while they are the same
        arrays: nothing is copied)."""
        arrays = self._collider_arrays()
        held = self._collider_view_list
        if held is None or held[0] is not arrays:
            held = self._collider_view_list = (arrays, [a.numpy() for a in arrays])
        return held[1]

    def _collider_values(self) -> np.ndarray:
        """The values of ``_collider_arrays`` now, one after the other (a vector's three
        numbers in turn): through views on the CPU, in one transfer on a GPU."""
        if self.device.is_cpu:
            views = self._collider_views()
            return np.concatenate(views) if views else np.empty(0, dtype=self.types.np_dtype)
        arrays = self._collider_arrays()
        # One transfer into a buffer kept for it (each read of a device array waits for the device).
        stage = self._collider_stage
        if stage is None:
            stage = self._collider_stage = wp.empty(sum(a.shape[0] for a in arrays), dtype=self.scalar, device=self.device)
        self._stage_colliders(stage, 0, arrays)
        return stage.numpy()

    @staticmethod
    def _stage_colliders(stage: wp.array, at: int, arrays: list) -> None:
        """Copy the collider arrays (``_collider_arrays``) into ``stage`` from ``at``, on the device."""
        for a in arrays:
            wp.copy(stage, a, dest_offset=at, count=a.shape[0])
            at += a.shape[0]

    def _collider_rows(self, flat: np.ndarray) -> dict[str, np.ndarray]:
        """``_collider_values``'s numbers as each field's rows (a row per collider of the model)."""
        out, at = {}, 0
        for name, kind, width in self._collider_fields:
            rows = len(getattr(self, kind))
            out[name] = flat[at:at + rows * width].reshape(rows, width)
            at += rows * width
        return out

    def static_colliders(self, held: bool = False) -> tuple[list[Plane], list[Sphere], list[Box]]:
        """The static colliders ``(planes, spheres, boxes)`` as the step's kernels run them, read
        from their arrays (``COLLIDER_FIELDS``): a collider whose arrays hold the build's values is
        the entry of ``model.planes``, ``spheres`` or ``boxes`` itself (so its ``repr``, which a
        checkpoint's fingerprint hashes, is the build's), one written in place
        (``model.plane_offset.assign(...)``) a copy of it with the values its arrays hold, each the
        shortest number that is that value in the model's precision (0.1, not 0.100000001490116):
        the record of a plane moved to 0.1 is that of one built there, as the kernels run both
        alike. A value the precision does not hold records as its shortest number (a float32
        plane moved to 1/3 as one built at 0.33333334, not at 1/3, whose entry keeps the decimal it
        was given: the array cannot say which decimal it came from). The lists only record the build: what read them for a record or a check (a
        checkpoint's fingerprint, the reaction rows' reference points, the divergence check's
        floor, the USD export, a model made from this one) read a ground moved to 0.1 m at 0,
        and a checkpoint of the moved scene resumed into one on the ground at 0. Each call reads
        the arrays (on a GPU, one transfer): for records, not for each step.

        ``held``: every value as the precision holds it, moved or not: an entry whose build value
        is not the shortest number of what its array holds (a float32 plane built at -1/3) is a
        copy with that number (-0.33333334), so that one built there and one moved there in place
        record alike, as the kernels run them (a checkpoint's fingerprint from its version 3). A
        value the precision holds as given (0.1 in float32; every float64 value) is the build's,
        and its entry the build's own."""
        lists = tuple(list(c) for c in (self.planes, self.spheres, self.boxes))
        k = self._image_row
        if k is not None and lists[0][k].shear_cap != self._shear_cap:
            # ``shear_cap`` written after the build is the one the kernels run (a checkpoint of
            # a scene held at 0 resumed into one held at the build's K).
            lists[0][k] = dataclasses.replace(lists[0][k], shear_cap=self._shear_cap)
        now, built = self._collider_values(), self._collider_built
        if now.tobytes() == built.tobytes() and not held:
            return lists
        values, built = self._collider_rows(now), self._collider_rows(built)
        kinds, shown = ("planes", "spheres", "boxes"), self._shown_plane_value
        for name, kind, width in self._collider_fields:
            colliders = lists[kinds.index(kind)]
            attribute = COLLIDER_ATTRIBUTES[name]
            for k, (v, b) in enumerate(zip(values[name], built[name])):
                moved = v.tobytes() != b.tobytes()
                if moved or held:
                    value = float(shown(v[0])) if width == 1 else tuple(float(shown(c)) for c in v)
                    if moved or not np.array_equal(np.asarray(value, dtype=np.float64),
                                                   np.asarray(getattr(colliders[k], attribute), dtype=np.float64)):
                        colliders[k] = dataclasses.replace(colliders[k], **{attribute: value})
        return lists

    def check_colliders(self) -> None:
        """Refuse (``ValueError``) the static colliders' arrays (``COLLIDER_FIELDS``) written in
        place after the build (a caller, an optimiser of a friction's gradient) with values no
        collider takes: a friction NaN, inf or negative, as ``add_ground``, ``add_plane``,
        ``add_sphere_collider`` and ``add_box_collider`` refuse it; an offset, centre or normal
        not finite, a normal not of unit length (the contact moves a particle by the depth along
        it, so a longer one left it off the surface); a radius or half extent not a finite number
        > 0. Unchecked, a NaN friction ran the particles to NaN and a negative one drove them
        along the surface, without a word. Of an imaged ground (``add_ground(images=True)``)
        the friction's being 0 or positive, the offset and the normal are the build's as well:
        its images are made when the model is built, at that plane, and at rest over each step or
        moving with their particles as its friction was positive or 0 (``image_motion``); a
        frictionless imaged ground given a friction ran on frictionless, a rough one given
        friction 0 ran the rough floor that ``add_ground`` refuses to call frictionless for no
        other reason, and a moved ground left its images under the old one. A positive friction
        changed to another positive one is the contact's alone and taken, as any valid value of
        another collider. ``Solver.step`` calls it before its first launch: on a GPU on the
        values that the step's one read of the parameter arrays brings in its transfer
        (``_parameters_read_once``; none of their own), on the CPU through views of the arrays,
        as a call outside a step reads them."""
        # Inside _parameters_read_once the last read is its own (each other returns its rows).
        now = self._collider_read if self._held_parameters is not None else None
        if now is None and self.device.is_cpu:
            # The views' bytes joined: the values unchanged since the last check (every step of
            # a run) cost no copy of them (np.concatenate took twice as long).
            views = self._collider_views()
            if b"".join([v.tobytes() for v in views]) == self._colliders_checked:
                return
        if now is None:
            now = self._collider_values()
        if now.tobytes() == self._colliders_checked:
            return
        values, built = self._collider_rows(now), self._collider_rows(self._collider_built)
        if self._image_row is not None:
            self._check_image_plane(values, built)
        # A method, not a closure: a recursive closure made each step's call a reference cycle
        # (the garbage test of a taped rollout counts them).
        shown = self._shown_plane_value
        # float32's round-off in either precision: a unit normal made in float32 (a float32
        # model's, a torch tensor's) is 2e-8 off unit length, which 64 float64 epsilons refused
        # in a float64 model; the depth it scales is off by as little.
        tol = 64.0 * float(np.finfo(np.float32).eps)
        for name, kind, width in self._collider_fields:
            for k, (v, b) in enumerate(zip(values[name], built[name])):
                v, b = (v[0], b[0]) if width == 1 else (v, b)
                if not np.isfinite(v).all():
                    allowed = "finite"
                elif name.endswith("friction") and v < 0.0:
                    allowed = "a finite number >= 0"
                elif name in ("sphere_radius", "box_half") and not (v > 0.0).all():
                    allowed = "finite and > 0"
                elif name == "plane_normal" and not abs(float(np.linalg.norm(v.astype(np.float64))) - 1.0) <= tol:
                    allowed = "a finite vector of unit length (write normal / norm and offset / norm)"
                else:
                    continue
                raise ValueError(f"model.{name}[{k}] = {shown(v)} is not allowed: must be {allowed} (built {shown(b)})")
        self._colliders_checked = now.tobytes()

    def _check_image_plane(self, values: dict, built: dict) -> None:
        """``check_colliders``'s rules of the imaged ground: its friction 0 or positive as built,
        and its plane where it was built."""
        k = self._image_row
        shown = self._shown_plane_value
        now_f, built_f = values["plane_friction"][k, 0], built["plane_friction"][k, 0]
        if not 0.0 <= now_f < np.inf:
            # NaN, inf or a negative friction passed the rule below (neither 0 nor changed from
            # 0): the contact ran on it, where add_ground refuses it by name.
            raise ValueError(f"model.plane_friction[{k}] = {shown(now_f)} is not allowed: the imaged ground's friction is a "
                             f"finite number >= 0 (built {shown(built_f)}; add_ground's friction)")
        if (now_f == 0.0) != (built_f == 0.0):
            moving = built_f == 0.0
            raise ValueError(
                f"model.plane_friction[{k}] = {shown(now_f)} is not allowed: the imaged ground was built with "
                f"friction {shown(built_f)}, " + (
                    "so its images move with their particles (a frictionless floor), and a friction does not stop them"
                    if moving else "so its images stand still over each step (a rough floor whatever its friction), "
                    "and friction 0 does not make them move") + "; build the scene again with "
                f"add_ground(friction={shown(now_f)}, images=True)")
        now_plane = np.concatenate((values["plane_offset"][k], values["plane_normal"][k]))
        built_plane = np.concatenate((built["plane_offset"][k], built["plane_normal"][k]))
        if not np.array_equal(now_plane, built_plane):
            name, value = (f"plane_offset[{k}]", now_plane[0]) if now_plane[0] != built_plane[0] else (f"plane_normal[{k}]", now_plane[1:])
            raise ValueError(
                f"model.{name} = {shown(value)} is not allowed: the imaged ground's images are made at the plane it was "
                f"built at (normal {shown(built_plane[1:])}, offset {shown(built_plane[0])}) and would stay there; build "
                f"the scene again with the ground where it is to be")

    def _shown_plane_value(self, v) -> str:
        """The shortest text of a plane value in the model's precision: 0.3, not 0.300000011921."""
        if np.ndim(v) == 0:
            return str(self.types.np_dtype(v))
        return "(" + ", ".join(self._shown_plane_value(c) for c in v) + ")"

    def image_args(self) -> list:
        """The kernels' arguments of the image plane: normal, offset, the images' least depth and
        how they move (``image_motion``: 0 without an image plane; the same list every call: a
        replayed launch then finds the very objects it packed)."""
        if self._image_args is None:
            n, off = self.image_plane if self.image_plane is not None else ((0.0, 1.0, 0.0), 0.0)
            self._image_args = [self.types.vec3(*n), self.scalar(off), self.scalar(IMAGE_MIN_DEPTH * self.spacing),
                                int(self.image_motion)]
        return self._image_args

    MATERIAL_FIELDS = ("mu", "lam", "yield_stress", "flow_rate", "hardening", "pressure_stiffness", "viscosity")

    def __setattr__(self, name, value):
        if name in Model.MATERIAL_FIELDS and name in self.__dict__:
            self._check_parameter_array(name, value)
        elif name == "materials" and name in self.__dict__:
            raise ValueError(f"model.materials = {checks.shorten(value)!r} is not allowed: {MaterialList.ADVICE}; change a "
                             f"material with model.set_material(index, material), or finalize a model with other materials")
        elif name in PARTICLE_ROWS:
            value = self._particle_rows(name, value)
        object.__setattr__(self, name, value)

    def _particle_rows(self, name: str, value):
        """``value`` as the per-particle array ``name`` (``PARTICLE_ROWS``) is held: any
        array-like of one row per particle (a list of rows, a tuple, a warp or torch array) in
        the model's dtype, on its device for the kernels' arrays; a numpy array of reals given
        for the start as it is (the state copies it in the model's dtype). A list was refused only at the
        next ``state()`` ('must be a numpy array'), a numpy mass array by the step. A warp
        array the kernels take is kept as it is (the caller's, written into later); one of
        another dtype or device stays the caller's too, refused at use (``_check_kernel_array``).
        The values are judged where they are read (``check_start``, ``check_particles``), as
        values written in place are, but for a number the dtype cannot hold."""
        kind = PARTICLE_ROWS[name]
        if kind != "start" and isinstance(value, wp.array):
            return value
        n, integer = self.particle_count, kind == "integers"
        shape = (n, 3) if kind == "start" else (n,)
        dtype = np.dtype(np.int32 if integer else self.types.np_dtype)
        allowed = (f"must be an array-like of shape {shape} of {'integers' if integer else 'real numbers'}, one "
                   f"{'row' if kind == 'start' else 'value'} per particle (taken as {dtype.name}"
                   f"{'' if kind == 'start' else f' on {self.device}'})")
        try:
            a = value.numpy() if isinstance(value, wp.array) else np.asarray(value)
        except (TypeError, ValueError, RuntimeError) as e:  # ragged rows; a torch tensor on a GPU or with a gradient
            said = (str(e).splitlines() or [type(e).__name__])[0]
            raise ValueError(f"model.{name} = a {type(value).__name__} is not allowed: {allowed}; numpy could not read it: "
                             f"{said}") from None
        if a.shape != shape or a.dtype.kind not in ("iu" if integer else "fiu"):
            raise ValueError(f"model.{name} = a {type(value).__name__} of shape {a.shape} and dtype {a.dtype} is not "
                             f"allowed: {allowed}")
        with np.errstate(over="ignore", invalid="ignore"):  # refused below by name, not warned of by numpy
            held = a.astype(dtype, copy=False)
        lost = (held != a) if integer else (np.isfinite(a) & ~np.isfinite(held))
        if lost.any():  # beyond the dtype: a value other than the one given, or inf for a finite one
            i = np.unravel_index(int(np.flatnonzero(lost)[0]), a.shape)
            raise ValueError(f"model.{name}[{', '.join(map(str, i))}] = {a[i].item()!r} is not allowed: {dtype.name} does not "
                             f"hold it")
        if kind == "start":
            # A numpy array of reals stays the caller's, as a warp array above does: a copy in the
            # model's dtype (a float64 array given a float32 model) left the caller's writes into
            # it after this unread. Its values are judged above as the model holds them.
            return value if isinstance(value, np.ndarray) and value.dtype.kind == "f" else np.ascontiguousarray(held)
        return wp.array(held, dtype=wp.int32 if integer else self.scalar, device=self.device)

    def _check_parameter_array(self, name: str, value) -> None:
        """A parameter array put in place of ``name``'s must be one the kernels take: one of
        another precision failed in Warp's launch (``Struct field 'mu' expects dtype float32,
        got float64``), numpy values or a float with an AttributeError, another length in
        numpy's stack, one without a gradient in the tape's backward."""
        old = self.__dict__[name]
        grad = self.requires_grad
        if (isinstance(value, wp.array) and value.dtype is old.dtype and value.shape == old.shape
                and value.device == old.device and (value.requires_grad or not grad)):
            return
        if isinstance(value, wp.array):
            kind = getattr(value.dtype, "__name__", str(value.dtype))
            what = (f"a wp.array of {kind}, shape {value.shape}, on {value.device}"
                    f"{', without requires_grad' if grad and not value.requires_grad else ''}")
        else:
            what = f"a {type(value).__name__}"
        raise ValueError(f"model.{name} = {checks.shorten(value)!r} is not allowed: it is {what}, and the model's is a "
                         f"wp.array of {old.dtype.__name__}, shape {old.shape} (one value per material), on {old.device}"
                         f"{', with requires_grad' if grad else ''}; to change its values use model.{name}.assign(...), "
                         f"Rollout.set_parameters or model.set_material")

    def _material_array(self, name: str) -> wp.array:
        values = [getattr(m, name) for m in self.materials]
        return wp.array(values, dtype=self.scalar, device=self.device, requires_grad=self.requires_grad)

    @property
    def shear_cap(self) -> float:
        """``K`` of the Tresca ground (``SceneBuilder.add_ground(shear_cap=K)``), 0 without one.
        Written after the build (an ablation, a sweep of ``K``), the next step holds with the
        new value: the static colliders' struct is refilled when it changes (it was filled once
        and a later value ignored: a strip stepped 30 times, then given 0 or 3, slid as at 1).
        ``K > 0`` needs the frictionless imaged ground and a material with a shear yield stress
        (``check_shear_cap``), as ``add_ground`` does; ``static_colliders`` (a checkpoint's
        fingerprint, a model made from this one) records the value written."""
        return self._shear_cap

    @shear_cap.setter
    def shear_cap(self, value: float):
        cap = checks.non_negative("shear_cap", value)
        if cap > 0.0 and self.image_motion != IMAGES_MOVING:
            raise ValueError(f"model.shear_cap = {checks.shorten(value)!r} is not allowed: the hold is the frictionless "
                             "imaged ground's and the model has none; build the scene with add_ground(friction=0, "
                             "images=True, shear_cap=K)")
        check_shear_cap(self.materials, cap)
        self._shear_cap = cap

    @property
    def shear_cap_plane(self) -> int | None:
        """The Tresca ground's row of the plane arrays, None while ``shear_cap`` is 0."""
        return self._image_row if self._shear_cap > 0.0 else None

    @property
    def contact_ramp(self) -> float:
        """The contact law of the colliders and tools (``colliders.coulomb_response``): ``r > 0``
        removes, in a touchdown step, the share ``smoothstep(depth / (r (-v_n) dt))`` of the
        inward normal velocity of a particle found inside (``colliders.touchdown_share``;
        all of it once the particle started the step on the surface, or within its depth's
        round-off outside it), with the stick-slip
        transition rounded, which is continuous in the state, so a
        loss is continuous in the parameters through contact (1, the default:
        ``colliders.CONTINUOUS_CONTACT_RAMP``); 0 (``colliders.INSTANT_CONTACT_RAMP``, "instant")
        removes all of it, the first law, whose loss jumps (docs/method.md §1, "Contact")."""
        return self._contact_ramp

    @contact_ramp.setter
    def contact_ramp(self, value: float):
        self._contact_ramp = check_contact_ramp("contact_ramp", value)

    @property
    def fit(self) -> str:
        """The incremental fit (``FITS``) a ``Solver`` of this model runs unless its ``fit=``
        says otherwise: ``"linear"``, the paper's eqs. 5-6; ``"curvature_corrected"``, the fit
        that also carries the mixed quadratic terms (``sim/curvature.py``; docs/physics.md,
        "Bending stiffness"); ``"auto"``, one of the two by the materials (``solver_choice``).
        Until one is set: ``DEFAULT_FIT`` (``"auto"``), or ``"linear"`` for a model with a
        Fig. 8 comparison deformation model (``"curvature_corrected"`` runs for those only
        when asked for and every material is ``"rest"``; ``Solver``). Scene files set it in
        ``[solver]`` (docs/scene_format.md)."""
        if self._fit is not None:
            return self._fit
        return "linear" if self.uses_comparison_models else DEFAULT_FIT

    @fit.setter
    def fit(self, value: str | None):
        """None: back to the default."""
        if value is not None and (not isinstance(value, str) or value not in FITS):
            raise ValueError(f"fit = {checks.shorten(value)!r} is not allowed: must be one of {', '.join(map(repr, FITS))}")
        self._fit = value

    @property
    def hourglass(self) -> float | None:
        """Strength ``c`` (>= 0) of the hourglass control a ``Solver`` of this model runs
        unless its ``hourglass=`` says otherwise (``sim/hourglass.py``; docs/physics.md,
        "Hourglass modes"); None (default): by the fit, ``AUTO_HOURGLASS`` where ``fit="auto"``
        chose the curvature-corrected fit, else 0 (off; ``solver_choice``). For elastic solids
        only: it measures the motion against the rest positions. Scene files set it in ``[solver]``
        (docs/scene_format.md)."""
        return self._hourglass

    @hourglass.setter
    def hourglass(self, value: float | None):
        self._hourglass = None if value is None else checks.hourglass("hourglass", value)

    @property
    def elastic_only(self) -> bool:
        """Whether no material can flow plastically now (every one has ``yield_stress = inf`` or
        ``flow_rate = 0`` in the current parameter arrays, ``parameter_values``), each has the
        variational elastic force and the incremental deformation model: the models
        ``fit="auto"`` runs with the curvature-corrected fit and the hourglass control."""
        return self._elastic_only(slice(None))

    def _elastic_only(self, materials: slice) -> bool:
        """``elastic_only`` of the materials ``materials`` (a world's, ``world_materials``)."""
        chosen = self.materials[materials]
        if any(m.deformation != "incremental" or m.elastic_force != "variational" for m in chosen):
            return False

        return self._answer(("elastic_only", materials.start, materials.stop, materials.step),
                            lambda rows: not bool(np.any(self._can_flow(rows)[materials])))

    def flowing_materials(self) -> tuple[int, ...]:
        """The materials that can flow plastically now: a finite ``yield_stress`` and a
        ``flow_rate`` not <= 0 in the current parameter arrays (``parameter_values``)."""
        return self._answer(("flowing_materials",), lambda rows: tuple(int(i) for i in np.flatnonzero(self._can_flow(rows))))

    def _can_flow(self, rows: np.ndarray) -> np.ndarray:
        """Per material of the parameter rows (``_read_parameters``): whether it can flow."""
        rows = dict(zip(self.MATERIAL_FIELDS, rows))
        return np.isfinite(rows["yield_stress"]) & ~(rows["flow_rate"] <= 0.0)

    def _answer(self, question: tuple, answer):
        """``answer(rows)`` of the parameter rows (``_read_parameters``), kept with the rows'
        bytes: asked again of the same bytes, the answer kept. A step asks ``elastic_only``
        twice and ``sph_active`` once at parameters that seldom change (about 20 us a step of
        the fit example's 0.55 ms at 142 particles, docs/performance.md). Inside
        ``_parameters_read_once`` the bytes are its read's, taken once."""
        rows, raw = None, self._held_bytes
        if raw is None:
            rows = self._read_parameters()
            raw = rows.tobytes()
        kept = self._row_answers.get(question)
        if kept is not None and kept[0] == raw:
            return kept[1]
        value = answer(self._read_parameters() if rows is None else rows)
        self._row_answers[question] = (raw, value)
        return value

    def worlds_auto_differ(self, fit: str | None = None) -> list[int]:
        """The worlds that, alone, ``fit="auto"`` would run otherwise than the model of all of
        them does (all elastic and without a ghost floor where another world can flow or has a
        ghost floor: alone, the curvature-corrected fit and the hourglass control; in the
        model, the linear fit for every world); empty where the choice is the same for every
        world or the fit (``fit``; None: the model's) is not "auto"."""
        if self.world_count == 1 or (self.fit if fit is None else fit) != "auto":
            return []
        # A ghost floor enters the linear fit only (solver_choice), so a world beside one ran it
        # though alone it chose the curvature-corrected fit: every such model was left out here.
        ghost = {b.world for b in self.bodies if b.ghost_floor > 0}
        alone = [w not in ghost and self._elastic_only(self.world_materials(w)) for w in range(self.world_count)]
        return [] if self.solver_choice("auto")[0] == "curvature_corrected" else [w for w, c in enumerate(alone) if c]

    def worlds_fused_differ(self) -> tuple[list[int], str]:
        """The worlds that alone run the fused kernels where a solver of the model of all of them
        (``fused=True``) runs the non-fused ones, and what in the other worlds makes it: a ghost
        floor or a comparison deformation model (``Material.deformation`` 'rest' or 'additive').
        The kernels are chosen for the whole model, and the two paths sum in another order, so
        such a world ends round-off off its separate run (2e-17 m of a 6 cm box in float64
        beside a ghost floor, 2e-16 m beside an 'additive' material, measured). Beside a ghost
        floor it equals its separate run made with ``Solver(fused=False)`` to the bit; beside a
        comparison model, whose kernels the other worlds' fits then run too, it does not.
        ``([], "")`` where every world alone runs the same kernels as in the model. With
        ``fit="auto"`` a world ``worlds_auto_differ`` names runs another fit alone, not these
        kernels: ``Solver`` leaves it out of its warning here."""
        if self.world_count == 1:
            return [], ""
        ghost = sorted({b.world for b in self.bodies if b.ghost_floor > 0})
        cmp = [w for w in range(self.world_count)
               if any(m.deformation != "incremental" for m in self.materials[self.world_materials(w)])]
        plain = [w for w in range(self.world_count) if w not in ghost and w not in cmp]
        if not plain or len(plain) == self.world_count:
            return [], ""
        why = ([f"a ghost floor in world(s) {ghost}"] if ghost else []) + \
            ([f"a comparison deformation model (Material.deformation 'rest' or 'additive') in world(s) {cmp}"] if cmp else [])
        return plain, " and ".join(why)

    def auto_runs_rest(self, fit: str | None = None) -> bool:
        """Whether a ``Solver(model, fit=fit)`` runs the rest-configuration model now in place of
        the incremental composition ``F <- dF F``: where ``may_run_rest(fit)`` and
        ``elastic_only`` hold. Then the stored ``F`` is the curvature-corrected total fit against
        the rest neighbourhood, with its variational force (``sim/comparison.py``), the gradient
        of an energy of the positions alone: the undamped energy of an elastic body is kept at
        the stable step, where the incremental composition's grows (docs/physics.md, "The energy
        of undamped elastic bodies")."""
        return self.may_run_rest(fit) and self.elastic_only

    def may_run_rest(self, fit: str | None = None) -> bool:
        """Whether ``fit="auto"`` (``fit``; None: the model's) may run the rest-configuration model
        for this scene, whatever the parameters: every material variational and incremental, and
        none of what the rest neighbourhood cannot follow. A ghost floor and floor images enter
        the incremental fit only. Tools (moving colliders, ``SceneBuilder.add_tool``), pins and
        static colliders are allowed: a tool pressed deep into a body inverts rest fits, whose
        energy is continued through det = 0, and every probe of a tool striking, squeezing,
        pressing or sweeping a body runs on (the incremental composition diverged in some),
        keeping energy and rebound better (docs/physics.md, the rest model's Limits)."""
        asked = self.fit if fit is None else fit
        return (asked == "auto" and self.scene_allows_rest
                and all(m.deformation == "incremental" and m.elastic_force == "variational" for m in self.materials))

    def corrected_incremental(self, fit: str | None = None, state: "State | None" = None) -> bool:
        """Whether a ``Solver(model, fit=fit)`` (None: the model's fit) runs the
        curvature-corrected fit with the incremental composition for some material now, in a
        step from ``state`` (None: a new state): the fit ``solver_choice`` resolves to is
        corrected, some material's ``deformation`` is ``"incremental"``, and the parameters do
        not choose the rest model (``auto_runs_rest``) or ``state`` keeps the incremental
        composition all the same (``keeps_incremental``: a flowed body made elastic). Then
        ``stable_dt`` keeps ``CORRECTED_INCREMENTAL_STEP`` of the wave limit."""
        if state is not None:
            checks.same_state(self, "state", state)
        return self._corrected_incremental(fit, state is not None and self.auto_runs_rest(fit) and keeps_incremental(state))

    def _corrected_incremental(self, fit: str | None, kept: bool) -> bool:
        # ``kept``: the step's start keeps the incremental composition where the parameters
        # choose the rest model (``auto_runs_rest``, which implies the corrected fit).
        return (self.solver_choice(fit)[0] == "curvature_corrected" and (kept or not self.auto_runs_rest(fit))
                and any(m.deformation == "incremental" for m in self.materials))

    @property
    def scene_allows_rest(self) -> bool:
        """The scene's part of ``may_run_rest``: no ghost floor, no floor images (tools, pins
        and static colliders allowed)."""
        return self.ghost_floor is None and self.image_plane is None

    def solver_choice(self, fit: str | None = None, hourglass: float | None = None) -> tuple[str, float]:
        """``(fit, c)``: the incremental fit and the hourglass strength a ``Solver(model, fit=fit,
        hourglass=hourglass)`` runs now (None: this model's ``fit``, ``hourglass``).

        ``fit="auto"`` is ``"curvature_corrected"`` where ``elastic_only`` (a beam 6 particles
        thick bends within 3 % of Timoshenko instead of 16 % too far) and ``"linear"``, the
        paper's fit and its fused fast path, bit-identical to choosing it, wherever a material
        can flow or uses the paper's force or a comparison model (the control measures the
        motion against the rest positions, which plastic flow leaves behind; docs/physics.md,
        "The default: the fit by material"). A strength of None is ``AUTO_HOURGLASS`` with the
        fit that ``"auto"`` made curvature-corrected, else 0: an explicit ``fit`` or ``c``
        runs as given."""
        asked = self.fit if fit is None else fit
        if not isinstance(asked, str) or asked not in FITS:
            raise ValueError(f"fit = {checks.shorten(asked)!r} is not allowed: must be one of {', '.join(map(repr, FITS))}")
        chosen = asked
        if asked == "auto":
            # A ghost floor (sim/ghost_floor.py) enters the linear fit only.
            chosen = "curvature_corrected" if self.elastic_only and self.ghost_floor is None else "linear"
        strength = self.hourglass if hourglass is None else hourglass
        if strength is None:
            strength = AUTO_HOURGLASS if asked == "auto" and chosen == "curvature_corrected" else 0.0
        return chosen, checks.hourglass("hourglass", strength)

    def solver_record(self, fit: str | None = None, hourglass: float | None = None) -> dict:
        """What a ``Solver(model, fit=fit, hourglass=hourglass)`` runs now, for a run's records
        beside the requested ``fit`` (``"auto"`` resolves by the parameters, so a sweep over
        ``flow_rate`` that reaches 0 switches models there): ``resolved_fit`` and
        ``resolved_hourglass`` (``solver_choice``) and ``rest_model`` (``auto_runs_rest``:
        whether the step runs the rest-configuration model, whose total fit is ``resolved_fit``)."""
        chosen, c = self.solver_choice(fit, hourglass)
        return {"resolved_fit": chosen, "resolved_hourglass": float(c), "rest_model": bool(self.auto_runs_rest(fit))}

    def _collider_array(self, values, dtype) -> wp.array:
        # Zero colliders of a kind still pass a (never read) one-element array.
        values = list(values) or [np.zeros(3) if dtype is self.types.vec3 else 0.0]
        return wp.array(np.array(values, dtype=self.types.np_dtype), dtype=dtype, device=self.device)

    def set_materials(self, materials: Sequence[Material]):
        """Replace every material at once (``set_material`` of each, in order; one entry per
        material of the model, worlds after each other), so that a model of several materials
        can switch to or from ``pressure_force = "isotropic"``, which every material or none
        must have (``check_pressure_forces``) and one ``set_material`` at a time cannot change.
        The combination is checked first; if a material is refused on the way, those set
        before it are set back."""
        if isinstance(materials, Material) or not isinstance(materials, Sequence):
            raise ValueError(f"materials = {checks.shorten(materials)!r} is not allowed: must be a list of "
                             f"{len(self.materials)} warp_esph.Material, one per material of the model")
        materials = list(materials)
        if len(materials) != len(self.materials):
            raise ValueError(f"materials (a list of {len(materials)}) is not allowed: must have {len(self.materials)} "
                             "entries, one per material of the model")
        for k, m in enumerate(materials):
            if not isinstance(m, Material):
                raise ValueError(f"materials[{k}] = {checks.shorten(m)!r} is not allowed: must be a warp_esph.Material")
        check_pressure_forces(materials, self.image_plane is not None)
        check_shear_cap(materials, self.shear_cap)
        old = list(self.materials)
        # Each set_material checks the whole combination, which is the new one only at the end.
        self._combination_checked = True
        try:
            for k, m in enumerate(materials):
                if m is not self.materials[k]:
                    self.set_material(k, m)
        except ValueError:
            for k, m in enumerate(old):
                if m is not self.materials[k]:
                    self.set_material(k, m)
            raise
        finally:
            self._combination_checked = False

    def set_material(self, index: int, material: Material, world: int | None = None):
        """Replace material ``index`` in place (its particles keep their state).

        ``world=None``: ``index`` counts every material of the model (worlds after each
        other); ``world=w``: ``index`` is the material's index within world ``w`` (as in its
        builder), and only world ``w``'s copy changes."""
        # 0.0 was refused as 'must be in [0, 0]', a range it lies in.
        integer = not isinstance(index, bool) and isinstance(index, (int, np.integer))
        if world is not None:
            w = self._world_index(world)
            first, end = self.world_material_start[w], self.world_material_start[w + 1]
            if not integer or not 0 <= index < end - first:
                raise ValueError(f"index = {checks.shorten(index)!r} is not allowed: {'' if integer else 'must be an integer; '}"
                                 f"world {w} has materials 0..{end - first - 1}")
            index = int(first + index)
        if not integer or not 0 <= index < len(self.materials):
            raise ValueError(f"index = {checks.shorten(index)!r} is not allowed: must be an integer in [0, {len(self.materials) - 1}]")
        if not isinstance(material, Material):
            raise ValueError(f"material = {checks.shorten(material)!r} is not allowed: must be a warp_esph.Material")
        old = self.materials[index]
        if material.deformation != old.deformation:
            # The deformation model decides the solver's stages (a Solver made before ran the
            # new one as the old) and the rest neighbours, which finalize sets up.
            raise ValueError(f"material.deformation = {checks.shorten(material.deformation)!r} is not allowed here: material {index} is "
                             f"{old.deformation!r}, and a model's deformation models are set when it is built "
                             "(finalize a model with the new one)")
        check_material_precision(material, self.scalar)
        if not getattr(self, "_combination_checked", False):
            check_pressure_forces([material if k == index else m for k, m in enumerate(self.materials)],
                                  self.image_plane is not None)
            check_shear_cap([material if k == index else m for k, m in enumerate(self.materials)], self.shear_cap)
        if material.density != old.density:
            # The particles' masses and rest densities come from it when the model is built:
            # a new density changed the stable step and the wave speeds but not the motion, and
            # a copy (replicate_worlds, split_materials, so a fit with worlds=True) ran with it.
            raise ValueError(f"material.density = {checks.shorten(material.density)!r} is not allowed here: material {index} has "
                             f"density {old.density!r}, and a model's particle masses are set when it is built "
                             "(finalize a model with the new one)")
        # The rest density is the pressure density's: its kernel may change with the force.
        new_density_kernel = (self.materials[index].pressure_force in SPIKY_DENSITY_FORCES) != (
            material.pressure_force in SPIKY_DENSITY_FORCES)
        list.__setitem__(self.materials, index, material)
        for name in self.MATERIAL_FIELDS:
            arr = getattr(self, name)
            values = arr.numpy()
            values[index] = getattr(material, name)
            arr.assign(values)
        for arr, value in (
            (self.material_model, MODEL_IDS[material.model]),
            (self.clamp_pressure, int(material.clamp_pressure)),
            (self.pair_repulsion, material.pair_repulsion),
            (self.material_deformation, DEFORMATION_IDS[material.deformation]),
            (self.material_elastic_force, ELASTIC_FORCE_IDS[material.elastic_force]),
            (self.material_pressure_force, PRESSURE_FORCE_IDS[material.pressure_force]),
        ):
            values = arr.numpy()
            values[index] = value
            arr.assign(values)
        if new_density_kernel:
            # Only this material's particles: the others keep theirs (a copied or edited one).
            kept = self.particle_rest_density.numpy()
            self.compute_rest_density()
            fresh = self.particle_rest_density.numpy()
            others = self.particle_material_np != index
            fresh[others] = kept[others]
            self.particle_rest_density.assign(fresh)

    # ----------------------------------------------------------------- worlds
    def _check_worlds(self):
        # Every world-indexed slice assumes particles and materials come world after world.
        w, ms = self.world_of_particle, self.world_material_start
        if w.shape != (self.particle_count,) or (self.particle_count and (w[0] != 0 or (np.diff(w) < 0).any() or (np.diff(w) > 1).any())):
            raise ValueError("particle_world is not allowed: must be one world per particle, 0, 1, ... in order, none empty")
        if ms.shape != (self.world_count + 1,) or ms[0] != 0 or ms[-1] != len(self.materials) or (np.diff(ms) < 0).any():
            raise ValueError(
                f"world_material_start = {ms.tolist()} is not allowed: must be {self.world_count + 1} non-decreasing "
                f"offsets from 0 to {len(self.materials)}"
            )
        if self.particle_count:
            mat = self.particle_material_np
            if ((mat < ms[w]) | (mat >= ms[w + 1])).any():
                raise ValueError("particle_material is not allowed: a particle uses a material of another world")

    def _world_index(self, world) -> int:
        if isinstance(world, bool) or not isinstance(world, (int, np.integer)) or not 0 <= world < self.world_count:
            raise ValueError(f"world = {checks.shorten(world)!r} is not allowed: must be an integer in [0, {self.world_count - 1}]")
        return int(world)

    def world_particles(self, world: int) -> slice:
        """The particle range of ``world``: ``state.x.numpy()[model.world_particles(w)]``."""
        w = self._world_index(world)
        return slice(int(self.world_start[w]), int(self.world_start[w + 1]))

    def world_materials(self, world: int) -> slice:
        """The entries of the per-material arrays (``mu``, ..., their gradients) of ``world``."""
        w = self._world_index(world)
        return slice(int(self.world_material_start[w]), int(self.world_material_start[w + 1]))

    def world_view(self, array, world: int):
        """The part of a per-particle array (a ``State`` field, Warp or numpy) that is
        ``world``'s; for a Warp array, a view (no copy)."""
        if array.shape[0] != self.particle_count:
            raise ValueError(f"array with {array.shape[0]} entries is not allowed: must have one per particle ({self.particle_count})")
        s = self.world_particles(world)
        return array[s.start:s.stop]

    def per_world(self, values, kind: str | None = None) -> list:
        """Split a per-particle (length ``particle_count``) or per-material (length
        ``len(materials)``) array into one array per world; with equal worlds, stack
        them with ``np.stack``. ``kind`` (``"particles"`` or ``"materials"``) says which
        where the two lengths are equal; by default the length decides, particles first."""
        a = values.numpy() if isinstance(values, wp.array) else np.asarray(values)
        if kind not in (None, "particles", "materials"):
            raise ValueError(f"kind = {checks.shorten(kind)!r} is not allowed: must be None, 'particles' or 'materials'")
        if a.ndim == 0:  # a number has no entries: a.shape[0] was an IndexError
            raise ValueError(f"values = {checks.shorten(values)!r} is not allowed: must have one entry per particle "
                             f"({self.particle_count}) or one per material ({len(self.materials)})")
        if a.shape[0] == self.particle_count and kind != "materials":
            starts = self.world_start
        elif a.shape[0] == len(self.materials) and kind != "particles":
            starts = self.world_material_start
        else:
            raise ValueError(
                f"values with {a.shape[0]} entries is not allowed: must have one per particle ({self.particle_count}) "
                f"or one per material ({len(self.materials)})"
            )
        return [a[starts[w]:starts[w + 1]] for w in range(self.world_count)]

    def scene_snapshot(self) -> tuple:
        """``(bodies, rest positions)`` as they are now: each body's (name, first particle,
        count, world) and a read-only copy of ``particle_x0``. The states made while they are
        unchanged share one copy: comparing with it costs 0.015 ms at 50k particles (CPU), where
        hashing them (sha1) cost 0.29 ms, a seventh of ``state()``'s 2.0 ms."""
        bodies = [(b.name, b.start, b.count, b.world) for b in self.bodies]
        held = self._snapshot
        if held is None or held[0] != bodies or not np.array_equal(held[1], self.particle_x0):
            x0 = np.array(self.particle_x0)
            x0.flags.writeable = False
            held = self._snapshot = (bodies, x0)
        return held

    def check_start(self, velocities: bool = True) -> None:
        """Refuse (``ValueError``) the start ``particle_x0`` or ``particle_v0`` (numpy arrays a
        caller may write in place) where no state can start from it: not an ``(n, 3)`` array of
        real numbers, or an entry NaN or infinite. A new state (``state()``) and a rollout's
        forward from the model's start check it, and the arrays the kernels index
        (``check_particles``). Unchecked, a NaN position or velocity written after the build
        ran to NaN positions without a word: a state copies them, and the step reads no
        particle back. ``velocities``: False where the run does not read ``particle_v0`` (a
        start given in its place, ``_scratch_state``); ``particle_x0`` is read by every run,
        as the rest configuration and the record of the scene (``scene_snapshot``)."""
        n = self.particle_count
        for name in ("particle_x0", "particle_v0")[:2 if velocities else 1]:
            a = getattr(self, name)
            if not isinstance(a, np.ndarray) or a.shape != (n, 3) or a.dtype.kind not in "fiu":
                shown = f"an array of shape {a.shape} and dtype {a.dtype}" if isinstance(a, np.ndarray) else f"a {type(a).__name__}"
                raise ValueError(f"model.{name} = {shown} is not allowed: must be a numpy array of shape ({n}, 3) of real "
                                 f"numbers, one row per particle (write into it: model.{name}[...] = ...)")
            if not np.isfinite(a).all():
                i = int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])
                body = self.bodies[int(self.particle_body_np[i])].name
                raise ValueError(f"model.{name}[{i}] = {self._shown_plane_value(a[i])} is not allowed: must be finite "
                                 f"(particle {i}, of body {body!r})")
        self.check_particles()

    def _particle_arrays(self) -> list:
        """The arrays of ``PARTICLE_FIELDS`` as the model holds them now, each refused where it
        is not one the kernels were made for (``_check_kernel_array``); kept while they are the
        same arrays."""
        now = self._particle_getter(self)
        held = self._particle_held
        if held is not None and all(map(operator.is_, held[0], now)):
            return held[0]
        rows = {"particles": self.particle_count, "materials": len(self.materials)}
        for (name, kind, integer), a in zip(PARTICLE_FIELDS, now):
            self._check_kernel_array(name, a, rows[kind], wp.int32 if integer else self.scalar)
        # On the CPU views of their memory, read by check_particles without a copy.
        self._particle_held = (now, [a.numpy() for a in now] if self.device.is_cpu else None)
        return now

    def check_particles(self) -> None:
        """Refuse (``ValueError``) the per-particle and per-material arrays the kernels index
        (``PARTICLE_FIELDS``) written in place, or replaced, after the build with values the
        model was not built for: a ``particle_material`` other than the build's (the kernels
        index every material array with it, so a value past the materials read memory past
        them; ``stable_dt``, checkpoints and diagnostics read ``particle_material_np``), a
        ``particle_mass`` not finite and > 0, a ``particle_volume`` not finite and >= 0 (a
        ghost floor's is 0), a material code (``material_model``, ``material_deformation``,
        ``material_elastic_force``, ``material_pressure_force``, ``clamp_pressure``) other than
        its material's in ``model.materials`` (``set_material`` writes both; the solver chose
        its stages from the materials), a ``pair_repulsion`` not finite and >= 0. A new state
        (``state()``) and a rollout's forward from the model's start check them on every device
        (``check_start``); ``Solver.step`` checks them before its first launch where the arrays
        are read through views (the CPU: their bytes compared with those last passed, a few
        microseconds), not on a GPU, where it would read the particles back every step."""
        arrays = self._particle_arrays()
        views = self._particle_held[1]
        if views is None:  # a GPU's: read back
            views = [a.numpy() for a in arrays]
        now = b"".join([v.tobytes() for v in views])
        if now == self._particles_checked:
            return
        self._judge_particles(dict(zip((f[0] for f in PARTICLE_FIELDS), views)))
        self._particles_checked = now

    def _judge_particles(self, values: dict) -> None:
        """``check_particles``'s rules, on the arrays' values (numpy, by name)."""
        def particle(i):
            return f"particle {i}, of body {self.bodies[int(self.particle_body_np[i])].name!r}"

        material = values["particle_material"]
        if not np.array_equal(material, self.particle_material_np):
            i = int(np.flatnonzero(material != self.particle_material_np)[0])
            raise ValueError(f"model.particle_material[{i}] = {int(material[i])} is not allowed: the particles' materials "
                             f"are set when the model is built ({particle(i)}, built {int(self.particle_material_np[i])}; "
                             f"model.set_material changes a material's parameters, or finalize a model with the new ones)")
        for name, least in (("particle_mass", "> 0"), ("particle_volume", ">= 0")):
            v = values[name]
            bad = ~np.isfinite(v) | ((v <= 0.0) if least == "> 0" else (v < 0.0))
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ValueError(f"model.{name}[{i}] = {self._shown_plane_value(v[i])} is not allowed: must be finite and "
                                 f"{least} ({particle(i)})")
        for name, field, ids in MATERIAL_CODES:
            built = np.array([ids[getattr(m, field)] for m in self.materials], dtype=np.int32)
            if not np.array_equal(values[name], built):
                k = int(np.flatnonzero(values[name] != built)[0])
                raise ValueError(f"model.{name}[{k}] = {int(values[name][k])} is not allowed: a material's codes are its "
                                 f"material's (model.materials[{k}].{field} = {getattr(self.materials[k], field)!r}, code "
                                 f"{built[k]}); change a material with model.set_material")
        v = values["pair_repulsion"]
        bad = ~(np.isfinite(v) & (v >= 0.0))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ValueError(f"model.pair_repulsion[{k}] = {self._shown_plane_value(v[k])} is not allowed: must be finite "
                             f"and >= 0 (Material.pair_repulsion)")

    def state(self, requires_grad: bool | None = None) -> State:
        """A new state at the initial configuration (F = I, alpha = 0)."""
        return State(self, self.requires_grad if requires_grad is None else checks.boolean("requires_grad", requires_grad))

    def _scratch_state(self, requires_grad: bool = False) -> State:
        """A new state whose every field the caller writes before a step reads it (a given start
        copied in, a step's output, a rollout's states): ``state()``'s, but at rest, so that a
        ``particle_v0`` the run does not read is not refused. A NaN velocity left in the
        model refused ``simulate(state=)`` and a rollout's ``forward(initial_state=)`` and
        ``forward(v0=)``, which never read it."""
        return State(self, requires_grad, start_velocities=False)

    def material_arrays(self, rest: bool = False):
        """The per-material arrays as one ``sim.materials`` struct, holding these very
        arrays (so gradients reach ``model.mu.grad`` and the others). ``rest``: with every
        material's deformation code ``"rest"`` (what ``fit="auto"`` runs for a purely elastic
        model, ``auto_runs_rest``), the other arrays the same."""
        deformation = self.material_deformation
        if rest:
            deformation = self._rest_codes
            if deformation is None or deformation.shape[0] != len(self.materials):
                deformation = self._rest_codes = wp.full(len(self.materials), DEFORMATION_IDS["rest"], dtype=wp.int32,
                                                         device=self.device)
        arrays = dict(
            mu=self.mu, lam=self.lam, yield_stress=self.yield_stress, flow_rate=self.flow_rate,
            hardening=self.hardening, pressure_stiffness=self.pressure_stiffness, viscosity=self.viscosity,
            model=self.material_model, deformation=deformation, elastic_force=self.material_elastic_force,
            clamp_pressure=self.clamp_pressure, pressure_force=self.material_pressure_force,
            pair_repulsion=self.pair_repulsion,
        )
        # A struct copies each array's data and gradient pointers when it is filled, so it is
        # reused only while every array and its gradient are the very same allocations: a
        # gradient attached later (requires_grad) or an array replaced (set_material) builds
        # a new one. Building it costs about as much as a small model's kernel, once per stage.
        # The rest codes' struct is cached beside the model's own: a step reads one or the other.
        key = pointer_key(arrays.values())
        cached = self._rest_material_struct if rest else self._material_struct
        if cached is None or cached[0] != key:
            cached = (key, material_struct.make(self.scalar, self.device, **arrays), tuple(arrays.values()))
            if rest:
                self._rest_material_struct = cached
            else:
                self._material_struct = cached
        return cached[1]

    def settings(self) -> dict:
        """This model's scene-wide constructor arguments (spacing, support radius, gravity,
        static colliders, neighbour rows, device, precision), for a model made from it."""
        planes, spheres, boxes = self.static_colliders()  # as they run: a plane moved in place moves in the copy
        return dict(spacing=self.spacing, support_radius=self.support_radius, gravity=self.gravity, planes=planes,
                    spheres=spheres, boxes=boxes, max_neighbors=self.max_neighbors,
                    bodies_interact=self.bodies_interact, device=self.device, scalar=self.scalar,
                    fit_weight=self.fit_weight)

    def _read_parameters(self) -> np.ndarray:
        """The ``MATERIAL_FIELDS`` arrays as one host array (a row each), read in one
        transfer: on a GPU they are copied on the device into one buffer first, since each
        read of a device array waits for the device and the step asks every step
        (``stable_dt``, ``sph_active``); the buffer has no gradient, so a recording tape takes
        no note of the copies. On the CPU the arrays' own memory is read through views. On a
        GPU the static colliders' values come in the same transfer (``_collider_read``), which
        ``check_colliders`` judges in a step without a transfer of its own."""
        if self._held_parameters is not None:
            return self._held_parameters.copy()
        if self._staged_reads:
            rows, self._collider_read = self._read_staged()
            return rows
        # A CPU array's numpy() is a view of its memory: nothing to transfer, and views kept
        # while the arrays are the same ones cost less than the copies of _read_staged. The
        # colliders' values are read through views as well, by check_colliders.
        arrays = [getattr(self, name) for name in self.MATERIAL_FIELDS]
        key = pointer_key(arrays)
        if self._parameter_views is None or self._parameter_views[0] != key:
            self._parameter_views = (key, [a.numpy() for a in arrays])
        return np.stack(self._parameter_views[1])

    def _read_staged(self) -> tuple[np.ndarray, np.ndarray]:
        """``_read_parameters`` on a GPU: the arrays, and the static colliders' values
        (``_collider_values``), copied on the device into one buffer, read in one transfer."""
        arrays = [getattr(self, name) for name in self.MATERIAL_FIELDS]
        colliders = self._collider_arrays()
        n = arrays[0].shape[0]
        end = len(arrays) * n
        size = end + sum(a.shape[0] for a in colliders)
        stage = self._parameter_stage
        if stage is None or stage.shape[0] != size or stage.dtype != arrays[0].dtype:
            stage = self._parameter_stage = wp.empty(size, dtype=arrays[0].dtype, device=self.device)
        for k, arr in enumerate(arrays):
            wp.copy(stage, arr, dest_offset=k * n, count=n)
        self._stage_colliders(stage, end, colliders)
        out = stage.numpy()
        return out[:end].reshape(len(arrays), n).copy(), out[end:].copy()

    def _parameters_key(self) -> bytes:
        """The parameter arrays' values as bytes: inside ``_parameters_read_once`` those of its
        read (no read again), else a read's. What was decided of equal bytes holds (``_answer``;
        the solver's hourglass warning asks whether a material can flow only when they
        changed), whoever wrote the arrays: a caller in place, ``set_material``, a fit."""
        held = self._held_bytes
        return held if held is not None else self._read_parameters().tobytes()

    @contextlib.contextmanager
    def _parameters_read_once(self):
        """Inside, every question about the parameter arrays (``elastic_only``,
        ``sph_active``, ``stable_dt``, ``parameter_values``) is answered from one read made on
        entry: the start of ``Solver.step`` asks all three, and nothing writes the arrays
        there."""
        self._held_parameters = self._held_bytes = None
        self._held_parameters = self._read_parameters()
        self._held_bytes = self._held_parameters.tobytes()  # once for every question (_answer)
        try:
            yield
        finally:
            self._held_parameters = self._held_bytes = None

    def parameter_values(self) -> dict[str, np.ndarray]:
        """The current per-material parameters (``MATERIAL_FIELDS``), read from the arrays
        the kernels use: after a fit or ``warp_esph.torch`` wrote them, these differ from
        ``materials`` (which ``set_material`` keeps in step)."""
        return self._parameter_values(self._read_parameters())

    def _parameter_values(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        out = {}
        for name, row in zip(self.MATERIAL_FIELDS, rows):
            current = row.astype(np.float64)
            declared = np.array([getattr(m, name) for m in self.materials], dtype=np.float64)
            # Where the array still holds the material's value (rounded to the model's
            # precision), the material's exact float: stable_dt then does not depend on
            # the precision.
            same = declared.astype(self.types.np_dtype).astype(np.float64) == current
            out[name] = np.where(same, declared, current)
        return out

    @property
    def sph_active(self) -> bool:
        """Whether any material has SPH pressure or viscosity now (``parameter_values``)."""
        def answer(rows):
            rows = dict(zip(self.MATERIAL_FIELDS, rows))
            return bool((rows["pressure_stiffness"] > 0.0).any() or (rows["viscosity"] > 0.0).any())

        return self._answer(("sph_active",), answer)

    @property
    def spacing(self) -> float:
        """The lattice spacing (m) the model was built with; fixed once built."""
        return self._spacing

    @spacing.setter
    def spacing(self, value):
        raise ValueError(f"Model.spacing = {checks.shorten(value)!r} is not allowed: the particles, their masses and the neighbour grid "
                         f"were built on {self._spacing!r}; set SceneBuilder(spacing=...) and finalize again")

    @property
    def support_radius(self) -> float:
        """The kernels' support radius ``h`` (m) the model was built with; fixed once built."""
        return self._support_radius

    @support_radius.setter
    def support_radius(self, value):
        raise ValueError(f"Model.support_radius = {checks.shorten(value)!r} is not allowed: the volumes, densities and neighbour rows "
                         f"were built on {self._support_radius!r}; set SceneBuilder(support_radius=...) and finalize again")

    @property
    def gravity(self) -> tuple[float, float, float]:
        """The acceleration of gravity (m/s^2) every step reads; may be set between steps (a
        ramp, a tilted ground) to three finite numbers the model's precision holds."""
        return self._gravity

    @gravity.setter
    def gravity(self, value):
        g = checks.vector("gravity", value)
        big = float(np.finfo(self.types.np_dtype).max)
        if max(abs(c) for c in g) > big:
            raise ValueError(f"gravity = {checks.shorten(value)!r} is not allowed in {self.scalar.__name__}: must be at most {big:.3g}")
        self._gravity = g

    def stable_dt(self, courant: float = 0.3, hourglass: float | None = None, fit: str | None = None,
                  state: "State | None" = None) -> float:
        """Explicit limit over all materials, from the current parameters
        (``parameter_values``): the wave limit ``C dx / c_P`` of docs/method.md §8, and the
        viscous limit ``(C / 12) rho0 h^2 / eta`` of the explicit viscous force.

        (The viscous force, ``sim/pressure.py``, measured unstable above ``dt eta / (rho0 h^2)
        = 0.0375`` and stable at 0.03, in a column of 7 x 7 x 20 particles; at ``C = 0.3``
        the limit is 0.025.)

        The limit assumes well-conditioned fits: a particle whose neighbours leave a
        direction nearly unsampled is stiffer along it (``dF - I`` grows as ``A^-1``). The
        solver's fit guard (``Solver(max_condition=20)``, docs/method.md §2) drops such fits;
        with it the toothpaste preset without viscosity, whose plastic flow spreads it into
        a thin layer, rests at 0.5 and 1.0 x this step (with the old threshold 1e3 it blew
        up at 0.3-0.5 x; docs/physics.md, "The step bound of undamped fast plastic flow").
        No flow-rate term is needed. The SPH pressure enters ``c_P`` as ``rho0 k_p`` whatever its
        force (``material.p_wave_speed``): that is 1 / 0.95 of what the energy force adds to
        the bulk stiffness, 2 x the spiky force's and 1.7-2 x ``energy_spiky``'s, whose spiky
        core needs no shorter step (an undamped elastic box rests at 1.0 and 2.5 x, blows up at
        3.5 x, as with the energy force: ``tests/test_adaptive_dt.py``), nor ``isotropic``'s,
        the same pressure applied through the moments (the same box: the same three results).

        ``hourglass``: the strength ``c`` of the hourglass control the step runs (None: what a
        ``Solver(model)`` runs now, ``solver_choice()``; ``Solver.check_dt`` passes its own). Its springs add to the elastic stiffness, so with ``c > 0`` the wave limit
        ``dt_w`` combines with the control's own limit ``dt_c = 0.8 (C / 0.3) sqrt(rho S / (c mu
        W))`` as ``1 / dt^2 = 1 / dt_w^2 + 1 / dt_c^2`` (the squared frequencies of two
        stiffnesses add at most). ``sqrt(...)`` is ``2 / omega`` for the largest frequency its
        springs can have (``sim/hourglass.py``, worst material ``mu / rho``); the lattice's
        checkerboard mode is at 0.8 of it, and the factor 0.8 leaves it the margin of 1.5 the
        wave limit has at least (docs/method.md §8). E = 1e5 Pa, nu = 0.3: the step is 0.1 %
        shorter at ``c = 0.1``, 4.0 % at 3 without the SPH pressure (3.1 % with the default
        pressure force, whose stiffness already shortens the wave limit); the control rules from ``c`` of about 100.
        (Measured, 512 particles shaken at random, ``tests/test_adaptive_dt.py``: at ``c = 1000``
        stable at 1.45 x the returned step, blown up at 1.6 x; at ``c = 300``, 1.6 and 1.8 x.)

        The force fields (``SceneBuilder.add_compression_field``) are springs too: a field of
        strength ``k`` adds ``k`` to every squared frequency of the particles it acts on, and
        symplectic Euler follows a spring only while ``dt < 2 / sqrt(k)``. Their limit
        ``dt_f = (C / 0.3) 2 / (1.5 sqrt(k))`` (``_field_limit``: ``k`` the largest net
        strength a particle ever feels, fields switched on later included; the margin of 1.5
        the wave limit has) joins the same sum, ``1 / dt^2 = 1 / dt_w^2 + 1 / dt_c^2 + 1 /
        dt_f^2``. (Measured, isolated particles under the field alone: bounded up to 0.98-0.99
        x ``2 / sqrt(k)``.) It bounds the field's own oscillation; a field strong enough to set
        the step also crushes any body of more than a particle across (strain about ``k L^2 /
        (8 c_P^2)`` over a width ``L``), and the crushed material's stiffness is not the rest
        state's: docs/method.md §8.

        ``fit``: the fit a ``Solver(model, fit=fit)`` is asked for (None: the model's, as
        ``hourglass``; ``Solver.check_dt`` passes its own). Where the step runs the
        curvature-corrected fit with the incremental composition for any material
        (``corrected_incremental``), the wave limit is ``CORRECTED_INCREMENTAL_STEP`` (0.5) of
        the above: under compression that fit stiffens a mode past the step (docs/method.md §8).
        ``state``: the state the step starts from (None: a new state). A flowed body made elastic
        under ``fit="auto"`` keeps that fit on the incremental composition
        (``keeps_incremental``), where the parameters alone choose the rest model: from such a
        state the step is the half too (``Solver.check_dt`` passes the step's ``state_in``)."""
        return self._stable_dt_from(courant, hourglass, fit, state)

    def _stable_dt_from(self, courant, hourglass, fit, state, flowed: bool | None = None) -> float:
        # ``flowed``: ``state.has_flowed()`` where the step has read it for its path (a second
        # read would wait for the device again); None: read here where the path hangs on it.
        courant = checks.courant(courant)
        self._check_force_fields()
        if state is not None:
            checks.same_state(self, "state", state)
        # Solver.check_dt asks every step; the answer is kept while the parameter arrays hold
        # the same values (a fit or torch writes them in place) and the materials and settings
        # are the same, with whether they choose the rest model (asked anew, it cost a step
        # 4 us).
        rows = self._read_parameters()
        key = (rows.tobytes(), tuple(self.materials), tuple(self.force_fields),
               self.fit, self._hourglass, self.spacing, self.support_radius, courant, hourglass, fit)
        cached = self._stable_dt
        if cached is None or cached[0] != key:
            self._check_parameter_values(rows)
            cached = self._stable_dt = (key, self.auto_runs_rest(fit), {})
        _, rest, dts = cached
        # Read only where the parameters choose the rest model: only there can the state change
        # the path, and only there does the step read alpha back itself (Solver._runs_rest).
        kept = rest and state is not None and keeps_incremental(state, flowed)
        dt = dts.get(kept)
        if dt is None:
            dt = dts[kept] = self._stable_dt_now(courant, hourglass, rows, fit=fit, kept=kept)
        return dt

    def world_stable_dts(self, courant: float = 0.3, hourglass: float | None = None, fit: str | None = None,
                         state: "State | None" = None) -> list[float]:
        """Each world's ``stable_dt`` alone: its own materials and the fields acting on its
        bodies, as its separate model's (the hourglass strength is the model's, as
        ``worlds_auto_differ`` warns), from its part of ``state`` (None: a new state; a world
        whose body flowed keeps the incremental composition, ``keeps_incremental``, and half the
        wave limit where the parameters choose the rest model). ``stable_dt``, the default step of ``simulate`` and a
        sweep, is the least of them, the stiffest world's: a softer world runs more steps a frame
        than alone, and ends off its separate run (2.8e-4 m of a 6 cm box in 3 frames, float64,
        measured), as ``resolve_timestep`` warns."""
        courant = checks.courant(courant)
        self._check_force_fields()
        if state is not None:
            checks.same_state(self, "state", state)
        rows = self._read_parameters()
        self._check_parameter_values(rows)
        # Each world's own hardening: the step keeps every world on the incremental composition
        # where one flowed (Solver._warn_worlds_kept), a world's separate run only where it did.
        alpha = (state.alpha.numpy() if state is not None and state.rest_model is False and self.auto_runs_rest(fit)
                 else None)
        return [self._stable_dt_now(courant, hourglass, rows, w, fit,
                                    kept=alpha is not None and flowed_by_hardening(alpha[self.world_particles(w)]))
                for w in range(self.world_count)]

    def _check_force_fields(self) -> None:
        """The force fields as they are now hold what ``finalize`` asks of them: each a
        ``CompressionField`` whose centre, strength and times fit the model's float type, on a
        body the model has (or -1, every particle). A field appended after ``finalize`` had no
        check: a strength of 1e39 in float32 wrote NaN positions in the first step, and a body
        index past the bodies acted on nothing without a word. Runs where ``stable_dt`` reads
        them, so before any step (``Solver.step`` asks it before its first launch); a list of
        the same fields is not checked again."""
        fields = self.force_fields
        checked = self._checked_fields
        if isinstance(fields, list) and len(fields) == len(checked) and all(a is b for a, b in zip(fields, checked)):
            return
        if not isinstance(fields, (list, tuple)):
            raise ValueError(f"model.force_fields = {checks.shorten(fields)!r} is not allowed: must be a list of "
                             f"CompressionField (SceneBuilder.add_compression_field makes them)")
        bodies = len(self.bodies)
        for i, f in enumerate(fields):
            what = f"model.force_fields[{i}] = {checks.shorten(f)!r}"
            if not isinstance(f, CompressionField):
                raise ValueError(f"{what} is not allowed: must be a warp_esph.sim.fields.CompressionField")
            problem = field_precision_problem(f, self.scalar)
            if problem is not None:
                # The field's refusal says 'is not allowed' itself: wrapped, it was said twice.
                raise ValueError(f"{what}: {problem}")
            if not f.body < bodies:
                raise ValueError(f"{what} is not allowed: CompressionField.body = {f.body} is not a body of the model: must "
                                 f"be a body index in 0..{bodies - 1} or -1 (every particle)")
        self._checked_fields = list(fields)

    def _check_parameter_values(self, rows: np.ndarray, what: str = "the model's parameter arrays") -> None:
        """The parameter arrays (a fit, torch or a user writes them in place) hold values each
        material takes, by ``Material``'s own checks: a NaN or negative shear modulus made the
        stable step NaN and the positions NaN without a word, a negative viscosity flung the
        body, a negative flow rate ran on. Runs where ``stable_dt`` reads new values, so before
        the step that would use them, and where values are given (``Rollout.set_parameters``,
        ``what``: what the message names first; the material's refusal after it says 'is not
        allowed', which 'the model's parameter arrays are not allowed as they are' said twice)."""
        for k, m in enumerate(self.materials):
            values = {name: float(rows[f, k]) for f, name in enumerate(self.MATERIAL_FIELDS)}
            try:
                problem = modulus_precision_problem(m.replace(**values), self.scalar)
            except ValueError as e:
                raise ValueError(f"{what}: material {k}: {e}") from None
            if problem is not None:
                field, v, why = problem
                raise ValueError(f"{what}: material {k}: Material.{field} = {v:g} is not allowed in "
                                 f"{self.scalar.__name__}: {why}")

    def wave_speeds(self, values: dict | None = None) -> np.ndarray:
        """Each material's p-wave speed (``material.p_wave_speed``, m/s) from its current
        parameters (``parameter_values()``, or ``values`` of that form): the speed the step,
        the adaptive step and the divergence monitor must resolve."""
        p = self.parameter_values() if values is None else values
        rho = np.array([m.density for m in self.materials], dtype=np.float64)
        return p_wave_speed(p["mu"], p["lam"], rho, p["pressure_stiffness"])

    def _hourglass_limit(self, courant: float, hourglass: float | None, p: dict | None = None,
                         rho: np.ndarray | None = None) -> tuple[float, float]:
        """``(dt_c, c)``: the hourglass control's own limit ``dt_c`` of ``stable_dt`` and the
        strength ``c`` it is taken at (None: ``solver_choice()``'s); ``dt_c`` is ``inf`` where
        ``c = 0``. ``p``: the parameter values (default: ``parameter_values()``); ``rho``: the
        densities of the materials ``p`` holds (default: every material's)."""
        strength = self.solver_choice()[1] if hourglass is None else checks.hourglass("hourglass", hourglass)
        if not strength > 0.0:
            return math.inf, strength
        from .sim import hourglass as hg  # noqa: PLC0415 (model data first, kernels on demand)

        p = self.parameter_values() if p is None else p
        if rho is None:
            rho = np.array([m.density for m in self.materials], dtype=np.float64)
        limit = hg.stable_dt(strength, float(np.max(p["mu"] / rho)), self.spacing, self.support_radius)
        return 0.8 * courant / 0.3 * limit, strength

    def _repulsion_limit(self, courant: float, p: dict | None = None, mats: slice = slice(None)) -> tuple[float, tuple[int, ...]]:
        """``(dt_r, (a, b))``: the pair repulsion's own limit ``dt_r`` of ``stable_dt`` and the
        materials ``a, b`` (indices into ``materials``) of the pair that sets it; ``(inf, ())``
        where no material of ``mats`` has ``pair_repulsion > 0`` (or ``k_p = 0``), so the step
        is then the one without the option, to the bit. ``p``: the parameter values of
        ``mats`` (default: ``parameter_values()``'s).

        Two particles closer than ``r0`` are a spring whose stiffness is the potential's
        curvature ``U'' = 6 s (1 - r/r0) / r0^2`` (``pressure.pair_repulsion_force``), largest
        at contact, ``6 s / r0^2``; per the pair's reduced mass ``m_i m_j / (m_i + m_j)``, with
        ``s = (c_i k_i + c_j k_j)/2 sqrt(m_i m_j)`` and ``m = rho dx^3``, its squared frequency
        is ``omega^2 = 3 (c_i k_i + c_j k_j) (sqrt(rho_i / rho_j) + sqrt(rho_j / rho_i)) / r0^2``
        (``12 c k_p / r0^2`` for one material). Symplectic Euler follows it while ``dt < 2 /
        omega``, so ``dt_r = (C / 0.3) 2 / (1.5 omega)``, the force fields' margin (without it a
        head-on pair at ``c = 8`` stepped at the wave limit left at 1.671 of its speed)."""
        from .sim.pressure import PAIR_REPULSION_RANGE  # noqa: PLC0415 (model data first, kernels on demand)

        materials = self.materials[mats]
        c = np.array([m.pair_repulsion for m in materials], dtype=np.float64)
        if not (c > 0.0).any():
            return math.inf, ()
        p = self.parameter_values() if p is None else p
        ck = c * np.asarray(p["pressure_stiffness"], dtype=np.float64)
        root = np.sqrt(np.array([m.density for m in materials], dtype=np.float64))
        r0 = PAIR_REPULSION_RANGE * self.support_radius
        omega2 = 3.0 * (ck[:, None] + ck[None, :]) * (root[:, None] / root[None, :] + root[None, :] / root[:, None]) / r0**2
        a, b = np.unravel_index(int(np.argmax(omega2)), omega2.shape)
        if not omega2[a, b] > 0.0:
            return math.inf, ()
        first = mats.start or 0
        return courant / 0.3 * 2.0 / (FIELD_MARGIN * math.sqrt(float(omega2[a, b]))), (first + int(a), first + int(b))

    def _field_limit(self, courant: float, world: int | None = None) -> tuple[float, float, tuple[int, ...]]:
        """``(dt_f, k, fields)``: the force fields' own limit ``dt_f = (C / 0.3) 2 / (1.5
        sqrt(k))`` of ``stable_dt``, the net strength ``k`` (1/s^2) it is taken at and the
        indices into ``force_fields`` of the fields that make it; ``(inf, 0.0, ())`` where no
        particle ever feels a net ``k > 0``.

        Fields acting on one particle at one time add up to one spring of the summed strength,
        so ``k`` is the largest such sum over the bodies (each has particles) and over the times
        the set of active fields changes, a field's ``t_on`` and its ``t_off``: a field switched
        on later bounds the step from the start, since the step is chosen before the run and a
        run crosses ``t_on``, and so does one left alone when a repelling field over it
        switches off. A repelling field (``k < 0``) grows as ``exp(sqrt(-k) t)`` at any step
        size, so it sets no limit of its own; it lessens the net strength of the fields it
        overlaps, as it does the force. ``world``: the fields acting on that world's bodies
        alone (``world_stable_dts``); None: every body's."""
        fields = self.force_fields
        mine = range(len(self.bodies)) if world is None else {i for i, b in enumerate(self.bodies) if b.world == world}
        bodies = len(mine)
        best, chosen = 0.0, ()
        # Taken at the t_on only, a repelling field's t_off was missed: +k on [0, inf) under -k
        # on [0, 0.5) set no limit, and the run past 0.5 s had the field's spring unbounded.
        for t in sorted({f.t_on for f in fields} | {f.t_off for f in fields if math.isfinite(f.t_off)}):
            acting = [i for i, f in enumerate(fields) if f.active(t)]
            on_all = [i for i in acting if fields[i].body < 0]
            own: dict[int, list[int]] = {}
            for i in acting:
                if fields[i].body >= 0 and fields[i].body in mine:
                    own.setdefault(fields[i].body, []).append(i)
            # The fields on every body alone act on a body only where it has none of its own
            # (counted anyway, they set a limit no particle needed when every body's own field
            # cancelled them).
            groups = ([on_all] if len(own) < bodies else []) + [sorted(on_all + theirs) for theirs in own.values()]
            for group in groups:
                net = math.fsum(fields[i].strength for i in group)
                if net > best:
                    best, chosen = net, tuple(group)
        if not best > 0.0:
            return math.inf, 0.0, ()
        return courant / 0.3 * 2.0 / (FIELD_MARGIN * math.sqrt(best)), best, chosen

    def _repulsion_words(self, which: tuple[int, ...]) -> str:
        """How every message names the pair repulsion of the materials ``which``
        (``_repulsion_limit``'s pair): ``the pair repulsion of material 0 (pair_repulsion = 8,
        k_p = 1)``, or of materials 0 and 1 with each one's values."""
        p = self.parameter_values()
        names = " and ".join(str(k) for k in dict.fromkeys(which))
        values = "; ".join(f"pair_repulsion = {self.materials[k].pair_repulsion:g}, k_p = {float(p['pressure_stiffness'][k]):g}"
                           for k in dict.fromkeys(which))
        return f"the pair repulsion of material{'s' if len(set(which)) > 1 else ''} {names} ({values})"

    def _field_words(self, which: tuple[int, ...]) -> str:
        """How every message names the force fields ``which`` (``_field_limit``'s indices):
        their indices into ``force_fields`` and the bodies they act on, ``compression field 0
        (on body 'a')``; the refusals, the divergence's advice and the solver's warning alike."""
        names = self.body_names
        bodies = sorted({self.force_fields[i].body for i in which})
        on = ("every body" if bodies == [-1] else
              "body " + ", ".join(repr(names[b]) for b in bodies if b >= 0) + (" (and fields on every body)" if -1 in bodies else ""))
        fields = f"field {which[0]}" if len(which) == 1 else "fields " + ", ".join(str(i) for i in which)
        return f"compression {fields} (on {on})"

    def _stable_dt_now(self, courant: float, hourglass: float | None, rows: np.ndarray, world: int | None = None,
                       fit: str | None = None, kept: bool = False) -> float:
        # ``world``: that world's materials and fields alone (``world_stable_dts``); None: all.
        # ``kept``: the start keeps the incremental composition (``keeps_incremental``). The
        # path (fit, control, rest model) is the one ``rows`` choose: a fit's trial values
        # (``fit._Values.stable_step``) were judged by the values the arrays held.
        held = self._held_parameters, self._held_bytes
        self._held_parameters, self._held_bytes = rows, rows.tobytes()
        try:
            return self._stable_dt_of(courant, hourglass, rows, world, fit, kept)
        finally:
            self._held_parameters, self._held_bytes = held

    def _stable_dt_of(self, courant, hourglass, rows, world, fit, kept) -> float:
        full = self._parameter_values(rows)
        mats = slice(None) if world is None else self.world_materials(world)
        c = np.asarray(self.wave_speeds(full))[mats]
        p = {k: np.asarray(v)[mats] for k, v in full.items()}
        rho = np.array([m.density for m in self.materials[mats]], dtype=np.float64)
        dt = courant * self.spacing / float(np.max(c))
        if self._corrected_incremental(fit, kept):
            dt *= CORRECTED_INCREMENTAL_STEP
        dt_c, strength = self._hourglass_limit(courant, hourglass, p, rho)
        dt_f, k, _ = self._field_limit(courant, world)
        dt_r, _ = self._repulsion_limit(courant, p, mats)
        if strength > 0.0 or k > 0.0 or dt_r < math.inf:
            # In numpy: dt_c^2 passes the float range for a strength below 1e-155, where Python's
            # float raised OverflowError; its inverse, 0, is the right limit (dt itself). So
            # does dt_f^2 for a field strength below 1e-300.
            with np.errstate(over="ignore"):
                dt = 1.0 / float(np.sqrt(1.0 / dt**2 + 1.0 / np.float64(dt_c) ** 2 + 1.0 / np.float64(dt_f) ** 2
                                         + 1.0 / np.float64(dt_r) ** 2))
        eta = p["viscosity"]
        viscous = eta > 0.0
        if viscous.any():
            dt = min(dt, float(np.min(courant / 12.0 * rho[viscous] * self.support_radius**2 / eta[viscous])))
        return dt

    def neighbor_options(self, bodies: bool = True) -> dict:
        """The ``NeighborSearch`` keywords that keep worlds (and, without body
        interaction and with ``bodies``, bodies) out of each other's neighbour lists, and the
        fit's weight (the guard's moment matrix sums it)."""
        worlds = self.world_count > 1
        group = self.neighbor_group if bodies else (self.particle_world if worlds else None)
        return {"group": group, "world": self.particle_world if worlds else None, "fit_weight": self.fit_weight}

    @property
    def body_names(self) -> list[str]:
        """The bodies' names, in the order they were added."""
        return [b.name for b in self.bodies]

    def __repr__(self):
        return (
            f"Model({self.particle_count} particles, {len(self.bodies)} bodies, {len(self.materials)} materials, "
            + (f"{self.world_count} worlds, " if self.world_count > 1 else "")
            + f"spacing={self.spacing:g}, h={self.support_radius:g}, dtype={self.scalar.__name__}, device={self.device})"
        )

    @property
    def uses_comparison_models(self) -> bool:
        """Whether any material uses a Fig. 8 comparison deformation model (docs/method.md §7)."""
        return any(m.deformation != "incremental" for m in self.materials)

    def rest_neighbors(self):
        """``(X, neighbours, counts)`` of the initial configuration (same-body lists, built once)."""
        if self.rest_x is None:
            from .sim import neighbors  # noqa: PLC0415

            state = State(self, requires_grad=False)
            # Across bodies as always (the kernels keep to the body), never across worlds.
            search = neighbors.NeighborSearch(
                self.particle_count, self.scalar, self.device, self.support_radius, **self.neighbor_options(bodies=False)
            )
            search.build(state.x, self.particle_body, state.neighbors, state.neighbor_d2, state.neighbor_count, state.guard)
            self.rest_x, self.rest_nbr, self.rest_count = state.x, state.neighbors, state.neighbor_count
            self.rest_guard = state.guard
            self._rest_from = self.particle_x0.copy()
        return self.rest_x, self.rest_nbr, self.rest_count

    def rest_guard_for(self, min_neighbors: int, max_condition: float) -> wp.array:
        """The guard (``neighbors.GUARD_*``) of each rest neighbourhood with a solver's thresholds
        (``Solver(min_neighbors=..., max_condition=...)``): ``rest_guard`` itself with the
        defaults, else evaluated once per pair of thresholds on the same rest neighbourhoods.
        The rest model reads it as the incremental fit reads the guard of the current ones."""
        from .sim import neighbors  # noqa: PLC0415

        self.rest_neighbors()
        key = (int(min_neighbors), float(max_condition))
        if key == (neighbors.MIN_NEIGHBORS, float(neighbors.MAX_CONDITION)):
            return self.rest_guard
        if key not in self._rest_guards:
            n, K, dev = self.particle_count, self.max_neighbors, self.device
            # Only what the search writes (a whole State allocated every state array as scratch).
            nbr = wp.zeros((n, K), dtype=wp.int32, device=dev)
            d2 = wp.zeros((n, K), dtype=self.scalar, device=dev)
            count = wp.zeros(n, dtype=wp.int32, device=dev)
            guard = wp.zeros(n, dtype=wp.int32, device=dev)
            search = neighbors.NeighborSearch(
                self.particle_count, self.scalar, self.device, self.support_radius,
                min_neighbors=key[0], max_condition=key[1], **self.neighbor_options(bodies=False)
            )
            # From the positions the rest neighbourhoods were built from, not particle_x0 as it
            # is now: a solver made before particle_x0 changed runs against those.
            search.build(self.rest_x, self.particle_body, nbr, d2, count, guard)
            self._rest_guards[key] = guard
        return self._rest_guards[key]

    def rest_moments(self, curved: bool, rest: tuple | None = None) -> tuple[wp.array, wp.array]:
        """``(A~^-1, K)`` of each particle's rest neighbourhood for the rest model's total fit
        (``curved``: the curvature-corrected one; else ``A^-1`` and ``K = 0``;
        ``comparison.rest_moments``), evaluated once per fit and ``fit_weight`` on the rest
        neighbourhoods: they are moments of the rest offsets alone, which every step's fit and
        variational force (and their adjoints) read, and recomputed each step they cost a pass
        over every rest pair. Constants: the rest positions carry no gradient. ``rest``: a
        solver's rest set (``Solver.rest_set``), whose moments these are then, kept with it (a
        solver made before ``particle_x0`` changed fits with its old rest set's moments after a
        later solver has the model build new ones); None: the model's rest neighbourhoods."""
        from .sim import comparison  # noqa: PLC0415

        if rest is None:
            rest_x, rest_nbr, rest_count = self.rest_neighbors()
            cache = self._rest_moments
        else:
            rest_x, rest_nbr, rest_count, _, cache = rest
        # The weights are in the moments: kept across a change of fit_weight, the fit paired the
        # new weights' displacement moments with the old weights' A~^-1 (a 5 % stretch fitted
        # as 1.000003 after poly6 -> biweight, their normalisations differing).
        key = (bool(curved), self.fit_weight)
        if key not in cache:
            cache[key] = comparison.launch_rest_moments(self, rest_x, rest_nbr, rest_count, key[0])
        return cache[key]

    def _drop_stale_rest(self):
        """Forget the rest neighbourhoods (and their guards and moments, ``rest_moments``) where
        ``particle_x0`` changed since they were built (``Solver`` calls it when made): a solver
        made since takes the rest configuration as the positions are now, as its hourglass
        control does. Kept, they held the positions an
        earlier solver saw, so a body edited after it (``calibrate.jitter_model``, a scaled or
        moved ``particle_x0``) started stressed against them and sprang back."""
        if self.rest_x is not None and not np.array_equal(self._rest_from, self.particle_x0):
            self.rest_x = self.rest_nbr = self.rest_count = self.rest_guard = None
            self._rest_guards = {}
            # A new dict, not the old one cleared: a solver made before holds the old one with
            # its rest set (Solver.rest_set) and keeps fitting with those moments.
            self._rest_moments = {}

    @property
    def isotropic_pressure(self) -> bool:
        """Whether the materials' pressure force is ``isotropic`` (all of them, or none:
        ``check_pressure_forces``)."""
        return any(m.pressure_force == "isotropic" for m in self.materials)

    @property
    def separate_pressure_density(self) -> bool:
        """Whether a material's pressure reads a density of its own (``energy_spiky``,
        ``isotropic``: the spiky
        sum, ``State.pressure_density``); otherwise the pressure reads the SPH density."""
        return any(m.pressure_force in SPIKY_DENSITY_FORCES for m in self.materials)

    def compute_rest_density(self):
        """The pressure density of the initial configuration (``particle_rest_density``): each
        particle's pressure-free density (the poly6 sum; the spiky sum for ``energy_spiky`` and
        ``isotropic``)."""
        from .sim import neighbors, pressure  # noqa: PLC0415 (model data first, kernels on demand)

        state = State(self, requires_grad=False)
        search = neighbors.NeighborSearch(
            self.particle_count, self.scalar, self.device, self.support_radius, bodies_interact=self.bodies_interact,
            **self.neighbor_options(),
        )
        search.image_args = self.image_args() if self.image_plane is not None else None
        search.build(state.x, self.particle_body, state.neighbors, state.neighbor_d2, state.neighbor_count, state.guard)
        pressure.launch_density(self, state.x, state.neighbors, state.neighbor_count, self.particle_rest_density,
                                of_pressure=True)
