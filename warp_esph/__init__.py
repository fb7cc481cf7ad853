"""warp_esph: differentiable point-based elastoplastic solids in NVIDIA Warp.

An implementation of Gerszewski, Bhattacharya & Bargteil 2009, "A Point-based Method
for Animating Elastoplastic Solids": ``SceneBuilder -> Model -> State``,
``Solver.step(state_in, state_out, dt)``.
"""

from .builder import SceneBuilder, finalize_worlds
from .material import MODELS, PRESETS, Material
from .model import Body, Model, State
from .simulate import SimulationError, simulate
from .sim.solver import GUARD_NAMES, Solver
from .usd import UsdWriter

__version__ = "0.1.0"

__all__ = [
    "SceneBuilder", "finalize_worlds", "Material", "MODELS", "PRESETS", "Model", "State", "Body", "Solver", "GUARD_NAMES",
    "simulate", "SimulationError", "UsdWriter", "__version__",
]
