"""Re-exports the spheres backend's problem (``dejaview.backends.spheres``) and the helpers of
``dejaview.backends.base``: what infers imports the backends, never the other way; this module
keeps ``dejaview.inference.problem`` imports working."""

from dejaview.backends.base import DEFAULT_ORIENTATION_WEIGHT, check_inference, model_points, objective_to_loss
from dejaview.backends.spheres import InferenceProblem

__all__ = ["DEFAULT_ORIENTATION_WEIGHT", "InferenceProblem", "check_inference", "model_points",
           "objective_to_loss"]
