"""Static solution of the variational force's linear stiffness (docs/physics.md, "Bending stiffness").

For a small load the variational elastic force is linear in the displacement ``u``: its
stiffness is ``K = sum_i V_i G_i^T C G_i``, with ``G_i`` the gradient operator of particle
``i``'s fit (``grad u_i = sum_j (u_j - u_i) g_ij^T``) and ``C`` the isotropic elasticity.
Solving ``K u = m g`` with the supports held gives the deflection that dynamic relaxation
should reach, without the relaxation. numpy only, dense: small lattices (a few thousand
particles).

    python -m benchmarks.static_stiffness                  # the table of docs/physics.md
    python -m benchmarks.static_stiffness --modes          # the free cube's modes, the ridge and the residual penalty

Fits: ``"paper"`` (eqs. 5-6, ``g = w A^-1 xb``), ``"corrected"`` (the curvature-corrected
fit of ``warp_esph/sim/curvature.py``, ``Solver(fit="curvature_corrected")``, ``g = w A~^-1 (xb - K^T q(xb))``), ``"centroid"``
(an affine fit with an intercept, for comparison).

``hourglass = c`` adds the stiffness of a penalty on each fit's residual (not a part of
the solver: the remedy docs/physics.md, "Side effects of the corrected fit", measured):
``c mu / 2 sum_i sum_j (w_ij / sum_k w_ik) |u_j - u_i - G_i xb_ij|^2 / |xb_ij|^2``, with
``G_i`` the fit's gradient (either fit), so affine motions cost nothing.
"""

import numpy as np

from benchmarks import _cli

EPS = 1.0e-4  # curvature.CURVATURE_RIDGE: the ridge of curvature_projection, relative to tr(A) / 3
DET_RATIO = 0.1  # curvature.CURVATURE_DET_RATIO: the correction is dropped below det A~ / det A


def neighbours(x: np.ndarray, h: float) -> list:
    r2 = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(r2, np.inf)
    return [np.nonzero(row < h * h)[0] for row in r2]


def gradient_ops(x: np.ndarray, nb: list, h: float, fit: str = "paper", eps: float = EPS,
                 det_ratio: float = DET_RATIO) -> list:
    """Per particle ``(j, g)``: ``grad u_i = sum_j (u_j - u_i) g_j^T``."""
    ops = []
    for i in range(len(x)):
        xb = x[nb[i]] - x[i]
        w = (h * h - (xb * xb).sum(1)) ** 3
        A = np.einsum("n,ni,nj->ij", w, xb, xb)
        if fit == "paper":
            g = w[:, None] * np.linalg.solve(A, xb.T).T
        elif fit == "corrected":
            q = np.stack([xb[:, 0] * xb[:, 1], xb[:, 0] * xb[:, 2], xb[:, 1] * xb[:, 2]], 1) / h
            C = np.einsum("n,ni,nj->ij", w, xb, q)
            D = np.einsum("n,ni,nj->ij", w, q, q) + eps * np.trace(A) / 3.0 * np.eye(3)
            K = np.linalg.solve(D, C.T)
            if np.linalg.det(A - C @ K) <= det_ratio * np.linalg.det(A):
                K = np.zeros((3, 3))
            g = w[:, None] * np.linalg.solve(A - C @ K, (xb - q @ K).T).T
        elif fit == "centroid":
            ws = np.concatenate([[h**6], w])
            xs = np.concatenate([np.zeros((1, 3)), xb])
            xc = xs - (ws[:, None] * xs).sum(0) / ws.sum()
            Ac = np.einsum("n,ni,nj->ij", ws, xc, xc)
            g = (ws[:, None] * np.linalg.solve(Ac, xc.T).T)[1:]
        else:
            raise ValueError(f"fit = {fit!r} is not allowed: must be 'paper', 'corrected' or 'centroid'")
        ops.append((nb[i], g))
    return ops


