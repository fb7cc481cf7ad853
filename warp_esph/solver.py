"""The time step (SPEC §1): ``Solver(model).step(state_in, state_out, dt)``.

``step`` reads ``state_in`` and writes only ``state_out``, so a rollout with one state
per step can be recorded on a ``wp.Tape`` and differentiated.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import warp as wp

from . import checks, deformation, forces, integrate, neighbors, plasticity, pressure
from .model import Model, State

GUARD_NAMES = ("few_neighbors", "ill_conditioned", "inverted", "plasticity_skipped")


class Solver:
    """Explicit elastoplastic step of Gerszewski et al. 2009.

    ``min_neighbors`` and ``max_condition`` are the guards of paper §4 on the
    deformation update; ``guard_counts()`` says how often each fired.
    """

    def __init__(self, model: Model, *, min_neighbors: int = 6, max_condition: float = 1.0e3):
        self.model = model
        self.min_neighbors = checks.positive_int("min_neighbors", min_neighbors)
        self.max_condition = checks.greater_than("max_condition", max_condition, 1.0, "1")
        S = model.scalar
        self.search = neighbors.NeighborSearch(
            model.particle_count, S, model.device, model.support_radius,
            min_neighbors=self.min_neighbors, max_condition=self.max_condition,
        )
        self._k_deform = deformation.kernels(S)
        self._k_plastic = plasticity.kernels(S)
        self._k_forces = forces.kernels(S)
        self._k_pressure = pressure.kernels(S)
        self._k_integrate = integrate.kernels(S, len(model.planes), len(model.spheres), len(model.boxes))
        self._sph = any(m.pressure_stiffness > 0.0 or m.viscosity > 0.0 for m in model.materials)
        self._counters = wp.zeros(len(GUARD_NAMES), dtype=wp.int32, device=model.device)
        self._stable_dt = model.stable_dt()
        self._warned_dt = set()
        self.step_count = 0

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
                f"(0.3 * spacing / p-wave speed, SPEC §8); the run may blow up",
                RuntimeWarning,
                stacklevel=3,
            )
        return dt

    def step(self, state_in: State, state_out: State, dt: float):
        if state_in is state_out:
            raise ValueError("state_out is state_in: the step reads state_in and writes state_out, pass two states")
        dt = self.check_dt(dt)
        m = self.model
        n = m.particle_count
        S = m.scalar
        h = S(m.support_radius)
        dev = m.device

        # 1. Neighbour lists and neighbourhood guards (integers, not taped).
        self.search.build(
            state_in.x, m.particle_body, state_out.neighbors, state_out.neighbor_d2, state_out.neighbor_count, state_out.guard
        )
        nbr, count = state_out.neighbors, state_out.neighbor_count
        state_out.force.zero_()

        # 2. SPH density, finished before any pressure uses it (WARP_NOTES trap 1).
        if self._sph:
            wp.launch(self._k_pressure.density, n, [state_in.x, m.particle_mass, nbr, count, h], [state_out.density], device=dev)

        # 3. Plastic flow of the stored F, stress, F^-1.
        wp.launch(
            self._k_plastic.constitutive_update,
            n,
            [state_in.F, state_in.alpha, m.particle_material, m.mu, m.lam, m.yield_stress, m.flow_rate, m.hardening, m.material_model, S(dt)],
            [state_out.F_flowed, state_out.alpha, state_out.stress, state_out.F_inv, self._counters],
            device=dev,
        )

        # 4. Elastic pair forces, pressure and viscosity.
        wp.launch(
            self._k_forces.elastic_forces,
            n,
            [state_in.x, m.particle_body, nbr, count, m.particle_volume, state_out.stress, state_out.F_inv, h],
            [state_out.force],
            device=dev,
        )
        if self._sph:
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

        # 5. Symplectic Euler, gravity, colliders.
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

        # 6. Incremental deformation gradient over the step (eqs. 1-8).
        wp.launch(
            self._k_deform.update_deformation,
            n,
            [state_in.x, state_out.x, m.particle_body, nbr, count, state_out.guard, state_out.F_flowed, h],
            [state_out.F, self._counters],
            device=dev,
        )
        self.step_count += 1
