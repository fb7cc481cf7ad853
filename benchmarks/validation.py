"""Validation suite: the simulated material against closed-form results of rheology and
elasticity, at two or more resolutions, for both elastic forces.

    python -m benchmarks.validation            # full run (tens of minutes on one core), writes docs/validation.md
    python -m benchmarks.validation --quick    # CI-sized run (a few minutes)
    python -m benchmarks.validation --quick --out /tmp/v   # write the report elsewhere
    python -m benchmarks.validation --only slump:resolution=12 --merge docs/validation.json   # re-run a subset
                                           # into the existing report; every row names the run that measured it
    python -m benchmarks.validation --merge docs/validation.json --add gpu_rows.json   # rows measured elsewhere
                                           # (a JSON list of slump(...) results, each maybe with a "device")

Each case is a function taking its size (``resolution``: particles across the thinnest
dimension) and returning a dict of what was measured next to the theory. The report is
``docs/validation.md`` (a table per case), ``docs/images/validation/*.png`` (measured vs
theory and vs resolution) and ``docs/validation.json`` (every number).

Every case builds its scene on Warp's current device (``wp.get_device()``; the command line's
``--device``, default the CPU, sets it for its runs), so a case called from Python on a machine
with a GPU runs there. Only ``warp_esph``'s public API is used: ``SceneBuilder``, ``Material``, ``Solver``,
``Model.stable_dt`` and the ``State`` arrays. Quasi-static results are read only after
the kinetic energy has decayed, and the residual rate of change is reported with them.
Where a case needs a static equilibrium of an elastic body (beam, column, plates) it is
found by dynamic relaxation: every particle's velocity is multiplied by ``exp(-c dt)``
after each step, a mass-proportional damping that does not change the equilibrium (SPH
viscosity cannot damp a bending mode within its explicit step limit).

Every result also says how its run's neighbour rows were chosen (``_row_fields``):
``neighbors_cut`` (``Solver.guard_counts``), ``full_row_particle_steps`` and
``particle_steps``. A full row holds ``max_neighbors`` particles: exactly that many
candidates, or more, of which the search chose which to keep. Only a run with full rows can
move when that choice changes; a run with none cannot (the count errs on the full side).
"""

from __future__ import annotations

import functools
import json
import math
import pathlib
import sys
import time
import warnings

import numpy as np

# The fit's weights, and the one a scene gets without naming one: a case function's
# ``fit_weight`` and a plan entry without one run it, so the plan's base entries measure what
# a user gets; each base entry's twins name the others. From the module the kernels read them
# from, which imports no Warp (this module must not load it).
from warp_esph.sim.fit_weights import DEFAULT_FIT_WEIGHT, FIT_WEIGHTS

G = 9.81
RHO = 1000.0
FORCES = ("paper", "variational")
ROOT = pathlib.Path(__file__).resolve().parent.parent


#: Dimensionless uniaxial yield stresses of the slump runs (0.05: the spread regime).
SLUMP_S = (0.05, 0.1, 0.2, 0.3, 0.5)
#: A slump is at rest when, over the last quarter of its run, the top's height moves less than
#: ``REST_RATE`` % H0/s (the linear fit's slope, either sign) and the largest sampled kinetic
#: energy stays below ``REST_KINETIC`` M g H0 (M: the free particles' mass). The rate is the
#: issue's target; the energy bound catches a pile that still spreads at its rim or rings under a
#: still top. 1e-8 is twice the energy of the whole pile moving at the rate bound (1e-4 m/s at
#: H0 = 0.1 m: 5.1e-9 M g H0). Measured over 6-8 s at 8 across (docs/validation.md): the piles
#: that had stopped held at most 4e-11, those still settling (top creeping, rim spreading)
#: 8e-8 to 3e-6, so the bound sits in that gap with a decade or more to either side.
REST_RATE, REST_KINETIC = 0.1, 1.0e-8
#: The slump's duration in the full plan: long enough that a pile which will stop has stopped
#: (under the variational force and energy_spiky pressure the S = 0.3 and 0.05 piles at 8 across
#: still sink at 0.56 and 0.67 % H0/s at 4 s).
SLUMP_DURATION = 8.0
#: The 16-across slumps run longer: the finer pile settles more slowly (S = 0.1 at 16 across:
#: the top still below the rate bound, but the largest kinetic energy 3.6e-8 M g H0 over
#: 6-8 s, 1.7e-9 over 10-12 s; docs/validation.md).
SLUMP_DURATION_FINE = 12.0
#: Nominal strain amplitudes of the energy runs (the measured peak strain is reported).
SMALL, LARGE = 0.002, 0.05


def _we():
    import warp as wp

    import warp_esph as we

    we.init_warp()

    return wp, we


class _FirstStep(Exception):
    """Raised by a ``_solver`` solver's first step under ``first_step``: ``(solver, state, dt)``."""


#: Set by ``first_step`` alone: a case stops at its first step, before taking it.
_first_step_only = False


@functools.cache
def _count_full_rows_kernel():
    """The kernel ``_solver``'s solvers count full rows with, made once per process: made in
    each ``_solver`` call it was hashed again each time (about 13 ms a case under load, 5 s of
    the 398 scenes ``first_step`` builds) and loaded as a module of its own at each run's first
    step."""
    wp, _ = _we()

    @wp.kernel(module="unique")
    def count_full_rows(count: wp.array(dtype=wp.int32), width: int, total: wp.array(dtype=wp.int64)):
        i = wp.tid()
        if count[i] >= width:
            wp.atomic_add(total, 0, wp.int64(1))

    return count_full_rows


def _solver(model, **kwargs):
    """``warp_esph.Solver(model, **kwargs)`` that also counts, over its steps, the particle-steps
    whose neighbour row was full (``State.neighbor_count`` at ``Model.max_neighbors``), on the
    model's device; ``_row_fields`` reads the counts into a case's result."""
    wp, we = _we()
    count_full_rows = _count_full_rows_kernel()

    class RowCountingSolver(we.Solver):
        particle_steps = 0
        rest_model_steps = 0

        def __init__(self, model, **kw):
            super().__init__(model, **kw)
            # On the device the rows are counted: reading neighbor_count back every step was a
            # device-to-host copy and a sync a step on a GPU. int64: a long fine run passes 2^31.
            self.full_row_total = wp.zeros(1, dtype=wp.int64, device=model.device)

        @property
        def full_rows(self) -> int:
            return int(self.full_row_total.numpy()[0])

        def step(self, state_in, state_out, dt):
            if _first_step_only:
                raise _FirstStep(self, state_in, dt)
            super().step(state_in, state_out, dt)
            # Every step, not once per sample: a row is full for a few steps of a collision or
            # a stretch, between samples.
            wp.launch(count_full_rows, dim=self.model.particle_count,
                      inputs=[state_out.neighbor_count, self.model.max_neighbors, self.full_row_total],
                      device=self.model.device)
            self.particle_steps += self.model.particle_count
            # What ran, as the state it wrote says: fit="auto" runs the rest-configuration model
            # for purely elastic scenes.
            self.rest_model_steps += int(bool(state_out.rest_model))

    return RowCountingSolver(model, **kwargs)


def _row_fields(solver) -> dict:
    """What a reader needs to judge a run's neighbour rows: a full row is one whose members the
    search chose (of more candidates than ``max_neighbors``: since the stretched rows of
    ``select_neighbors``, by their weight, not their distance), so a result whose run had full
    rows may differ from one measured before that choice changed; ``neighbors_cut`` counts the
    particle-steps whose row may have dropped a neighbour of non-zero weight
    (``Solver.guard_counts``), ``full_row_particle_steps`` those whose row was full, of
    ``particle_steps`` (every particle, pinned ones included, every step); ``rest_model_steps``:
    the steps that ran the rest-configuration model (``State.rest_model``: ``fit="auto"`` on
    a purely elastic scene without tools), the deformation model the row measured."""
    return {"neighbors_cut": solver.guard_counts()["neighbors_cut"], "full_row_particle_steps": solver.full_rows,
            "particle_steps": solver.particle_steps, "rest_model_steps": solver.rest_model_steps}


def _swap_run(model, solver, a, c, dt, steps, after=None):
    """``steps`` steps from ``a``; ``after(state, k)`` sees each new state (``k`` from 1)."""
    for k in range(1, steps + 1):
        solver.step(a, c, dt)
        a, c = c, a
        if after is not None and after(a, k) is False:
            break
    return a, c


def _kinetic(model, state, mask=None) -> float:
    """The kinetic energy of the particles ``mask`` picks (None: all)."""
    m = model.particle_mass.numpy()
    v = state.v.numpy().astype(np.float64)
    e = 0.5 * m * (v**2).sum(axis=1)
    return float((e if mask is None else e[mask]).sum())


def _damp(state, factor: float):
    # Mass-proportional damping of dynamic relaxation (docstring of the module).
    state.v.assign(state.v.numpy() * factor)


def come_to_rest(solver, state, probe, dt: float):
    """Stops every free particle where it is, for the solver's symplectic Euler: ``v = -dt a(x) / 2``.

    The stored velocity is the step's, half a step behind ``x``; ``v = 0`` leaves the velocity
    ``dt a / 2`` at ``x``, which is not rest: it can add up to ``1 / (1 - (omega dt / 2)^2)``
    to a mode's energy (the least of the integrator's conserved energy over ``v`` is at ``-dt a
    / 2``), and zeroings in step with a mode pumped the held cantilever's (docs/physics.md, "The
    held cantilever's float32 late growth"). ``a(x)`` is read from one step into ``probe``
    (a state of the same model, overwritten); ``state`` keeps its ``x`` and time.
    A pinned particle keeps its velocity, its pin's: ``probe.v`` is the pin's too, and
    ``(V - V) / 2`` would stop a moving pin for the next step's neighbours (the viscosity
    reads it). Free particles beside a moving tool or pin are stopped all the same: kinetic
    damping is for scenes that come to rest."""
    solver.step(state, probe, dt)  # probe.v = v + dt a(x) (a pinned particle: its pin's velocity)
    v = state.v.numpy()
    stopped = 0.5 * (v - probe.v.numpy())
    for pin in solver.model.tools.pins if solver.model.tools is not None else ():
        stopped[pin.indices] = v[pin.indices]
    state.v.assign(stopped)


def kinetic_damping(solver, state, probe, dt: float, mass: np.ndarray, ke_prev: float) -> float:
    """One check of kinetic damping, the dynamic-relaxation route to a static state that does
    not change it: if the kinetic energy (``mass`` per particle, a column) has dropped since
    the last check (``ke_prev``), every particle is stopped where it is (``come_to_rest``).
    Returns the energy the next check compares with (0 after a stop)."""
    v = state.v.numpy().astype(np.float64)
    ke = 0.5 * float((mass * v * v).sum())
    if ke < ke_prev:
        come_to_rest(solver, state, probe, dt)
        return 0.0
    return ke


def _deviatoric_norm(F: np.ndarray, mu: float) -> np.ndarray:
    """|s| = 2 mu |sigma - mean(sigma)| of the yield test (warp_esph/sim/plasticity.py), sigma
    the singular values of the stored elastic F."""
    s = np.linalg.svd(F.astype(np.float64), compute_uv=False)
    dev = s - s.mean(axis=1, keepdims=True)
    return 2.0 * mu * np.linalg.norm(dev, axis=1)


# --------------------------------------------------------------------- floors
#: The frictionless imaged ground that holds its base up to the material's shear yield stress
#: (``add_ground(friction=0, images=True, shear_cap=1)``, the Tresca ground; ``friction`` unused).
TRESCA = "tresca_images"
#: The suite's slump floor (since 2026-12-07; before, the particle floor, which stays the case
#: functions' default): the plan's slumps and spread piles stand on it, and the report counts
#: its rows as the suite's. Its wall law is a continuum's, so a yield stress fitted on it is a
#: defined wall's; the particle floor grips between slip and no-slip, a law no continuum runs
#: (docs/validation.md, "The suite's floor"; docs/physics.md, "Still open").
SUITE_FLOOR = TRESCA
FLOORS = ("ground", "particles", "ground_images", "elastic_particles", "ghost_particles", "slip_ghost_particles", TRESCA)
#: The floors of pinned particles (``SceneBuilder.add_particle_floor``), the others colliders.
PARTICLE_FLOORS = ("particles", "elastic_particles", "ghost_particles", "slip_ghost_particles")
#: Layers of pinned particles under a body on a ``floor="particles"`` (two: a particle's fit
#: reaches one spacing below it at the default support radius 2 dx, and so sees an interior
#: neighbourhood at the base).
FLOOR_LAYERS = 2
#: Where ``incline`` puts its walls normal to z (see its docstring).
INCLINE_WALLS = ("faces", "centres")


#: ``slump``'s reference for the frictionless floors: no floor, the cylinder's mirror image
#: below the plane y = 0 in its place and gravity pointing at that plane from both sides
#: (``_Mirror``). The plane is then an exact frictionless wall of the particle method's own
#: bulk: what a pile does there is the method's, not a floor's (docs/physics.md, "The slip
#: ghost floor").
MIRROR = "mirror"
#: The floors ``slump`` takes.
SLUMP_FLOORS = FLOORS + (MIRROR,)


def _add_ground(b, floor: str, friction: float, shear_cap: float = 1.0) -> None:
    """The ground collider of ``floor`` (``"ground"``, ``"ground_images"`` or ``TRESCA``, the
    last holding up to ``shear_cap`` times the material's shear yield stress)."""
    if floor == TRESCA:
        b.add_ground(0.0, friction=0.0, images=True, shear_cap=shear_cap)
    else:
        b.add_ground(0.0, friction=friction, images=floor == "ground_images")


def _check_floor(floor: str, allowed: tuple = FLOORS):
    if floor not in allowed:
        raise ValueError(f"floor = {floor!r} is not allowed: must be one of {', '.join(map(repr, allowed))}")


class _Mirror:
    """``slump(floor="mirror")``'s work between steps. The particles ``half`` on are the
    mirror images of the first ``half`` across y = 0 (``i + half`` of ``i``), the model's
    gravity is 0, and ``__call__`` (after each step, and once before the first) makes every
    per-particle field of the lower half the mirror image of the upper's (positions and
    vectors with y negated, matrices ``R M R``, scalars copied): a flowing packing breaks
    the symmetry from round-off within a second, and particles then cross the plane (measured
    at 8 across, S = 0.2: from 0.4 s in float32 and 1.0 s in float64, 30-56 of the 832 from
    0.6 s on in float32; docs/physics.md, "The slip ghost floor"). It then
    gives the next step gravity ``g`` towards the plane as a velocity kick, ``v_y -= g dt
    sign(y)``, which symplectic Euler adds as it would the model's gravity."""

    def __init__(self, model, half: int):
        self.model, self.half = model, half
        self.flip = np.array([1.0, -1.0, 1.0])

    def __call__(self, state, g: float, dt: float):
        n, h, T = self.model.particle_count, self.half, self.model.types
        for arr in vars(state).values():
            if not (hasattr(arr, "numpy") and arr.ndim == 1 and arr.shape[0] == n):
                continue
            a = arr.numpy()
            if arr.dtype == T.vec3:
                a[h:] = a[:h] * self.flip.astype(a.dtype)
            elif arr.dtype == T.mat33:
                a[h:] = a[:h] * np.outer(self.flip, self.flip).astype(a.dtype)
            elif arr.dtype == T.scalar:
                a[h:] = a[:h]
            else:
                continue  # integers: neighbour counts and guards, whose rows the next step rebuilds
            arr.assign(a)
        v = state.v.numpy()
        v[:, 1] -= (g * dt * np.sign(state.x.numpy()[:, 1])).astype(v.dtype)
        state.v.assign(v)


def _add_on_floor(b, points: np.ndarray, material, floor: str, radius: float, friction: float, name: str,
                  layers: int = FLOOR_LAYERS):
    """Adds the body ``points`` (its base at y = 0) on the floor: ``"ground"``, the static
    ground collider with Coulomb ``friction``; ``TRESCA`` (``"tresca_images"``), the
    frictionless imaged ground holding its base up to the material's shear yield stress; ``"particles"``, FLOOR_LAYERS layers of pinned
    particles of the same body (so in every fit) under a disc of ``radius`` on the body's
    lattice (``SceneBuilder.add_particle_floor``): a rough floor whose first layer of
    material has an interior neighbourhood; ``"elastic_particles"``, the same floor made
    elastic (``add_particle_floor(elastic=True)``: it holds the material within a support
    radius of it, docs/physics.md, "The floor's plasticity"); ``"ghost_particles"``, the same
    floor as a no-slip wall of odd ghosts (``add_particle_floor(ghost=True)``, holding no
    layer: docs/physics.md, "The no-slip ghost floor"); ``"slip_ghost_particles"``, the
    frictionless ghost floor (``ghost=True, slip=True``). Returns the mask of the free
    particles (all of them on the ground)."""
    b.add_particles(points, material, name=name)
    if floor in ("ground", "ground_images", TRESCA):
        _add_ground(b, floor, friction)
        return np.ones(len(points), dtype=bool)
    # A margin of radius + dx reaches the whole disc from the column nearest the axis.
    b.add_particle_floor(name, margin=radius + b.spacing, layers=layers, name="floor",
                         where=lambda p: np.hypot(p[:, 0], p[:, 2]) <= radius, elastic=floor == "elastic_particles",
                         ghost=floor in ("ghost_particles", "slip_ghost_particles"), slip=floor == "slip_ghost_particles")
    return np.arange(b.particle_count) < len(points)


# --------------------------------------------------------------------- slump
def slump_theory(S: float) -> float:
    """h / H0 = S (1 - ln S) of the 1-D static analysis (Murata 1984, Pashias et al. 1996)."""
    return S * (1.0 - math.log(S)) if S < 1.0 else 1.0


def slump_at_rest(rate_pct_H0_per_s: float, kinetic_over_MgH0: float) -> bool:
    """The rest verdict of a slump (``REST_RATE``, ``REST_KINETIC``): over the last quarter of
    the run the top's rate below ``REST_RATE`` % H0/s in magnitude and the kinetic energy below
    ``REST_KINETIC`` M g H0. A nan (a run too short to fit a rate) is not at rest."""
    return bool(abs(rate_pct_H0_per_s) < REST_RATE and kinetic_over_MgH0 < REST_KINETIC)


def spread_radius_theory(volume: float, tau_y: float, rho: float = RHO, g: float = G) -> float:
    """R = (225 rho g Omega^2 / (128 pi^2 tau_y))^(1/5), Roussel & Coussot (2005)."""
    return (225.0 * rho * g * volume**2 / (128.0 * math.pi**2 * tau_y)) ** 0.2


def spread_height_theory(radius: float, tau_y: float, rho: float = RHO, g: float = G) -> float:
    """Central height sqrt(2 tau_y R / (rho g)) of the shallow no-slip profile
    h(r) = sqrt(2 tau_y (R - r) / (rho g)) of Roussel & Coussot (2005)."""
    return math.sqrt(2.0 * tau_y * radius / (rho * g))


def slump_shallow_theory(S: float, aspect: float = 1.0) -> float:
    """h_RC / H0: the central height of Roussel & Coussot's shallow no-slip pile
    (``spread_height_theory``) holding the volume ``pi R0^2 H0`` of ``slump``'s cylinder
    (``aspect`` = H0 / (2 R0)), of the slump's shear yield stress ``tau_y = Y / sqrt(2) = S rho g
    H0 / sqrt(3)``. Unlike the 1-D height it depends on the aspect (through the volume)."""
    ell = S / math.sqrt(3.0)  # tau_y / (rho g) in units of H0
    volume = math.pi * (0.5 / aspect) ** 2  # pi R0^2 H0 in units of H0^3
    return spread_height_theory(spread_radius_theory(volume, ell, rho=1.0, g=1.0), ell, rho=1.0, g=1.0)


