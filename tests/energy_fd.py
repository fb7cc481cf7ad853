"""The energy the variational force is minus the gradient of, and the central differences
that check it: one step of ``dt`` in which a single coordinate moves by ``delta``."""

import numpy as np


def stvk_psi(model, F):
    """St. Venant-Kirchhoff energy density of each ``F`` (material 0's ``mu``, ``lam``)."""
    C = np.einsum("nki,nkj->nij", F, F)
    E = 0.5 * (C - np.eye(3))
    tr = np.trace(E, axis1=1, axis2=2)
    mu, lam = model.materials[0].mu, model.materials[0].lam
    return mu * np.einsum("nij,nij->n", E, E) + 0.5 * lam * tr**2


def stvk_energy(model, F) -> float:
    """``sum_i V_i psi(F_i)`` with ``Model.particle_volume``."""
    return float((model.particle_volume.numpy() * stvk_psi(model, F)).sum())


def mover(solver, a, b, dt: float = 1.0e-9):
    """``moved(k, delta)``: ``b`` after one step from ``a`` in which coordinate ``k`` (of the
    flattened positions) alone moves by ``delta``."""
    n = a.x.shape[0]

    def moved(k, delta):
        v = np.zeros((n, 3))
        v.flat[k] = delta / dt
        a.v.assign(v)
        solver.step(a, b, dt)
        return b

    return moved


def central_gradient(energy, coords, delta: float = 1.0e-7) -> np.ndarray:
    """``(energy(k, delta) - energy(k, -delta)) / (2 delta)`` for each coordinate ``k``."""
    return np.array([(energy(k, delta) - energy(k, -delta)) / (2 * delta) for k in coords])


def image_heights(y, spacing: float) -> np.ndarray:
    """Heights of the floor images of points at heights ``y`` over the plane y = 0
    (``deformation.image_depth``, written again here): mirrors from half a spacing up, half a
    spacing deep below a quarter spacing, and between them the cubic that joins the two with
    a continuous slope."""
    m = 0.5 * spacing
    w = 0.5 * m
    t = np.clip(1.0 + (y - m) / w, 0.0, 1.0)
    return -np.where(y >= m, y, m + w * t * t * (t - 1.0))
