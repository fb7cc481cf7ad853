"""Which kernels a block of code launches, forward and adjoint: the instrument the gradient
coverage table (docs/method.md, "Which test checks each kernel's adjoint") is built and kept
with. Every launch goes through ``wp.launch`` (Warp's tape replays a generated adjoint with
it) or a ``Launches`` (``sim/replay.py``: the step's replayed launches, hand-written adjoints
included), so both are wrapped for the block's length."""

import contextlib
import os

import warp as wp

from warp_esph.sim import replay


def kernel_name(kernel) -> str:
    """``module.function`` of a kernel, its source file's stem and the function's name: the
    same for a dtype's or a twin's compilation of one kernel (``replay.forward_only``)."""
    func = kernel.func
    stem = os.path.splitext(os.path.basename(func.__code__.co_filename))[0]
    return f"{stem}.{func.__name__}"


@contextlib.contextmanager
def launched_kernels(log: set, variants: set | None = None):
    """Adds ``(kernel_name, "forward" | "adjoint")`` to ``log`` for every launch in the block:
    ``"adjoint"`` for a launch of a kernel's adjoint (Warp's generated one); a hand-written
    adjoint is a kernel of its own, launched forward in the backward pass. ``variants``, if
    given, gets the same with the kernel's compiled module's name appended: one kernel
    specialised to a scene (the tools' integrator to its shapes, a fit to its weight, float32
    or float64) is compiled into a module named after its content's hash."""
    launch, call = wp.launch, replay.Launches.__call__
    seen = set()

    def logged_launch(kernel, *args, **kwargs):
        seen.add((kernel, "adjoint" if kwargs.get("adjoint") else "forward"))
        return launch(kernel, *args, **kwargs)

    def logged_call(self, kernel, *args, **kwargs):
        seen.add((kernel, "adjoint" if kwargs.get("adjoint") else "forward"))
        return call(self, kernel, *args, **kwargs)

    wp.launch, replay.Launches.__call__ = logged_launch, logged_call
    try:
        yield log
    finally:
        wp.launch, replay.Launches.__call__ = launch, call
        # (A module is named after its hash when it is loaded, at its first launch.)
        for kernel, phase in seen:
            log.add((kernel_name(kernel), phase))
            if variants is not None:
                variants.add((kernel_name(kernel), phase, kernel.module.name))