def centre_thickness(x: np.ndarray, volume: np.ndarray, J: np.ndarray, radius: float) -> float:
    """The material's thickness on the axis of a pile standing on y = 0: the particles'
    current volumes ``volume J`` summed with the smooth weight ``w = (1 - r^2 / radius^2)^2``
    (r the distance from the axis, 0 beyond ``radius``) over its integral ``pi radius^2 / 3``.
    A volume measure: it does not read the particle-scale roughness of the top, which the top
    particle's height does (docs/physics.md, why the S = 0.1 pile stands above the 1-D
    height), and its weight, smooth at ``radius``, keeps the lattice's count of columns inside
    a disc out of it (a cylinder on the lattice reads within 0.5 % of its height from 8
    across at ``radius`` = R0 / 2; a sharp disc 4-13 % off)."""
    q = np.clip(1.0 - (x[:, 0] ** 2 + x[:, 2] ** 2) / radius**2, 0.0, None)
    return float((volume * J * q * q).sum() / (math.pi * radius**2 / 3.0))


def pile_profile(x0: np.ndarray, x: np.ndarray, depth0: np.ndarray, plastic: np.ndarray, ratio: np.ndarray,
                 R0: float, spacing: float, H0: float) -> tuple[list, list]:
    """A slumped pile's shape, as both slump solvers report it (``slump`` here, the MPM's in
    ``benchmarks/mpm_slump.py``), from its particles' initial and final positions ``x0``, ``x``,
    initial depths ``depth0``, accumulated plastic strains ``plastic`` (in yield strains) and
    stress ratios ``ratio`` (|s| / Y), on a lattice of ``spacing``: the top (+ spacing / 2) per
    band R0 / 4 wide from the axis (a bowl or a flat top; None for a band no particle is in,
    up to the outermost that has one), and per initial layer on the axis
    (initial radius below R0 / 4) its mean height, plastic strain, stress ratio and the
    fraction of it that never yielded."""
    r = np.hypot(x[:, 0], x[:, 2])
    bands = []
    for b in range(8):
        sel = (r >= b * 0.25 * R0) & (r < (b + 1) * 0.25 * R0)
        bands.append(float((x[sel, 1].max() + 0.5 * spacing) / H0) if sel.any() else None)
    while bands and bands[-1] is None:
        bands.pop()
    layers = []
    axis = np.hypot(x0[:, 0], x0[:, 2]) < 0.25 * R0
    for d in np.unique(np.round(depth0[axis] / spacing, 6)):
        sel = axis & (np.abs(depth0 / spacing - d) < 1e-3)
        layers.append({"depth0_over_H0": float(d * spacing / H0), "y_over_H0": float(x[sel, 1].mean() / H0),
                       "plastic_mean_yield_strains": float(plastic[sel].mean()),
                       "never_yielded_fraction": float((plastic[sel] == 0.0).mean()),
                       "stress_ratio_mean": float(ratio[sel].mean())})
    return bands, layers


def plug_measures(depth0: np.ndarray, r0: np.ndarray, ratio: np.ndarray, plastic: np.ndarray, S: float, H0: float,
                  R0: float, resolved: bool = True) -> dict:
    """The suite's reading of a slumped pile's plug, shared by both slump solvers (``slump``
    here, the MPM's in ``benchmarks/mpm_slump.py``) so that the continuum is held to the same
    criterion: the particles that start within ``R0 / 2`` of the axis and less than
    ``S H0 / 2`` deep (the part of the 1-D plug the sudden release leaves below yield;
    docs/validation.md, the plug), from their initial depths ``depth0`` and radii ``r0``, final
    stress ratios ``ratio`` (|s| / Y) and accumulated plastic strains ``plastic`` (in yield
    strains ``Y / (2 mu)``). Where ``resolved`` is false, or no particle is in the region, the
    fractions are nan."""
    plug = (depth0 < 0.5 * S * H0) & (r0 < 0.5 * R0) & bool(resolved)
    nan = float("nan")
    return {
        "plug_particles": int(plug.sum()),
        # At rest: a particle of the plug that never flowed keeps |s| < Y (the 0.99 of
        # "at yield"); one that flowed stays at Y (the flow stops where |s| reaches it).
        "plug_unyielded_fraction": float((ratio[plug] < 0.99).mean()) if plug.any() else nan,
        # Accumulated plastic strain (State.alpha, sum of gamma |dev ln sigma|) in yield
        # strains: below 1 the particle changed shape less plastically than the largest
        # elastic strain it can hold, i.e. it did not flow.
        "plug_plastic_strain": float(plastic[plug].mean()) if plug.any() else nan,
        "plug_plastic_strain_max": float(plastic[plug].max()) if plug.any() else nan,
    }


def slump_model(S: float, resolution: int = 12, elastic_force: str = "variational", H0: float = 0.1,
                flow_rate: float = 200.0, viscosity: float = 2.0, friction: float = 1.0, pressure_force: str = "energy_spiky",
                floor: str = "particles", floor_radius: float = 3.2, pressure_stiffness: float | None = None,
                support_radius: float = 2.0, stiffness: float = 10.0, floor_layers: int = FLOOR_LAYERS,
                aspect: float = 1.0, dtype=None, requires_grad: bool = False, fit_weight: str = DEFAULT_FIT_WEIGHT):
    """``slump``'s scene (its arguments, its docstring): ``(model, free, mu, Y)``, the model in
    ``dtype`` (default float32; ``requires_grad`` for a taped run), the mask of its free
    particles, the shear modulus and the yield stress. With ``floor="mirror"`` the model has
    no gravity of its own and ``free`` is the upper half: a run needs ``_Mirror`` between its
    steps, as ``slump`` does."""
    wp, we = _we()
    _check_floor(floor, SLUMP_FLOORS)
    R0 = H0 / (2.0 * aspect)
    dx = 2.0 * R0 / resolution
    sigma_y = S * RHO * G * H0
    Y = sigma_y * math.sqrt(2.0 / 3.0)
    mu = stiffness * RHO * G * H0
    mat = we.Material(mu=mu, lam=1.5 * mu, yield_stress=Y, flow_rate=flow_rate, density=RHO, viscosity=viscosity,
                      elastic_force=elastic_force, pressure_force=pressure_force, pressure_stiffness=pressure_stiffness)
    mirror = floor == MIRROR
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0 if mirror else -G, 0.0), support_radius=support_radius * dx,
                        fit_weight=fit_weight)
    from warp_esph.meshes import lattice_points

    pts = lattice_points(np.array([-R0, 0.0, -R0]), np.array([R0, H0, R0]), dx)
    pts = pts[np.hypot(pts[:, 0], pts[:, 2]) <= R0]  # what add_cylinder places
    if mirror:
        b.add_particles(np.concatenate([pts, pts * np.array([1.0, -1.0, 1.0])]), mat, name="cylinder0")
        free = np.arange(2 * len(pts)) < len(pts)
    else:
        free = _add_on_floor(b, pts, mat, floor, floor_radius * R0, friction, "cylinder0", layers=floor_layers)
    model = b.finalize(device=wp.get_device(), dtype=wp.float32 if dtype is None else dtype, requires_grad=requires_grad)
    return model, free, mu, Y


