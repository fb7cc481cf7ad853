"""The time step (SPEC §1): ``Solver(model).step(state_in, state_out, dt)``.

``step`` reads ``state_in`` and writes only ``state_out``, so a rollout with one state
per step can be recorded on a ``wp.Tape`` and differentiated.
"""

from __future__ import annotations

import contextlib
import math
import time
import warnings

import numpy as np
import warp as wp

from . import checks, comparison, deformation, fields, forces, integrate, neighbors, plasticity, pressure
from . import fused as fused_kernels
from .model import Model, State

GUARD_NAMES = ("few_neighbors", "ill_conditioned", "inverted", "plasticity_skipped")

#: Default Verlet skin of the neighbour candidates, in units of the support radius
#: (measured in benchmarks/step.py, docs/performance.md).
DEFAULT_SKIN = 0.15

#: Names ``profile_phases`` times: the fused step has neighbors, fused, integrate and
#: deformation; the differentiable one (under a tape, or ``fused=False``) splits
#: ``fused`` into density, constitutive, forces and pressure.
PHASES = ("neighbors", "density", "constitutive", "forces", "pressure", "fused", "integrate", "deformation")


_NO_PHASE = contextlib.nullcontext()


def tape_recording() -> bool:
    """Whether a ``wp.Tape`` is recording launches now."""
    runtime = getattr(getattr(getattr(wp, "_src", None), "context", None), "runtime", None)
    if runtime is None:  # pragma: no cover (older layout)
        runtime = wp.context.runtime
    return getattr(runtime, "tape", None) is not None