def stiffness(n_particles: int, ops: list, mu: float, lam: float, volume: float = 1.0) -> np.ndarray:
    T = np.zeros((9, 9))
    for a in range(3):
        for b in range(3):
            T[3 * a + b, 3 * b + a] = 1.0
    t = np.eye(3).reshape(9)
    Dm = mu * (np.eye(9) + T) + lam * np.outer(t, t)  # psi = mu eps:eps + lam/2 tr(eps)^2
    K = np.zeros((3 * n_particles, 3 * n_particles))
    for i, (js, g) in enumerate(ops):
        idx = np.concatenate([[i], js])
        B = np.zeros((9, 3 * len(idx)))
        for a in range(3):
            for b in range(3):
                B[3 * a + b, 3 * np.arange(1, len(idx)) + a] = g[:, b]
                B[3 * a + b, a] = -g[:, b].sum()
        dof = (3 * idx[:, None] + np.arange(3)).reshape(-1)
        K[np.ix_(dof, dof)] += volume * B.T @ Dm @ B
    return K


def residual_stiffness(x: np.ndarray, ops: list, h: float, mu: float, c: float) -> np.ndarray:
    """Stiffness of the residual penalty (module docstring, ``hourglass = c``)."""
    n = len(x)
    K = np.zeros((3 * n, 3 * n))
    for i, (js, g) in enumerate(ops):
        xb = x[js] - x[i]
        r2 = (xb * xb).sum(1)
        w = (h * h - r2) ** 3
        R = np.eye(len(js)) - xb @ g.T  # r_j = sum_k R[j, k] (u_k - u_i)
        Rf = np.concatenate([-R.sum(1, keepdims=True), R], 1)
        M = c * mu * Rf.T @ ((w / w.sum() / r2)[:, None] * Rf)
        idx = np.concatenate([[i], js])
        for a in range(3):
            K[np.ix_(3 * idx + a, 3 * idx + a)] += M
    return K


def _operator(x: np.ndarray, hdx: float, fit: str, nu: float, hourglass: float, **fit_kw) -> np.ndarray:
    mu, lam = _lame(nu)
    ops = gradient_ops(x, neighbours(x, hdx), hdx, fit, **fit_kw)
    K = stiffness(len(x), ops, mu, lam)
    return K + residual_stiffness(x, ops, hdx, mu, hourglass) if hourglass else K


def cube_modes(n: int = 6, hdx: float = 2.0, fit: str = "paper", nu: float = 0.3, hourglass: float = 0.0, **fit_kw) -> np.ndarray:
    """``omega^2`` of a free ``n^3`` lattice cube (dx = 1, E = 1, unit masses), the six rigid
    modes left out, ascending."""
    k, j, l = np.meshgrid(*(np.arange(n),) * 3, indexing="ij")
    x = np.stack([k, j, l], -1).reshape(-1, 3).astype(float)
    K = _operator(x, hdx, fit, nu, hourglass, **fit_kw)
    return np.sort(np.linalg.eigvalsh(0.5 * (K + K.T)))[6:]


def _lame(nu: float, E: float = 1.0):
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def beam(n: int = 6, span: int = 5, hdx: float = 2.0, fit: str = "paper", nu: float = 0.3, kappa: float = 0.85,
         hourglass: float = 0.0, **fit_kw) -> float:
    """``benchmarks.validation.beam_deflection``'s beam (dx = 1, E = 1, rho g = 1): the bottom
    particles of the two end columns held vertically; midspan deflection / Timoshenko."""
    cols = n * span
    k, j, l = np.meshgrid(np.arange(cols + 1), np.arange(n), np.arange(n), indexing="ij")
    x = np.stack([k - cols / 2, j, l - (n - 1) / 2], -1).reshape(-1, 3).astype(float)
    L, t = float(cols), float(n)
    mu, lam = _lame(nu)
    K = _operator(x, hdx, fit, nu, hourglass, **fit_kw)
    f = np.zeros(3 * len(x))
    f[1::3] = -1.0
    ends = np.abs(np.abs(x[:, 0]) - L / 2) < 0.25
    mid = np.abs(x[:, 0]) < 0.25
    free = np.setdiff1d(np.arange(3 * len(x)), 3 * np.nonzero(ends & (x[:, 1] < 0.25))[0] + 1)
    Kf = K[np.ix_(free, free)]
    Kf += 1e-12 * np.trace(Kf) / len(free) * np.eye(len(free))  # the free rigid modes (x, z, about y)
    u = np.zeros(3 * len(x))
    u[free] = np.linalg.solve(Kf, f[free])
    d = -(u[1::3][mid].mean() - u[1::3][ends].mean())
    A, I = t * t, t**4 / 12
    return d / (5 * A * L**4 / (384 * I) + A * L**2 / (8 * kappa * mu * A))