def slump(S: float, resolution: int = 12, elastic_force: str = "variational", duration: float = 4.0,
          H0: float = 0.1, flow_rate: float = 200.0, viscosity: float = 2.0, friction: float = 1.0,
          dt_factor: float = 0.9, samples: int = 200, pressure_force: str = "energy_spiky", floor: str = "particles",
          floor_radius: float = 3.2, pressure_stiffness: float | None = None, support_radius: float = 2.0,
          stiffness: float = 10.0, gravity_ramp: float = 0.0, floor_layers: int = FLOOR_LAYERS,
          aspect: float = 1.0, fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """A cylinder H0 = 2 R0 of a yield-stress material slumps on a rough floor.

    ``S = sigma_y / (rho g H0)`` with sigma_y the uniaxial yield stress: ``yield_stress = Y
    = sigma_y sqrt(2/3)`` (the code compares the Frobenius norm of the deviatoric stress with
    Y; under uniaxial stress it is sqrt(2/3) sigma). mu = 10 rho g H0, nu = 0.3, default SPH
    pressure, ``viscosity`` Pa s (a little, so that an unyielded body's ringing decays).
    ``resolution`` is particles across the diameter (and across H0 at the default ``aspect``
    1; ``aspect`` = H0 / (2 R0), H0 kept: a taller, narrower cylinder of the same S, whose
    slumped pile is taller against its radius, as the 1-D analysis assumes). The height ``h`` is the top
    of the particles within R0/2 of the axis (plus dx/2: each stands for a cell); the
    thickness (``thickness_over_H0``) the material's volume per area there
    (``centre_thickness`` over R0/2), which the top's particle-scale roughness does not
    raise (at S = 0.1, 12 / 16 across, h reads 0.6 / 1.0 dx above it).
    ``pressure_force``: ``Material.pressure_force`` (docs/physics.md, the SPH pressure).
    ``floor``: ``"particles"`` (the default: pinned layers of the same body under a disc of
    ``floor_radius`` R0, ``_add_on_floor``) or ``"ground"`` (the ground collider with Coulomb
    ``friction``) or ``"tresca_images"`` (``TRESCA``: the frictionless imaged ground that holds
    its base up to the material's shear yield stress, ``add_ground(shear_cap=1)``, the
    continuum's Tresca floor; ``friction`` unused). Both theories assume a no-slip base; the particle floor is the one that
    gives a thin layer its continuum shear strength, the ground collider makes a layer 3
    particles thick about 2.5 x too strong (docs/physics.md, the spread regime, thin layers
    in shear); on it the pile rests where a continuum on a slip floor does, and on
    ``"elastic_particles"`` (the same floor made elastic, which holds a band a support radius
    thick) where one on a no-slip floor does (docs/physics.md, "The floor's plasticity").
    ``floor_radius`` must reach past the resting pile (``radius_over_R0``) by a
    support radius or more: the S = 0.1 pile rests within 2.2 R0 at 8-16 across (2.6 R0 at aspect 2; S = 0.2 within
    1.8). Every measure is over the free particles. One change at a time
    (docs/physics.md, the spread regime): ``pressure_stiffness`` (``Material``'s; 0: the SPH
    pressure off), ``support_radius`` (h in dx), ``stiffness`` (mu in rho g H0),
    ``gravity_ramp`` (s: gravity rises linearly from 0 over that time instead of acting at
    once; 0: at once), ``floor_layers`` (pinned layers of a particle floor), ``fit_weight``
    (``SceneBuilder(fit_weight=)``: the weight of the incremental fit).
    ``nearest_neighbor_mean`` / ``_p05``: the free particles' nearest-neighbour distance in
    dx at the end (mean, 5th percentile; uncorrelated points of the same density: 0.554).
    ``floor="mirror"`` (``MIRROR``): no floor but the cylinder's mirror image under gravity
    towards the plane between them (``_Mirror``), an exact frictionless wall of the method's
    own bulk; the measures are the upper half's, ``floor_radius``, ``friction`` and
    ``floor_layers`` unused."""
    wp, we = _we()
    _check_floor(floor, SLUMP_FLOORS)
    if not gravity_ramp >= 0.0:
        raise ValueError(f"gravity_ramp = {gravity_ramp!r} is not allowed: must be >= 0 (seconds)")
    if not aspect > 0.0:
        raise ValueError(f"aspect = {aspect!r} is not allowed: must be > 0 (H0 / (2 R0))")
    R0 = H0 / (2.0 * aspect)
    dx = 2.0 * R0 / resolution
    model, free, mu, Y = slump_model(S, resolution, H0=H0, flow_rate=flow_rate, viscosity=viscosity, friction=friction,
                                     elastic_force=elastic_force, pressure_force=pressure_force, floor=floor,
                                     floor_radius=floor_radius, pressure_stiffness=pressure_stiffness,
                                     support_radius=support_radius, stiffness=stiffness, floor_layers=floor_layers,
                                     aspect=aspect, fit_weight=fit_weight)
    n = int(free.sum())
    x0 = model.particle_x0.astype(np.float64)[free]
    r0 = np.hypot(x0[:, 0], x0[:, 2])
    # The 1-D analysis's plug: material less deep than sigma_y / (rho g) = S H0 never yields
    # under its static load rho g z. The run starts stress-free and gravity acts at once, so
    # the release overshoots the static stress up to 2 rho g z (docs/validation.md, the plug):
    # only the top half, depth < S H0 / 2, stays below yield throughout. A particle's
    # deformation is fitted over its support radius h, so that region is resolved only where
    # it is at least h thick; elsewhere the plug measures are nan.
    depth0 = x0[:, 1].max() + 0.5 * dx - x0[:, 1]
    resolved = 0.5 * S * H0 >= model.support_radius * (1.0 - 1e-9)  # equal at S = 0.5, 8 across
    # More than h below the 1-D yield surface the material has flowed: the reference scale.
    flowed = (depth0 > S * H0 + model.support_radius) & (r0 < 0.5 * R0)
    solver = _solver(model)
    dt = dt_factor * model.stable_dt()
    steps = int(round(duration / dt))
    every = max(1, steps // samples)
    a, c = model.state(), model.state()
    times, heights, kes, radii, thick = [], [], [], [], []
    volume = model.particle_volume.numpy().astype(np.float64)[free]

    def height(x):
        r = np.hypot(x[:, 0], x[:, 2])
        near = r < 0.5 * R0
        return float(x[near, 1].max() + 0.5 * dx) if near.any() else float("nan")

    mirror = _Mirror(model, n) if floor == MIRROR else None

    def gravity_after(k):
        # The gravity of step k + 1.
        return G * min(1.0, (k * dt) / gravity_ramp) if gravity_ramp > 0.0 else G

    def sample(state, k):
        out = record(state, k)
        # After the reading: the mirror's kick is the next step's, not this state's velocity.
        if mirror is not None:
            mirror(state, gravity_after(k), dt)
        elif gravity_ramp > 0.0:
            model.gravity = (0.0, -gravity_after(k), 0.0)
        return out

    def record(state, k):
        if k % every and k != steps:
            return
        x = state.x.numpy().astype(np.float64)[free]
        times.append(k * dt)
        heights.append(height(x))
        thick.append(centre_thickness(x, volume, np.linalg.det(state.F.numpy().astype(np.float64)[free]), 0.5 * R0))
        kes.append(_kinetic(model, state, free))
        radii.append(float(np.hypot(x[:, 0], x[:, 2]).max() + 0.5 * dx))
        if not np.isfinite(x).all():
            return False

    if mirror is not None:
        mirror(a, gravity_after(0), dt)
    elif gravity_ramp > 0.0:
        model.gravity = (0.0, 0.0, 0.0)
    t0 = time.perf_counter()
    a, c = _swap_run(model, solver, a, c, dt, steps, sample)
    wall = time.perf_counter() - t0
    t, h, ke, th = np.array(times), np.array(heights), np.array(kes), np.array(thick)
    last = t >= t[-1] - 0.25 * duration
    rate = -np.polyfit(t[last], h[last], 1)[0] if last.sum() > 2 else float("nan")
    weight_scale = float(model.particle_mass.numpy()[free].sum()) * G * H0
    ke_last = float(ke[last].max() / weight_scale)
    rate_th = -np.polyfit(t[last], th[last], 1)[0] if last.sum() > 2 else float("nan")
    ratio = _deviatoric_norm(a.F.numpy()[free], mu) / Y
    x_end = a.x.numpy().astype(np.float64)[free]
    alpha = a.alpha.numpy().astype(np.float64)[free]
    yield_strain = Y / (2.0 * mu)
    # Nearest neighbour of each free particle (floor included) from the last step's rows,
    # which hold every particle within h: near-coincident pairs are what a pressure force
    # without a repulsive core lets form (docs/physics.md, the S = 0.1 slump under the energy
    # pressure force).
    d2 = solver.scratch.neighbor_d2.numpy().astype(np.float64)[free]
    cnt = a.neighbor_count.numpy()[free]
    d2 = np.where(np.arange(d2.shape[1])[None, :] < cnt[:, None], d2, np.inf)
    nearest = np.sqrt(d2.min(axis=1)) / dx
    volume = n * dx**3
    tau_y = Y / math.sqrt(2.0)
    R_rc = spread_radius_theory(volume, tau_y)
    bands, layers = pile_profile(x0, x_end, depth0, alpha / yield_strain, ratio, R0, dx, H0)
    return {
        "case": "slump", "S": S, "resolution": resolution, "aspect": aspect, "elastic_force": elastic_force,
        "pressure_force": pressure_force, "fit_weight": fit_weight,
        "floor": floor, "particles": n, "dt": dt, "duration": float(t[-1]), "steps": steps,
        "h_over_H0": h[-1] / H0, "theory_h_over_H0": slump_theory(S),
        # The top of the whole pile (+ dx/2): above h where the top is a bowl, as the S <= 0.3
        # piles' is (docs/physics.md, the S = 0.2 pile below the 1-D height); h reads its centre.
        "top_max_over_H0": (float(x_end[:, 1].max()) + 0.5 * dx) / H0,
        "top_per_quarter_R0_band_over_H0": bands, "axis_layers": layers,
        "ratio_to_theory": (1.0 - h[-1] / H0) / (1.0 - slump_theory(S)),
        # The material's thickness on the axis (centre_thickness over R0 / 2): the pile's
        # height as a volume, not as its highest particle near the axis (h above), which
        # also reads the top's particle-scale roughness (docs/physics.md, why the S = 0.1 pile
        # stands above the 1-D height).
        "thickness_over_H0": th[-1] / H0, "thickness_rate_pct_H0_per_s": 100.0 * rate_th / H0,
        "thickness_history": (th / H0).tolist(),
        "top_rate_pct_H0_per_s": 100.0 * rate / H0,
        "kinetic_energy": ke[-1], "kinetic_over_MgH0": ke[-1] / weight_scale,
        # The largest sampled kinetic energy over the last quarter, the rate's window.
        "kinetic_last_quarter_over_MgH0": ke_last,
        "at_rest": slump_at_rest(100.0 * rate / H0, ke_last),
        "rest_rate_pct_H0_per_s": REST_RATE, "rest_kinetic_over_MgH0": REST_KINETIC,
        "fraction_at_yield": float((ratio >= 0.99).mean()),
        "fraction_above_0p9_yield": float((ratio >= 0.9).mean()),
        **plug_measures(depth0, r0, ratio, alpha / yield_strain, S, H0, R0, resolved),
        "flowed_plastic_strain": float(alpha[flowed].mean() / yield_strain) if flowed.any() else float("nan"),
        "nearest_neighbor_mean": float(nearest[np.isfinite(nearest)].mean()),
        "nearest_neighbor_p05": float(np.percentile(nearest, 5)),
        "radius_over_R0": radii[-1] / R0, "spread_theory_radius_over_R0": R_rc / R0,
        "radius_over_spread_theory": radii[-1] / R_rc,
        "spread_theory_h_over_H0": spread_height_theory(R_rc, tau_y) / H0,
        "time_history": t.tolist(), "h_history": (h / H0).tolist(), "ke_history": (ke / weight_scale).tolist(),
        "finite": bool(np.isfinite(h).all()), "wall_s": wall, **_row_fields(solver)
    }


def spread(resolution: int = 4, shallowness: float = 0.25, duration: float = 4.0, elastic_force: str = "variational",
           flow_rate: float = 200.0, viscosity: float = 2.0, friction: float = 1.0, dt_factor: float = 0.9,
           pressure_stiffness: float | None = None, support_radius: float = 2.0, initial_height: float = 2.0,
           samples: int = 200, floor: str = "particles", floor_radius: float = 1.2,
           pressure_force: str = "energy_spiky", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """The spread limit of Roussel & Coussot (2005): a wide, low cylinder of a yield-stress
    material spreads on a rough floor into a pile much wider than tall.

    The scene is built from its theoretical end state. ``shallowness`` ``a = h_RC / R_RC`` is
    the aspect ratio of the shallow no-slip pile ``h(r) = sqrt(2 l (R - r))``, ``l = tau_y /
    (rho g)`` (tau_y = Y / sqrt(2), the shear yield stress), whose centre height is ``h_RC =
    sqrt(2 l R_RC)``: so ``R_RC = 2 l / a^2`` and ``h_RC = 2 l / a``. ``resolution`` is
    particles through ``h_RC`` (dx = h_RC / resolution). The initial cylinder is
    ``initial_height`` x ``h_RC`` tall (default 2, so that all of it has to flow: a part that
    never yields keeps its initial thickness, and the theory's profile is reached only where
    the pile flowed) and holds the theory's volume ``Omega = pi sqrt(128 l / 225) R^(5/2)``
    (the integral of the profile). h_RC = 0.025 m; mu = 20 rho g h_RC (= 10 rho g H_i at the
    default initial height, so the yield strain ``Y / (2 mu)`` is that of the S = 0.1 slump);
    nu = 0.3, the rest as in ``slump``.

    The theory keeps only the basal shear; its radius is the smallest a static shallow pile
    of that volume can have (any static shallow pile has ``h |h'| <= l``), so a pile that
    overshoots in its flow rests wider, never narrower. Radius: the outermost particle +
    dx/2; height: the top of the particles within R_RC / 8 of the axis + dx/2 (as in
    ``slump``); profile: the top of each radial band R_RC / 8 wide (+ dx/2) over the theory
    at the band's middle. ``floor``: as in ``slump`` (``"particles"``, the default: pinned
    layers of the same body under a disc of ``floor_radius`` R_RC). ``pressure_force``: as in
    ``slump``, and so is ``fit_weight``. Volumes over the theory's: ``volume_over_theory`` the scene's as built (its
    particles times dx^3), ``end_volume_over_theory`` the material's at the end (each free
    particle's rest volume times det F)."""
    wp, we = _we()
    _check_floor(floor)
    h_rc = 0.025
    ell = 0.5 * shallowness * h_rc
    R_rc = 2.0 * ell / shallowness**2
    tau_y = RHO * G * ell
    Y = math.sqrt(2.0) * tau_y
    volume = math.pi * math.sqrt(128.0 * ell / 225.0) * R_rc**2.5
    H_i = initial_height * h_rc
    R_i = math.sqrt(volume / (math.pi * H_i))
    dx = h_rc / resolution
    mu = 20.0 * RHO * G * h_rc
    mat = we.Material(mu=mu, lam=1.5 * mu, yield_stress=Y, flow_rate=flow_rate, density=RHO, viscosity=viscosity,
                      elastic_force=elastic_force, pressure_force=pressure_force,
                      pressure_stiffness=pressure_stiffness)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -G, 0.0), support_radius=support_radius * dx, fit_weight=fit_weight)
    from warp_esph.meshes import lattice_points

    pts = lattice_points(np.array([-R_i, 0.0, -R_i]), np.array([R_i, H_i, R_i]), dx)
    pts = pts[np.hypot(pts[:, 0], pts[:, 2]) <= R_i]  # what add_cylinder places
    free = _add_on_floor(b, pts, mat, floor, floor_radius * R_rc, friction, "cylinder0")
    model = b.finalize(device=wp.get_device())
    n = int(free.sum())
    solver = _solver(model)
    dt = dt_factor * model.stable_dt()
    steps = int(round(duration / dt))
    every = max(1, steps // samples)
    a, c = model.state(), model.state()
    times, heights, kes, radii = [], [], [], []

    def sample(state, k):
        if k % every and k != steps:
            return
        x = state.x.numpy().astype(np.float64)[free]
        r = np.hypot(x[:, 0], x[:, 2])
        near = r < R_rc / 8.0
        times.append(k * dt)
        heights.append(float(x[near, 1].max() + 0.5 * dx) if near.any() else float("nan"))
        kes.append(_kinetic(model, state))
        radii.append(float(r.max() + 0.5 * dx))
        if not np.isfinite(x).all():
            return False

    t0 = time.perf_counter()
    a, c = _swap_run(model, solver, a, c, dt, steps, sample)
    wall = time.perf_counter() - t0
    t, h, ke, R = np.array(times), np.array(heights), np.array(kes), np.array(radii)
    last = t >= t[-1] - 0.25 * duration
    rate = np.polyfit(t[last], R[last], 1)[0] if last.sum() > 2 else float("nan")
    x = a.x.numpy().astype(np.float64)[free]
    r = np.hypot(x[:, 0], x[:, 2])
    # The profile against the theory's h(r) = sqrt(2 l (R_RC - r)): the top of each radial
    # band of width R_RC / 8 (+ dx/2), over the theory at the band's middle.
    bands = []
    for k in range(8):
        sel = (r >= k * R_rc / 8.0) & (r < (k + 1) * R_rc / 8.0)
        mid = (k + 0.5) * R_rc / 8.0
        bands.append(float(x[sel, 1].max() + 0.5 * dx) / math.sqrt(2.0 * ell * (R_rc - mid)) if sel.any() else 0.0)
    Fe = a.F.numpy().astype(np.float64)[free]
    ratio = _deviatoric_norm(Fe, mu) / Y
    # The material's volume at the end (rest volumes times det F), against the theory's.
    end_volume = float((model.particle_volume.numpy().astype(np.float64)[free] * np.linalg.det(Fe)).sum())
    weight_scale = float(model.particle_mass.numpy()[free].sum()) * G * h_rc
    return {
        "case": "spread", "shallowness": shallowness, "resolution": resolution, "elastic_force": elastic_force,
        "pressure_force": pressure_force, "floor": floor, "fit_weight": fit_weight,
        "flow_rate": flow_rate, "particles": n, "dt": dt, "duration": float(t[-1]), "steps": steps,
        "initial_height": H_i, "initial_radius": R_i, "yield_length": ell,
        "volume_over_theory": n * dx**3 / volume, "end_volume_over_theory": end_volume / volume,
        "S_initial": math.sqrt(3.0) * tau_y / (RHO * G * H_i),
        "theory_radius": R_rc, "theory_height": h_rc,
        "radius_over_theory": R[-1] / R_rc, "height_over_theory": h[-1] / h_rc,
        "height_over_radius": h[-1] / R[-1],
        "profile_over_theory": bands,
        "radius_rate_pct_per_s": 100.0 * rate / R_rc,
        "kinetic_energy": ke[-1], "kinetic_over_Mgh": ke[-1] / weight_scale,
        "fraction_at_yield": float((ratio >= 0.99).mean()),
        "time_history": t.tolist(), "radius_history": (R / R_rc).tolist(), "height_history": (h / h_rc).tolist(),
        "finite": bool(np.isfinite(R).all()), "wall_s": wall, **_row_fields(solver)
    }


# ------------------------------------------------------------------ incline
def incline(layers: int = 3, load: float = 1.0, floor: str = "ground", duration: float = 1.5, spacing: float = 0.005,
            critical_angle: float = 10.0, length: float = 12.0, width: int = 2, yield_strain: float = 0.005,
            flow_rate: float = 1000.0, viscosity: float = 0.5, friction: float = 5.0, dt_factor: float = 0.9,
            ramp: float = 0.15, samples: int = 40, walls: str = "faces", pressure_force: str = "energy_spiky",
            fit_weight: str = DEFAULT_FIT_WEIGHT, floor_margin: float = 0.0) -> dict:
    """The shear strength of a thin layer: ``layers`` particles thick (h = layers x spacing),
    ``length`` h long, on an incline (gravity tilted by theta in the x-y plane), plane strain
    (``width`` particles between frictionless walls normal to z).

    In a continuum the infinite slope flows iff its basal shear ``rho g h sin theta``
    exceeds the shear yield stress ``tau_y = Y / sqrt(2)`` (docs/validation.md), and then at
    the Bingham surface speed ``rho g sin theta (h - h_p)^2 / (2 eta)``, ``h_p = tau_y /
    (rho g sin theta)``, ``eta = mu / flow_rate`` (tests/test_units.py). ``load`` is
    ``rho g h sin theta / tau_y``: tau_y is set so that the continuum's critical angle is
    ``critical_angle`` degrees, and ``sin theta = load sin(critical_angle)``. The speed is
    read on the top layer of the middle quarter of the strip (away from its free ends).

    ``floor``: ``"ground"``, the static ground collider with Coulomb ``friction`` at the
    layer's base (the floor of ``slump`` and ``spread``); ``"ground_images"``, the same with
    ``add_ground(images=True)``, the plane a rough floor of the fits (docs/physics.md, "The
    ground collider's thin-layer strength"); ``"particles"``, FLOOR_LAYERS
    layers of the same body below the base, pinned (``SceneBuilder.add_particle_floor``): a floor that is
    part of every fit, as the material's own interior would be; ``"elastic_particles"``, the
    same floor made elastic (``add_particle_floor(elastic=True)``). ``floor_margin``: how many
    spacings (a whole number; particle floors only) the particle floors reach past the strip's
    ends, not past its walls (0: under its starting footprint only, where the ends, slumping
    off it, make the middle run in bursts from about 0.8 s; 8 leaves no burst, docs/physics.md,
    "Read against the thinned strip"). mu = Y / (2 yield_strain), nu = 0.3.
    Gravity grows linearly from 0 over the first ``ramp`` seconds (``Model.gravity`` is read
    at every step), so that the load is applied without the dynamic overshoot of a sudden
    release (up to twice the static stress).

    ``walls``: where the frictionless walls normal to z stand. ``"faces"``, at the strip's
    faces (z = 0 and ``width`` x spacing); a plane collider acts on particle centres, so the
    outer rows, half a spacing inside, may move out to it and the strip widen by one
    spacing. ``"centres"``, through the outer rows' centres: the strip cannot widen
    (docs/physics.md, thin layers in shear: widening lets the layers close up and stop).
    ``pressure_force``: the material's (``Material.pressure_force``), its default k_p.
    ``fit_weight``: ``SceneBuilder(fit_weight=)``.

    The strip thins as its free ends slump and its middle lengthens, and near yield B goes as
    (h - h_p)^2, so the nominal ``bingham_surface_speed`` is no reference for a strip that has
    thinned. ``thickness`` is the middle quarter's at the end, h_eff = h x the top layer's
    mean height over its start (the last three samples, those of ``top_speed``: a uniform
    stretch scales every height above the base alike); ``thinned_bingham_surface_speed`` is
    B(h_eff), the Bingham surface speed of a layer that thick (the same tau_y, slope and
    eta; 0 at or below ``plug_thickness`` h_p), the speed at which a continuum layer of it
    flows and which falls to 0 as it comes to rest; ``height_ratio_history``, the top's
    height over its start at each sample."""
    wp, we = _we()
    _check_floor(floor)
    if walls not in INCLINE_WALLS:
        raise ValueError(f"walls = {walls!r} is not allowed: one of {INCLINE_WALLS}")
    from warp_esph import checks

    margin = checks.non_negative("floor_margin", floor_margin)
    if margin != math.floor(margin):
        # The floor is on the strip's lattice: 2.5 reached 2 spacings, recorded as 2.5.
        raise ValueError(f"floor_margin = {checks.shorten(floor_margin)!r} is not allowed: must be a whole number of spacings (the floor "
                         "lies on the strip's lattice)")
    if margin and floor not in PARTICLE_FLOORS:
        # The ground collider has no edge to reach past: the margin was dropped, the row recorded it.
        raise ValueError(f"floor_margin = {checks.shorten(floor_margin)!r} is not allowed with floor = {floor!r}: it is how far "
                         f"a particle floor reaches past the strip's ends; give floor one of {', '.join(map(repr, PARTICLE_FLOORS))}, "
                         "or leave floor_margin at 0")
    dx = spacing
    h = layers * dx
    tau_y = RHO * G * h * math.sin(math.radians(critical_angle))
    Y = math.sqrt(2.0) * tau_y
    mu = Y / (2.0 * yield_strain)
    s = load * math.sin(math.radians(critical_angle))
    if not 0.0 < s < 1.0:
        raise ValueError(f"load = {load!r} is not allowed: sin(theta) = load sin(critical_angle) must be in (0, 1)")
    theta = math.asin(s)
    mat = we.Material(mu=mu, lam=1.5 * mu, yield_stress=Y, flow_rate=flow_rate, density=RHO, viscosity=viscosity,
                      pressure_force=pressure_force)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0) if ramp > 0.0 else (G * s, -G * math.cos(theta), 0.0),
                        fit_weight=fit_weight)
    L = length * h
    W = width * dx
    b.add_box((L / 2.0, h / 2.0, W / 2.0), (L, h, W), mat, name="layer")
    if floor in PARTICLE_FLOORS:
        # The walls normal to z bound the strip, its ends are free: the floor reaches past
        # them by floor_margin spacings along x only (not past the walls, where it would
        # add only pinned particles to the neighbour search).
        try:
            b.add_particle_floor("layer", margin=margin * dx, where=lambda p: (p[:, 2] > 0.0) & (p[:, 2] < W), layers=FLOOR_LAYERS, name="floor", elastic=floor == "elastic_particles",
                                 ghost=floor in ("ghost_particles", "slip_ghost_particles"), slip=floor == "slip_ghost_particles")
        except ValueError as e:
            # The builder's margin is in metres ('margin = 5000.0' for floor_margin = 1e6 spacings).
            if not str(e).startswith("margin = "):
                raise
            raise ValueError(f"floor_margin = {checks.shorten(floor_margin)!r} is not allowed: "
                             f"{str(e).split(' is not allowed: ', 1)[1]}") from None
    else:
        _add_ground(b, floor, friction)
    inset = 0.5 * dx if walls == "centres" else 0.0
    b.add_plane((0.0, 0.0, 1.0), inset, 0.0)
    b.add_plane((0.0, 0.0, -1.0), -(W - inset), 0.0)
    model = b.finalize(device=wp.get_device())
    solver = _solver(model)
    dt = dt_factor * model.stable_dt()
    steps = int(round(duration / dt))
    every = max(1, steps // samples)
    x0 = model.particle_x0.astype(np.float64)
    middle = (np.abs(x0[:, 0] - L / 2.0) < L / 8.0) & (x0[:, 1] > 0.0)
    top = middle & (x0[:, 1] > h - dx)
    a, c = model.state(), model.state()
    times, speeds, heights = [], [], []
    g_full = (G * s, -G * math.cos(theta), 0.0)

    def sample(state, k):
        f = min((k + 1) * dt / ramp, 1.0) if ramp > 0.0 else 1.0
        model.gravity = tuple(f * g for g in g_full)
        if k % every and k != steps:
            return
        times.append(k * dt)
        speeds.append(float(state.v.numpy()[top, 0].astype(np.float64).mean()))
        heights.append(float(state.x.numpy()[top, 1].astype(np.float64).mean()))

    t0 = time.perf_counter()
    a, c = _swap_run(model, solver, a, c, dt, steps, sample)
    wall = time.perf_counter() - t0
    x_end = a.x.numpy().astype(np.float64)
    eta = mu / flow_rate
    h_p = tau_y / (RHO * G * s)
    bingham = RHO * G * s * max(h - h_p, 0.0) ** 2 / (2.0 * eta)
    v = np.array(speeds)
    k23 = (2 * len(v)) // 3
    h_eff = h * float(np.mean(heights[-3:])) / float(x0[top, 1].mean())
    bingham_thinned = RHO * G * s * max(h_eff - h_p, 0.0) ** 2 / (2.0 * eta)
    return {
        "case": "incline", "layers": layers, "load": load, "floor": floor, "fit_weight": fit_weight,
        "theta_deg": math.degrees(theta),
        "particles": model.particle_count, "dt": dt, "steps": steps, "duration": float(times[-1]),
        "tau_y": tau_y, "bingham_surface_speed": bingham, "floor_margin": margin,
        "thickness": h_eff, "plug_thickness": h_p, "thinned_bingham_surface_speed": bingham_thinned,
        # The top's speed at the end and at two thirds of the run (mean of 3 samples each):
        # a flowing layer keeps it, a stopping one loses it.
        "top_speed": float(v[-3:].mean()), "top_speed_two_thirds": float(v[max(k23 - 1, 0):k23 + 2].mean()),
        "time_history": times, "speed_history": speeds,
        "height_ratio_history": [y / float(x0[top, 1].mean()) for y in heights], "finite": bool(np.isfinite(v).all()), "wall_s": wall,
        # At the end, over their initial values (both 1 while the strip keeps its shape): the
        # top layer's height above the base, and the strip's width (the mean distance from
        # its mid-plane in z) over the middle quarter.
        "top_height_ratio": float(x_end[top, 1].mean() / x0[top, 1].mean()),
        "width_ratio": float(np.abs(x_end[middle, 2] - W / 2.0).mean() / np.abs(x0[middle, 2] - W / 2.0).mean()),
        **_row_fields(solver)
    }


# ---------------------------------------------------------------------- bar
def bar_frequency(resolution: int = 4, elastic_force: str = "variational", slenderness: int = 10,
                  periods: float = 3.2, strain: float = 1.0e-3, E: float = 1.0e5, nu: float = 0.3, fit: str | None = None, hourglass: float | None = None,
                  deformation: str = "incremental", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """Free-free bar, ``resolution`` x ``resolution`` particles across, ``slenderness`` times
    as long, pressure off, no gravity, started in its first longitudinal mode
    (``v = strain c cos(pi X / L)``). The frequency is read from the upward zero crossings
    of the end-to-end length; theory f = c / (2 L), c = sqrt(E / rho), L = the bar's
    material length (particles x dx). ``fit_weight``: ``SceneBuilder(fit_weight=)``, as in
    every elastic case."""
    wp, we = _we()
    dx = 0.01
    n, nl = resolution, resolution * slenderness
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=0.0, elastic_force=elastic_force,
                                 deformation=deformation)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    L = nl * dx
    b.add_box((L / 2, 0.0, 0.0), (L, n * dx, n * dx), mat)
    model = b.finalize(device=wp.get_device())
    x0 = model.particle_x0.astype(np.float64)
    X = x0[:, 0] - x0[:, 0].min() + 0.5 * dx
    c_bar = math.sqrt(E / RHO)
    f_theory = c_bar / (2.0 * L)
    v = np.zeros_like(x0)
    v[:, 0] = strain * c_bar * np.cos(math.pi * X / L)
    a, c = model.state(), model.state()
    a.v.assign(v)
    left = x0[:, 0] < x0[:, 0].min() + 0.5 * dx
    right = x0[:, 0] > x0[:, 0].max() - 0.5 * dx
    solver = _solver(model, fit=fit, hourglass=hourglass)
    dt = solver.stable_dt()
    steps = int(periods / f_theory / dt)
    lengths = []

    def sample(state, k):
        x = state.x.numpy()
        lengths.append(float(x[right, 0].mean() - x[left, 0].mean()))

    _swap_run(model, solver, a, c, dt, steps, sample)
    s = np.array(lengths) - np.mean(lengths)
    up = np.nonzero((s[:-1] < 0.0) & (s[1:] >= 0.0))[0]
    # Linear interpolation of each crossing between its two samples.
    tc = (up + s[up] / (s[up] - s[up + 1]) + 1.0) * dt
    f = (len(tc) - 1) / (tc[-1] - tc[0]) if len(tc) >= 2 else float("nan")
    return {"case": "bar", "resolution": n, "elastic_force": elastic_force, "fit_weight": fit_weight,
            "particles": model.particle_count,
            "frequency": f, "theory": f_theory, "ratio": f / f_theory, "periods_measured": len(tc) - 1,
            **_row_fields(solver)}


# --------------------------------------------------------------------- beam
def beam_deflection(resolution: int = 6, elastic_force: str = "variational", span_over_thickness: int = 10,
                    periods: float = 3.0, nu: float = 0.3, deflection_over_thickness: float = 0.03,
                    kappa: float = 0.85, dtype: str = "float32", fit: str | None = None,
                    hourglass: float | None = None, deformation: str = "incremental", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """A square beam ``resolution`` particles thick on two supports under its own weight
    (``fit``, ``hourglass``: the solver's incremental fit and hourglass control,
    ``Solver(fit=..., hourglass=...)``; None: the default, ``Model.solver_choice``).

    The supports are two frictionless box colliders one particle column wide under the end
    columns (span L between their centres: a simply supported beam with dx/2 overhangs).
    E is chosen so that the Euler-Bernoulli deflection is ``deflection_over_thickness`` of
    the thickness (small strain). Pressure off, no viscosity; the static deflection is found
    by dynamic relaxation with c = 1.4 omega_1 (omega_1 the Euler-Bernoulli first bending
    frequency) over ``periods`` of it. Deflection: mean height of the mid-span column
    against the mean of the two support columns, from the start.
    Theory (Timoshenko): 5 q L^4 / (384 E I) + q L^2 / (8 kappa G A). ``dtype``:
    ``"float32"`` or ``"float64"``."""
    wp, we = _we()
    scalar = _lab_dtype(wp, dtype)
    n = resolution
    t = 0.04
    dx = t / n
    cols = n * span_over_thickness  # even: a mid-span column
    L = cols * dx
    A, I = t * t, t**4 / 12.0
    q = RHO * G * A
    E = 5.0 * q * L**4 / (384.0 * I) / (deflection_over_thickness * t)
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=0.0, elastic_force=elastic_force,
                                 deformation=deformation)
    Gs = mat.mu
    theory_eb = 5.0 * q * L**4 / (384.0 * E * I)
    theory = theory_eb + q * L**2 / (8.0 * kappa * Gs * A)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -G, 0.0), fit_weight=fit_weight)
    # The bottom layer starts on the supports' top faces (y = 0).
    b.add_box((0.0, t / 2.0 - dx / 2.0, 0.0), ((cols + 1) * dx, t, t), mat)
    for xs in (-L / 2.0, L / 2.0):
        b.add_box_collider((xs, -0.5, 0.0), (0.5 * dx * 0.999, 0.5, 1.0), friction=0.0)
    model = b.finalize(device=wp.get_device(), dtype=scalar)
    x0 = model.particle_x0.astype(np.float64)
    mid = np.abs(x0[:, 0]) < 0.25 * dx
    ends = np.abs(np.abs(x0[:, 0]) - L / 2.0) < 0.25 * dx
    omega1 = (math.pi / L) ** 2 * math.sqrt(E * I / (RHO * A))
    damping = 1.4 * omega1
    solver = _solver(model, fit=fit, hourglass=hourglass)
    dt = solver.stable_dt()
    steps = int(periods * 2.0 * math.pi / omega1 / dt)
    factor = math.exp(-damping * dt)
    hist_t, hist_d = [], []
    every = max(1, steps // 200)

    def deflection(x):
        return float((x0[mid, 1].mean() - x[mid, 1].mean()) - (x0[ends, 1].mean() - x[ends, 1].mean()))

    def after(state, k):
        _damp(state, factor)
        if k % every == 0 or k == steps:
            hist_t.append(k * dt)
            hist_d.append(deflection(state.x.numpy().astype(np.float64)))

    a, c = model.state(), model.state()
    a, c = _swap_run(model, solver, a, c, dt, steps, after)
    ht, hd = np.array(hist_t), np.array(hist_d)
    last = ht >= ht[-1] - 0.1 * ht[-1]
    rate = np.polyfit(ht[last], hd[last], 1)[0]
    ke = _kinetic(model, a)
    # Relaxed, the kinetic energy is round-off; a beam that broke up keeps moving.
    blew_up = bool(not math.isfinite(ke) or ke > 1e-3 * float(model.particle_mass.numpy().sum()) * G * theory)
    return {"case": "beam", "resolution": n, "elastic_force": elastic_force, "fit_weight": fit_weight, "fit": solver.fit,
            "hourglass": solver.hourglass,
            "particles": model.particle_count, "span_over_thickness": span_over_thickness, "deflection": hd[-1], "theory": theory,
            "theory_euler_bernoulli": theory_eb, "ratio": hd[-1] / theory,
            "residual_rate_pct_per_s": 100.0 * rate / theory, "kinetic_energy": ke, "blew_up": blew_up,
            "t": ht.tolist(), "deflection_over_theory": (hd / theory).tolist(), **_row_fields(solver)}


# ------------------------------------------------------------------- column
#: The floors a free-standing column stands on (``_free_column``).
COLUMN_FLOORS = ("ground", "slip_ghost_particles", TRESCA)


def _free_column(we, mat, n: int, aspect: int, dx: float, dtype: str = "float32", floor: str = "ground",
                 fit_weight: str = DEFAULT_FIT_WEIGHT, shear_cap: float = 1.0):
    """A square column of ``mat``, ``n`` particles across and ``aspect`` times as tall, standing
    on a frictionless floor (laterally free). Returns the model, its height, the initial
    positions, the masks of its top and bottom layers and of its particles (not the floor's)
    and the distance between the top and bottom layers' centres.

    ``floor="ground"``: the frictionless ground collider at the bottom layer's centres
    (y = dx / 2), where the collider holds a particle: a ground at the box's face (y = 0) let
    the column fall half a spacing first, rigidly, and land with its weight applied at once
    (with gravity ramped over 4 axial periods, at 4 across it landed as the ramp ended).
    ``"slip_ghost_particles"``: the slip ghost floor (``add_particle_floor(ghost=True,
    slip=True)``, two spacings wider than the column), whose wall plane is the box's face:
    the bottom layer is fitted two-sided and slides freely. ``TRESCA``: the Tresca ground at
    the box's face (its images mirror the lattice there, so the bottom layer is fitted
    two-sided), holding the base up to ``shear_cap`` times ``mat``'s shear yield stress."""
    if floor not in COLUMN_FLOORS:
        raise ValueError(f"floor = {floor!r} is not allowed: must be one of {', '.join(map(repr, COLUMN_FLOORS))}")
    H = n * aspect * dx
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -G, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, H / 2.0, 0.0), (n * dx, H, n * dx), mat, name="column")
    count = b.particle_count
    if floor == "ground":
        b.add_ground(0.5 * dx, friction=0.0)
    elif floor == TRESCA:
        _add_ground(b, floor, 0.0, shear_cap)
    else:
        b.add_particle_floor("column", margin=2.0 * dx, layers=FLOOR_LAYERS, ghost=True, slip=True)
    wp = _we()[0]
    model = b.finalize(device=wp.get_device(), dtype=_lab_dtype(wp, dtype))
    x0 = model.particle_x0.astype(np.float64)
    free = np.arange(model.particle_count) < count
    top = free & (x0[:, 1] > x0[free, 1].max() - 0.5 * dx)
    bottom = free & (x0[:, 1] < x0[free, 1].min() + 0.5 * dx)
    return model, H, x0, top, bottom, free, x0[top, 1].mean() - x0[bottom, 1].mean()


