"""warp_esph: differentiable point-based elastoplastic solids in NVIDIA Warp.

An implementation of Gerszewski, Bhattacharya & Bargteil 2009, "A Point-based Method
for Animating Elastoplastic Solids": ``SceneBuilder -> Model -> State``,
``Solver.step(state_in, state_out, dt)``.

The names below are imported on first use (PEP 562), so ``import warp_esph.cli`` does not
load Warp and pxr: the command line installs its Ctrl-C handler before they load.
"""

import importlib
import sys
import types

__version__ = "0.1.0"

#: Public name -> the module that defines it.
_EXPORTS = {
    "SceneBuilder": ".builder", "finalize_worlds": ".builder", "replicate_worlds": ".builder",
    "Material": ".material", "MODELS": ".material", "PRESETS": ".material",
    "Model": ".model", "State": ".model", "Body": ".model",
    "simulate": ".simulate", "SimulationError": ".simulate",
    "Solver": ".sim.solver", "GUARD_NAMES": ".sim.solver",
    "UsdWriter": ".usd", "init_warp": ".startup",
}

__all__ = [
    "SceneBuilder", "finalize_worlds", "replicate_worlds", "Material", "MODELS", "PRESETS", "Model", "State", "Body", "Solver", "GUARD_NAMES",
    "simulate", "SimulationError", "UsdWriter", "init_warp", "__version__",
]


def __getattr__(name):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'warp_esph' has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


class _Package(types.ModuleType):
    """``simulate`` is both a submodule and the function the package exports: importing the
    submodule sets the package attribute to the module, which must not hide the function
    (the eager imports this package had rebound it after the import)."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and _EXPORTS.get(name) == f".{name}":
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
