"""The float64 loss the gradient tests differentiate: ``sum_i dot(x_i, w_i)`` over the last
state of a taped rollout, with fixed random weights ``w`` (every particle and every direction
reaches the loss, with no symmetry that could hide a wrong adjoint); and a loss's central
differences in the positions it compares."""

import numpy as np
import warp as wp


@wp.kernel(module="unique")
def dot_loss(x: wp.array(dtype=wp.vec3d), w: wp.array(dtype=wp.vec3d), loss: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(loss, 0, wp.dot(x[i], w[i]))


def random_weights(count: int, seed: int) -> wp.array:
    """Normal weights for ``count`` particles, the same for a given seed."""
    return wp.array(np.random.default_rng(seed).normal(size=(count, 3)), dtype=wp.vec3d)


def taped_rollout_loss(solver, states, dt: float, weights: wp.array):
    """Steps ``solver`` through ``states`` (``len(states) - 1`` steps of ``dt``) under a tape
    and adds the loss on the last state; returns ``(loss, tape)``, ``loss`` a 1-element
    float64 array, for the caller's ``tape.backward(loss)``."""
    losses, tape = taped_rollout_losses(solver, states, dt, [weights])
    return losses[0], tape


def taped_rollout_losses(solver, states, dt: float, weights):
    """``taped_rollout_loss`` with a loss for each of ``weights`` (a list of weight arrays) on
    the one tape: ``(losses, tape)``; a ``tape.backward`` of one loss fills its gradients alone
    (the others' seeds are zero), ``tape.zero()`` between them."""
    losses = [wp.zeros(1, dtype=wp.float64, requires_grad=True) for _ in weights]
    tape = wp.Tape()
    with tape:
        for a, b in zip(states[:-1], states[1:]):
            solver.step(a, b, dt)
        for w, loss in zip(weights, losses):
            wp.launch(dot_loss, len(w), [states[-1].x, w], [loss])
    return losses, tape


def untaped_rollout_loss(solver, state, dt: float, steps: int, weights: wp.array, forward_only: bool = True) -> float:
    """``taped_rollout_loss``'s loss without the tape, for the central differences: ``steps``
    steps of ``dt`` from ``state`` (changed by them) and one more state in turn, made without
    gradient arrays. A taped rollout needs a state per step and their gradient arrays, which a
    central difference never reads; the step runs the same kernels with and without the tape,
    so its loss is the taped one to the bit (``test_gradient_coverage.py`` asserts it).
    ``forward_only=False``: the untaped launches run the kernels the taped rollout runs, with
    their adjoints, not their forward-only twins (``replay.forward_only``), so a test that tapes
    the scene too compiles no twin of its kernels; the same bits, as that test asserts."""
    return untaped_rollout_losses(solver, state, dt, steps, [weights], forward_only)[0]


def untaped_rollout_losses(solver, state, dt: float, steps: int, weights, forward_only: bool = True) -> list:
    """``untaped_rollout_loss`` for each of ``weights`` (a list of weight arrays), all from the
    one rollout."""
    launches = (solver.model.launches, solver.search.launches)
    kept = [x.forward_only for x in launches]
    for x in launches:
        x.forward_only = forward_only
    try:
        a, b = state, solver.model.state(requires_grad=False)
        for _ in range(steps):
            solver.step(a, b, dt)
            a, b = b, a
    finally:
        for x, k in zip(launches, kept):
            x.forward_only = k
    values = []
    for w in weights:
        loss = wp.zeros(1, dtype=wp.float64)
        wp.launch(dot_loss, len(w), [a.x, w], [loss])
        values.append(float(loss.numpy()[0]))
    return values


def taped_gradients(model, states, loss, tape, names) -> dict:
    """Runs ``tape.backward(loss)`` and returns the gradients of ``names``, each a copy keyed by
    name: ``"v0"`` the first state's velocities, any other name the model's array of it."""
    tape.backward(loss)
    return {n: (states[0].v if n == "v0" else getattr(model, n)).grad.numpy().copy() for n in names}


def rollout_central_difference(rollout, loss, name: str, rel_step: float = 1e-5) -> tuple[float, float]:
    """``(tape, central difference)`` of ``loss`` through ``rollout`` in the first value of the
    parameter ``name``, the difference at a step of ``rel_step`` of that value; the rollout is
    left at the perturbed values' last run."""
    _, grads = rollout.value_and_grad(loss)
    base = rollout.get_parameters()
    h = rel_step * base[name][0]
    vals = []
    for d in (h, -h):
        rollout.set_parameters({name: base[name] + d})
        rollout.forward()
        vals.append(loss.value(dict(zip(rollout.frames, rollout.frame_positions))))
    return float(grads[name][0]), (vals[0] - vals[1]) / (2 * h)



def assert_central_differences_converge(g: float, loss_at, step: float, ladder, bound, spread, what=None) -> tuple:
    """Asserts that central differences of ``loss_at(offset)`` (the loss with the input moved
    by ``offset``) close on the tape's gradient ``g`` over a ladder of steps, ``step / k`` for
    ``k`` in ``ladder`` (from 1 up): within ``bound`` (relative) at the smallest step, or with
    ``bound`` a sequence, each step within its own; and in each ring between two steps, the
    mean slope ``(L(a) - L(b) + L(-b) - L(-a)) / 2(a - b)`` within ``spread`` of ``g`` (none
    where ``spread`` is None; all relative to the smallest step's difference). Returns the
    relative errors at the steps and in the rings.

    Why a ladder rather than one step: the contact and flow laws have kinks (the flow's onset,
    a tool's whole-depth contact) and steep C1 bends (the touchdown share's smoothstep end,
    friction's rounded end), and the fit weight moves where a particle meets them. A step
    that crosses a kink reads the gradient's mean over it, off by up to half the gradient's
    change there, and falls onto the tape once it no longer reaches the kink; a bend makes
    the error fall as the step squared, from however far off. A jump J of the loss within
    a ring reads J / 2(a - b) there, and one inside the smallest step J / 2h: with the
    largest step the test's old one, a jump within it shows in one ring or at the bottom,
    while a kink reads at most half the gradient's change, which ``spread`` bounds. Where
    every step has its bound (a fit weight whose trajectory meets no kink within the steps:
    the old steps' bounds kept) the rings need none: a ring's error is at most
    ``(a e_a + b e_b) / (a - b)``, ``e`` the steps' errors."""
    steps = [step / k for k in ladder]
    plus = [loss_at(h) for h in steps]
    minus = [loss_at(-h) for h in steps]
    fd = [(p - m) / (2 * h) for p, m, h in zip(plus, minus, steps)]
    assert fd[-1] != 0.0, ("the loss does not reach the input", what)
    scale = abs(fd[-1])
    errors = [abs(f - g) / scale for f in fd]
    rings = [abs((plus[i] - plus[i + 1] + minus[i + 1] - minus[i]) / (2 * (steps[i] - steps[i + 1])) - g) / scale
             for i in range(len(steps) - 1)]
    bounds = list(bound) if np.ndim(bound) else [np.inf] * (len(steps) - 1) + [bound]
    assert len(bounds) == len(steps), ("one bound per step", what)
    assert errors[-1] <= bounds[-1], ("the central differences do not close on the tape", what, steps, errors)
    assert all(e <= b for e, b in zip(errors, bounds)), ("a step's difference strays from the tape", what, steps, errors)
    if spread is not None:
        assert max(rings, default=0.0) <= spread, ("a ring's slope strays from the tape: a jump", what, steps, rings)
    return errors, rings


def loss_central_differences(loss, x, entries, frame: int, eps: float = 1e-7) -> list:
    """d loss / d x[i, c] by central differences of ``loss.value`` at ``frame`` (float64
    positions ``x``), for each ``(i, c)`` of ``entries``."""
    fd = []
    for i, c in entries:
        vals = []
        for d in (eps, -eps):
            p = x.copy()
            p[i, c] += d
            vals.append(loss.value({frame: wp.array(p, dtype=wp.vec3d)}))
        fd.append((vals[0] - vals[1]) / (2 * eps))
    return fd


def set_first_material(model, **values) -> None:
    """Writes material 0's row of each named parameter array (``mu=...``, ``yield_stress=...``;
    a value None leaves its array as built): the perturbed models of a central difference."""
    for name, value in values.items():
        if value is not None:
            arr = getattr(model, name)
            a = arr.numpy()
            a[0] = value
            arr.assign(a)