def column_buckling_length(E: float, width: float) -> float:
    """The height at which a square column ``width`` across of Young's modulus ``E`` (density
    ``RHO``) buckles under its own weight, its base held upright and its top free (Greenhill's
    heavy column: ``(7.837 E I / q)^(1/3)``, ``q = rho g A`` its weight per length, I / A =
    width^2 / 12). A frictionless floor holds the base upright as well as a clamp while the
    whole base stays pressed on it: a lean carries no sideways force at the base. Taller
    columns lean under their weight even without yielding (docs/physics.md, "The near-yield
    column's late collapse")."""
    return (7.837 * E * width * width / (12.0 * RHO * G)) ** (1.0 / 3.0)


#: The near-yield column's width in the plan's fixed-width study (m): at aspect 5 and E 1.5e5,
#: 0.79 of ``column_buckling_length``.
NEAR_YIELD_WIDTH = 0.04

#: The spacing of the columns that take no ``width`` (m): each is then ``n`` cm across, so
#: its width and height grow with the resolution.
COLUMN_DX = 0.01


def column_spacing(resolution: int, width: float | None) -> float:
    """The lattice spacing of a column ``resolution`` particles across: ``COLUMN_DX`` without a
    ``width`` (the column grows with the resolution), else ``width / resolution``, so that
    its width, height and ``length_over_buckling`` stay put and the resolutions form a
    convergence study of one column (docs/physics.md, "The near-yield column at a fixed
    width")."""
    if width is None:
        return COLUMN_DX
    from warp_esph import checks

    return checks.positive("width", width) / resolution


def _tilt(state, x0, free, bottom, L0: float, dx: float, tilt: float):
    """Lean the column: each of its particles moved along x by ``tilt dx (h / L0)^2``, h its
    height over the bottom layer's centres (the shape of the heavy column's first buckling
    mode near its base, and a lean the top shows as ``tilt`` spacings)."""
    if tilt:
        x = state.x.numpy()
        h = (x0[free, 1] - x0[bottom, 1].mean()) / L0
        x[free, 0] += tilt * dx * h * h
        state.x.assign(x)


def _lean(x: np.ndarray, top, bottom) -> float:
    """The top layer's sideways offset from the bottom layer's centre (m)."""
    d = x[top][:, [0, 2]].mean(axis=0) - x[bottom][:, [0, 2]].mean(axis=0)
    return float(np.hypot(d[0], d[1]))


#: The Tresca ground's ``shear_cap`` under ``column_settlement``'s elastic column: its material's
#: yield stress is the ground's hold over this (times sqrt 2), some 1e6 x any stress the column
#: carries, so it never flows and the ground holds what it held the plastic column's base to.
ELASTIC_TWIN_CAP = 1.0e-6


def column_settlement(resolution: int = 6, elastic_force: str = "variational", aspect: int = 5,
                      E: float = 1.5e5, nu: float = 0.3, periods: float = 4.0, fit: str | None = None, hourglass: float | None = None,
                  deformation: str = "incremental", pressure_stiffness: float | None = 0.0, floor: str = "ground",
                  fit_weight: str = DEFAULT_FIT_WEIGHT, tilt: float = 0.0, width: float | None = None,
                  shear_cap_pa: float | None = None) -> dict:
    """A free-standing square column, ``resolution`` particles across and ``aspect`` times as
    tall (``width``: its width in m, the spacing ``width / resolution``; None: spacing 0.01 m,
    ``column_spacing``), on a frictionless floor (laterally free; ``floor``: ``_free_column``'s), pressure off
    (``pressure_stiffness``; None: the material's default SPH pressure, which stiffens it), relaxed dynamically. The
    shortening between the centres of the top and bottom layers, against
    ``rho g L (L - dx) / (2 E)`` (the continuum ``rho g L^2 / (2 E)`` integrated between
    those centres). ``tilt``: an initial lean of the top, in spacings (``_tilt``); ``lean``
    is the top's at the end, in spacings, and ``length_over_buckling`` the column's height
    over ``column_buckling_length``: past 1 the lean grows (docs/physics.md, "The near-yield
    column's late collapse"). ``shear_cap_pa``: on the Tresca ground (``floor=TRESCA``; required
    there, refused elsewhere) its hold in Pa: the elastic column has no shear yield stress to
    scale it, so it is the plastic column's (``near_yield_column``'s elastic reference), as the
    continuum's elastic twin keeps its cap in Pa (``benchmarks.mpm_slump.near_yield_column``);
    the column's material gets a yield stress it never reaches (``ELASTIC_TWIN_CAP``)."""
    wp, we = _we()
    n = resolution
    dx = column_spacing(n, width)
    from warp_esph import checks

    tilt = checks.number("tilt", tilt)
    yielding = {}
    if floor == TRESCA:
        if shear_cap_pa is None:
            raise ValueError(f"shear_cap_pa = None is not allowed with floor = {TRESCA!r}: the elastic column has no "
                             "shear yield stress to scale the Tresca ground's hold; give the hold in Pa")
        cap = checks.positive("shear_cap_pa", shear_cap_pa)
        if cap > E:
            # Above the column's own stiffness no hold is a plastic column's, and the twin's
            # scaled yield stress (cap / ELASTIC_TWIN_CAP) would leave float32's range.
            raise ValueError(f"shear_cap_pa = {checks.shorten(shear_cap_pa)!r} is not allowed: must be in (0, E] = "
                             f"(0, {E:g}] Pa, the elastic column's Young's modulus (the plastic column's shear yield "
                             "stress is what it stands for)")
        yielding = {"yield_stress": math.sqrt(2.0) * cap / ELASTIC_TWIN_CAP}
    elif shear_cap_pa is not None:
        raise ValueError(f"shear_cap_pa = {checks.shorten(shear_cap_pa)!r} is not allowed with floor = {floor!r}: it is "
                         f"the Tresca ground's hold; give floor = {TRESCA!r} or leave shear_cap_pa at None")
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=pressure_stiffness, elastic_force=elastic_force,
                                 deformation=deformation, **yielding)
    model, H, x0, top, bottom, free, L0 = _free_column(we, mat, n, aspect, dx, floor=floor, fit_weight=fit_weight,
                                                       shear_cap=ELASTIC_TWIN_CAP)
    theory = RHO * G * H * (H - dx) / (2.0 * E)
    omega = 0.5 * math.pi * math.sqrt(E / RHO) / H  # fixed-free axial mode
    solver = _solver(model, fit=fit, hourglass=hourglass)
    dt = solver.stable_dt()
    steps = int(periods * 2.0 * math.pi / omega / dt)
    factor = math.exp(-1.4 * omega * dt)
    hist = []

    def after(state, k):
        _damp(state, factor)
        if k > 0.9 * steps:
            x = state.x.numpy().astype(np.float64)
            hist.append((k * dt, L0 - (x[top, 1].mean() - x[bottom, 1].mean())))

    a, c = model.state(), model.state()
    _tilt(a, x0, free, bottom, L0, dx, tilt)
    a, c = _swap_run(model, solver, a, c, dt, steps, after)
    h = np.array(hist)
    rate = np.polyfit(h[:, 0], h[:, 1], 1)[0]
    return {"case": "column", "resolution": n, "elastic_force": elastic_force, "fit_weight": fit_weight,
            **({"width": width} if width is not None else {}), "particles": model.particle_count, "tilt": tilt, "lean": _lean(a.x.numpy().astype(np.float64), top, bottom) / dx,
            "length_over_buckling": H / column_buckling_length(E, n * dx),
            "shortening": h[-1, 1], "theory": theory, "ratio": h[-1, 1] / theory,
            "residual_rate_pct_per_s": 100.0 * rate / theory, "kinetic_energy": _kinetic(model, a),
            **_row_fields(solver)}


def near_yield_column_theory(yield_depth: float) -> float:
    """Plastic shortening over L of a laterally free column whose weight exceeds the uniaxial
    yield stress only below the depth ``z0 = yield_depth L`` (``sigma_y = rho g z0``), by the
    slump's 1-D analysis: a layer at depth ``z > z0`` spreads at constant volume until it
    carries ``sigma_y``, so its thickness falls by ``1 - z0 / z``; integrated from z0 to L,
    ``(1 - z0 / L) - (z0 / L) ln(L / z0)`` (0.0215 at z0 = 0.8 L)."""
    return (1.0 - yield_depth) + yield_depth * math.log(yield_depth)


