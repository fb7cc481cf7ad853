"""The loss is smooth in the material parameters (docs/method.md §1, "Neighbour rows").

A neighbour enters or leaves a row only where every kernel of the step is zero: the rows
reach ``h sigma_max(F)`` where the paper's elastic kernel is evaluated at ``F^-1 (x_j - x_i)``
(eq. 11), else ``h``, and are wide enough that no row is cut. Central differences at a relative step of 1e-4
then match the float64 tape in a flowing scene of 640 particles, at h = 2 dx and at
h = 2.5 dx (where rows hold up to ~100 particles). With the paper's rows (the 30 nearest
within h) the same check failed by 12-31 % (mu, lam) at 2 dx and 51-70 % (mu, lam,
flow_rate, viscosity) at 2.5 dx.

Through ground contact the contact law must be continuous too (docs/method.md §1,
"Contact"): a block that lands on a rough ground while it flows."""

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from taped_loss import (random_weights, taped_rollout_loss, taped_rollout_losses, untaped_rollout_loss,
                        untaped_rollout_losses)
from warp_esph.sim.colliders import CONTINUOUS_CONTACT_RAMP

STEPS = 50
DT = 1.0e-3
DX = 0.02
# k_p = 0.5, about the energy force's default K / (4 rho0) = 0.54 (the default pressure
# force, energy_spiky, runs here at half its default 0.46 K / rho0 = 1.0): the
# SPH pressure adds about 0.23 K to the bulk stiffness, as k_p = 1.0 (about K / (2 rho0) =
# 1.08) did with the spiky force, whose pair forces carry about half of grad p
# (material.PRESSURE_BULK_SHARE; docs/physics.md, the SPH pressure). At k_p = 1.0 the
# energy force is twice as stiff in bulk as this scene was with the spiky one.
PARAMS = {"mu": 1.0e3, "lam": 1.5e3, "yield_stress": 10.0, "flow_rate": 50.0, "hardening": 200.0,
          "pressure_stiffness": 0.5, "viscosity": 2.0}


def _model(h_over_dx, params=None, **builder):
    p = dict(PARAMS, **(params or {}))
    b = we.SceneBuilder(spacing=DX, support_radius=h_over_dx * DX, **builder)
    b.add_box((0.0, 0.0, 0.0), (10 * DX, 8 * DX, 8 * DX), we.Material(density=1000.0, **p))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    # A jittered lattice (no exact distance ties) stretched along x and squeezed along y
    # fast enough that the elastic part of F grows well past yield while it flows.
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    model.particle_v0 = 10.0 * (model.particle_x0 - model.particle_x0.mean(axis=0)) * np.array([1.0, -0.5, 0.0])
    return model


def _loss(model, grad_of=None):
    solver = we.Solver(model)
    states = [model.state() for _ in range(STEPS + 1)]
    loss, tape = taped_rollout_loss(solver, states, DT, random_weights(model.particle_count, 0))
    grad = None
    if grad_of is not None:
        tape.backward(loss)
        if isinstance(grad_of, str):
            grad = getattr(model, grad_of).grad.numpy()[0]
        else:  # one backward pass fills every parameter's gradient
            grad = {name: getattr(model, name).grad.numpy()[0] for name in grad_of}
    return loss.numpy()[0], grad, solver, states


def _value(model, steps=STEPS):
    """The loss of ``_loss`` alone, run without a tape (a central difference's run)."""
    return untaped_rollout_loss(we.Solver(model), model.state(requires_grad=False), DT, steps,
                                random_weights(model.particle_count, 0))


SCANNED = ("mu", "lam", "yield_stress", "flow_rate", "viscosity")


@pytest.fixture(scope="module")
def taped_base():
    """``taped_base(key, model, loss)``: the taped run of ``model`` (a function making it at
    ``PARAMS``) through ``loss`` and its one backward pass, made once per ``key`` for the
    five parameters' tests of a scene: each test reads its parameter's gradient and asserts
    the same of the run (the neighbour cuts, the flow, the final positions). The landing's
    run is also the centre value of its scans and the lift-off test's trajectory (a scan's
    centre is ``PARAMS`` to the bit, and the backward pass does not change the forward one),
    so those read it here rather than run it again; what it holds is read-only."""
    runs = {}

    def get(key, model, loss):
        if key not in runs:
            value, grads, solver, states = loss(model(), grad_of=SCANNED)
            run = {"loss": value, "grads": grads, "neighbors_cut": solver.guard_counts()["neighbors_cut"],
                   "alpha_max": states[-1].alpha.numpy().max(), "x": states[-1].x.numpy(),
                   "xs": np.array([s.x.numpy() for s in states]), "vs": np.array([s.v.numpy() for s in states])}
            for a in run.values():
                if isinstance(a, np.ndarray):
                    a.flags.writeable = False
            runs[key] = run
        return runs[key]

    return get


def _landing_run(taped_base, images=False):
    """The landing's taped run at ``PARAMS`` (on the imaged ground with ``images``)."""
    return taped_base("imaged landing" if images else "landing", lambda: _landing_model(images=images), _landing_loss)


@pytest.mark.parametrize("h_over_dx", [2.0, 2.5])
@pytest.mark.parametrize("name", SCANNED)
def test_loss_is_smooth_in_the_parameters(h_over_dx, name, taped_base):
    run = taped_base(("block", h_over_dx), lambda: _model(h_over_dx), _loss)
    grad = run["grads"][name]
    assert run["neighbors_cut"] == 0
    assert run["alpha_max"] > 0.2, "the block flows"
    base = PARAMS[name]
    eps = 1e-4 * base
    fd = (_value(_model(h_over_dx, {name: base + eps})) - _value(_model(h_over_dx, {name: base - eps}))) / (2 * eps)
    assert abs(fd) > 1e-9, f"the loss does not reach {name}"
    assert grad == pytest.approx(fd, rel=1e-3)