def cantilever(n: int = 5, clamp_cols: int = 3, hdx: float = 2.0, fit: str = "paper", nu: float = 0.3,
               kappa: float = 0.85, length_over_t: int = 4, clamp_line: float = -0.5) -> float:
    """tests/test_tools.py's cantilever (clamp: the particles at x < 0 held): tip deflection /
    (Euler-Bernoulli + shear) at the tip particles' x, the theory's clamp at ``x =
    clamp_line`` (dx = 1): the centre of the outermost held column, -0.5 (as the tools test
    reads it), or 0, the held region's face."""
    L = length_over_t * n
    k, j, l = np.meshgrid(np.arange(L + clamp_cols), np.arange(n), np.arange(n), indexing="ij")
    x = np.stack([k - clamp_cols + 0.5, j + 0.5, l - (n - 1) / 2], -1).reshape(-1, 3).astype(float)
    mu, lam = _lame(nu)
    K = stiffness(len(x), gradient_ops(x, neighbours(x, hdx), hdx, fit), mu, lam)
    f = np.zeros(3 * len(x))
    f[1::3] = -1.0
    held = (3 * np.nonzero(x[:, 0] < 0)[0][:, None] + np.arange(3)).reshape(-1)
    free = np.setdiff1d(np.arange(3 * len(x)), held)
    u = np.zeros(3 * len(x))
    u[free] = np.linalg.solve(K[np.ix_(free, free)], f[free])
    tip = x[:, 0] > x[:, 0].max() - 0.5
    xt, t, Lc = x[tip, 0].mean() - clamp_line, float(n), L - clamp_line
    A, I = t * t, t**4 / 12
    ref = A * xt**2 * (6 * Lc * Lc - 4 * Lc * xt + xt * xt) / (24 * I) + A * (Lc * xt - xt * xt / 2) / (kappa * mu * A)
    return -u[1::3][tip].mean() / ref


def _modes_table():
    for hdx in (2.0, 2.5):
        for fit, kw in (("paper", {}), ("corrected", {}), ("corrected", {"eps": 0.05}), ("corrected", {"eps": 0.1}),
                        ("corrected", {"det_ratio": 0.5}), ("paper", {"hourglass": 0.05}), ("corrected", {"hourglass": 0.05})):
            w2 = cube_modes(6, hdx, fit, **kw)
            b = beam(6, 5, hdx, fit, **kw)
            print(f"h {hdx} dx {fit:9s} {str(kw):22s} cube 6^3: lowest omega^2 {w2[0]:.4f}, {int((w2 < 0.01).sum())} below 0.01, "
                  f"highest {w2[-1]:.3f}; beam 6 thick static {b:.4f}", flush=True)


PROG = "python -m benchmarks.static_stiffness"


def main(argv=None) -> int:
    p = _cli.Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--modes", action="store_true",
                   help="the free cube's modes, the ridge and the residual penalty (instead of the table)")
    args = p.parse_args(argv)
    if args.modes:
        _modes_table()
        return 0
    for fit in ("paper", "corrected"):
        for n in (4, 6, 8):
            print(f"{fit:9s} beam {n} thick, span 5 t, h 2 dx: {beam(n, 5, 2.0, fit):.4f}", flush=True)
        for hdx in (2.5, 3.0):
            print(f"{fit:9s} beam 6 thick, span 5 t, h {hdx} dx: {beam(6, 5, hdx, fit):.4f}", flush=True)
        print(f"{fit:9s} beam 4 thick, span 10 t: {beam(4, 10, 2.0, fit):.4f}", flush=True)
        for n in (5, 8):
            for line in (0.0, -0.5):
                print(f"{fit:9s} cantilever {n} across, clamp line {line:+.1f} dx: {cantilever(n, 3, 2.0, fit, clamp_line=line):.4f}",
                      flush=True)
    print(f"centroid  beam 6 thick, span 5 t: {beam(6, 5, 2.0, 'centroid'):.4f}")
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(_cli.run(main, PROG))
