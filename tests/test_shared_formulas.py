"""The formulas that several kernels share, each written once as a ``wp.func``: what each
computes, in both precisions, at the cases its callers meet."""

import functools

import numpy as np
import pytest
import warp as wp

from warp_esph._types import type_set
from warp_esph.sim import deformation

SCALARS = [wp.float32, wp.float64]


@functools.cache
def _uncompensated_update_kernel(scalar):
    T = type_set(scalar)
    update = deformation.funcs(scalar, "poly6").uncompensated_update

    @wp.kernel
    def run(F: wp.array(dtype=T.mat33), inc: wp.array(dtype=T.mat33), scale: wp.array(dtype=scalar),
            out: wp.array(dtype=T.mat33), applied: wp.array(dtype=wp.int32)):
        i = wp.tid()
        o, a = update(F[i], inc[i], scale[i])
        out[i] = o
        applied[i] = a

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_uncompensated_update_is_eq8_unless_it_inverts(scalar):
    """``deformation``'s ``uncompensated_update`` (eq. 8 faded, the floor image's own update
    of both fits and what the update adjoint recomputes): ``F + (s inc) F`` and 1 where its
    determinant is positive; ``F`` and 0 where it would invert (paper §4), however the fade
    ``s`` gets there."""
    T = type_set(scalar)
    np_t = np.float32 if scalar == wp.float32 else np.float64
    rng = np.random.default_rng(3)
    F0 = np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    squash = np.diag([0.0, 0.0, -1.6])  # dF = diag(1, 1, -0.6) at s = 1: inverted
    cases = [(F0, 0.05 * rng.normal(size=(3, 3)), 1.0), (F0, squash, 1.0), (F0, squash, 0.5),
             (F0, 0.05 * rng.normal(size=(3, 3)), 0.0)]
    F = np.array([c[0] for c in cases], dtype=np_t)
    inc = np.array([c[1] for c in cases], dtype=np_t)
    s = np.array([c[2] for c in cases], dtype=np_t)
    out = wp.zeros(len(cases), dtype=T.mat33)
    applied = wp.zeros(len(cases), dtype=wp.int32)
    wp.launch(_uncompensated_update_kernel(scalar), len(cases),
              [wp.array(F, dtype=T.mat33), wp.array(inc, dtype=T.mat33), wp.array(s, dtype=scalar)], [out, applied])
    out, applied = out.numpy(), applied.numpy()
    want = F.astype(np.float64) + np.einsum("k,kij,kjl->kil", s.astype(np.float64), inc.astype(np.float64),
                                            F.astype(np.float64))
    assert applied.tolist() == [1, 0, 1, 1]
    tol = 1e-6 if scalar == wp.float32 else 1e-14
    np.testing.assert_allclose(out[[0, 2, 3]], want[[0, 2, 3]], rtol=0, atol=tol)
    assert np.array_equal(out[1], F[1]), "an inverting update keeps F"
    assert np.array_equal(out[3], F[3]), "a fade of 0 leaves F as it was"
    assert np.linalg.det(want[1]) < 0 < np.linalg.det(want[2])


@functools.cache
def _pair_viscosity_kernel(scalar):
    from warp_esph.sim import pressure

    pair_viscosity = pressure.funcs(scalar).pair_viscosity

    @wp.kernel
    def run(eta: wp.array(dtype=scalar), out: wp.array(dtype=scalar)):
        i = wp.tid()
        out[i] = pair_viscosity(eta[2 * i], eta[2 * i + 1])

    return run


@pytest.mark.parametrize("scalar", SCALARS)
def test_pair_viscosity_is_the_mean_and_symmetric(scalar):
    """``pressure``'s ``pair_viscosity``, the ``eta_ij`` of the viscous force on both the
    fused and the differentiable path (and its adjoint): the mean of the two viscosities,
    the same for ``(i, j)`` and ``(j, i)`` so that a pair's forces are equal and opposite
    across materials."""
    np_t = np.float32 if scalar == wp.float32 else np.float64
    eta = np.array([0.0, 3.0, 3.0, 0.0, 1.5, 1.5, 0.25, 40.0], dtype=np_t)
    out = wp.zeros(len(eta) // 2, dtype=scalar)
    wp.launch(_pair_viscosity_kernel(scalar), len(out), [wp.array(eta, dtype=scalar)], [out])
    got = out.numpy()
    np.testing.assert_allclose(got, 0.5 * (eta[0::2] + eta[1::2]), rtol=1e-7, atol=0)
    assert got[0] == got[1], "the pair's coefficient does not depend on its order"
