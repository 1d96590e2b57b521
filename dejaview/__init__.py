"""DejaView: infer where an object came from with a differentiable rigid-body simulator.

Importing the package is cheap; the heavy parts (torch, trimesh, the server) are
imported by the submodules that need them.
"""

from __future__ import annotations

__version__ = "0.1.0"

from dejaview.errors import (  # noqa: E402
    DejaViewError,
    GeometryError,
    InferenceError,
    SceneError,
    SimulationError,
)



def __getattr__(name):
    # heavy parts load on first use: ``dejaview.solve``, ``dejaview.Scene``, ``dejaview.World``
    if name == "solve":
        from dejaview.inference.solve import solve

        return solve
    if name == "SolveParams":
        from dejaview.inference.solve import SolveParams

        return SolveParams
    if name == "Scene":
        from dejaview.scene import Scene

        return Scene
    if name == "World":
        from dejaview.sim import World

        return World
    raise AttributeError(f"module 'dejaview' has no attribute {name!r}")


__all__ = [
    "__version__",
    "Scene",
    "World",
    "solve",
    "SolveParams",
    "DejaViewError",
    "GeometryError",
    "InferenceError",
    "SceneError",
    "SimulationError",
]