def near_yield_column(resolution: int = 6, aspect: int = 5, yield_depth: float = 0.8, E: float = 1.5e5,
                      nu: float = 0.3, flow_rate: float = 200.0, periods: float = 36.0, ramp: float = 4.0,
                      elastic_force: str = "variational", pressure_stiffness: float | None = None,
                      dtype: str = "float32", elastic_periods: float = 8.0, floor: str = "ground",
                      tilt: float = 0.0, width: float | None = None, fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """A free-standing square column (as ``column_settlement``: ``resolution`` across,
    ``aspect`` times as tall, ``width`` m wide or, without one, spacing 0.01 m, frictionless
    ground collider, relaxed dynamically) of a
    yield-stress material whose uniaxial yield stress is the weight above the depth
    ``yield_depth`` L: by the 1-D analysis only the bottom ``1 - yield_depth`` of it yields.
    ``floor``: ``"ground"`` (the collider; its one-sided bottom layer holds the base in,
    docs/physics.md, "The near-yield column"), ``"slip_ghost_particles"`` (a frictionless
    floor the bottom layer is fitted against two-sided; ``_free_column``) or ``TRESCA`` (the
    Tresca ground, fitted two-sided and holding the base up to the shear yield stress, as the
    continuum's Tresca floor, ``benchmarks.mpm_slump.near_yield_column(floor_shear_cap=1)``;
    its elastic reference is held up to the same stress in Pa).
    ``pressure_stiffness``: None, the material's default SPH pressure (the pressure does not
    change the yield condition in uniaxial stress: the sides are free, so the difference of
    the vertical and lateral stresses of ``F`` is the weight's stress either way); 0 switches
    it off, and then float32 columns of 6 and 8 across pair their particles inside the
    yielded base and collapse their core (docs/physics.md, "The near-yield column").

    Measured: where the particles reached the yield stress over the run (the highest one's
    initial depth); the largest peak yield ratio between 0.1 L and 0.5 L deep against the
    weight's uniaxial ``depth / yield_depth`` (1: the unyielded part carries exactly its
    weight); the shortening between the top and bottom layers' centres, its elastic part
    measured on the same column with the yield off (``column_settlement`` with the same
    pressure and the plastic run's fit, over ``elastic_periods``), and the plastic rest against
    ``near_yield_column_theory`` (layers that spread freely and do not restrain each other,
    taken as the upper bound: a base held in, or layers held by the column above, spread less); the top's residual rate over the last tenth, the kinetic energy, and the
    smallest neighbour distance at the end (particle pairing). Gravity rises linearly over
    ``ramp`` periods of the column's axial mode: applied at once, its stress wave doubles the
    weight's stress at the base and yields the column far above ``yield_depth``, which the
    static analysis does not describe. The run lasts ``periods`` axial periods: the yielded
    base creeps to rest over seconds (6 across: 0.44 x the theory at 12 periods, at rest at
    0.50 x by 36). ``dtype``: ``"float32"`` or ``"float64"``. ``tilt``: an initial lean of the
    top, in spacings (``column_settlement``'s); ``lean`` is the top's at the end, in spacings,
    ``lean_efolds_per_period`` its growth over the last tenth (log per axial period), and
    ``length_over_buckling`` the column's height over ``column_buckling_length``: without a
    ``width`` the column of E 1.5e5 is past it from 8 across (dx 0.01 m: its width grows with
    the resolution), and on its yielded base it leans and topples well before (docs/physics.md,
    "The near-yield column's late collapse"); ``width=0.04`` keeps it at 0.79 at every
    resolution ("The near-yield column at a fixed width"); ``dx`` and ``height`` are the scene's
    spacing and the column's height (m), and a run given a ``width`` records it. ``fit_weight``:
    ``SceneBuilder(fit_weight=)``, the weight of the incremental fit, for the plastic run and
    its elastic reference alike (the row records the model's)."""
    wp, we = _we()
    from warp_esph import checks

    _lab_dtype(wp, dtype)  # refused before the elastic reference run
    tilt = checks.number("tilt", tilt)
    dx = column_spacing(resolution, width)
    n, nh = resolution, resolution * aspect
    H = nh * dx
    sigma_y = RHO * G * yield_depth * H
    Y = math.sqrt(2.0 / 3.0) * sigma_y
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=pressure_stiffness, yield_stress=Y,
                                 flow_rate=flow_rate, elastic_force=elastic_force)
    mu = mat.mu
    model, H, x0, top, bottom, free, L0 = _free_column(we, mat, n, aspect, dx, dtype=dtype, floor=floor,
                                                       fit_weight=fit_weight)
    # Initial depth of each particle over L (a floor's particles: below 1, never yielded).
    depth = (x0[:, 1].max() + 0.5 * dx - x0[:, 1]) / H
    elastic = RHO * G * H * (H - dx) / (2.0 * E)
    plastic = near_yield_column_theory(yield_depth) * (H - dx)
    omega = 0.5 * math.pi * math.sqrt(E / RHO) / H  # fixed-free axial mode
    solver = _solver(model)
    dt = model.stable_dt()
    steps = int(periods * 2.0 * math.pi / omega / dt)
    factor = math.exp(-1.4 * omega * dt)
    peak = np.zeros(model.particle_count)
    hist = []

    ramp_time = ramp * 2.0 * math.pi / omega

    def after(state, k):
        _damp(state, factor)
        if ramp_time > 0.0:
            model.gravity = (0.0, -G * min(1.0, (k + 1) * dt / ramp_time), 0.0)
        if k % 10 == 0 or k == steps:
            np.maximum(peak, _deviatoric_norm(state.F.numpy(), mu) / Y, out=peak)
        if k > 0.9 * steps:
            x = state.x.numpy().astype(np.float64)
            hist.append((k * dt, L0 - (x[top, 1].mean() - x[bottom, 1].mean()), _lean(x, top, bottom)))

    if ramp_time > 0.0:
        model.gravity = (0.0, -G * dt / ramp_time, 0.0)
    a, c = model.state(), model.state()
    _tilt(a, x0, free, bottom, L0, dx, tilt)
    a, c = _swap_run(model, solver, a, c, dt, steps, after)
    h = np.array(hist)
    rate = np.polyfit(h[:, 0], h[:, 1], 1)[0]
    yielded = (peak >= 0.99) & free
    ratio_end = _deviatoric_norm(a.F.numpy(), mu) / Y
    upper = (depth >= 0.1) & (depth < 0.5)
    d2 = solver.scratch.neighbor_d2.numpy().astype(np.float64)
    cnt = a.neighbor_count.numpy()
    d2 = np.where(np.arange(d2.shape[1])[None, :] < cnt[:, None], d2, np.inf)
    # The same column with the yield off: the elastic part the scene's pressure and fit give.
    ref = column_settlement(n, elastic_force, aspect=aspect, E=E, nu=nu, fit=solver.fit, hourglass=solver.hourglass,
                            pressure_stiffness=mat.pressure_stiffness, periods=elastic_periods, floor=floor, width=width,
                            fit_weight=model.fit_weight, shear_cap_pa=mat.shear_yield_stress if floor == TRESCA else None)
    plastic_measured = h[-1, 1] - ref["shortening"]
    return {"case": "near_yield_column", "resolution": n, "elastic_force": elastic_force, "particles": model.particle_count,
            "pressure_stiffness": mat.pressure_stiffness, "dtype": dtype, "fit": solver.fit,
            "fit_weight": model.fit_weight, **({"width": width} if width is not None else {}), "dx": dx, "height": H,
            "yield_depth": yield_depth, "tilt": tilt, "lean": h[-1, 2] / dx,
            # A lean of round-off size has no rate worth fitting (its log is noise).
            "lean_efolds_per_period": float(np.polyfit(h[:, 0], np.log(np.maximum(h[:, 2], 1e-12)), 1)[0])
            * 2.0 * math.pi / omega,
            "length_over_buckling": H / column_buckling_length(E, n * dx),
            "shortening": h[-1, 1], "theory": elastic + plastic,
            "theory_elastic": elastic, "theory_plastic": plastic, "ratio": h[-1, 1] / (elastic + plastic),
            "elastic_measured": ref["shortening"], "elastic_residual_rate_pct_per_s": ref["residual_rate_pct_per_s"],
            "plastic_measured": plastic_measured,
            "plastic_over_theory": plastic_measured / plastic,
            "highest_yielded_depth": float(depth[yielded].min()) if yielded.any() else float("nan"),
            "fraction_yielded": float(yielded[free].mean()), "floor": floor,
            "top_half_max_ratio": float(ratio_end[depth < 0.5].max()),
            "upper_peak_over_weight": float((peak[upper] / (depth[upper] / yield_depth)).max()),
            "nearest_neighbour_min": float(np.sqrt(d2.min())) / dx,
            "residual_rate_pct_per_s": 100.0 * rate / (elastic + plastic), "kinetic_energy": _kinetic(model, a),
            "kinetic_over_weight": _kinetic(model, a) / (float(model.particle_mass.numpy().sum()) * G * (elastic + plastic)),
            "duration": steps * dt,
            # Per tenth of the initial depth (top first): the fraction of its particles that
            # reached the yield stress, and the largest yield ratio any of them reached.
            "yielded_by_depth": [float(yielded[(depth >= k / 10) & (depth < (k + 1) / 10)].mean()) for k in range(10)],
            "peak_ratio_by_depth": [float(peak[(depth >= k / 10) & (depth < (k + 1) / 10)].max()) for k in range(10)],
            **_row_fields(solver)}


# ------------------------------------------------------------------ poisson
def poisson_compression(resolution: int = 6, elastic_force: str = "variational", strain: float = 1.0e-3,
                        E: float = 1.0e5, nu: float = 0.3, aspect: int = 2, periods: float = 20.0, fit: str | None = None, hourglass: float | None = None,
                  deformation: str = "incremental", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """A block ``resolution`` particles across and ``aspect`` times as long, compressed along
    x by ``strain`` (positions and F together) and held between two frictionless planes
    at its end layers; no gravity, pressure off, relaxed dynamically. Measured: the lateral
    strain of the middle third (centres of the side layers) against ``nu strain``, and the
    plate force (internal force on an end layer) against ``E A strain``, A = (n dx)^2."""
    wp, we = _we()
    dx = 0.01
    n, nl = resolution, resolution * aspect
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=0.0, elastic_force=elastic_force,
                                 deformation=deformation)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, 0.0, 0.0), (nl * dx, n * dx, n * dx), mat)
    model = b.finalize(device=wp.get_device())
    x0 = model.particle_x0.astype(np.float64)
    S = np.diag([1.0 - strain, 1.0, 1.0])
    xs = x0 @ S.T
    a_end = xs[:, 0].max()
    b.add_plane((1.0, 0.0, 0.0), -a_end, friction=0.0)
    b.add_plane((-1.0, 0.0, 0.0), -a_end, friction=0.0)
    with warnings.catch_warnings():
        # The builder's box is the rest shape, its end layers ``strain`` of their distance
        # inside the plates; finalize places them on the plates (warning), but this start is
        # the strained box below, so the rest shape is put back.
        warnings.filterwarnings("ignore", r"body .* start inside plane", UserWarning)
        model = b.finalize(device=wp.get_device())
    model.particle_x0[:] = x0
    model.compute_rest_density()
    a, c = model.state(), model.state()
    a.x.assign(xs)
    a.F.assign(np.tile(S, (model.particle_count, 1, 1)))
    middle = np.abs(x0[:, 0]) <= (nl * dx) / 6.0
    W0 = x0[:, 1].max() - x0[:, 1].min()
    sides = [(middle & (x0[:, k] > x0[:, k].max() - 0.5 * dx), middle & (x0[:, k] < x0[:, k].min() + 0.5 * dx)) for k in (1, 2)]
    end = x0[:, 0] > x0[:, 0].max() - 0.5 * dx
    c_p = mat.p_wave_speed
    omega = math.pi * c_p / (n * dx)
    solver = _solver(model, fit=fit, hourglass=hourglass)
    dt = solver.stable_dt()
    steps = int(periods * 2.0 * math.pi / omega / dt)
    factor = math.exp(-omega * dt)
    hist = []

    def after(state, k):
        _damp(state, factor)
        if k > 0.9 * steps:
            x = state.x.numpy().astype(np.float64)
            lat = np.mean([(x[p, k_].mean() - x[m, k_].mean()) / W0 - 1.0 for (p, m), k_ in zip(sides, (1, 2))])
            hist.append((k * dt, lat, float(state.force.numpy()[end, 0].sum())))

    a, c = _swap_run(model, solver, a, c, dt, steps, after)
    h = np.array(hist)
    lat, force = h[-1, 1], h[-1, 2]
    area = (n * dx) ** 2
    return {"case": "poisson", "resolution": n, "elastic_force": elastic_force, "fit_weight": fit_weight,
            "particles": model.particle_count,
            "lateral_strain": lat, "poisson_measured": lat / strain, "poisson_theory": nu,
            "poisson_ratio": lat / strain / nu, "force": force, "force_theory": E * area * strain,
            "young_ratio": force / (E * area * strain),
            "lateral_rate_per_s": float(np.polyfit(h[:, 0], h[:, 1], 1)[0]) / strain,
            "kinetic_energy": _kinetic(model, a), **_row_fields(solver)}


# ------------------------------------------------------------------ lab tests with tools
def _lab_resolution(value, minimum: int, multiple: int = 1, why: str = "") -> int:
    """A lab test's ``resolution``: an integer >= ``minimum`` and a multiple of ``multiple``,
    else a ``ValueError`` naming it (a resolution of 0 was a ZeroDivisionError, and one too
    coarse for the test's measure a result of NaN or 0 without a word)."""
    from warp_esph import checks

    n = checks.positive_int("resolution", value, minimum=minimum)
    if n % multiple:
        raise ValueError(f"resolution = {value!r} is not allowed: must be a multiple of {multiple}{why}")
    return n


def _lab_dtype(wp, value):
    """A lab test's ``dtype``: ``"float32"`` or ``"float64"``, as Warp's scalar type."""
    from warp_esph import checks

    return getattr(wp, checks.choice("dtype", value, ("float32", "float64")))


def _open_interval(name: str, value, lo: float, hi: float, why: str = "") -> float:
    """A number strictly between ``lo`` and ``hi``, else a ``ValueError`` naming it."""
    from warp_esph import checks

    v = checks.number(name, value)
    if not lo < v < hi:
        raise ValueError(f"{name} = {value!r} is not allowed: must be in ({lo:g}, {hi:g}){why}")
    return v


def _relaxed_reaction(model, solver, names, load_time: float, hold_time: float, a=None, c=None, every: int = 10,
                      average: int = 100, after=None, viscous: float = 0.0):
    """Step through ``load_time`` (the tools move) and ``hold_time`` (they stay) with kinetic
    damping during the hold (``kinetic_damping`` every ``every`` steps: every particle stopped
    where it is whenever the kinetic energy has dropped since the last check), or, with ``viscous`` = c > 0, mass-proportional damping
    instead (every velocity times exp(-c dt) after each step of the hold: it also holds back
    a slowly growing motion, which kinetic damping, acting only when the energy drops, lets
    grow). Returns the states and, per tool name, the mean reaction force on the material
    over the last ``average`` steps."""
    dt = solver.stable_dt()
    if a is None:
        a, c = model.state(), model.state()
    mass = model.particle_mass.numpy().astype(np.float64)[:, None]
    probe = model.state() if viscous <= 0.0 else None
    t_end = a.time + load_time + hold_time
    t_hold = a.time + load_time
    rows, ke_prev, k = [], 0.0, 0
    while a.time < t_end - 0.5 * dt:
        solver.step(a, c, dt)
        a, c = c, a
        k += 1
        if a.time > t_hold and viscous > 0.0:
            _damp(a, math.exp(-viscous * dt))
        elif a.time > t_hold and k % every == 0:
            ke_prev = kinetic_damping(solver, a, probe, dt, mass, ke_prev)
        r = solver.reaction_forces(a)
        rows.append([r[n][0] for n in names])
        if after is not None:
            after(a)
    f = np.array(rows[-average:], dtype=np.float64).mean(axis=0)
    return a, c, {n: f[i] for i, n in enumerate(names)}


def plate_compression(resolution: int = 8, strain: float = 0.01, E: float = 1.0e5, nu: float = 0.3,
                      dtype: str = "float32", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """Uniaxial compression between two frictionless plane tools (the texture-analyser test
    with slip): a cube ``resolution`` particles across on a fixed plane, the top plane
    lowered by ``strain`` of the lattice height in 0.05 s, then held and relaxed for 0.1 s;
    no gravity, pressure off, variational force. Measured: the top plate's reaction force
    against ``E A eps`` (A: the cube's face, resolution x spacing squared) and the lateral
    strain (centres of the two side layers) against ``nu eps``; at ``nu = 0`` its ratio is NaN.
    ``resolution`` >= 2 (the lateral strain needs two side layers), ``strain`` in (0, 1).
    ``dtype``: ``"float32"`` or ``"float64"``; a strain near float32's resolution of the
    sample's place wants float64 (at 1e-6 and 4 across the lateral ratio read 0.62 in float32,
    for 0.92 at 1 %). ``fit_weight``: ``SceneBuilder(fit_weight=)``."""
    wp, we = _we()
    from warp_esph import tools

    scalar = _lab_dtype(wp, dtype)

    n = _lab_resolution(resolution, 2)
    # 0 read inf x the theory, a negative strain lifted the plate off (force 0), one of 1 or
    # more put the top plate through the bottom one: each a result without a word.
    strain = _open_interval("strain", strain, 0.0, 1.0, " (the share of the sample's height the top plate goes down)")
    dx = 0.08 / n
    H = n * dx
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=0.0, elastic_force="variational")
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, H / 2, 0.0), (H, H, H), mat, name="sample")
    pts = np.concatenate(b._points)
    ylo, yhi = pts[:, 1].min(), pts[:, 1].max()
    d = strain * (yhi - ylo)  # strain of the particle lattice between the plates
    b.add_tool("plane", normal=(0, 1, 0), position=(0, ylo, 0), name="bottom")
    b.add_tool("plane", normal=(0, -1, 0), motion=tools.Keyframes([0.0, 0.05], [(0, yhi, 0), (0, yhi - d, 0)]), name="top")
    model = b.finalize(device=wp.get_device(), dtype=scalar)
    solver = _solver(model)
    a, c, f = _relaxed_reaction(model, solver, ["top", "bottom"], 0.05, 0.10)
    force = 0.5 * (-f["top"][1] + f["bottom"][1])
    xs = pts[:, 0]
    right, left = xs > xs.max() - 0.5 * dx, xs < xs.min() + 0.5 * dx
    x = a.x.numpy().astype(np.float64)
    lateral = (x[right, 0].mean() - x[left, 0].mean()) / (xs[right].mean() - xs[left].mean()) - 1.0
    theory = E * H * H * strain
    return {"case": "plates", "resolution": n, "particles": model.particle_count, "strain": strain, "dtype": dtype,
            "fit_weight": model.fit_weight,
            "force": force, "force_theory": theory, "force_ratio": force / theory,
            "lateral_strain": lateral, "lateral_theory": nu * strain,
            "lateral_ratio": lateral / (nu * strain) if nu else float("nan"),
            "kinetic_energy": _kinetic(model, a), **_row_fields(solver)}


def _plastic_cube(resolution: int, S: float, H0: float, pressure_stiffness, support_radius: float, squeeze: float,
                  load_time: float, fit_weight: str = DEFAULT_FIT_WEIGHT):
    """The slump's material (``plastic_compression``'s docstring) as a cube ``resolution``
    across between two frictionless plane tools, the top one lowered by ``squeeze`` of the span
    between the plates in ``load_time``: ``(model, span, dx, mu, Y, sigma_y)``."""
    wp, we = _we()
    from warp_esph import tools

    dx = H0 / resolution
    sigma_y = S * RHO * G * H0
    Y = sigma_y * math.sqrt(2.0 / 3.0)
    mu = 10.0 * RHO * G * H0
    mat = we.Material(mu=mu, lam=1.5 * mu, yield_stress=Y, flow_rate=200.0, density=RHO, viscosity=2.0,
                      elastic_force="variational", pressure_stiffness=pressure_stiffness)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), support_radius=support_radius * dx, fit_weight=fit_weight)
    b.add_box((0.0, H0 / 2, 0.0), (H0, H0, H0), mat, name="sample")
    pts = np.concatenate(b._points)
    ylo, yhi = pts[:, 1].min(), pts[:, 1].max()
    span = yhi - ylo
    b.add_tool("plane", normal=(0, 1, 0), position=(0, ylo, 0), name="bottom")
    b.add_tool("plane", normal=(0, -1, 0),
               motion=tools.Keyframes([0.0, load_time], [(0, yhi, 0), (0, yhi - squeeze * span, 0)]), name="top")
    return b.finalize(device=wp.get_device()), span, dx, mu, Y, sigma_y


def _interior_axial_and_spacing(x: np.ndarray, F: np.ndarray, mu: float, sigma_y: float):
    """The particles away from the cube's side faces (within half its half-width of the axis),
    their mean elastic deviator's uniaxial pattern (2 mu times its y component less the mean of
    x and z, compressive positive, in sigma_y), and every particle's nearest-neighbour distance."""
    U, s, _ = np.linalg.svd(F)
    ls = np.log(s)
    dev = np.einsum("nij,nj,nkj->nik", U, ls - ls.mean(axis=1, keepdims=True), U)
    half = 0.5 * np.abs(x[:, [0, 2]]).max(axis=0)
    inner = np.all(np.abs(x[:, [0, 2]]) < half, axis=1)
    axial = -2.0 * mu * (dev[inner, 1, 1] - 0.5 * (dev[inner, 0, 0] + dev[inner, 2, 2])).mean() / sigma_y
    d2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return inner, float(axial), np.sqrt(d2.min(axis=1))


