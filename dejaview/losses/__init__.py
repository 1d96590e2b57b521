"""Losses of inverse physical inference: how far a simulated trajectory is from an observation.

- ``dejaview.losses.pose``: position, orientation (geodesic), velocity and pose errors;
- ``dejaview.losses.add``: ADD, the average distance of model points;
- ``dejaview.losses.trajectory``: a rollout against a scene ``<target>``
  (best / final / pinned time), the ``LOSSES`` table and ``TrajectoryLoss``;
- ``dejaview.losses.penalty``: ``<penalty>`` contact terms.

Every loss is batched (returns ``(B,)`` for a batch of candidates) and
differentiable in reverse and forward mode, with finite gradients at zero error.
"""

from dejaview.losses.add import add_error, body_model_points, model_points
from dejaview.losses.penalty import contact_penalty
from dejaview.losses.pose import (DEFAULT_ORIENTATION_WEIGHT, SMOOTH_EPS, orientation_error, pose_error,
                                  position_error, smooth_norm, velocity_error)
from dejaview.losses.trajectory import (DEFAULT_VELOCITY_WEIGHT, LOSSES, TrajectoryLoss, nearest_record,
                                        softmin, trajectory_loss)

__all__ = [
    "DEFAULT_ORIENTATION_WEIGHT", "DEFAULT_VELOCITY_WEIGHT", "LOSSES", "SMOOTH_EPS", "TrajectoryLoss",
    "add_error", "body_model_points", "contact_penalty", "model_points", "nearest_record",
    "orientation_error", "pose_error", "position_error", "smooth_norm", "softmin", "trajectory_loss",
    "velocity_error",
]
