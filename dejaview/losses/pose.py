"""Pose errors: position, orientation and velocity distances between two rigid-body states.

Every function is batched over leading dimensions, differentiable in reverse
and forward mode (``torch.func.jvp`` under ``vmap``) and has a finite gradient
at exactly zero error.

Smoothing: a Euclidean norm ``|d|`` has a cone at ``d = 0``: its gradient is
undefined there (autograd gives NaN) and jumps across it, which L-BFGS line
searches dislike. Distances here are pseudo-Huber norms

    smooth_norm(d) = sqrt(|d|^2 + eps^2) - eps,

equal to ``|d|^2 / (2 eps)`` for ``|d| << eps`` and to ``|d| - eps`` for
``|d| >> eps``: zero at zero, smooth everywhere, convex, and within ``eps`` of
the true distance. The default ``eps`` (``SMOOTH_EPS`` = 1e-6: a micron, a
microradian) is far below anything a simulation resolves, so reported losses
read as plain metres and radians. ``eps = 0`` gives the exact norm, still with
finite gradients in both modes; but at zero error that gradient is a
subgradient (zero for positions; for angles, the ~1e-17 rad roundoff of the
relative quaternion picks an arbitrary unit direction), another reason to smooth.

Orientation is the geodesic angle on SO(3) (``dejaview.sim.rotation.geodesic_angle``),
invariant to the sign of either quaternion (q and -q are the same rotation).
"""

from __future__ import annotations

import torch

from dejaview.sim.rotation import geodesic_angle

SMOOTH_EPS = 1e-6
"""Default pseudo-Huber scale: metres for positions, radians for angles, m/s or rad/s for velocities."""

DEFAULT_ORIENTATION_WEIGHT = 0.05
"""Metres of loss per radian of orientation error (m/rad).

A point at distance r from the centre of mass moves by about ``r * theta`` when
the body turns by ``theta``; 0.05 m is the half-size of the household objects
DejaView scenes hold (a mug, a box, a ball), so 1 rad of orientation error
costs what moving the object's surface by ~5 cm would. Use the body's bounding
radius (``World.bound``) to weigh orientation like its own surface.
"""


def _smooth(sq: torch.Tensor, eps: float) -> torch.Tensor:
    """Pseudo-Huber of a squared norm: sqrt(sq + eps^2) - eps, finite gradient at sq = 0."""
    # eps = 0 falls back to the smallest normal number: exact norm, zero subgradient at 0
    e2 = max(float(eps) ** 2, torch.finfo(sq.dtype).tiny)
    return torch.sqrt(sq + e2) - e2 ** 0.5


def smooth_norm(d: torch.Tensor, eps: float = SMOOTH_EPS) -> torch.Tensor:
    """Pseudo-Huber norm of vectors.

    Args:
        d: (..., K) vectors.
        eps: smoothing scale (same unit as ``d``); 0 for the exact norm.
    Returns:
        (...) ``sqrt(|d|^2 + eps^2) - eps``.
    """
    return _smooth((d * d).sum(-1), eps)


def position_error(pos: torch.Tensor, target_pos: torch.Tensor, eps: float = SMOOTH_EPS) -> torch.Tensor:
    """Euclidean distance between positions (metres), pseudo-Huber smoothed.

    Args:
        pos: (..., 3) positions.
        target_pos: (..., 3) target positions (broadcast against ``pos``).
        eps: smoothing scale in metres (see the module docstring); 0 for exact.
    Returns:
        (...) distances, within ``eps`` of ``|pos - target_pos|``.
    """
    return smooth_norm(pos - target_pos, eps)


def orientation_error(q: torch.Tensor, target_q: torch.Tensor, eps: float = SMOOTH_EPS) -> torch.Tensor:
    """Geodesic angle between orientations (radians, in [0, pi]), pseudo-Huber smoothed at zero.

    Invariant to the sign of ``q`` and ``target_q`` and to their scale.

    Args:
        q: (..., 4) quaternions, w x y z.
        target_q: (..., 4) target quaternions (broadcast against ``q``).
        eps: smoothing scale in radians; 0 for the plain geodesic angle.
    Returns:
        (...) angles, within ``eps`` of the geodesic angle.
    """
    q, target_q = torch.broadcast_tensors(q, target_q)
    angle = geodesic_angle(q, target_q)
    return _smooth(angle * angle, eps)


def velocity_error(v: torch.Tensor, target_v: torch.Tensor, eps: float = SMOOTH_EPS) -> torch.Tensor:
    """Euclidean distance between velocity vectors (linear m/s or angular rad/s), smoothed.

    Args:
        v: (..., 3) velocities.
        target_v: (..., 3) target velocities (broadcast against ``v``).
        eps: smoothing scale in the velocity's unit; 0 for exact.
    Returns:
        (...) ``|v - target_v|`` (pseudo-Huber).
    """
    return smooth_norm(v - target_v, eps)


def pose_error(pos: torch.Tensor, q: torch.Tensor, target_pos: torch.Tensor, target_q: torch.Tensor,
               orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
               eps: float = SMOOTH_EPS) -> torch.Tensor:
    """Position error plus weighted geodesic orientation error, added in quadrature, in metres.

    ``sqrt(position_error(pos, target_pos)^2 + (orientation_weight * orientation_error(q, target_q))^2)``.

    Why in quadrature and not as a plain sum: the optimisers minimise
    ``0.5 * loss^2``. For the sum ``a + w b`` that has a cross term ``w a b``,
    which is a V-shaped valley along every pose whose position matches
    (``a = 0``) while its orientation does not: L-BFGS lands on the valley
    floor and stalls there (docs/inference.md, "Parameters and losses", has a
    case). In quadrature ``0.5 * loss^2 = 0.5 (a^2 + w^2 b^2)`` is
    smooth wherever either part vanishes. Both parts stay bounded by the loss:
    a loss of 3 mm means a position within 3 mm and an angle within
    3 mm / ``orientation_weight`` (3.4 degrees at 0.05 m/rad).

    Args:
        pos: (..., 3) positions (compare like with like: centres of mass or object origins).
        q: (..., 4) quaternions, w x y z.
        target_pos: (..., 3) target positions.
        target_q: (..., 4) target quaternions.
        orientation_weight: metres per radian (default ``DEFAULT_ORIENTATION_WEIGHT`` = 0.05).
        eps: smoothing scale of both terms (metres and radians).
    Returns:
        (...) losses in metres.
    """
    a = position_error(pos, target_pos, eps)
    b = orientation_weight * orientation_error(q, target_q, eps)
    # the smallest normal number keeps the gradient finite (zero) where both parts are exactly zero
    return torch.sqrt(a * a + b * b + torch.finfo(a.dtype).tiny)