def plastic_compression(resolution: int = 8, squeeze: float = 0.25, S: float = 0.2, H0: float = 0.1,
                        load_time: float = 0.5, hold_time: float = 0.2, pressure_stiffness: float | None = None,
                        fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """The slump's material in homogeneous uniaxial flow: a cube ``resolution`` particles across
    (side H0) between two frictionless plane tools, no gravity, the top one lowered by
    ``squeeze`` of the lattice height in ``load_time``, then held ``hold_time`` with
    mass-proportional damping (50 /s) until at rest. The material is ``slump_model``'s at
    ``S`` (mu = 10 rho g H0, lam = 1.5 mu, Y = sqrt(2/3) S rho g H0, flow rate 200 /s,
    viscosity 2, ``pressure_stiffness`` None: the default SPH pressure, 0: off). Measured:
    the plates' mean reaction over the current area (the rest face over 1 - squeeze: the flow
    keeps volume) against the uniaxial yield stress sigma_y = S rho g H0 (docs/physics.md,
    "The S = 0.2 gap, part by part": the method's flow stress after plastic flow, without
    the slump's geometry), and the interior particles' mean elastic deviator along the
    uniaxial pattern (y less the mean of x and z) in sigma_y. ``fit_weight``: ``SceneBuilder(fit_weight=)``."""
    if not 0.0 < squeeze < 1.0:
        raise ValueError(f"squeeze = {squeeze!r} is not allowed: must be in (0, 1)")
    _, we = _we()
    model, _, dx, mu, Y, sigma_y = _plastic_cube(resolution, S, H0, pressure_stiffness, 2.0, squeeze, load_time,
                                                 fit_weight)
    solver = _solver(model)
    a, c, f = _relaxed_reaction(model, solver, ["top", "bottom"], load_time, hold_time, viscous=50.0)
    force = 0.5 * (-f["top"][1] + f["bottom"][1])
    area = H0 * H0 / (1.0 - squeeze)
    x = a.x.numpy().astype(np.float64)
    F = a.F.numpy().astype(np.float64)
    _, axial, nn = _interior_axial_and_spacing(x, F, mu, sigma_y)
    return {"case": "plastic_compression", "resolution": resolution, "squeeze": squeeze,
            "log_strain": -math.log(1.0 - squeeze), "pressure_stiffness": pressure_stiffness, "fit_weight": model.fit_weight,
            "stress_over_sigma_y": float(force / area / sigma_y), "interior_axial_over_sigma_y": axial,
            "particle_yield_ratio_mean": float((_deviatoric_norm(F, mu) / Y).mean()),
            "nearest_neighbor_min": float(nn.min() / dx), "kinetic_energy": _kinetic(model, a), **_row_fields(solver)}


def bingham_uniaxial_stress(S: float, strain_rate: float, H0: float = 0.1, stiffness: float = 10.0,
                            flow_rate: float = 200.0) -> float:
    """The uniaxial stress of the slump's material flowing at ``strain_rate`` (1/s): the uniaxial
    yield stress ``S rho g H0`` plus the extensional viscous stress ``3 eta_p strain_rate``, with
    ``eta_p = mu / flow_rate`` the plastic viscosity of ``Material``'s flow rule (its docstring)."""
    mu = stiffness * RHO * G * H0
    return S * RHO * G * H0 + 3.0 * mu / flow_rate * abs(strain_rate)


def uniaxial_flow(resolution: int = 8, strain: float = 0.75, duration: float = 4.0, S: float = 0.2, H0: float = 0.1,
                  pressure_stiffness: float | None = None, support_radius: float = 2.0, samples: int = 40,
                  fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """The slump's material in sustained uniaxial flow to large strain: a cube ``resolution``
    particles across (side H0), no gravity, between two frictionless plane tools, the top one
    lowered at a constant speed by ``strain`` of the span between the plates' rows in
    ``duration``. The material is ``plastic_compression``'s (flow rate 200 /s, viscosity 2,
    ``pressure_stiffness`` None: the default SPH pressure, 0: off); ``fit_weight`` the model's
    (``SceneBuilder(fit_weight=)``).

    Per sample (the means over the steps since the last one): the log strain of the plates'
    span, the body's mean axial stress by the mean stress theorem (the plates' mean reaction
    times their gap over the body's volume H0^3: exact for the total stress, pressure and
    viscosity included, whatever its distribution, and free of the question where a particle
    body's face lies), the Bingham stress at the span's true strain rate
    (``bingham_uniaxial_stress``), the interior particles' coherent elastic stress (their mean
    deviator's uniaxial pattern, y less the mean of x and z, in sigma_y), their mean yield
    ratio |s| / Y (what each particle's flow rule sees) and the nearest neighbour (min, mean,
    in dx). A continuum carries the Bingham stress throughout; docs/physics.md, "The flow
    stress in sustained uniaxial flow", has what this method carries."""
    if not 0.0 < strain < 1.0:
        raise ValueError(f"strain = {strain!r} is not allowed: must be in (0, 1)")
    if not duration > 0.0:
        raise ValueError(f"duration = {duration!r} is not allowed: must be > 0 (seconds)")
    _, we = _we()
    model, span, dx, mu, Y, sigma_y = _plastic_cube(resolution, S, H0, pressure_stiffness, support_radius, strain,
                                                    duration, fit_weight)
    speed = strain * span / duration
    solver = _solver(model)
    dt = model.stable_dt()
    steps = int(round(duration / dt))
    every = max(1, steps // samples)
    volume = H0**3
    rows, acc = [], []
    a, c = model.state(), model.state()
    for k in range(1, steps + 1):
        solver.step(a, c, dt)
        a, c = c, a
        r = solver.reaction_forces(a)
        gap = span - speed * min(a.time, duration)
        acc.append(0.5 * (-r["top"][0][1] + r["bottom"][0][1]) * gap / volume)
        if k % every and k != steps:
            continue
        x = a.x.numpy().astype(np.float64)
        F = a.F.numpy().astype(np.float64)
        inner, axial, nn = _interior_axial_and_spacing(x, F, mu, sigma_y)
        nn = nn / dx
        rows.append({"time": a.time, "log_strain": -math.log(gap / span),
                     "stress_over_sigma_y": float(np.mean(acc)) / sigma_y,
                     "bingham_over_sigma_y": bingham_uniaxial_stress(S, speed / gap, H0) / sigma_y,
                     "interior_axial_over_sigma_y": axial,
                     "particle_yield_ratio_mean": float((_deviatoric_norm(F, mu) / Y)[inner].mean()),
                     "nearest_neighbor_min": float(nn.min()), "nearest_neighbor_mean": float(nn.mean())})
        acc = []
    return {"case": "uniaxial_flow", "resolution": resolution, "strain": strain, "duration": duration,
            "pressure_stiffness": pressure_stiffness, "support_radius": support_radius, "fit_weight": fit_weight, "dt": dt,
            "history": rows, **_row_fields(solver)}


def hertz_force(E: float, nu: float, R: float, depth: float) -> float:
    """Hertz: a rigid sphere of radius R pressed ``depth`` into an elastic half-space,
    F = 4/3 E* sqrt(R) d^1.5 with E* = E / (1 - nu^2)."""
    return 4.0 / 3.0 * E / (1.0 - nu * nu) * math.sqrt(R) * depth**1.5


def layer_factor(nu: float, chi: float, bonded: bool = True) -> float:
    """F / F_Hertz for a rigid sphere pressed into an elastic layer of thickness h on a rigid
    base, chi = sqrt(R d) / h the contact radius over the thickness: Dimitriadis et al.
    (2002, Biophys. J. 82:2798), 1 - 2 a0 chi / pi + 4 a0^2 chi^2 / pi^2
    - 8 / pi^3 (a0^3 + 4 pi^2 b0 / 15) chi^3, with, for a layer bonded to the base,
    a0 = -(1.2876 - 1.4678 nu + 1.3442 nu^2) / (1 - nu), b0 = (0.6387 - 1.0277 nu
    + 1.5164 nu^2) / (1 - nu), and for one that slides on it freely a0 = -0.347 (3 - 2 nu)
    / (1 - nu), b0 = 0.056 (5 - 2 nu) / (1 - nu). At nu = 0.5 these give the paper's
    incompressible series (bonded 1 + 1.133 chi + 1.283 chi^2 + 0.769 chi^3, free 1 + 0.884
    chi + 0.781 chi^2 + 0.386 chi^3). The chi^4 term is left out: it is below 0.15 % for
    chi < 0.26 (and its sign for bonded layers differs between the paper's general and
    incompressible forms)."""
    if bonded:
        a0 = -(1.2876 - 1.4678 * nu + 1.3442 * nu * nu) / (1.0 - nu)
        b0 = (0.6387 - 1.0277 * nu + 1.5164 * nu * nu) / (1.0 - nu)
    else:
        a0 = -0.347 * (3.0 - 2.0 * nu) / (1.0 - nu)
        b0 = 0.056 * (5.0 - 2.0 * nu) / (1.0 - nu)
    pi = math.pi
    return (1.0 - 2.0 * a0 * chi / pi + 4.0 * a0 * a0 * chi**2 / pi**2
            - 8.0 / pi**3 * (a0**3 + 4.0 * pi * pi * b0 / 15.0) * chi**3)


def sphere_indentation(resolution: int = 8, depths=(0.001, 0.002), E: float = 1.0e5, nu: float = 0.3,
                       R: float = 0.04, hold: float = 0.015, late: float = 0.1, hourglass: float | None = None,
                       width: float = 0.10, height: float = 0.04, fit: str | None = None,
                       deformation: str = "incremental", dtype: str = "float32", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """A frictionless rigid sphere (R = 4 cm) pressed into a block ``width`` x ``height`` x
    ``width`` (default 10 x 4 x 10 cm; ``resolution`` particles across its height) standing on a plane tool that holds its
    base (mu = 2); no gravity, pressure off, variational force. The sphere starts touching
    the top layer's particle centres and is lowered to each of ``depths`` in 0.02 s, then
    held ``hold`` s with kinetic damping; the force is the mean reaction over the last 50
    steps of each hold. At the deepest it is then held ``late`` s longer and the force read
    again: the point-based contact under a sphere is not stable for long without the
    hourglass control (the particle columns under the apex slide sideways between their
    neighbours and the force decays, docs/validation.md), so the first reading is the
    elastic response before that. ``fit``, ``hourglass``: ``Solver(fit=..., hourglass=...)``
    (None: the default, ``Model.solver_choice``: for this elastic block the curvature-corrected
    fit with the control at ``AUTO_HOURGLASS``).

    Theory: Hertz for a half-space (``hertz_force``) times the correction of a layer bonded
    to a rigid base (``layer_factor``), whose thickness is that of the lattice between the
    held base layer's centres (on the plane) and the top layer's (where the sphere pushes):
    h = ``height`` - dx. The contact radius sqrt(R d) is 6-9 mm, so in the 4 cm block chi =
    sqrt(R d) / h is 0.16-0.26 and the layer is 17-28 % stiffer than the half-space. Also
    returned: the ratios to Hertz, to the bonded layer of the full ``height``, to a layer that slides on its base, and
    how much the base layer moved (``base_slip``: its largest sideways displacement,
    ``base_lift``: its largest rise off the plane, both over the sphere's depth), which says
    whether the base is held as the bonded theory assumes.

    ``resolution`` >= 2; each depth in (0, min(R, h)) (h at the given resolution); ``hold``
    and ``late`` > 0; ``dtype`` ``"float32"`` or ``"float64"``; ``fit_weight``: ``SceneBuilder(fit_weight=)``."""
    wp, we = _we()
    from warp_esph import checks, tools

    scalar = _lab_dtype(wp, dtype)
    resolution = _lab_resolution(resolution, 2)
    R = checks.positive("R", R)
    H, Wd = checks.positive("height", height), checks.positive("width", width)
    # A zero hold was blamed on the keyframe times, a zero late reading was NaN.
    hold, late = checks.positive("hold", hold), checks.positive("late", late)
    dx = H / resolution
    deepest = min(R, H - dx)
    try:
        depths = tuple(depths)
    except TypeError:
        raise ValueError(f"depths = {depths!r} is not allowed: must be a sequence of depths (m)") from None
    if not depths:
        # Read as the state of no step: AttributeError 'NoneType' object has no attribute 'x'.
        raise ValueError(f"depths = {depths!r} is not allowed: must hold one depth or more (m)")
    for i, dep in enumerate(depths):
        # A negative depth was a math domain error; one past the block's thickness pushed the
        # sphere through the block onto its base, and was read against Hertz.
        _open_interval(f"depths[{i}]", dep, 0.0, deepest,
                       " m: below the sphere's radius R and the block's thickness between its outer layers' "
                       "centres, height - height / resolution")
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=0.0, elastic_force="variational",
                                 deformation=deformation)
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, H / 2, 0.0), (Wd, H, Wd), mat, name="block")
    pts = np.concatenate(b._points)
    ylo, ytop = pts[:, 1].min(), pts[:, 1].max()
    b.add_tool("plane", position=(0, ylo, 0), friction=2.0, name="base")
    times = [0.0]
    heights = [ytop + R]
    for dep in depths:
        times += [times[-1] + 0.02, times[-1] + 0.02 + hold]
        heights += [ytop + R - dep] * 2
    b.add_tool("sphere", radius=R, name="indenter",
               motion=tools.Keyframes(times, [(0.0, h, 0.0) for h in heights]))
    model = b.finalize(device=wp.get_device(), dtype=scalar)
    solver = _solver(model, hourglass=hourglass, fit=fit)
    x0 = model.particle_x0.astype(np.float64)
    base = x0[:, 1] < ylo + 0.5 * dx
    a = c = None
    forces, base_forces = [], []
    for _ in depths:
        a, c, f = _relaxed_reaction(model, solver, ["indenter", "base"], 0.02, hold, a, c, average=50)
        forces.append(-f["indenter"][1])  # the material pushes the sphere up: reaction on the material is down
        base_forces.append(f["base"][1])
    x = a.x.numpy().astype(np.float64)
    base_slip = float(np.linalg.norm((x - x0)[base][:, [0, 2]], axis=1).max()) / depths[-1]
    base_lift = float((x[base, 1] - ylo).max()) / depths[-1]
    ke = _kinetic(model, a)
    a, c, f = _relaxed_reaction(model, solver, ["indenter"], 0.0, late, a, c, average=50)
    h = float(ytop - ylo)
    hertz = [hertz_force(E, nu, R, dep) for dep in depths]
    theory = [fh * layer_factor(nu, math.sqrt(R * dep) / h) for fh, dep in zip(hertz, depths)]
    full = [fh * layer_factor(nu, math.sqrt(R * dep) / H) for fh, dep in zip(hertz, depths)]
    free = [fh * layer_factor(nu, math.sqrt(R * dep) / h, bonded=False) for fh, dep in zip(hertz, depths)]
    exponent = math.log(forces[1] / forces[0]) / math.log(depths[1] / depths[0]) if len(depths) > 1 else float("nan")
    theory_exponent = (math.log(theory[1] / theory[0]) / math.log(depths[1] / depths[0]) if len(depths) > 1
                       else float("nan"))
    late_force = -f["indenter"][1]
    return {"case": "indentation", "resolution": resolution, "hourglass": solver.hourglass, "fit": solver.fit, "dtype": dtype,
            "fit_weight": model.fit_weight,
            "particles": model.particle_count, "R": R,
            "width": Wd, "height": H, "thickness": h, "depths": list(depths), "forces": forces, "base_forces": base_forces,
            "hertz": hertz, "theory": theory, "ratios": [f / t for f, t in zip(forces, theory)],
            "ratios_hertz": [f / t for f, t in zip(forces, hertz)],
            "ratios_full_thickness": [f / t for f, t in zip(forces, full)],
            "ratios_unbonded": [f / t for f, t in zip(forces, free)],
            "chi": [math.sqrt(R * dep) / h for dep in depths], "exponent": exponent, "theory_exponent": theory_exponent,
            "contact_radius_over_dx": [math.sqrt(R * dep) / dx for dep in depths], "kinetic_energy": ke,
            "base_slip": base_slip, "base_lift": base_lift,
            "late_s": late, "late_force": late_force, "late_ratio": late_force / theory[-1], **_row_fields(solver)}


def three_point_stiffness(E: float, nu: float, L: float, t: float, kappa: float = 0.85) -> tuple[float, float]:
    """Mid-span stiffness F / delta of a simply supported square beam (side t, span L) under
    a central load: Euler-Bernoulli 48 E I / L^3, and with Timoshenko's shear deflection
    F L / (4 kappa G A) added to the bending one F L^3 / (48 E I)."""
    I, A, Gs = t**4 / 12.0, t * t, E / (2.0 * (1.0 + nu))
    eb = 48.0 * E * I / L**3
    return eb, 1.0 / (1.0 / eb + L / (4.0 * kappa * Gs * A))


def three_point_bending(resolution: int = 4, E: float = 1.0e6, nu: float = 0.3, deflection: float = 0.0005,
                        kappa: float = 0.85, hold: float = 0.5, hourglass: float = 0.1, damping: float = 1.0,
                        average: float = 0.1, fit: str = "linear", dtype: str = "float32", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """A 24 x 4 x 4 cm beam (``resolution`` particles across its 4 cm) on two frictionless
    cylinder tools (r = 1 cm) 18 cm apart, a frictionless cylinder loading pin lowered
    ``deflection`` at mid-span in 0.1 s and held ``hold`` s; no gravity, pressure off,
    variational force, ``Solver(hourglass=hourglass, fit=fit)``. During the hold the
    velocities are damped mass-proportionally at c = ``damping`` omega_1 (omega_1 the first
    bending frequency of the span, Euler-Bernoulli); ``damping=0``: kinetic damping instead
    (``kinetic_damping``; when it zeroed the velocities a motion starting at the beam's free
    ends grew after about 0.25 s of hold until contact was lost, 0.277 x Timoshenko at 8
    across, 0.6 s; with its stop 0.9212, as damped, docs/validation.md Notes). Measured, as means over the last ``average``
    s: the pin's reaction force, the supports' and the mid-span deflection of the beam (mean
    height change of the mid-span particle column's middle layers against that of the two
    columns over the supports, which takes out the local indentation under the pin and at
    the supports); the stiffness is force over deflection, against 48 E I / L^3 with and
    without the shear term (``three_point_stiffness``). ``creep``: the deflection's rate of
    change over that window (a straight-line fit), per s, as a fraction of it.

    ``resolution``: a multiple of 4, so that particle columns stand over the supports;
    ``deflection`` in (0, 4 cm); ``average`` in (0, ``hold``]; ``dtype`` ``"float32"`` or
    ``"float64"``; ``fit_weight``: ``SceneBuilder(fit_weight=)``."""
    wp, we = _we()
    from warp_esph import checks, tools

    scalar = _lab_dtype(wp, dtype)
    t, L, r = 0.04, 0.18, 0.01
    # At other resolutions the supports fell between two columns, below the beam's bottom
    # layer (0.57 mm at 6 across): the pin's 0.5 mm pushed the beam down without a force, read
    # as a stiffness of 0.
    resolution = _lab_resolution(resolution, 4, 4, " (4, 8, 12, ...): only then do particle columns stand over the "
                                                   "supports 18 cm apart, as the beam must rest on them")
    deflection = _open_interval("deflection", deflection, 0.0, t, " m (the pin's travel into the 4 cm beam)")
    hold = checks.positive("hold", hold)
    average = checks.positive("average", average)
    if average > hold:
        # The window then reached back into the loading: creep 17.9 per s at hold = 0.
        raise ValueError(f"average = {average!r} is not allowed: must be <= hold = {hold!r} (the window the static "
                         "state is read over lies in the hold)")
    damping, kappa = checks.non_negative("damping", damping), checks.positive("kappa", kappa)
    dx = t / resolution
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=0.0, elastic_force="variational")
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    # An odd number of particle columns (24 cm + dx): columns at mid-span and over the
    # supports, so the pin and the supports touch a column's face on their axis.
    b.add_box((0.0, t / 2, 0.0), (0.24 + dx, t, t), mat, name="beam")
    pts = np.concatenate(b._points)
    ylo, yhi = pts[:, 1].min(), pts[:, 1].max()
    along_z = (math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4))
    for name, x in (("support_left", -L / 2), ("support_right", L / 2)):
        b.add_tool("cylinder", radius=r, half_height=t, position=(x, ylo - r, 0.0), orientation=along_z, name=name)
    top = (0.0, yhi + r, 0.0)
    b.add_tool("cylinder", radius=r, half_height=t, name="pin", orientation=along_z,
               motion=tools.Keyframes([0.0, 0.1], [top, (0.0, yhi + r - deflection, 0.0)], [along_z, along_z]))
    model = b.finalize(device=wp.get_device(), dtype=scalar)
    solver = _solver(model, hourglass=hourglass, fit=fit)
    x0 = model.particle_x0.astype(np.float64)
    core = np.abs(x0[:, 1] - 0.5 * (ylo + yhi)) < 0.5 * t - 0.75 * dx  # away from the loaded faces
    mid = core & (np.abs(x0[:, 0]) < 0.6 * dx)
    ends = core & (np.abs(np.abs(x0[:, 0]) - L / 2) < 0.6 * dx)
    sags = []

    def record(state):
        y = state.x.numpy()[:, 1].astype(np.float64) - x0[:, 1]
        sags.append((state.time, -(y[mid].mean() - y[ends].mean())))

    omega1 = (math.pi / L) ** 2 * math.sqrt(E * t * t / (12.0 * RHO))
    steps = max(1, int(round(average / solver.stable_dt())))
    a, c, f = _relaxed_reaction(model, solver, ["pin", "support_left", "support_right"], 0.1, hold,
                                average=steps, after=record, viscous=damping * omega1)
    ts, ss = np.array(sags[-steps:]).T
    sag = float(ss.mean())
    creep = float(np.polyfit(ts, ss, 1)[0]) / sag
    force = -f["pin"][1]
    eb, timo = three_point_stiffness(E, nu, L, t, kappa)
    k = force / sag
    return {"case": "bending", "resolution": resolution, "particles": model.particle_count, "hourglass": hourglass,
            "dtype": dtype, "fit_weight": model.fit_weight,
            "damping": damping, "fit": fit, "hold": hold, "force": force,
            "support_force": float(f["support_left"][1] + f["support_right"][1]), "deflection": sag,
            "creep": creep, "pin_travel": deflection, "stiffness": k, "theory_euler_bernoulli": eb, "theory": timo,
            "ratio": k / timo, "ratio_euler_bernoulli": k / eb, "kinetic_energy": _kinetic(model, a),
            **_row_fields(solver)}


