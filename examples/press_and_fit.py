"""Gradients through a tool: optimise a press's trajectory, and fit a stiffness to a force curve.

1. **Press to a target shape.** A block of dough (``Material.preset("dough")``) sits on a
   base plate; a box press follows keyframes (``tools.Keyframes``). The press's keyframe
   lowest point is found from the gradient through the taped rollout so that the dough's
   top surface (the mean height of its top particle layer) ends at a target height after
   the press has come back up (the dough keeps
   what it yielded: the press must overshoot by the elastic spring-back).
2. **Fit a material to a force-displacement curve.** A plate compresses an elastic sample;
   the "measured" curve is the plate's reaction force (``state.reaction_force``) every step
   for a true Young's modulus. Starting from half of it, the log-modulus is fitted from the
   gradient of the misfit through the differentiable reaction forces.

    python examples/press_and_fit.py          # about 10 s on one CPU core once Warp has compiled its kernels

Everything is float64 (``finalize(dtype=wp.float64, requires_grad=True)``); see docs/tools.md.
"""

import argparse
import os
import sys

import numpy as np
import warp as wp

try:
    import warp_esph as we
except ImportError:  # run from a checkout without installing the package
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import warp_esph as we
from warp_esph import tools

DX = 0.01


# ------------------------------------------------------------------ 1. press to a target
def press_model(heights):
    """Dough block 6 x 3 x 6 cm on a base; the (frictionless) press's bottom face touches the top particle
    layer at t = 0, goes to ``heights[0]`` at 40 ms and back to ``heights[1]`` at 80 ms."""
    b = we.SceneBuilder(spacing=DX)
    # A firm dough: the preset (yield stress 150 Pa) slumps under its own weight.
    b.add_box((0.0, 0.015, 0.0), (0.06, 0.03, 0.06), we.Material.preset("dough").replace(yield_stress=1000.0), name="dough")
    b.add_tool("plane", friction=0.5, name="base", position=(0.0, 0.5 * DX, 0.0))  # at the bottom particle layer
    top = 0.025  # the top particle layer: the press starts touching it
    pad = 0.005  # half the press's thickness: its position is 5 mm above its bottom face
    # A frictionless press: with friction 0.5 the mean top height, smooth between the steps
    # where a particle sticks or slips, jumps at them, and between the jumps it rises as the press
    # goes deeper (measured: the local derivative at 16 mm points the wrong way, and the
    # search stopped at 16.2 mm with the top at 21.8 mm).
    b.add_tool("box", half_extents=(0.06, pad, 0.06), friction=0.0, name="press",
               motion=tools.Keyframes([0.0, 0.04, 0.08], [(0, top + pad, 0), (0, heights[0] + pad, 0), (0, heights[1] + pad, 0)]))
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(0).normal(scale=1e-3 * DX, size=model.particle_x0.shape)
    return model


@wp.kernel(module="unique")
def mean_height(x: wp.array(dtype=wp.vec3d), top: wp.array(dtype=wp.int32), mean: wp.array(dtype=wp.float64)):
    k = wp.tid()
    wp.atomic_add(mean, 0, x[top[k]][1] / wp.float64(top.shape[0]))


@wp.kernel(module="unique")
def squared_error(mean: wp.array(dtype=wp.float64), target: wp.float64, loss: wp.array(dtype=wp.float64)):
    d = mean[0] - target
    loss[0] = d * d


def press_loss(heights, target, steps=250, dt=4e-4, grad=False, positions=None):
    """The squared distance of the top layer's mean height from ``target`` after the press,
    and that mean height; with ``grad``, also the loss's derivatives with respect to the two
    moving keyframes' heights. ``positions``: a dict to which ``heights[0]`` maps
    ``(x0, x)``, the particles' start and final positions (what the notebook plots, read
    from this run rather than run again)."""
    model = press_model(heights)
    solver = we.Solver(model)
    states = [model.state() for _ in range(steps + 1)]
    x0 = model.particle_x0
    top = wp.array(np.nonzero(x0[:, 1] > x0[:, 1].max() - 0.5 * DX)[0].astype(np.int32), dtype=wp.int32)
    mean = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        for k in range(steps):
            solver.step(states[k], states[k + 1], dt)
        # On the mean height of the top layer, not on each particle's: the mean top height
        # grows with the depth, the particles' spread does not, and a loss summed per particle
        # has a local minimum at 16.4 mm (measured) that the search would stop in.
        wp.launch(mean_height, top.shape[0], [states[-1].x, top], [mean])
        wp.launch(squared_error, 1, [mean, target], [loss])
    value = float(loss.numpy()[0])
    mean_top = float(mean.numpy()[0])
    if positions is not None:
        positions[heights[0]] = (x0, states[-1].x.numpy())
    if not grad:
        return value, mean_top
    tape.backward(loss)
    kp = model.tools.keyframe_positions.grad.numpy()
    start = model.tools.keyframe_start[model.tools.index("press")]
    return value, mean_top, np.array([kp[start + 1][1], kp[start + 2][1]])


