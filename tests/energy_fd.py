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


def corotated_psi(model, F):
    """The corotated energy density ``mu sum(s - 1)^2 + lam/2 (sum(s - 1))^2`` of each ``F``
    (material 0's ``mu``, ``lam``) in its signed singular values (the smallest negative where
    det F < 0, as the rotation-variant SVD's): the energy whose gradient the linear models'
    stress is where the material cannot flow (``forces.corotated_stress``)."""
    U, s, Vt = np.linalg.svd(np.asarray(F, dtype=np.float64))
    s[:, 2] *= np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    e = s - 1.0
    mu, lam = model.materials[0].mu, model.materials[0].lam
    return mu * (e * e).sum(axis=1) + 0.5 * lam * e.sum(axis=1) ** 2


def corotated_energy(model, F) -> float:
    """``sum_i V_i corotated_psi(F_i)``."""
    return float((model.particle_volume.numpy() * corotated_psi(model, F)).sum())


def continued_stvk_psi(model, F):
    """``stvk_psi``, and where det F <= 0 the rest model's continuation through det = 0
    (``comparison``'s ``inverted_stress``): ``psi(s_0, s_1, 0) + (lam + 2 mu) s_2^2 / 2`` of the
    singular values with the reflection in the smallest, ``s_2 <= 0``."""
    F = np.asarray(F, dtype=np.float64)
    psi = stvk_psi(model, F)
    inverted = np.linalg.det(F) <= 0.0
    if inverted.any():
        s = np.linalg.svd(F[inverted], compute_uv=False)
        s2 = -s[:, 2]
        s[:, 2] = 0.0
        mu, lam = model.materials[0].mu, model.materials[0].lam
        psi[inverted] = stvk_psi(model, np.einsum("ni,ij->nij", s, np.eye(3))) + 0.5 * (lam + 2.0 * mu) * s2**2
    return psi


def continued_stvk_energy(model, F) -> float:
    """``sum_i V_i continued_stvk_psi(F_i)``."""
    return float((model.particle_volume.numpy() * continued_stvk_psi(model, F)).sum())


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


def image_energy_share(y, h: float, spacing: float) -> np.ndarray:
    """The share ``c`` of each particle's image's energy at heights ``y`` over the plane y = 0
    on the frictionless imaged ground (``forces.image_energy_share``, written again here):
    1/2 up to half a spacing under ``h``, fading to 0 at ``h`` by the smoothstep."""
    t = np.clip((h - y) / (0.5 * spacing), 0.0, 1.0)
    return 0.5 * t * t * (3.0 - 2.0 * t)