# ------------------------------------------------------------------- energy
def _stvk_energy(model, F: np.ndarray, mu: float, lam: float) -> float:
    F = F.astype(np.float64)
    C = np.einsum("nki,nkj->nij", F, F)
    Eg = 0.5 * (C - np.eye(3))
    tr = np.trace(Eg, axis1=1, axis2=2)
    psi = mu * np.einsum("nij,nij->n", Eg, Eg) + 0.5 * lam * tr**2
    return float((model.particle_volume.numpy() * psi).sum())


def _corotated_energy(model, F: np.ndarray, mu: float, lam: float) -> float:
    """``sum V psi(F)`` of the corotated energy ``psi = mu sum(s - 1)^2 + lam/2 (sum(s - 1))^2``
    in the signed singular values (the smallest negative where det F < 0): the energy whose
    gradient the linear models' stress is where the material cannot flow."""
    U, s, Vt = np.linalg.svd(F.astype(np.float64))
    s[:, 2] *= np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    e = s - 1.0
    psi = mu * (e * e).sum(axis=1) + 0.5 * lam * e.sum(axis=1) ** 2
    return float((model.particle_volume.numpy() * psi).sum())


def _hourglass_energy(model, c: float):
    """The hourglass control's energy ``sum_i E_i`` as a function of the positions
    (``warp_esph/sim/hourglass.py``: ``E_i = c mu_i V_i / (2 S_i) min_G sum_j w_ij |x_ij - G
    X_ij|^2``, poly6 weights of the rest distances) over the same-body pairs within the support
    at rest (the only pairs of non-zero weight; the breathing cube's strain keeps them in the
    list); 0 where ``c = 0``. The control is conservative: ``energy_drift``'s total with it is
    what the step conserves."""
    if c == 0.0:
        return lambda x: 0.0
    from warp_esph.sim import hourglass

    X = np.asarray(model.particle_x0, dtype=np.float64)
    h = float(model.support_radius)
    body = model.particle_body.numpy()
    r2 = ((X[None, :, :] - X[:, None, :]) ** 2).sum(-1)
    near = (r2 < h * h) & (body[None, :] == body[:, None])
    np.fill_diagonal(near, False)
    width = int(near.sum(1).max())
    nb = np.zeros((len(X), width), dtype=np.int64)
    w = np.zeros((len(X), width))
    for i, row in enumerate(near):
        js = np.nonzero(row)[0]
        nb[i, :len(js)] = js
        w[i, :len(js)] = (h * h - r2[i, js]) ** 3
    d = X[nb] - X[:, None, :]
    S = (w * (d * d).sum(-1)).sum(1)
    A = np.einsum("ij,ijk,ijl->ikl", w, d, d)
    ok = (S > 0.0) & (np.linalg.det(A) > hourglass.MIN_DET * (S / 3.0) ** 3)  # no control below it
    A_inv = np.linalg.inv(A[ok])
    mu = np.array([m.mu for m in model.materials])[model.particle_material.numpy()]
    coef = (0.5 * c * mu * model.particle_volume.numpy().astype(np.float64) / np.where(S > 0.0, S, 1.0))[ok]
    nb, w, d = nb[ok], w[ok], d[ok]
    rows = np.nonzero(ok)[0]

    def energy(x: np.ndarray) -> float:
        x = x.astype(np.float64)
        xb = x[nb] - x[rows, None, :]
        G = np.einsum("ij,ijk,ijl->ikl", w, xb, d) @ A_inv
        res = xb - np.einsum("ikl,ijl->ijk", G, d)
        return float((coef * (w * (res * res).sum(-1)).sum(1)).sum())

    return energy


#: The elastic energy density ``energy_drift`` measures for each material model: the one
#: whose gradient the model's stress is where the material cannot flow.
ENERGY_OF_MODEL = {"stvk": "St. Venant-Kirchhoff", "hyperelastic": "2 x St. Venant-Kirchhoff",
                   "linear": "corotated", "non_newtonian": "corotated"}


def conserves_elastic_energy(elastic_force: str) -> bool:
    """Whether an elastic material that cannot flow, on ``elastic_force``, is pushed by minus
    the gradient of ``sum V psi(F)`` (``ENERGY_OF_MODEL``): the variational force is (docs/physics.md,
    "The elastic force: the paper's and the variational one"); the paper's is the gradient of
    no energy."""
    if elastic_force not in ("variational", "paper"):
        raise ValueError(f"elastic_force = {elastic_force!r} is not allowed: must be 'variational' or 'paper'")
    return elastic_force == "variational"


def energy_drift(amplitude: float = SMALL, elastic_force: str = "variational", resolution: int = 6,
                 periods: float = 50.0, dt_factor: float = 1.0, E: float = 2.0e5, nu: float = 0.3, fit: str | None = None, hourglass: float | None = None,
                 deformation: str = "incremental", model: str = "stvk", fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """An undamped elastic cube (``resolution``^3 particles, St. Venant-Kirchhoff or the
    material ``model`` given, pressure off, no gravity, no viscosity) set breathing with
    ``v = a (x - c)`` so that its peak strain is about ``amplitude``. The total energy
    (kinetic + sum V psi(F), psi the energy of the stored F whose gradient the model's stress
    is: St. Venant-Kirchhoff's, twice it for ``hyperelastic``, the corotated one,
    ``_corotated_energy``, for ``linear`` and ``non_newtonian``) over ``periods`` breathing periods:
    drift = (E_end - E_0) / E_0 and the largest |E - E_0| / E_0. With the variational
    force the elastic force is minus the gradient of exactly this energy: of the step's
    incremental fit ``dF F`` (``deformation="incremental"``, path dependent), or of the total
    fit against the rest neighbourhood (``"rest"``, a function of the positions alone).
    The paper's force (eqs. 10-13) is the gradient of no energy, this one's least: the sum is
    no quantity it conserves, even integrated exactly, and its change is that force's own work
    against psi, not the time step's error (4^3 cube, 3 periods, small amplitude: largest
    deviation 0.89, 0.86, 0.85 at dt, dt / 2, dt / 4, measured at 13155696; 0.81, 0.79, 0.79
    earlier). The row says which: ``energy`` names
    psi, ``conservative`` whether the force is minus its gradient (else ``drift`` and
    ``max_deviation`` measure the force, not the integration). The hourglass control's
    energy is not counted in them; ``drift_with_control`` and ``max_deviation_with_control``
    add it (``_hourglass_energy``; the same where the control is off): the total a step with
    the control conserves. ``fit_weight``: ``SceneBuilder(fit_weight=)``."""
    wp, we = _we()
    dx = 0.02
    n = resolution
    mat = we.Material.from_young(E, nu, density=RHO, pressure_stiffness=0.0, model=model, elastic_force=elastic_force,
                                 deformation=deformation)
    material_model = model
    conservative = conserves_elastic_energy(mat.elastic_force)  # the force the material resolved
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, 0.0, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, 0.0, 0.0), (n * dx,) * 3, mat)
    model = b.finalize(device=wp.get_device())

    def elastic_energy(F, mu, lam):
        if material_model in ("linear", "non_newtonian"):
            return _corotated_energy(model, F, mu, lam)
        return (2.0 if material_model == "hyperelastic" else 1.0) * _stvk_energy(model, F, mu, lam)

    x0 = model.particle_x0.astype(np.float64)
    # Breathing mode of a free cube: omega ~ pi c_p / side; strain amplitude a / omega.
    omega = math.pi * mat.p_wave_speed / (n * dx)
    rate = amplitude * omega
    a, c = model.state(), model.state()
    a.v.assign(rate * (x0 - x0.mean(axis=0)))
    mu, lam = mat.mu, mat.lam
    e0 = _kinetic(model, a) + elastic_energy(a.F.numpy(), mu, lam)
    solver = _solver(model, fit=fit, hourglass=hourglass)
    control_energy = _hourglass_energy(model, solver.hourglass)
    e0_control = e0 + control_energy(a.x.numpy())
    dt = dt_factor * solver.stable_dt()
    steps = int(periods * 2.0 * math.pi / omega / dt)
    every = max(1, steps // 400)
    hist = []
    peak_strain = [0.0]

    mass = model.particle_mass.numpy().astype(np.float64)[:, None]
    pending = []

    def after(state, k):
        # Symplectic Euler's velocities are the half steps': the energy at x_k takes the mean
        # of the velocities before and after it (read one step later), which removes the
        # O(dt) oscillation of the kinetic energy of v_{k-1/2} (10 % of E at the stable step).
        v = state.v.numpy().astype(np.float64)
        if pending:
            tk, pe, ce, v_before = pending.pop()
            e = 0.5 * float((mass * (0.5 * (v_before + v)) ** 2).sum()) + pe
            hist.append((tk, e / e0 - 1.0, (e + ce) / e0_control - 1.0))
            if not math.isfinite(e) or e > 100.0 * e0:
                return False
        if k % every == 0 or k == steps - 1:
            F = state.F.numpy()
            pending.append((k * dt, elastic_energy(F, mu, lam), control_energy(state.x.numpy()), v))
            s = np.linalg.svd(F.astype(np.float64), compute_uv=False)
            peak_strain[0] = max(peak_strain[0], float(np.abs(s - 1.0).max()))

    _swap_run(model, solver, a, c, dt, steps, after)
    h = np.array(hist)
    blew = bool(not np.isfinite(h[-1, 1]) or h[-1, 1] > 99.0)
    return {"case": "energy", "amplitude": amplitude, "elastic_force": mat.elastic_force, "deformation": deformation,
            "model": material_model, "energy": ENERGY_OF_MODEL[material_model],
            "conservative": conservative,
            "fit": solver.fit, "hourglass": solver.hourglass, "fit_weight": fit_weight, "resolution": n,
            "dt_factor": dt_factor, "periods": float(h[-1, 0] * omega / (2.0 * math.pi)),
            "peak_strain": peak_strain[0], "drift": float(h[-1, 1]), "max_deviation": float(np.nanmax(np.abs(h[:, 1]))),
            "drift_with_control": float(h[-1, 2]), "max_deviation_with_control": float(np.nanmax(np.abs(h[:, 2]))),
            "blew_up": blew, "t": h[:, 0].tolist(), "relative_energy": h[:, 1].tolist(), **_row_fields(solver)}


# ---------------------------------------------------------------- stability
def _stability_materials():
    _, we = _we()
    out = []
    for name in sorted(we.PRESETS):
        p = we.Material.preset(name)
        out.append((f"preset {name}", p))
        out.append((f"preset {name}, viscosity 0", p.replace(viscosity=0.0)))
        out.append((f"preset {name}, energy pressure, viscosity 0", p.replace(pressure_force="energy", viscosity=0.0)))
    default = we.Material(mu=1.0e5, lam=1.0e5)
    out.append(("Material(mu=1e5, lam=1e5)", default))
    out.append(("Material(mu=1e5, lam=1e5), viscosity 5", default.replace(viscosity=5.0)))
    out.append(("Material(mu=1e5, lam=1e5), energy pressure", default.replace(pressure_force="energy")))
    return out


def stability(material, duration: float = 1.0, resolution: int = 6, dt_factor: float = 0.5, limit: float = 5.0,
              fit_weight: str = DEFAULT_FIT_WEIGHT) -> dict:
    """A ``resolution``^3 box of ``material`` (2 cm spacing) resting on the ground (friction
    0.5), run at ``dt_factor`` x ``Model.stable_dt()`` for ``duration`` s. It blew up if a
    particle ever moved faster than ``limit`` m/s (a body at rest under gravity: well below
    it) or any value went non-finite. ``fit_weight``: ``SceneBuilder(fit_weight=)``."""
    wp, we = _we()
    dx = 0.02
    n = resolution
    b = we.SceneBuilder(spacing=dx, gravity=(0.0, -G, 0.0), fit_weight=fit_weight)
    b.add_box((0.0, n * dx / 2.0, 0.0), (n * dx,) * 3, material)
    b.add_ground(0.0, friction=0.5)
    model = b.finalize(device=wp.get_device())
    solver = _solver(model)
    dt = dt_factor * model.stable_dt()
    steps = int(duration / dt)
    peak = [0.0, None]

    def after(state, k):
        if k % 10 == 0 or k == steps:
            v = state.v.numpy()
            speed = float(np.sqrt((v.astype(np.float64) ** 2).sum(axis=1)).max()) if np.isfinite(v).all() else math.inf
            peak[0] = max(peak[0], speed)
            if speed > limit:
                peak[1] = k * dt
                return False

    a, c = model.state(), model.state()
    a, c = _swap_run(model, solver, a, c, dt, steps, after)
    return {"case": "stability", "elastic_force": material.elastic_force, "fit_weight": fit_weight, "dt": dt,
            "duration": duration,
            "max_speed": peak[0], "blew_up": peak[1] is not None, "blew_up_at": peak[1],
            "final_speed": float(np.abs(a.v.numpy()).max()) if peak[1] is None else None, **_row_fields(solver)}


# ------------------------------------------------------------------- driver
def plan(quick: bool) -> list[tuple[str, dict]]:
    """(function name, kwargs) of every run of the suite. An entry without a ``fit_weight``
    runs ``DEFAULT_FIT_WEIGHT``; the full plan's twins of it name each other weight, once."""
    runs: list[tuple[str, dict]] = []
    twins = tuple(w for w in FIT_WEIGHTS if w != DEFAULT_FIT_WEIGHT)
    # The slump and the spread stand on the suite's floor, the Tresca ground (since 2026-12-07,
    # docs/validation.md, "The suite's floor"); the case functions' own default stays the
    # particle floor, whose entries below name it: the rows the report counts apart.
    suite = {"floor": SUITE_FLOOR}
    if quick:
        for f in FORCES:
            # On the Tresca ground the variational S = 0.2 pile is not quite at rest at 5 s (its
            # top sinking 0.16 % H0/s, kinetic energy 1.7e-8 M g H0 over the last quarter, -7.0 %
            # of the 1-D height, 24 s of CPU; measured 2026-12-07), where the particle floor's
            # rested by about 4 s: a CI-sized check, not a rest.
            runs.append(("slump", {"S": 0.2, "resolution": 8, "elastic_force": f, "duration": 5.0} | suite))
            runs.append(("bar_frequency", {"resolution": 4, "elastic_force": f}))
            runs.append(("beam_deflection", {"resolution": 4, "elastic_force": f, "span_over_thickness": 6}))
            runs.append(("column_settlement", {"resolution": 4, "elastic_force": f}))
            runs.append(("poisson_compression", {"resolution": 4, "elastic_force": f}))
            runs.append(("energy_drift", {"amplitude": SMALL, "elastic_force": f, "periods": 20.0}))
        # The smallest run that resolves the plug (its top S H0 / 2 is one support radius); on
        # the Tresca ground at rest by 3 s, its plug all below 0.99 Y, none yielded (12 s of CPU).
        runs.append(("slump", {"S": 0.5, "resolution": 8, "elastic_force": "variational", "duration": 3.0} | suite))
        # The spread limit at its smallest size (3 particles through the theory's height); on
        # the Tresca ground 0.880 R_RC at 14 s, creeping 0.016 % R_RC/s (docs/physics.md, "The
        # Tresca ground (built)").
        runs.append(("spread", {"resolution": 3, "shallowness": 0.25, "duration": 14.0} | suite))
        # The lab tests with tools (variational force only: the default).
        runs.append(("plate_compression", {"resolution": 4}))
        runs.append(("three_point_bending", {"resolution": 4}))
        runs.append(("sphere_indentation", {"resolution": 8, "fit": "linear", "hourglass": 0.0}))
        runs.append(("sphere_indentation", {"resolution": 8}))
        runs.append(("uniaxial_flow", {"resolution": 6, "strain": 0.6, "duration": 2.0}))
        for label, _ in _stability_materials():
            for f in FORCES:
                runs.append(("stability", {"label": label, "elastic_force": f, "duration": 0.3}))
        return runs
    # Fast cases first: the JSON is rewritten after every run.
    for f in FORCES:
        for res in (4, 6):
            runs.append(("bar_frequency", {"resolution": res, "elastic_force": f}))
            runs.append(("beam_deflection", {"resolution": res, "elastic_force": f}))
            runs.append(("column_settlement", {"resolution": res, "elastic_force": f}))
            runs.append(("poisson_compression", {"resolution": res, "elastic_force": f}))
        for amp in (SMALL, LARGE):
            for dtf in (1.0, 0.5):
                runs.append(("energy_drift", {"amplitude": amp, "elastic_force": f, "periods": 50.0, "dt_factor": dtf}))
    # The conservative variant: the variational force of the total fit against the rest
    # neighbourhood (docs/physics.md, "The energy of undamped elastic bodies").
    for amp in (SMALL, LARGE):
        runs.append(("energy_drift", {"amplitude": amp, "deformation": "rest", "periods": 50.0}))
        runs.append(("energy_drift", {"amplitude": amp, "deformation": "rest", "periods": 50.0,
                                      "fit": "curvature_corrected", "hourglass": 0.05}))
    for res in (4, 8):
        runs.append(("plate_compression", {"resolution": res}))
    # A particle column over each support needs 9 cm to be a multiple of the spacing.
    runs.append(("three_point_bending", {"resolution": 4}))
    runs.append(("three_point_bending", {"resolution": 8, "hold": 0.6}))
    # The paper's linear fit without and with the control, and the default (for this elastic
    # block the curvature-corrected fit with the control at 0.05).
    for res in (8, 12):
        for hg in (0.0, 0.1):
            runs.append(("sphere_indentation", {"resolution": res, "fit": "linear", "hourglass": hg}))
        runs.append(("sphere_indentation", {"resolution": res}))
    runs.append(("sphere_indentation", {"resolution": 16, "fit": "linear", "hourglass": 0.1}))
    # The flow stress past the particles' rearrangement (docs/physics.md, "The flow stress in
    # sustained uniaxial flow"): the same log strains at four resolutions, with each fit weight.
    for weight in (DEFAULT_FIT_WEIGHT, *twins):
        for res in (6, 8, 12, 16):
            runs.append(("uniaxial_flow", {"resolution": res, "strain": 0.75, "duration": 4.0}
                         | ({"fit_weight": weight} if weight != DEFAULT_FIT_WEIGHT else {})))
    for res in (8, 12):
        for S in SLUMP_S:
            for f in FORCES:
                runs.append(("slump", {"S": S, "resolution": res, "elastic_force": f, "duration": SLUMP_DURATION} | suite))
    for label, _ in _stability_materials():
        for f in FORCES:
            runs.append(("stability", {"label": label, "elastic_force": f, "duration": 1.0}))
    # The other fit weight (docs/physics.md, "The fit's weight") on the elastic references and
    # the step bound, with the default elastic force: twins that run here, early, not at the end.
    for weight in twins:
        for res in (4, 6):
            for case in ("bar_frequency", "beam_deflection", "column_settlement", "poisson_compression"):
                runs.append((case, {"resolution": res, "elastic_force": "variational", "fit_weight": weight}))
        for label, _ in _stability_materials():
            for f in FORCES:
                runs.append(("stability", {"label": label, "elastic_force": f, "duration": 1.0, "fit_weight": weight}))
    # The spread limit: three resolutions at a = h_RC / R_RC = 0.25, and a shallower pile.
    for res in (3, 4, 5):
        runs.append(("spread", {"resolution": res, "shallowness": 0.25, "duration": 14.0} | suite))
    runs.append(("spread", {"resolution": 3, "shallowness": 0.18, "duration": 8.0} | suite))
    # At 16 across the Tresca ground's piles are at rest by 8 s (R98, R99), where the particle
    # floor's S = 0.1 pile still rang.
    for S in (0.1, 0.2, 0.3, 0.5):
        runs.append(("slump", {"S": S, "resolution": 16, "elastic_force": "variational", "duration": SLUMP_DURATION} | suite))
    # A third resolution for the convergence verdict (about 11k particles, 48-66 minutes of
    # CPU a pile, R101, R102, R105).
    for S in (0.2, 0.3, 0.1, 0.5):
        runs.append(("slump", {"S": S, "resolution": 24, "elastic_force": "variational", "duration": SLUMP_DURATION_FINE}
                     | suite))
    # The particle floor's piles, which the report counts apart (the rows "on the particle
    # floor"), with each fit weight, as its targets read them: the slumps at the three
    # resolutions of the convergence verdict and at 8 (with S = 0.05 at 8 and 12 across, which
    # the rest target names beside its finest rows), the 24-across ones with the default's
    # weight (its fitted yield stress), and the three spread piles.
    particles = {"floor": "particles"}
    for weight in (DEFAULT_FIT_WEIGHT, *twins):
        named = particles | ({"fit_weight": weight} if weight != DEFAULT_FIT_WEIGHT else {})
        for res in (8, 12, 16) if weight != DEFAULT_FIT_WEIGHT else (8, 12, 16, 24):
            for S in SLUMP_S if res < 16 else (0.1, 0.2, 0.3, 0.5):
                runs.append(("slump", {"S": S, "resolution": res, "elastic_force": "variational",
                                       "duration": SLUMP_DURATION_FINE if res >= 16 else SLUMP_DURATION} | named))
        for res in (3, 4, 5):
            runs.append(("spread", {"resolution": res, "shallowness": 0.25, "duration": 14.0} | named))
    # The same piles on the no-slip ghost floor, a wall that holds no layer (docs/physics.md,
    # "The no-slip ghost floor"); they rest by about 4 s. Then with the other weight, whose
    # targets include this floor's.
    for weight in (DEFAULT_FIT_WEIGHT, *twins):
        for res in (8, 12, 16):
            for S in (0.1, 0.2, 0.3, 0.5):
                runs.append(("slump", {"S": S, "resolution": res, "floor": "ghost_particles", "duration": SLUMP_DURATION}
                             | ({"fit_weight": weight} if weight != DEFAULT_FIT_WEIGHT else {})))
    # The near-yield column at a fixed width (docs/physics.md, "The near-yield column at a
    # fixed width"): 4 cm wide and 20 cm tall at every resolution, 0.79 of its self-weight
    # buckling length, so the resolutions resolve one column (without a width it grows with
    # them and buckles from 8 across). On the slip ghost floor, whose bottom layer spreads as
    # the 1-D analysis's, and on the ground collider. Measured (R63, one process beside other
    # jobs, load 8-14 on 2 cores): 230 / 584 / 1397 s at 4 / 6 / 8 across on the slip ghost floor.
    for floor in ("slip_ghost_particles", "ground"):
        for res in (4, 6, 8):
            runs.append(("near_yield_column", {"resolution": res, "width": NEAR_YIELD_WIDTH, "floor": floor}))
    # The other weight's twin of every other entry (the paper's force, the energy, the lab
    # tests, the near-yield column, the 24-across piles, ...): the plan measures both weights
    # (docs/physics.md, the Recommendation's step 4, and the switch of the default), and
    # ``--only <case>:fit_weight=<weight>`` must find each row's twin to run.
    named = {(n, tuple(sorted(k.items()))) for n, k in runs if "fit_weight" in k}
    for name, k in list(runs):
        for weight in twins if "fit_weight" not in k else ():
            twin = k | {"fit_weight": weight}
            if (name, tuple(sorted(twin.items()))) not in named:
                runs.append((name, twin))
    return runs


#: The case functions and the ``case`` of the results they return.
RESULT_CASES = {"slump": "slump", "spread": "spread", "incline": "incline", "bar_frequency": "bar",
                "beam_deflection": "beam", "column_settlement": "column", "near_yield_column": "near_yield_column",
                "poisson_compression": "poisson", "plate_compression": "plates",
                "plastic_compression": "plastic_compression", "uniaxial_flow": "uniaxial_flow",
                "sphere_indentation": "indentation", "three_point_bending": "bending", "energy_drift": "energy",
                "stability": "stability"}
#: Identity fields (``IDENTITY``) that are numbers, and of those the integers.
NUMERIC_IDENTITY = ("S", "resolution", "shallowness", "amplitude", "dt_factor", "hourglass", "span_over_thickness",
                    "aspect", "hold", "strain", "width")
INTEGER_IDENTITY = ("resolution", "span_over_thickness")


def result_rows(data, source: str, *, need_results: bool = False) -> list[dict]:
    """The results of a JSON document of the suite (an object with ``results``, as
    validation.json; or, unless ``need_results``, a list of results), checked: each row an
    object with a ``case`` of ``RESULT_CASES`` and numbers in its numeric identity fields.
    Else ``ValueError("<source> is not allowed: ...")`` naming the row."""
    where = f"{source} is not allowed"
    if isinstance(data, dict):
        if "results" not in data:
            keys = ", ".join(repr(k) for k in list(data)[:5]) or "none"
            raise ValueError(f"{where}: a JSON object must have 'results' (a list of results); its keys: {keys}")
        rows = data["results"]
    elif need_results:
        raise ValueError(f"{where}: it must be a validation.json, a JSON object with 'results', not a {type(data).__name__}")
    else:
        rows = data
    if not isinstance(rows, list):
        raise ValueError(f"{where}: 'results' must be a list of results, not {type(rows).__name__}")
    known = sorted(set(RESULT_CASES.values()))
    for i, r in enumerate(rows):
        if not isinstance(r, dict):
            raise ValueError(f"{where}: result {i} ({json.dumps(r)[:60]}) is not an object")
        if r.get("case") not in known:
            what = f"has case = {r['case']!r}" if "case" in r else "has no 'case'"
            raise ValueError(f"{where}: result {i} {what}; the cases of the suite: {', '.join(known)}")
        for k in NUMERIC_IDENTITY:
            v = r.get(k)
            if k in r and (isinstance(v, bool) or not isinstance(v, int if k in INTEGER_IDENTITY else (int, float))):
                kind = "an integer" if k in INTEGER_IDENTITY else "a number"
                raise ValueError(f"{where}: result {i} ({r['case']}) has {k} = {v!r}, not {kind}")
    return rows


def check_runs(doc: dict, source: str) -> None:
    """``ValueError`` unless ``doc``'s ``runs`` (if any) is a list of objects that every result's
    ``run`` indexes."""
    runs = doc.get("runs")
    if runs is not None and (not isinstance(runs, list) or not all(isinstance(m, dict) for m in runs)):
        raise ValueError(f"{source} is not allowed: 'runs' must be a list of objects (the runs that measured the results)")
    n = len(runs) if runs else 1
    for i, r in enumerate(doc["results"]):
        k = r.get("run", 0)
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < n:
            raise ValueError(f"{source} is not allowed: result {i} has run = {k!r}, not one of its {n} runs")


def run_one(name: str, kwargs: dict) -> dict:
    kwargs = dict(kwargs)
    if name == "stability":
        label = kwargs.pop("label")
        force = kwargs.pop("elastic_force")
        material = dict(_stability_materials())[label].replace(elastic_force=force)
        out = stability(material, **kwargs)
        out["label"] = label
        out["preset_force"] = dict(_stability_materials())[label].elastic_force
        return out
    return globals()[name](**kwargs)


def first_step(name: str, kwargs: dict) -> dict:
    """What the run ``run_one(name, kwargs)`` steps, read at its first step, which is not taken
    (the scene is built, nothing runs): the solver's ``record`` from that state
    (``resolved_fit``, ``rest_model``), ``corrected_incremental`` (the curvature-corrected fit on
    the incremental composition, ``Model.corrected_incremental``), the ``dt`` the case passes,
    the solver's ``stable_dt`` and ``full_dt``, the stable step with the whole wave limit (the
    rule before ``CORRECTED_INCREMENTAL_STEP``): a case whose ``dt`` scales ``stable_dt`` ran
    ``full_dt / stable_dt`` x its step before, and a row it measured then may change."""
    global _first_step_only
    _first_step_only = True
    try:
        run_one(name, kwargs)
    except _FirstStep as e:
        solver, state, dt = e.args
    else:
        raise RuntimeError(f"{name}({kwargs}) returned without taking a step")
    finally:
        _first_step_only = False
    model = solver.model
    record = solver.record(state)
    # The wave limit is kept whole for every fit but the corrected one on the incremental
    # composition; the hourglass, field and contact limits do not read the fit.
    full = model.stable_dt(hourglass=solver.hourglass, fit="linear")
    return {"case": name, "kwargs": dict(kwargs), "resolved_fit": record["resolved_fit"],
            "rest_model": record["rest_model"], "corrected_incremental": model.corrected_incremental(solver.asked_fit),
            "dt": float(dt), "stable_dt": solver.stable_dt(), "full_dt": full}


PROG = "python -m benchmarks.validation"


def main(argv=None) -> int:
    from tqdm import tqdm

    from benchmarks import _cli

    p = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="CI-sized run (reduced sizes and durations)")
    p.add_argument("--device", default="cpu",
                   help="Warp device the scenes are built and run on (cpu, cuda:0, ...); each row records it")
    p.add_argument("--out", default=str(ROOT / "docs"), type=_cli.output_folder,
                   help="folder for validation.md, validation.json, images/validation/")
    p.add_argument("--only", default=None,
                   help="comma-separated runs to keep: a case function (slump), or one with keyword values its "
                        "plan entries must have (slump:resolution=12:elastic_force=variational)")
    p.add_argument("--merge", default=None, metavar="JSON", type=_cli.json_file,
                   help="an earlier validation.json: its results stay in the report, each tagged with the run that "
                        "measured it, except those this run measures again (same case and parameters)")
    p.add_argument("--drop", default=None, metavar="CASES",
                   help="with --merge: comma-separated result cases (slump,spread,stability,...) whose earlier rows "
                        "are not kept, e.g. because they were measured on older defaults")
    p.add_argument("--no-report", action="store_true", help="only write the JSON")
    p.add_argument("--add", default=None, metavar="JSON", type=_cli.json_file,
                   help="rows measured elsewhere (a list of results of the case functions, e.g. slump(...) on a "
                        "GPU, each with an optional 'device', or a validation.json): merged as one run, replacing "
                        "the rows they measure again; without --only nothing else is run")
    args = p.parse_args(argv)
    wp, _ = _we()
    problem = _cli.device_problem(args.device)  # (Warp's native notes of a missing CUDA driver held back)
    if problem:
        raise ValueError(f"--device = {args.device!r} is not allowed: {problem}")
    if args.drop and not args.merge:
        raise ValueError(f"--drop = {args.drop!r} is not allowed without --merge (it drops rows of the merged JSON)")
    known = sorted(set(RESULT_CASES.values()))
    for case in args.drop.split(",") if args.drop else ():
        if case not in known:
            raise ValueError(f"--drop = {args.drop!r} is not allowed: {case!r} is not a case of the results; "
                             f"the cases: {', '.join(known)}")
    the_plan = plan(args.quick)
    if args.only is not None and not args.only.strip():
        # An unset shell variable ran the whole plan (185 runs).
        raise ValueError(f"--only = {args.only!r} is not allowed: give case names, or leave --only out for the "
                         "whole plan")
    if args.only:
        names = list(dict.fromkeys(n for n, _ in the_plan))
        for entry in args.only.split(","):
            if not select(the_plan, entry):
                raise ValueError(f"--only = {args.only!r} is not allowed: {entry.strip()!r} selects no run of the "
                                 f"{'quick ' if args.quick else ''}plan; its cases: {', '.join(names)}")
    runs = select(the_plan, args.only) if args.only or not args.add else []
    if not runs and not args.add:
        raise ValueError(f"--only = {args.only!r} selects no run of the plan; its cases: "
                         + ", ".join(dict.fromkeys(n for n, _ in the_plan)))
    earlier = None
    if args.merge:
        source = f"--merge = {args.merge!r}"
        earlier = _cli.load_json(args.merge, "--merge")
        result_rows(earlier, source, need_results=True)
        check_runs(earlier, source)
    if args.drop and earlier is not None:
        earlier = earlier | {"results": [r for r in earlier["results"] if r["case"] not in args.drop.split(",")]}
    if args.add:
        earlier = added_rows(earlier, pathlib.Path(args.add), source=f"--add = {args.add!r}")
    out = pathlib.Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"--out = {args.out!r} is not allowed: the folder cannot be made ({e.strerror or e})") from None
    results = []
    t0 = time.perf_counter()
    # No bar for rows added without runs (its empty line would stand before any error of the report).
    bar = tqdm(runs, desc="validation", unit="run", file=sys.stderr, disable=not runs)
    doc = earlier
    for name, kwargs in bar:
        bar.set_postfix_str((f"{name} " + " ".join(f"{k}={v}" for k, v in kwargs.items()))[:70])
        t_run = time.perf_counter()
        with wp.ScopedDevice(args.device):
            r = run_one(name, kwargs)
        r.setdefault("device", str(wp.get_device(args.device)))
        r.setdefault("wall_s", time.perf_counter() - t_run)
        results.append(r)
        doc = merge(earlier, results, _meta(args, t0))
        (out / "validation.json").write_text(json.dumps(doc, indent=1))
    if not runs:
        (out / "validation.json").write_text(json.dumps(doc, indent=1))
    if not args.no_report:
        from benchmarks import validation_report

        validation_report.write_checked(doc["results"], out, doc)
    return 0


