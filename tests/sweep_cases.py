"""The sweep tests' scene and sample functions, shared by ``test_sweep.py`` and
``test_sweep_ray.py``: a worker process or a Ray worker imports this module by name to run
the ``extra`` functions a sample is sent with.

The scene is a 125-particle box of toothpaste (2 cm spacing) dropped 1 cm onto the
ground, run for 10 frames at 30 fps (a third of a second): enough for a low yield stress
to slump visibly and a high one to stay a box."""

import os
import sys

from warp_esph.builder import SceneBuilder
from warp_esph.material import Material
from warp_esph.scenes import Scene
from warp_esph.sweep import SweepTable

FRAMES = 10
YIELD = "yield_stress=10:10000:log:3"


def _box() -> Scene:
    b = SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.06, 0.0), (0.1, 0.1, 0.1), Material.preset("toothpaste"), name="paste")
    b.add_ground(friction=0.5)
    return Scene("paste_box", "a small box of toothpaste", b, frames=FRAMES, fps=30.0)


def _rows(table: SweepTable):
    """The rows without ``wall_s``, the one column that depends on the machine's load."""
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in table.rows]


class _TwoPartError(Exception):
    """An exception pickle cannot rebuild (``cls(*args)`` with its one message): a worker
    process sends it, and the parent fails to read it back."""

    def __init__(self, what, why):
        super().__init__(f"{what}: {why}")


def _extra_raising_what_pickle_cannot_rebuild(model, state, seed):
    raise _TwoPartError("extra", "no column today")


def _extra_that_exits(model, state, seed):
    sys.exit(4)


def _extra_that_fails(model, state, seed):
    """An ``extra`` column function: kills its worker process in sample 0, raises in sample 1."""
    from warp_esph.sweep import _sample_seed

    if seed == _sample_seed(0, 0) and str(os.getpid()) != os.environ[PARENT]:
        os._exit(7)
    if seed == _sample_seed(0, 1):
        raise TypeError("a bug in extra")
    return {"top_x": float(state.x.numpy()[:, 0].max())}


# The spawned workers import this module; they inherit the variable with the test's pid.
PARENT = "WARP_ESPH_TEST_SWEEP_PARENT"
os.environ.setdefault(PARENT, str(os.getpid()))


def _extra_of_a_function(model, state, seed):
    return {"top": float(state.x.numpy()[:, 1].max()), "how": _box}


# The three ``extra`` functions above that fail every sample the same wherever it runs, two
# samples each (0-1, 2-3, 4-5) of one sweep: test_sweep's tests of them share one pool of
# worker processes instead of starting one each (a worker's start costs about 2 s of CPU).
SAMPLE_EXTRAS = (_extra_raising_what_pickle_cannot_rebuild, _extra_that_exits, _extra_of_a_function)


def _extra_by_sample(model, state, seed):
    """Sample ``i``'s ``extra`` is ``SAMPLE_EXTRAS[i // 2]`` (the sweep's seed is 0)."""
    from warp_esph.sweep import _sample_seed

    (i,) = [i for i in range(2 * len(SAMPLE_EXTRAS)) if seed == _sample_seed(0, i)]
    return SAMPLE_EXTRAS[i // 2](model, state, seed)
