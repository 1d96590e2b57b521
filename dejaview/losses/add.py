"""ADD: the average distance of model points between a simulated and a target pose.

ADD (Hinterstoisser et al., ACCV 2012) moves a fixed set of points on the
object by both poses and averages how far each point lands from its twin. It
weighs orientation by the object's own size and shape, so it needs no
metres-per-radian weight. The points are expressed in the body's
centre-of-mass frame, so a pose is ``(COM position, orientation)`` as in
``dejaview.sim.State``. Each point distance is pseudo-Huber smoothed like
``dejaview.losses.pose`` (finite gradient at zero error).
"""

from __future__ import annotations

import numpy as np
import torch

from dejaview.losses.pose import SMOOTH_EPS, smooth_norm
from dejaview.sim.rotation import quat_to_matrix

DEFAULT_POINT_BUDGET = 256


def model_points(vertices, budget: int = DEFAULT_POINT_BUDGET, seed: int = 0, *, com=None,
                 dtype: torch.dtype | None = None, device=None) -> torch.Tensor:
    """Deterministic farthest-point subsample of a model's vertices, in the COM frame.

    Duplicate vertices are merged first; the first point is drawn with
    ``numpy.random.default_rng(seed)``, each next one is the vertex farthest
    from those already taken, so the points spread evenly over the model.

    Args:
        vertices: (V, 3) numpy array or tensor of points in the object frame.
        budget: at most this many points (all unique vertices if fewer).
        seed: picks the first point.
        com: (3,) centre of mass in the object frame (``World.com[i]``),
            subtracted so the points live in the body's COM frame. None keeps
            the object frame (only right when the COM is the origin).
        dtype, device: of the result (default: ``com``'s if a tensor, else float64 / CPU).
    Returns:
        (M, 3) points, M = min(budget, unique vertices).
    """
    if budget < 1:
        raise ValueError(f"budget must be at least 1, got {budget}")
    if isinstance(vertices, torch.Tensor):
        vertices = vertices.detach().cpu().numpy()
    v = np.unique(np.asarray(vertices, dtype=np.float64).reshape(-1, 3), axis=0)
    if len(v) == 0:
        raise ValueError("model_points needs at least one vertex")
    if len(v) <= budget:
        chosen = np.arange(len(v))
    else:
        rng = np.random.default_rng(seed)
        chosen = np.empty(budget, dtype=np.int64)
        chosen[0] = rng.integers(len(v))
        dist = np.linalg.norm(v - v[chosen[0]], axis=1)
        for k in range(1, budget):
            chosen[k] = int(np.argmax(dist))
            dist = np.minimum(dist, np.linalg.norm(v - v[chosen[k]], axis=1))
    pts = v[chosen]
    if isinstance(com, torch.Tensor):
        dtype = dtype or com.dtype
        device = device if device is not None else com.device
        com = com.detach().cpu().numpy()
    if com is not None:
        pts = pts - np.asarray(com, dtype=np.float64).reshape(1, 3)
    return torch.as_tensor(pts, dtype=dtype or torch.float64, device=device)


def body_model_points(world, body: int | str, vertices=None, budget: int = DEFAULT_POINT_BUDGET,
                      seed: int = 0) -> torch.Tensor:
    """Model points of a movable body of ``world``, in its COM frame.

    Args:
        world: a ``dejaview.sim.World``.
        body: index or name of the movable body.
        vertices: (V, 3) object-frame vertices (e.g. the mesh's); None uses the
            centres of the body's sphere packing (already in the COM frame).
        budget, seed: see ``model_points``.
    Returns:
        (M, 3) points in the world's dtype and device.
    """
    i = world.body_index(body) if isinstance(body, str) else int(body)
    if vertices is None:
        centers = world.centers[i][world.mask[i] > 0]
        return model_points(centers, budget, seed, dtype=world.dtype, device=world.device)
    return model_points(vertices, budget, seed, com=world.com[i], dtype=world.dtype, device=world.device)


def add_error(pos: torch.Tensor, q: torch.Tensor, target_pos: torch.Tensor, target_q: torch.Tensor,
              points: torch.Tensor, eps: float = SMOOTH_EPS,
              weights: torch.Tensor | None = None) -> torch.Tensor:
    """Average distance between model points placed by a pose and by a target pose.

    ``mean_m | R(q) p_m + pos - R(target_q) p_m - target_pos |`` (each distance
    pseudo-Huber smoothed). Invariant to the sign of either quaternion.

    Args:
        pos: (..., 3) centre-of-mass positions.
        q: (..., 4) orientations, w x y z.
        target_pos: (..., 3) target centre-of-mass positions (broadcast).
        target_q: (..., 4) target orientations (broadcast).
        points: (M, 3) model points in the body's COM frame (``model_points``).
        eps: smoothing scale in metres; 0 for exact distances.
        weights: (M,) non-negative point weights (e.g. ``World.mask[i]`` to use
            the padded sphere centres ``World.centers[i]`` directly); None: equal.
    Returns:
        (...) mean distances in metres.
    """
    rot_diff = quat_to_matrix(q) - quat_to_matrix(target_q)  # (..., 3, 3)
    # R p + x - (R' p + x') = (R - R') p + (x - x'); one matmul for all points
    diff = points @ rot_diff.transpose(-1, -2) + (pos - target_pos).unsqueeze(-2)  # (..., M, 3)
    dist = smooth_norm(diff, eps)
    if weights is None:
        return dist.mean(-1)
    return (dist * weights).sum(-1) / weights.sum()
