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

__all__ = [
    "__version__",
    "DejaViewError",
    "GeometryError",
    "InferenceError",
    "SceneError",
    "SimulationError",
]
