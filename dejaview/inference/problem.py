"""Re-exports ``dejaview.backends.problem``: the spheres backend's problem sits below
``dejaview.inference`` (what infers imports the backends, never the other way); this module keeps
``dejaview.inference.problem`` imports working."""

from dejaview.backends.problem import (DEFAULT_ORIENTATION_WEIGHT, InferenceProblem, check_inference,
                                       model_points, objective_to_loss)

__all__ = ["DEFAULT_ORIENTATION_WEIGHT", "InferenceProblem", "check_inference", "model_points",
           "objective_to_loss"]