def _receding_pair_speed(d, viscosity):
    """Particle 0's speed along x after one step of 0.1 ms, float64, no gravity, of two
    particles ``d`` apart along x receding at 1 m/s (the SPH pressure off)."""
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    b.add_particles([[0.0, 0.0, 0.0], [d, 0.0, 0.0]],
                    we.Material(density=1000.0, **dict(PARAMS, pressure_stiffness=0.0, viscosity=viscosity)),
                    velocity=[[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    model = b.finalize(dtype=wp.float64)
    start, out = model.state(), model.state()
    we.Solver(model).step(start, out, 1.0e-4)
    return out.v.numpy()[0, 0]


def test_a_pair_leaves_the_viscous_force_with_zero_slope():
    """Müller et al.'s viscosity Laplacian ``(h - r)`` reaches 0 at ``h`` with a slope, so the
    step kinked wherever a pair crossed the support radius: in the biweight's landing
    (``_landing_model`` with ``fit_weight="biweight"``) the tape's ``lam`` gradient stepped
    from 2.026e-8 to 1.418e-8 (30 %) within 1e-15 of ``lam`` at -3.6e-5 of it, where a landing
    particle and one 1.5 spacings above it crossed ``h`` at step 42 (docs/physics.md, "The
    landing loss's kinks"). A cubic now joins it to 0 over the last 1 % of ``h``
    (``smoothing.VISCOSITY_EDGE``): a receding pair's velocity after a step is C1 in its
    distance at ``h``. Measured: the slope just inside ``h`` 2.1e-4 of the slope at 0.9 h
    (1.05 of it before), 0 outside."""
    h = 2.0 * DX
    step = 1e-6 * h
    for viscosity in (PARAMS["viscosity"], 0.0):
        v = {d: _receding_pair_speed(d * h, viscosity) for d in (0.9 - 1e-6, 0.9, 1.0 - 1e-6, 1.0, 1.0 + 1e-6)}
        line = (v[0.9] - v[0.9 - 1e-6]) / step
        inside = (v[1.0] - v[1.0 - 1e-6]) / step
        outside = (v[1.0 + 1e-6] - v[1.0]) / step
        assert v[1.0] == -0.5 and outside == 0.0, "no force from h on"
        if viscosity == 0.0:
            assert line == 0.0 and inside == 0.0, "the viscosity is all that acts on the pair"
            continue
        assert line < -0.5, "the viscous force slows the receding pair less as it parts"
        assert abs(inside) < 1e-3 * abs(line), (inside, line)


@pytest.mark.parametrize("elastic_force", ["paper", "variational"])
def test_rows_cover_the_stretched_elastic_support(elastic_force):
    """With the paper's force every pair with a non-zero elastic kernel, |F_i^-1 (x_j - x_i)|
    < h, is in i's row of the step, although it may be more than h apart now; with the
    variational force (every weight of the step 0 from h on) the rows are exactly the pairs
    within h. Either way the row holds every pair within h."""
    model = _model(2.5, {"elastic_force": elastic_force})
    _, _, solver, states = _loss(model)
    h = model.support_radius
    seen_beyond_h = 0
    for k in (10, 30, 50):
        x, F = states[k - 1].x.numpy(), states[k - 1].F.numpy()
        nbr, cnt = states[k].neighbors.numpy(), states[k].neighbor_count.numpy()
        for i in range(model.particle_count):
            d = x - x[i]
            near = set(np.flatnonzero(np.einsum("ij,ij->i", d, d) < h * h)) - {i}
            ref = np.linalg.solve(F[i], d.T).T
            stretched = set(np.flatnonzero(np.einsum("ij,ij->i", ref, ref) < h * h)) - {i}
            row = set(nbr[i, : cnt[i]])
            if elastic_force == "paper":
                assert near | stretched <= row, (k, i)
            else:
                assert row == near, (k, i)
            seen_beyond_h += len(stretched - near)
    assert seen_beyond_h > 0, "the scene stretches F so that some pairs are weighted beyond h"
    assert solver.guard_counts()["neighbors_cut"] == 0


def test_the_paper_cap_is_counted_and_warned():
    """``max_neighbors='paper'`` keeps the 30 nearest: at h = 2.5 dx rows are cut, which is
    counted and warned once."""
    model = _model(2.5, max_neighbors="paper")
    assert model.max_neighbors == 30
    with pytest.warns(RuntimeWarning, match="neighbour row was cut"):
        _, _, solver, states = _loss(model)
    assert states[-1].neighbor_count.numpy().max() == 30
    assert solver.guard_counts()["neighbors_cut"] > 0
    assert _model(2.0).max_neighbors == 96 and _model(2.5).max_neighbors == 240


def _squashed_step(max_neighbors, elastic_force, F0=(1.3, 0.35, 1.3), **plastic):
    """One step of a block of 5 x 16 x 5 particles squashed to F = diag(1.3, 0.35, 1.3)
    (positions and F alike, J = 0.59; 16 layers: the middle ones have their whole ball),
    float64: what the lowest particles of test_adaptive_dt's ball reach at its landing. The
    variational force runs with the hourglass control (it weighs rest distances), the
    paper's without."""
    F0 = np.diag(F0)
    b = we.SceneBuilder(spacing=DX, max_neighbors=max_neighbors)
    b.add_box((0.0, 0.0, 0.0), (5 * DX, 16 * DX, 5 * DX),
              we.Material.from_young(1.0e5, 0.3, elastic_force=elastic_force, **plastic))
    model = b.finalize(dtype=wp.float64)
    X = model.particle_x0 + np.random.default_rng(3).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    model.particle_x0 = X  # the rest positions the hourglass control weighs
    start, out = model.state(), model.state()
    start.x.assign(X @ F0.T)
    start.F.assign(np.tile(F0, (model.particle_count, 1, 1)))
    solver = we.Solver(model)
    assert (solver.hourglass > 0.0) == (elastic_force == "variational")
    solver.step(start, out, 1.0e-5)
    return model, start, out, solver


@pytest.mark.parametrize("elastic_force", ["paper", "variational"])
def test_a_full_row_that_drops_only_unweighed_pairs_is_not_cut(elastic_force):
    """Squashed as a landing ball's lowest particles are (F = diag(1.3, 0.35, 1.3)), a
    particle's selection radius h sigma_max(F) = 1.3 h holds up to 113 particles, more than
    a row's 96, of which at most 69 are weighed by a kernel of the step (closer than h now,
    at F^-1 (x_j - x_i), or at rest). A full row keeps the weighed pairs first
    (neighbors.weight_key): it holds them all, the step is bit for bit that of 256-wide rows,
    and no cut is counted or warned. It kept the 96 nearest, which lacked up to 3 weighed
    pairs at the rim of F B(h) (1.2-1.3 h away along x and z), and counted that as a cut.
    Rows of 40 drop weighed pairs: that is still a cut."""
    model, start, out, solver = _squashed_step(None, elastic_force)
    wide = _squashed_step(256, elastic_force)
    h = model.support_radius
    x, X, F = start.x.numpy(), model.particle_x0, start.F.numpy()
    nbr, cnt = out.neighbors.numpy(), out.neighbor_count.numpy()
    in_ball = ((x[:, None] - x[None]) ** 2).sum(-1) < (1.3 * h) ** 2
    assert model.max_neighbors == 96 and (in_ball.sum(1) - 1).max() == 113 and cnt.max() == 96  # full rows
    for i in range(model.particle_count):
        d = x - x[i]
        ref = np.linalg.solve(F[i], d.T).T
        weighed = ((d * d).sum(1) < h * h) | ((ref * ref).sum(1) < h * h) | (((X - X[i]) ** 2).sum(1) < h * h)
        weighed[i] = False
        assert set(np.flatnonzero(weighed)) <= set(nbr[i, : cnt[i]]), i
    assert wide[2].neighbor_count.numpy().max() > 96
    for name in ("x", "v", "F"):
        np.testing.assert_array_equal(getattr(out, name).numpy(), getattr(wide[2], name).numpy())
    assert solver.guard_counts()["neighbors_cut"] == 0
    with pytest.warns(RuntimeWarning, match="a neighbour row was cut: more than max_neighbors = 40"):
        narrow = _squashed_step(40, elastic_force)[3]
    assert narrow.guard_counts()["neighbors_cut"] > 0


def test_a_full_row_keys_the_pairs_the_flowed_F_may_weigh():
    """The paper's force weighs a pair at F'^-1 (x_j - x_i) with F' the F after this step's
    plastic flow, which moves each singular value to sigma^(1 - gamma) t^gamma (t^3 the volume
    clamped to [0.8, 1.25]): a squashed axis widens, so F' B(h) reaches pairs that F B(1.05 h)
    and B(h) both miss. Squashed to diag(1.4, 0.15, 1.4) and flowing (gamma ~ 0.3 in the step),
    the full rows kept by F^-1's key lacked 175 pairs that F'^-1 weighs, in 43 rows, and counted
    no cut. The key now bounds F'^-1 over every gamma (neighbors.flow_inverse_bound): a row
    that lacks a weighed pair is counted (and warned)."""
    with pytest.warns(RuntimeWarning, match="a neighbour row was cut: more than max_neighbors = 96"):
        model, start, out, solver = _squashed_step(None, "paper", (1.4, 0.15, 1.4), yield_stress=10.0, flow_rate=3.0e4)
    h = model.support_radius
    x, F_inv = start.x.numpy(), out.F_inv.numpy()
    nbr, cnt = out.neighbors.numpy(), out.neighbor_count.numpy()
    assert cnt.max() == 96 and np.abs(np.linalg.svd(F_inv, compute_uv=False) - 1 / 0.15).min() > 1.0  # it flowed
    short = 0
    for i in range(model.particle_count):
        e = (x - x[i]) @ F_inv[i].T
        weighed = (e * e).sum(1) < h * h
        weighed[i] = False
        short += not set(np.flatnonzero(weighed)) <= set(nbr[i, : cnt[i]])
    assert solver.guard_counts()["neighbors_cut"] >= short
    assert solver.guard_counts()["neighbors_cut"] > 0


def _reference_rows(x, F, rest, flows, image, kmax, h, cand_stretch):
    """numpy's rows and cut count of ``neighbors.select_neighbors``: every j within
    h sqrt(max(min(g, s^2), 1)) (g the stretch bound, s the candidates' stretch); where more
    than kmax, the kmax smallest (weight_key, j) (F not invertible: the smallest (d2, j)), in
    index order; a cut where g > s^2, where F is not invertible and the row overflows, or
    where a dropped candidate's key is below h^2."""
    def floor_image(p):  # deformation.floor_image in the plane y = image, min depth half a spacing
        d = p[..., 1] - image
        md = 0.5 * DX
        t = np.maximum(1.0 + (d - md) / (0.5 * md), 0.0)
        s = np.where(d < md, md + 0.5 * md * t * t * (t - 1.0), d)
        return p - (d + s)[..., None] * np.array([0.0, 1.0, 0.0])

    rows, cuts, slack2 = [], 0, we.sim.neighbors.STRETCH_SLACK ** 2
    for i in range(len(x)):
        g = np.abs(F[i].T @ F[i]).sum(1).max()
        cut = g > cand_stretch[i] ** 2
        d = x - x[i]
        d2 = (d * d).sum(1)
        d2[i] = np.inf
        idx = np.flatnonzero(d2 < h * h * max(min(g, cand_stretch[i] ** 2), 1.0))
        if len(idx) > kmax:
            k = d2[idx]
            keyed = 0.0 < np.linalg.det(F[i]) < 1e30
            if keyed:
                G = np.linalg.inv(F[i])
                if flows[i]:
                    U, sg, Vt = np.linalg.svd(F[i])
                    t = np.clip(np.linalg.det(F[i]), 0.8, 1.25) ** (1.0 / 3.0)
                    G = Vt.T @ np.diag(1.0 / np.maximum(sg, t)) @ U.T
                ends = [(x[idx], x[i])]
                if image is not None:
                    ends += [(floor_image(x[idx]), x[i]), (x[idx], floor_image(x[i]))]
                for n, (a, b) in enumerate(ends):
                    e = (a - b) @ G.T
                    k = np.minimum(k, (e * e).sum(1) / slack2)
                    if n >= 1:  # the image pairs' current distances (the fit, the variational force)
                        k = np.minimum(k, ((a - b) ** 2).sum(1))
                if rest is not None:
                    k = np.minimum(k, ((rest[idx] - rest[i]) ** 2).sum(1))
            order = np.lexsort((idx, k))
            cut = cut or not keyed or bool((k[order[kmax:]] < h * h).any())
            idx = np.sort(idx[order[:kmax]])
        rows.append(idx)
        cuts += int(cut)
    return rows, cuts


def test_full_rows_are_the_smallest_weight_keys_and_count_exactly_the_weighed_drops():
    """select_neighbors against numpy on random rows: jittered lattices under a random F0, each
    particle's F random (stretched and squashed 0.3-1.6, some past the rows' reach of 2, some
    not invertible, some of a material that flows), with or without a floor plane of images
    and rest positions, rows of 20-40; and exact lattices with F = I, whose keys tie. Each row
    must be the kmax smallest keys (k, j) of the candidates within the selection radius (ties
    to the lower index), in index order, and the cut count that of the rows that dropped a
    candidate of key below h^2 (or of an F not invertible, or past the reach)."""
    from warp_esph._types import type_set  # noqa: PLC0415
    from warp_esph.sim import materials, neighbors  # noqa: PLC0415

    T = type_set(wp.float64)
    rng = np.random.default_rng(5)
    h = 2.0 * DX

    def rotation():
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        return q * np.sign(np.diag(r)) * np.sign(np.linalg.det(q * np.sign(np.diag(r))))

    overflowing = keyed_uncut = 0
    for trial in range(40):
        X = np.stack(np.meshgrid(*[np.arange(int(rng.integers(5, 7))) * DX] * 3, indexing="ij"), -1).reshape(-1, 3)
        n = len(X)
        ties = trial % 5 == 0
        x = X.copy() if ties else X @ (rotation() * rng.uniform(0.6, 1.3, 3)).T + rng.normal(scale=0.05 * DX, size=X.shape)
        F = np.stack([rotation() * rng.uniform(0.3, 2.6 if rng.random() < 0.1 else 1.6, 3) @ rotation() for _ in range(n)])
        F[rng.random(n) < 0.05] *= np.array([1.0, 1.0, -1.0])
        if ties:
            F[:] = np.eye(3)
        flows = (rng.random(n) < 0.5) & (not ties)  # (the SVD of I is exact only to round-off)
        rest = X + rng.normal(scale=0.02 * DX, size=X.shape) if rng.random() < 0.5 else None
        image = float(x[:, 1].min() - rng.uniform(-0.3, 1.0) * DX) if rng.random() < 0.5 else None
        kmax = int(rng.integers(20, 41))
        search = neighbors.NeighborSearch(n, wp.float64, "cpu", h, spacing=DX)
        if image is not None:
            search.image_args = [T.vec3(0.0, 1.0, 0.0), wp.float64(image), wp.float64(0.5 * DX), 1]
        nbr, counters = wp.zeros((n, kmax), dtype=wp.int32), wp.zeros(8, dtype=wp.int32)
        count = wp.zeros(n, dtype=wp.int32)
        flow = (wp.array(flows.astype(np.int32)), materials.make(wp.float64, flow_rate=wp.array([0.0, 1.0], dtype=wp.float64)))
        search.build(wp.array(x, dtype=T.vec3), wp.zeros(n, dtype=wp.int32), nbr, wp.zeros((n, kmax), dtype=wp.float64),
                     count, None, F=wp.array(F, dtype=T.mat33), counters=counters, cut_index=4,
                     rest=None if rest is None else wp.array(rest, dtype=T.vec3), flow=flow)
        rows, cuts = _reference_rows(x, F, rest, flows, image, kmax, h, search._cand_stretch.numpy())
        nbr, count = nbr.numpy(), count.numpy()
        for i in range(n):
            np.testing.assert_array_equal(nbr[i, : count[i]], rows[i], err_msg=f"trial {trial}, particle {i}")
        assert counters.numpy()[4] == cuts, trial
        overflowing += int(sum(len(r) == kmax for r in rows))
        keyed_uncut += n - cuts
    assert overflowing > 1000 and keyed_uncut > 1000  # both paths ran


# Through ground contact: a block flowing as it lands on a rough ground (friction 0.6); the
# first particles touch at step 20 of 60. The continuous contact
# (``model.contact_ramp = CONTINUOUS_CONTACT_RAMP``) is the default; the instant law is
# selectable by name (``contact="instant"``).
CONTACT_STEPS = 60


def _landing_model(params=None, contact_ramp=CONTINUOUS_CONTACT_RAMP, images=False, **builder):
    p = dict(PARAMS, **(params or {}))
    b = we.SceneBuilder(spacing=DX, support_radius=2.0 * DX, **builder)
    b.add_box((0.0, 0.09, 0.0), (10 * DX, 8 * DX, 8 * DX), we.Material(density=1000.0, **p))
    b.add_ground(friction=0.6, images=images)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.contact_ramp = contact_ramp
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    stretch = 4.0 * (model.particle_x0 - model.particle_x0.mean(axis=0)) * np.array([1.0, -0.5, 0.0])
    model.particle_v0 = stretch + np.array([0.5, -1.0, 0.0])
    return model


def _landing_loss(model, grad_of=None):
    global STEPS
    steps, STEPS = STEPS, CONTACT_STEPS
    try:
        return _loss(model, grad_of)
    finally:
        STEPS = steps


def _landing_value(model):
    return _value(model, CONTACT_STEPS)


#: The seeds of the landing's random loss weights read together (``landing_losses``): seed 0
#: is the loss of the landing's other tests.
LOSS_SEEDS = (0, 1, 2, 3)


def _landing_weights(model):
    return [random_weights(model.particle_count, seed) for seed in LOSS_SEEDS]


@pytest.fixture(scope="module")
def landing_losses():
    """The landing's gradients at ``PARAMS`` of the loss at each of ``LOSS_SEEDS``' weights,
    ``{name: array over the seeds}``, from one taped run: one backward pass per loss."""
    model = _landing_model()
    states = [model.state() for _ in range(CONTACT_STEPS + 1)]
    losses, tape = taped_rollout_losses(we.Solver(model), states, DT, _landing_weights(model))
    grads = {name: [] for name in SCANNED}
    for loss in losses:
        tape.backward(loss)
        for name in SCANNED:
            grads[name].append(getattr(model, name).grad.numpy()[0])
        tape.zero()
    return {name: np.array(g) for name, g in grads.items()}


def _landing_values(model):
    """The loss at each of ``LOSS_SEEDS``' weights, from one untaped run of ``model``."""
    return np.array(untaped_rollout_losses(we.Solver(model), model.state(requires_grad=False), DT, CONTACT_STEPS,
                                           _landing_weights(model)))


@pytest.mark.parametrize("name", SCANNED)
def test_loss_is_smooth_through_ground_contact(name, taped_base, landing_losses):
    """Central differences match the tape in a flowing block that lands on a rough ground:
    a touchdown step removes only a share of the inward normal velocity, smooth in how far
    past the surface the particle drifted (``colliders.touchdown_share``: one that barely
    crosses barely responds), the stick-slip transition is rounded
    (``colliders.slip_speed``) and the plastic flow's volume factor is continuous in J.
    Measured before these changes: over +-1 % of viscosity, loss increments of -20 to 4
    times the tape's slope (see the next test).

    At a relative step of 1e-4 the central differences of the losses at four random weights
    (``LOSS_SEEDS``, one rollout for all) match their tape's gradients within 1e-3 of the
    gradients' rms over the four. Against each loss's own gradient the reading is
    ill-conditioned where a loss is nearly stationary in the parameter: with the biweight
    seed 0's lam gradient is 109 times smaller than poly6's and its difference read 1.0e-2
    of it off (docs/physics.md, "The contact and tools gradients read over a ladder of
    steps"), while the error is the loss's curvature, the same size in every direction of
    the weights. Measured, poly6 / biweight: within 3.8e-6 / 2.6e-5 of the rms (poly6's
    largest mu's, the biweight's lam's; its others within 1.2e-5); seed 0's lam 1.8e-5 / 1.0e-2 of its own gradient.
    What it catches: a jump J of a loss within the step reads J / 2h, so one over 2e-3 h
    times the rms (the flow's volume factor jumping in J read gradients -2.7 to 1.12 of the
    centre's in the scan below); a kink of the gradient by k within the step, at most k / 2.
    The viscosity's old edge (a kink where a pair left its support, docs/physics.md, "The
    landing loss's kinks are pairs leaving the viscosity's support") reads 9.3e-5 of the rms
    with the biweight, under the bound: the viscous pair's own test holds it. The instant
    contact law reads within 1.5e-6: none of its jumps falls within the step here, which the
    scans below look across."""
    run = _landing_run(taped_base)
    assert run["neighbors_cut"] == 0
    assert run["alpha_max"] > 0.2, "the block flows"
    on_ground = (run["x"][:, 1] < 1e-9).sum()
    assert on_ground > 50, "the block lies on the ground"
    grads = landing_losses[name]
    assert grads[0] == run["grads"][name], "seed 0's loss is the landing's"
    base = PARAMS[name]
    eps = 1e-4 * base
    fd = (_landing_values(_landing_model({name: base + eps})) - _landing_values(_landing_model({name: base - eps}))) / (2 * eps)
    rms = np.sqrt(np.mean(grads ** 2))
    print(name, "gradients", grads, "errors / rms", np.abs(fd - grads) / rms, "errors / own", np.abs(fd / grads - 1.0))
    assert rms > 1e-9, f"the loss does not reach {name}"
    assert (np.abs(fd - grads) <= 1e-3 * rms).all(), (name, grads, fd)


@pytest.mark.parametrize("name", SCANNED)
def test_loss_is_smooth_through_the_imaged_ground(name, taped_base):
    """The same landing on the ground with floor images (``add_ground(images=True)``), whose
    bottom layer the images hold at the plane: central differences at a relative step of 1e-4
    match the tape within 1e-3 (measured: 0.99991-1.00000). Two jumps of the step were
    removed for it (docs/physics.md, "The imaged ground's contact is smooth"):

    - the image of a particle less than half a spacing over the plane is held half a spacing
      deep; the plain ``max(d, dx/2)`` that did it had a kink, now a cubic joins the two
      (``deformation.image_depth``). Before: tape / difference 0.895 for mu, 0.662 for lam at
      a step of 1e-5;
    - an image's moment matrix summed its image-image pairs at their own distance, which is
      shorter than the particles' where the images are held: such a pair entered and left the
      sum at a non-zero weight as the particle crossed the edge of the row. It now weighs as
      its particles' pair (``deformation.floor_image_moment``). Before: a jump of 0.39 times
      the slope times the step in the loss at -0.55e-4 of the viscosity, tape / difference
      0.981 at 1e-4."""
    run = _landing_run(taped_base, images=True)
    grad = run["grads"][name]
    assert run["neighbors_cut"] == 0
    assert run["alpha_max"] > 0.2, "the block flows"
    assert (run["x"][:, 1] < 0.5 * DX).sum() > 50, "the block lies on the ground"
    base = PARAMS[name]
    eps = 1e-4 * base
    fd = (_landing_value(_landing_model({name: base + eps}, images=True))
          - _landing_value(_landing_model({name: base - eps}, images=True))) / (2 * eps)
    assert abs(fd) > 1e-9, f"the loss does not reach {name}"
    assert grad == pytest.approx(fd, rel=1e-3)


@pytest.mark.parametrize("name", ["mu", "viscosity"])
def test_no_jump_in_the_loss_through_ground_contact(name, taped_base):
    """The loss and the tape's gradient at the middle 5 of 11 values over +-1 % of the
    parameter (-0.4 % to +0.4 %, 0.2 % apart): the loss's increment over each interval is the
    mean of the tape's gradients at its ends (the trapezoid rule, exact to the loss's
    curvature) within 2 %; neighbouring gradients differ by at most 8 % of the centre's, and
    none by more than 25 %. A jump, or a kink, anywhere in the range shows as one interval far
    off the trapezoid and as a step between neighbouring gradients; a smooth bend does neither.

    Measured with the touchdown share (``colliders.touchdown_share``) over the 7 values:
    increments within 0.11 % (mu) and 0.17 % (viscosity) of the trapezoid; gradients
    0.926-1.092 (mu) and 0.916-1.129 (viscosity) of the centre's, neighbours at most 3.75 %
    and 4.6 % apart (over all 11: 0.90-1.13 and 0.89-1.21, 3.75 % and 5.0 %): the curvature of
    where 168 particles' touchdowns fall in their steps. With the flow's volume factor jumping
    where J leaves [0.8, 1.25] (the paper's target alone outside the range, the mutation), the
    7 values read increments 0.65-1.06 (mu) and -13.2 to 1.97 (viscosity) times the
    trapezoid's, gradients 0.74-1.50 and -2.7 to 1.12 of the centre's: every bound fails.
    With the share's first form, linear and so kinked at both ends of the touchdown step
    (over all 11): 0.55 % and 0.66 %, with
    gradients 0.93-1.03 here but down to 0.45 on the imaged ground (below). With the instant
    contact law, which removed all inward velocity of a particle once it crossed the surface:
    increments of -20 to 4 times the slope; with the flow's volume factor jumping where J left
    [0.8, 1.25]: 0.71 and 1.25 (over all 11, when first measured).

    The middle 5 (was 7; four taped runs and the shared centre instead of six, the suite's
    cost) are four of the 7's six intervals, so their readings lie within those above. The
    instant contact law (``contact_ramp = 0``, the mutation) still fails them, measured at
    2a8dfb3b: one interval at 0.351 (mu, +0.2 % to +0.4 %) and -0.634 (viscosity, 0 to +0.2 %)
    times the trapezoid, against the bound 2 %; the same two intervals are its worst over the
    middle 7."""
    _assert_smooth(*_scan_against_trapezoid(name, taped_base, points=range(3, 8)))


@pytest.mark.parametrize("fit_weight", ["poly6", "biweight"])
def test_the_pair_repulsion_smooths_the_landing_scan_at_the_default_pressure_stiffness(fit_weight):
    """At the default pressure force's default ``k_p`` (1.0 here, twice ``PARAMS``') poly6's
    landing's second layer falls onto the first, one particle onto another, and the
    viscosity's scan steps by 11.0 % of the centre's gradient between neighbours (gradients
    0.982-1.327: docs/physics.md, "Why the biweight lets particles pair at the ground"). With
    ``Material.pair_repulsion = 2`` the pair does not meet and the scan reads gradients
    0.985-1.018 of the centre's, neighbours at most 0.64 % apart, increments within 0.10 % of
    the trapezoid (the hand-written adjoints' tape).

    The 11 % step is poly6's (the biweight's scan steps by 1.1 % without the repulsion at
    this ``k_p``), so the range of 5 % is asserted for poly6. With the repulsion the
    biweight's second layer stops over the first and rises back, a loss that bends steadily
    in the viscosity: gradients 1.064 down to 0.944 of the centre's, each neighbour 1.2-1.5 %
    below the last but the end's 0.61 %, so the steps' own changes within 0.58 % (poly6's
    0.41 %), where a step (a kink or a jump: 11 % above) shows as one neighbour step far off
    the others; increments within 0.085 % of the trapezoid.

    The scan runs the middle 5 of the 11 values (-0.4 % to +0.4 %; 5 runs instead of 11, the
    suite's cost): measured without the repulsion there (``pair_repulsion = 0``), poly6's
    gradients read 0.982-1.071 of the centre's, neighbours up to 4.3 % apart, the steps' own
    changes up to 1.5 %: each of the three bounds fails (over all 11: 0.982-1.327, 11.0 %,
    2.5 %). The biweight without the repulsion passes (over all 11 too: 0.997-1.033, 1.1 %,
    0.61 %): its case asserts the repulsion's bend is smooth, not that it is needed."""
    ratios, grads = _scan_against_trapezoid("viscosity", None, params={"pressure_stiffness": 1.0, "pair_repulsion": 2.0},
                                            points=range(3, 8), fit_weight=fit_weight)
    assert np.abs(ratios - 1.0).max() < 0.01, np.round(ratios, 4)
    assert np.abs(np.diff(grads)).max() < 0.02, np.round(grads, 3)
    assert np.abs(np.diff(grads, 2)).max() < 0.01, np.round(grads, 3)
    if fit_weight == "poly6":
        assert np.abs(grads - 1.0).max() < 0.05, np.round(grads, 3)


def _assert_smooth(ratios, grads):
    assert np.abs(ratios - 1.0).max() < 0.02, np.round(ratios, 4)
    assert np.abs(np.diff(grads)).max() < 0.08, np.round(grads, 3)
    assert np.abs(grads - 1.0).max() < 0.25, np.round(grads, 3)


def _scan_against_trapezoid(name, taped_base, images=False, points=range(11), params=None, **builder):
    """The landing loss at 11 values over +-1 % of ``name`` (those of them ``points`` picks,
    in order): each interval's increment over the mean of the tape's gradients at its ends,
    and the gradients over the centre's. The centre, ``PARAMS`` itself (point 5, which
    ``points`` must hold), is the landing's shared taped run; with ``params`` (over
    ``PARAMS``) a run of the scan's own, its scene made with ``builder``'s arguments."""
    base = dict(PARAMS, **(params or {}))[name]
    points = list(points)
    values = base * (1.0 + np.linspace(-1e-2, 1e-2, 11))[points]
    assert 5 in points and values[points.index(5)] == base

    # One model and one set of taped states for the scan's runs, the parameter set
    # (set_materials) and the last run's gradients zeroed (its tape's zero(), the parameters'
    # too) before each: its loss and gradient are a new model's and states' to the bit
    # (measured at three values of mu on the ground and of the viscosity on the imaged ground).
    assert params is not None or not builder, "the shared centre is the default scene's"
    model = _landing_model(params, images=images, **builder)
    materials = list(model.materials)
    states = [model.state() for _ in range(CONTACT_STEPS + 1)]
    w = random_weights(model.particle_count, 0)
    tapes = []

    def at(v):
        if v == base and params is None:
            run = _landing_run(taped_base, images)
            return run["loss"], run["grads"][name]
        if tapes:
            tapes.pop().zero()
        model.set_materials([m.replace(**{name: v}) for m in materials])
        loss, tape = taped_rollout_loss(we.Solver(model), states, DT, w)
        tape.backward(loss)
        tapes.append(tape)
        return loss.numpy()[0], getattr(model, name).grad.numpy()[0]

    losses, grads = np.array([at(v) for v in values]).T
    secants = np.diff(losses) / np.diff(values)
    return secants / (0.5 * (grads[1:] + grads[:-1])), grads / grads[points.index(5)]


@pytest.mark.xfail(strict=True, reason="the imaged landing's loss bends steeply: its gradient moves by up to 10.5 % "
                   "of the centre's between neighbours 0.2 % apart (bound 8 %; worst interval 3.5 % off the trapezoid, "
                   "bound 2 %). Ten times finer it is C1 (within 0.65 %): the bends are the rounded lift-off of "
                   "bottom-layer particles the touchdown left inside the plane and the images push back up, over a "
                   "band d0 / dt of 1e-3 to 2e-2 m/s; a wider band spreads them over more of the layer and does not "
                   "pass; a soft contact on the imaged plane passes but leaves a block settled on it 1.7e-5 m inside "
                   "(docs/physics.md, \"The imaged landing's bends\")")
def test_no_jump_in_the_loss_through_the_imaged_ground(taped_base):
    """The same scan on the ground with mirror images (``ground_images``), whose bottom-layer
    particles lie on the plane: measured with the touchdown share, increments within 0.35 %
    of the trapezoid and gradients 0.88-1.00 of the centre's, neighbours at most 3.5 % apart.
    With the share's first form (linear, kinked at both ends of the touchdown step): 15 % off
    and gradients down to 0.45 (29 % and up to 4.0 at jitter seed 7; docs/physics.md, "The
    touchdown share"). With the images' own F the trajectory changed, and one interval read
    8.2 % off: a particle left inside by its touchdown whose next step's force just cancelled
    its inward speed, ``max(v_n, 0)``, rounded since (``colliders.inside_band``). That rounding
    is where the scan now bends: where the loss's second derivative is large, nearly all of it
    is added by bottom-layer particles lifting off from inside the plane (measured: -2.83 of
    -2.94 at the centre, one particle -1.82 of it; docs/physics.md, "The imaged landing's
    bends").

    The scan runs the four of its 11 values where the gradient bends most, -0.4 % to +0.2 %
    (three taped runs and the shared centre instead of ten and the centre): measured at all 11
    since the rough floor's images keep their own F (docs/physics.md, "Where the imaged
    ground's images store no energy"), gradients 1.06, 1.08, 1.02, 0.92, 0.90, 1.00, 1.01,
    0.98, 0.92, 0.87, 0.85 of the centre's, so the step of 10.5 % out of -0.2 % and the worst
    interval, 3.5 % off the trapezoid from -0.4 % to -0.2 %, lie in it (the only other step
    past 8 %, 10.0 % between -0.6 % and -0.4 %, outside; every other interval within 1.3 %).
    Just before, the four values read 1.1 % off at most and steps of up to 8.5 %; when the test
    was written, gradients 1.09-0.86 of the centre's, steps of 8.3 % and 13.9 % into and out
    of -0.2 %, 1.75 % off. Over the same four values the plain
    ground's scan passes (``test_no_jump_in_the_loss_through_ground_contact``'s landing), so a
    mend of the steepest bend reads as an unexpected pass here."""
    _assert_smooth(*_scan_against_trapezoid("viscosity", taped_base, images=True, points=range(3, 7)))


def test_only_the_imaged_ground_lifts_landed_particles_off_from_inside(taped_base):
    """What bends the imaged scan above (docs/physics.md, "The imaged landing's bends"): the
    images push the landed bottom layer back up, so particles the touchdown share left inside
    the plane leave it in the next step, some slower than their band ``d0 / dt``
    (``colliders.inside_band``), where their lift-off is rounded (measured: one particle in
    step 25, at 0.56 of its band; two, at 1.30 and 0.073, before the rough floor's images kept
    their own F, docs/physics.md, "Where the imaged ground's images store no energy"; nine
    when the test was written). On the plain ground the landed
    layer stays down: none of its particles that start a step inside leaves with an outward
    speed (of 168 such particle-steps)."""
    for images in (False, True):
        run = _landing_run(taped_base, images)
        y, vy = run["xs"][:, :, 1], run["vs"][:, :, 1]
        inside = y[:-1] < 0.0
        leaving = inside & (vy[1:] > 0.0)
        assert inside.sum() > 100, "the block lands"
        if not images:
            assert not leaving.any(), np.argwhere(leaving)
            continue
        band = -y[:-1] / DT
        assert leaving.sum() >= 1, np.argwhere(leaving)
        assert (vy[1:][leaving] < band[leaving]).sum() >= 1, (vy[1:][leaving], band[leaving])


def test_the_instant_contact_law_jumps_and_is_not_the_default():
    """The instant contact law (``contact_ramp = 0``, the first one, selectable by name)
    makes the loss jump through contact: the scan above is far off with it (measured: 0.49
    off for mu with the energy force at k_p = 0.5). So the continuous contact, the default,
    is what makes the loss smooth through contact, and the test above can fail.

    Run with the default pressure force (energy_spiky) at its default ``k_p = 0.46 K / rho0``
    (1.0 here), the same added bulk stiffness as the energy force at the scene's k_p = 0.5
    (``PARAMS``), over the middle 5 of the scan's 11 values (-0.4 % to +0.4 %, at its
    spacing): measured slopes 0.648-1.100 of the tape's, at most 0.436 between neighbours,
    the same over the middle 7 (0.65-1.61 and 0.52 over all 11; 0.21-2.14 over 21 values, more
    runs for the same verdict): the slope falls from 1.100 to 0.669 at -0.2 % and rises from
    0.648 to 1.084 at +0.2 % (the four intervals), both inside the middle 5, whose two outer
    neighbours in the middle 7 read 1.096 and 1.085. At the scene's k_p = 0.5, half
    its default bulk share, energy_spiky's loss does not jump in this range (0.999-1.019,
    measured), so the jump is not shown there; the energy force at k_p = 0.5 gives
    -1.99 to 1.70.

    Off the tape's slope alone does not always tell a jump from a bend: run with the
    continuous contact in its place (the mutation), the middle 7 values' slopes bend smoothly
    through 1.067-1.126 of the tape's centre slope, at most 0.034 between neighbours (so the
    middle 5's within those too), failing both bounds (over all 11 values 1.07-1.24, past the 0.2, and 1.07-1.25 over 21). A jump is
    a step between neighbouring slopes, as in ``_assert_smooth``: at most 0.44 between
    neighbours with the instant law (0.52 over all 11), 0.034 with the continuous one (0.06
    over 11), against the bound 0.2.

    The fit weight is named (poly6): where a jump falls is the trajectory's. With the biweight
    the instant law jumps too, past the middle 7 values (their slopes 1.067-1.071): the loss steps
    by 1.365e-4 at +0.757 % of mu (bisected to 6e-17), 0.34 of the tape's slope times the
    scan's spacing."""
    name = "mu"
    base = PARAMS[name]
    force = {"pressure_force": "energy_spiky", "pressure_stiffness": None}
    model = _landing_model(force, contact_ramp=0.0, fit_weight="poly6")
    assert model.contact_ramp == 0.0 and _model(2.0).contact_ramp == CONTINUOUS_CONTACT_RAMP
    assert model.materials[0].pressure_stiffness == pytest.approx(0.46 * (1.5e3 + 2.0e3 / 3.0) / 1000.0)
    centre, grad, _, _ = _landing_loss(model, grad_of=name)
    values = base * (1.0 + np.linspace(-1e-2, 1e-2, 11))[3:8]  # the middle 5 values of the scan above
    # The centre's loss is the taped run's (the same model to the bit; the tape does not change
    # the forward run), so its run is not made twice.
    losses = np.array([centre if v == base else
                       _landing_value(_landing_model(dict(force, **{name: v}), contact_ramp=0.0, fit_weight="poly6"))
                       for v in values])
    slopes = np.diff(losses) / np.diff(values) / grad
    assert np.abs(slopes - 1.0).max() > 0.2, np.round(slopes, 3)
    assert np.abs(np.diff(slopes)).max() > 0.2, np.round(slopes, 3)
    with pytest.raises(ValueError, match="contact_ramp"):
        model.contact_ramp = -1.0