class Solver:
    """Explicit elastoplastic step of Gerszewski et al. 2009.

    ``min_neighbors`` and ``max_condition`` are the guards of paper §4 on the
    deformation update; ``guard_counts()`` says how often each fired.

    ``neighbor_skin`` (in units of the support radius ``h``, in [0, 1]; default
    ``DEFAULT_SKIN``) is the Verlet margin of the neighbour candidates: they are rebuilt only when two
    particles may have moved by more than it relative to each other, and the 30
    nearest within ``h`` are selected from them every step, so the lists are those of
    a fresh search (``0``: search afresh every step). ``fused`` (default on) runs the
    constitutive update and all pair forces in one kernel with one SVD per particle
    when no ``wp.Tape`` is recording; under a tape the differentiable kernels run.

    A model with a material of a Fig. 8 comparison deformation model (``Material.deformation``
    ``"rest"`` or ``"additive"``, SPEC §7) always runs the non-fused kernels, with the
    constitutive and deformation updates of ``comparison.py``. The model's force fields
    (``fields.CompressionField``) act while active at ``state_in.time``.
    """

    def __init__(
        self,
        model: Model,
        *,
        min_neighbors: int = 6,
        max_condition: float = 1.0e3,
        neighbor_skin: float | None = None,
        fused: bool = True,
    ):
        self.model = model
        self.min_neighbors = checks.positive_int("min_neighbors", min_neighbors)
        self.max_condition = checks.greater_than("max_condition", max_condition, 1.0, "1")
        S = model.scalar
        skin = DEFAULT_SKIN if neighbor_skin is None else checks.in_range("neighbor_skin", neighbor_skin, 0.0, 1.0)
        if not isinstance(fused, bool):
            raise ValueError(f"fused = {fused!r} is not allowed: must be True or False")
        self.neighbor_skin = skin
        self.search = neighbors.NeighborSearch(
            model.particle_count, S, model.device, model.support_radius,
            min_neighbors=self.min_neighbors, max_condition=self.max_condition,
            skin=skin * model.support_radius, spacing=model.spacing, bodies_interact=model.bodies_interact,
        )
        self.fused = bool(fused)
        self._k_fused = fused_kernels.kernels(S)
        # Per-particle SPH pressure and volume m / rho of the fast path (scratch: written
        # and read within one step).
        self._pressure = wp.zeros(model.particle_count, dtype=S, device=model.device)
        self._sph_volume = wp.zeros(model.particle_count, dtype=S, device=model.device)
        #: Seconds per phase, summed over steps while ``profile_phases`` is on, else None.
        self.phase_times: dict[str, float] | None = None
        self._k_deform = deformation.kernels(S)
        self._k_plastic = plasticity.kernels(S)
        self._k_forces = forces.kernels(S)
        self._k_pressure = pressure.kernels(S)
        self._k_integrate = integrate.kernels(S, len(model.planes), len(model.spheres), len(model.boxes))
        self._cmp = model.uses_comparison_models
        self._k_cmp = comparison.kernels(S) if self._cmp else None
        if self._cmp:
            model.rest_neighbors()
        self._k_fields = fields.kernels(S)
        self._sph = any(m.pressure_stiffness > 0.0 or m.viscosity > 0.0 for m in model.materials)
        self._counters = wp.zeros(len(GUARD_NAMES), dtype=wp.int32, device=model.device)
        self._stable_dt = model.stable_dt()
        self._warned_dt = set()
        self.step_count = 0

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
        """How many particle-steps each guard skipped since construction or ``reset_counts``."""
        return dict(zip(GUARD_NAMES, (int(c) for c in self._counters.numpy())))

    def reset_counts(self):
        self._counters.zero_()

    def check_dt(self, dt) -> float:
        dt = checks.positive("dt", dt)
        if dt > self._stable_dt and dt not in self._warned_dt:
            self._warned_dt.add(dt)
            warnings.warn(
                f"dt = {dt:g} s is above the explicit stability limit {self._stable_dt:.3g} s "
                f"(Model.stable_dt: 0.3 * spacing / p-wave speed, SPEC §8, and the viscous limit "
                f"0.025 rho0 h^2 / viscosity); the run may blow up",
                RuntimeWarning,
                stacklevel=3,
            )
        return dt

    def step(self, state_in: State, state_out: State, dt: float):
        checks.step_states(self.model, state_in, state_out)
        dt = self.check_dt(dt)
        m = self.model
        n = m.particle_count
        S = m.scalar
        h = S(m.support_radius)
        dev = m.device

        fast = self.fused and not self._cmp and not tape_recording()
        phase = self._phase

        # 1. Neighbour lists and neighbourhood guards (integers, not taped). The fast
        # path also sums the SPH density there (WARP_NOTES trap 1: it is finished
        # before any pressure uses it).
        with phase("neighbors"):
            sph = None
            if fast and self._sph:
                sph = (
                    m.particle_mass, m.particle_material, m.particle_rest_density, m.pressure_stiffness,
                    m.clamp_pressure, state_out.density, self._pressure, self._sph_volume,
                )
            self.search.update(
                state_in.x, m.particle_body, state_out.neighbors, state_out.neighbor_d2, state_out.neighbor_count,
                None if fast else state_out.guard, sph,
            )
        nbr, count = state_out.neighbors, state_out.neighbor_count
        state_out.force.zero_()

        if fast:
            # 2-4 fused: plastic flow, stress, F^-1 and every pair force in one launch.
            with phase("fused"):
                wp.launch(
                    self._k_fused.constitutive_forces,
                    n,
                    [
                        state_in.x, state_in.v, state_in.F, state_in.alpha, m.particle_material, m.particle_body,
                        m.particle_volume, m.particle_mass, state_out.density, self._pressure, self._sph_volume,
                        m.mu, m.lam, m.yield_stress, m.flow_rate, m.hardening, m.material_model,
                        m.viscosity, m.material_elastic_force, nbr, count, h, S(dt), int(self._sph),
                        self.min_neighbors, S(self.max_condition),
                    ],
                    [state_out.F_flowed, state_out.alpha, state_out.stress, state_out.F_inv, state_out.force, self._counters],
                    device=dev,
                )
        else:
            # 2. SPH density, finished before any pressure uses it (WARP_NOTES trap 1).
            if self._sph:
                with phase("density"):
                    wp.launch(self._k_pressure.density, n, [state_in.x, m.particle_mass, nbr, count, h], [state_out.density], device=dev)

            # 3. Plastic flow of the stored F, stress, F^-1.
            with phase("constitutive"):
                if self._cmp:
                    wp.launch(
                        self._k_cmp.constitutive_update,
                        n,
                        [
                            state_in.F, state_in.alpha, state_in.F_p, m.particle_material, m.material_deformation, m.mu, m.lam,
                            m.yield_stress, m.flow_rate, m.hardening, m.material_model, S(dt),
                        ],
                        [state_out.F_flowed, state_out.alpha, state_out.F_p, state_out.stress, state_out.F_inv, self._counters],
                        device=dev,
                    )
                else:
                    wp.launch(
                        self._k_plastic.constitutive_update,
                        n,
                        [state_in.F, state_in.alpha, m.particle_material, m.mu, m.lam, m.yield_stress, m.flow_rate, m.hardening, m.material_model, S(dt)],
                        [state_out.F_flowed, state_out.alpha, state_out.stress, state_out.F_inv, self._counters],
                        device=dev,
                    )

            # 4. Elastic pair forces, pressure and viscosity.
            with phase("forces"):
                wp.launch(
                    self._k_forces.elastic_forces,
                    n,
                    [
                        state_in.x, m.particle_body, m.particle_material, m.material_elastic_force, nbr, count,
                        state_out.guard, m.particle_volume, state_out.stress, state_out.F_flowed, state_out.F_inv, h,
                    ],
                    [state_out.force],
                    device=dev,
                )
            if self._sph:
                with phase("pressure"):
                    wp.launch(
                        self._k_pressure.pressure_forces,
                        n,
                        [
                            state_in.x, state_in.v, m.particle_mass, state_out.density, m.particle_rest_density, m.particle_material,
                            m.pressure_stiffness, m.viscosity, m.clamp_pressure, nbr, count, h,
                        ],
                        [state_out.force],
                        device=dev,
                    )

        # External force fields active at the step's start time.
        for fld in m.force_fields:
            if fld.active(state_in.time):
                wp.launch(
                    self._k_fields.add_compression,
                    n,
                    [state_in.x, m.particle_mass, m.particle_body, int(fld.body), m.types.vec3(*fld.center), S(fld.strength)],
                    [state_out.force],
                    device=dev,
                )

        # 5. Symplectic Euler, gravity, colliders.
        with phase("integrate"):
            wp.launch(
                self._k_integrate.integrate,
                n,
                [
                    state_in.x, state_in.v, state_out.force, m.particle_mass, m.types.vec3(*m.gravity), S(dt),
                    m.plane_normal, m.plane_offset, m.plane_friction,
                    m.sphere_center, m.sphere_radius, m.sphere_friction,
                    m.box_center, m.box_half, m.box_friction,
                ],
                [state_out.x, state_out.v],
                device=dev,
            )

        # 6. Incremental deformation gradient over the step (eqs. 1-8); the fast path
        # evaluates the neighbourhood guards here, on the fit's own moment matrix.
        with phase("deformation"):
            if fast:
                wp.launch(
                    self._k_fused.update_deformation,
                    n,
                    [
                        state_in.x, state_out.x, m.particle_body, nbr, count, state_out.F_flowed, h,
                        self.min_neighbors, S(self.max_condition),
                    ],
                    [state_out.F, state_out.guard, self._counters],
                    device=dev,
                )
            elif self._cmp:
                rest_x, rest_nbr, rest_count = m.rest_neighbors()
                wp.launch(
                    self._k_cmp.update_deformation,
                    n,
                    [
                        state_in.x, state_out.x, rest_x, m.particle_body, nbr, count, rest_nbr, rest_count, state_out.guard,
                        m.particle_material, m.material_deformation, state_out.F_flowed, state_out.F_p, h,
                    ],
                    [state_out.F, self._counters],
                    device=dev,
                )
            else:
                wp.launch(
                    self._k_deform.update_deformation,
                    n,
                    [state_in.x, state_out.x, m.particle_body, nbr, count, state_out.guard, state_out.F_flowed, h],
                    [state_out.F, self._counters],
                    device=dev,
                )
        state_out.time = state_in.time + dt
        self.step_count += 1