def minimise_1d(fun_grad, x, step, iterations, label, tol):
    """Minimise a smooth 1-D function from its value and derivative: steps of ``step``
    downhill until the derivative changes sign, then regula falsi on the derivative inside
    that bracket (robust where Newton on a noisy curvature would overshoot)."""
    f, g = fun_grad(x)
    bracket = None
    for it in range(iterations):
        print(f"  iteration {it:2d}: {label(x)}, loss {f:.4e}, derivative {g:+.4e}")
        if f < tol:
            break
        if bracket is None:
            x_new = x - np.sign(g) * step
        else:
            (a, ga), (b, gb) = bracket
            x_new = a - ga * (b - a) / (gb - ga)
        f_new, g_new = fun_grad(x_new)
        if bracket is None and np.sign(g_new) != np.sign(g):
            bracket = ((x, g), (x_new, g_new))
        elif bracket is not None:
            (a, ga), (b, gb) = bracket
            bracket = ((a, ga), (x_new, g_new)) if np.sign(g_new) != np.sign(ga) else ((x_new, g_new), (b, gb))
        x, f, g = x_new, f_new, g_new
    return x


def optimise_press(target=0.021, iterations=10, history=None, positions=None):
    """How deep must the press go (it comes back up to 3 cm) to leave the top at ``target``?
    ``history``: a list to append ``(depth, loss, top, derivative)`` to at every evaluation;
    ``positions``: a dict to which each evaluated depth maps the particles' start and final
    positions (``press_loss``)."""
    print(f"press: target top height {1e3 * target:.1f} mm (top particle layer at rest: 25.0 mm)")

    def fun_grad(depth):
        loss, top, g = press_loss(np.array([depth, 0.03]), target, grad=True, positions=positions)
        fun_grad.top = top
        if history is not None:
            history.append((depth, loss, top, g[0]))
        return loss, g[0]

    return minimise_1d(fun_grad, 0.020, 0.002, iterations,
                       lambda d: f"press down to {1e3 * d:.2f} mm, top {1e3 * fun_grad.top:.2f} mm", tol=(2e-5) ** 2)


# -------------------------------------------------- 2. stiffness from a force curve
def compression_model(E):
    b = we.SceneBuilder(spacing=DX, gravity=(0.0, 0.0, 0.0))
    mat = we.Material.from_young(E, 0.3, density=1000.0, pressure_stiffness=0.0, viscosity=0.5, elastic_force="variational")
    b.add_box((0.0, 0.02, 0.0), (0.04, 0.04, 0.04), mat, name="sample")
    b.add_tool("plane", name="base", position=(0.0, 0.5 * DX, 0.0))
    b.add_tool("plane", normal=(0, -1, 0), name="plate",
               motion=tools.Velocity((0.0, -0.05, 0.0), position=(0.0, 0.04 - 0.5 * DX, 0.0)))
    return b.finalize(dtype=wp.float64, requires_grad=True)


@wp.kernel(module="unique")
def curve_loss(f: wp.array(dtype=wp.vec3d), k: int, target: wp.float64, loss: wp.array(dtype=wp.float64)):
    d = f[k][1] - target
    wp.atomic_add(loss, 0, d * d)


def force_curve(E, target=None, steps=60, dt=2e-4):
    """The plate's force every step; with ``target``, also the squared misfit and its
    derivative in log E (through mu and lam, at fixed Poisson's ratio)."""
    model = compression_model(E)
    solver = we.Solver(model)
    plate = model.tools.index("plate")
    states = [model.state() for _ in range(steps + 1)]
    loss = wp.zeros(1, dtype=wp.float64, requires_grad=True)
    tape = wp.Tape()
    with tape:
        for k in range(steps):
            solver.step(states[k], states[k + 1], dt)
            if target is not None:
                wp.launch(curve_loss, 1, [states[k + 1].reaction_force, plate, float(target[k])], [loss])
    curve = np.array([s.reaction_force.numpy()[plate][1] for s in states[1:]])
    if target is None:
        return curve
    tape.backward(loss)
    m = model.materials[0]
    dlogE = model.mu.grad.numpy()[0] * m.mu + model.lam.grad.numpy()[0] * m.lam  # d loss / d log E
    return curve, float(loss.numpy()[0]), dlogE


def fit_stiffness(E_true=2.0e4, E_start=1.0e4, iterations=10, history=None):
    """``E`` fitted from ``E_start`` to the force curve of ``E_true``. ``history``: a list to
    append ``(E, loss, curve)`` to at every evaluation."""
    measured = force_curve(E_true)
    print(f"fit: measured plate force {measured[-1]:.3f} N at the end (E = {E_true:g} Pa); start E = {E_start:g} Pa")

    def fun_grad(logE):
        curve, loss, g = force_curve(np.exp(logE), measured)
        if history is not None:
            history.append((float(np.exp(logE)), loss, curve))
        return loss, g

    logE = minimise_1d(fun_grad, np.log(E_start), 0.25, iterations, lambda x: f"E = {np.exp(x):8.1f} Pa",
                       tol=1e-8 * float(measured @ measured))
    return float(np.exp(logE))


def main(argv=None) -> int:
    # No options: a parser all the same, so that --help prints what the example does and a
    # mistyped option is refused before the minute of work rather than ignored.
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.parse_args(argv)
    we.init_warp()  # no start-up banner, no native note about a missing CUDA driver
    depth = optimise_press()
    print(f"press depth: {1e3 * depth:.2f} mm")
    E = fit_stiffness()
    print(f"fitted E = {E:.1f} Pa (true 20000)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