def select(runs: list[tuple[str, dict]], only: str | None) -> list[tuple[str, dict]]:
    """The runs of ``plan`` that ``--only`` keeps: each comma-separated entry is a case function
    name, optionally followed by ``:key=value`` pairs that the run's keyword arguments must
    match (compared as written: ``resolution=12``, ``S=0.2``, ``elastic_force=paper``); a run
    without the key matches its value in ``PLAN_DEFAULTS`` (``fit_weight=<DEFAULT_FIT_WEIGHT>``
    keeps the runs that do not name a weight)."""
    if not only:
        return list(runs)
    keep = []
    for entry in only.split(","):
        name, *pairs = entry.strip().split(":")
        want = {}
        for pair in pairs:
            if "=" not in pair:
                raise ValueError(f"--only entry {entry!r} is not allowed: after the case name, key=value pairs "
                                 "separated by ':'")
            k, v = pair.split("=", 1)
            want[k] = v
        keep.append((name, want))

    def matches(run, name, want):
        args = PLAN_DEFAULTS | run[1]
        return run[0] == name and all(k in args and str(args[k]) == v for k, v in want.items())

    return [r for r in runs if any(matches(r, name, want) for name, want in keep)]


#: The result fields that tell one run of a case from another (its parameters, not its outcome).
IDENTITY = ("S", "resolution", "elastic_force", "shallowness", "amplitude", "dt_factor", "deformation", "fit",
            "hourglass", "label", "dtype", "span_over_thickness", "aspect", "hold", "floor", "strain", "fit_weight",
            "width")


#: Identity fields whose absence from a ROW means a value: a row written before the field
#: existed ran the solver's default then, which stays its value whatever the default is now
#: (the fit weight was poly6 before it was an option). Not a plan entry's: ``PLAN_DEFAULTS``.
IDENTITY_DEFAULTS = {"fit_weight": "poly6"}
#: Keyword arguments whose absence from a PLAN ENTRY means a value: the entry calls the case
#: function without it, which runs the solver's default now, not what an old row ran.
PLAN_DEFAULTS = {"fit_weight": DEFAULT_FIT_WEIGHT}


def same_run(a: dict, b: dict) -> bool:
    """Whether two results measure the same row: the same case, and equal in every identity
    field both carry (a result written before a field existed matches on the others, or on
    the field's value then, ``IDENTITY_DEFAULTS``)."""
    if a["case"] != b["case"]:
        return False
    a = IDENTITY_DEFAULTS | a
    b = IDENTITY_DEFAULTS | b
    return all(a[k] == b[k] for k in IDENTITY if k in a and k in b)


def merge(earlier: dict | None, results: list[dict], meta: dict, drop=()) -> dict:
    """The JSON document of this run, merged into ``earlier`` (a validation.json) if given.

    ``runs`` lists every run merged so far (command, wall time, machine, commit), this one
    last; each result's ``run`` is its index there. Results of ``earlier`` that this run
    measured again (``same_run``) are dropped; the rest keep their run, which is carried over
    from ``earlier`` (a JSON written before runs were recorded is one run, its ``command``).
    Results of ``earlier`` whose case is in ``drop`` are not kept at all. A run left without
    results stays listed, marked ``"superseded": True``: the report's notes cite runs by
    number (R7), and dropping one would renumber every later run under them."""
    runs, kept = [], []
    if earlier is not None:
        old_runs = earlier.get("runs") or [{k: earlier[k] for k in ("command", "machine", "python", "wall_s")
                                           if k in earlier}]
        runs = [dict(r) for r in old_runs]
        for r in earlier["results"]:
            if r["case"] in drop or any(same_run(r, n) for n in results):
                continue
            kept.append(r | {"run": r.get("run", 0)})
        holding = {r["run"] for r in kept}
        for i, run in enumerate(runs):
            if i not in holding:
                run["superseded"] = True
    new = [r | {"run": len(runs)} for r in results]
    runs.append(meta)
    return {"command": "; ".join(r.get("command", "?") for r in runs), "runs": runs,
            "wall_s": sum(r.get("wall_s") or 0.0 for r in runs), "machine": meta["machine"],
            "python": meta["python"], "results": kept + new}


def added_rows(earlier: dict | None, path: pathlib.Path, source: str | None = None) -> dict:
    """``earlier`` (a validation.json, or None) with the rows of ``path`` merged in as one run
    (``merge``): ``path`` holds a list of results of the case functions (as ``slump(...)``
    returns them, optionally with a ``device``), or a document with ``results`` (and maybe a
    ``command``, ``commit``, ``date``, ``machine``). Rows that ``result_rows`` refuses, or none,
    are a ``ValueError`` that names ``source`` (default: the path)."""
    source = source or str(path)
    data = json.loads(pathlib.Path(path).read_text())
    rows = result_rows(data, source)
    if not rows:
        raise ValueError(f"{source} is not allowed: it holds no results, so there is nothing to add")
    doc = data if isinstance(data, dict) else {}
    devices = sorted({str(r["device"]) for r in rows if r.get("device")})
    machine = doc.get("machine") or "?"
    if devices:
        machine += " (" + ", ".join(devices) + ")"
    meta = {"command": doc.get("command") or f"rows of {pathlib.Path(path).name}, measured elsewhere",
            "commit": doc.get("commit"), "date": doc.get("date"), "machine": machine, "python": doc.get("python", "?"),
            "wall_s": float(sum(r.get("wall_s") or 0.0 for r in rows))}
    return merge(earlier, [{k: v for k, v in r.items() if k != "run"} for r in rows], meta)


def _meta(args, t0) -> dict:
    import platform
    import subprocess

    cmd = "python -m benchmarks.validation" + (" --quick" if args.quick else "") + \
        (f" --only {args.only}" if args.only else "") + (f" --merge {args.merge}" if args.merge else "") + \
        (f" --drop {args.drop}" if args.drop else "") + (f" --add {args.add}" if args.add else "")
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"command": cmd, "commit": commit, "date": time.strftime("%Y-%m-%d", time.gmtime()),
            "machine": platform.machine(), "python": platform.python_version(), "wall_s": time.perf_counter() - t0}


if __name__ == "__main__":
    from benchmarks import _cli

    sys.exit(_cli.run(main, PROG))  # bad arguments (ValueError, OSError): one line, exit status 2
