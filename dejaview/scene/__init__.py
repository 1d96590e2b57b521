"""Scene format: dataclasses, hardened XML reading/writing and validation."""

from dejaview.errors import SceneError
from dejaview.scene.model import (
    EVALUATES,
    GRADIENTS,
    LOSSES,
    OPTIMIZERS,
    SHAPES,
    Exploration,
    HeatmapSettings,
    InferenceSettings,
    JointKeyframe,
    ModelUncertainty,
    PhysicsPrior,
    Observation,
    Optimize,
    Penalty,
    Pose,
    PosteriorRequest,
    Prior,
    Scene,
    SceneObject,
    SimulationSettings,
    StartArea,
    Target,
    Velocity,
)

__all__ = [
    "EVALUATES", "GRADIENTS", "LOSSES", "OPTIMIZERS", "SHAPES",
    "Exploration", "HeatmapSettings", "InferenceSettings", "ModelUncertainty", "PhysicsPrior", "Observation", "Optimize", "Penalty",
    "JointKeyframe", "Pose", "PosteriorRequest", "Prior", "Scene", "SceneError", "SceneObject", "SimulationSettings",
    "StartArea",
    "Target", "Velocity",
]
