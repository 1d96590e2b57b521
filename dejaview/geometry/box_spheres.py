"""Sphere packing of a box, built from its shape instead of a lattice.

Every sphere touches a face of the box from inside: a grid of points is laid on
each face, and at each point the largest sphere that touches the face there and
stays inside the box is placed (its radius the distance from the point to the
face's border, at most the half thickness across the face), but never smaller
than the edge radius. Points on a face's border thus give spheres of the edge
radius that touch two faces (edges) or three (corners), and the union of the
spheres has the box's extent in every direction up to the rounding of its edges
and corners by that radius: a box resting or tipping on an edge touches where
the real box does. Each face grid is mirror-symmetric, so is the packing: a box
pushed straight keeps going straight. The spheres are the box's medial axis
sampled (the big ones on its mid-plane, smaller ones towards the edges), so they
also fill its inside.
"""

from __future__ import annotations

import numpy as np

from dejaview.errors import GeometryError

# Edge and corner radius as a fraction of the smallest half extent: small enough
# for sharp edges (the union misses a true edge by 0.41 of it, a corner by 0.73),
# large enough that the first face spheres beside an edge meet the edge spheres.
EDGE_FRACTION = 0.12
# Edge spheres are this many times as dense as the face grids: an edge is where a
# box tipping over a table's edge or landing on the floor touches.
EDGE_SPLIT = 2
# At most this many spheres touch one face: fewer than the engines' contact capacity
# per body and static shape (``dejaview.sim.world.DEFAULT_MAX_STATIC_CONTACTS``, 64),
# so a box resting on a face keeps every touching sphere. Beyond the capacity the
# deepest are kept, and among spheres at exactly equal depth that choice breaks the
# symmetry (a box slid straight drifts and yaws, and the two engines, whose top-k break
# ties differently, part).
MAX_FACE_SPHERES = 56
# Face grids coarser than this fraction of the thinnest half extent leave too much of
# the inside empty (the mid-plane spheres, that radius, too far apart): no packing.
MAX_SPACING = 0.75


def _axis_points(half: float, spacing: float) -> np.ndarray:
    """(M,) points from -half to half, ``spacing`` apart from each end inwards, the middle gap
    between 0.5 and 1.5 ``spacing`` (0 included when that needs it), exactly mirror-symmetric.

    Points at the same distances from the ends on every axis make spheres near an edge, built
    from either of its faces, the same sphere."""
    positive = half - spacing * np.arange(int(np.floor(half / spacing - 0.5 + 1e-9)) + 1)
    positive = positive[positive > 0] if len(positive) else np.array([half])
    middle = [0.0] if positive[-1] > 0.75 * spacing else []
    return np.concatenate([-positive, middle, positive[::-1]])


def _face_spheres(half: np.ndarray, spacing: float, edge_radius: float,
                  edge_split: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Spheres touching each face at a grid of points, duplicates removed.

    Args:
        half: (3,) half extents.
        spacing: of the face grids' points.
        edge_radius: the smallest radius.
        edge_split: the edges' points are ``edge_split`` times as dense as the faces'.
    Returns:
        centers (N, 3) and radii (N,), sorted, exactly mirror-symmetric.
    """
    points = [_axis_points(h, spacing) for h in half]
    rows = []
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        u, v = np.meshgrid(points[a], points[b], indexing="ij")
        u, v = u.ravel(), v.ravel()
        radius = np.minimum(half[k], np.minimum(half[a] - np.abs(u), half[b] - np.abs(v)))
        radius = np.maximum(radius, edge_radius)
        for sign in (-1.0, 1.0):
            center = np.empty((len(u), 3))
            center[:, k] = sign * (half[k] - radius)
            center[:, a] = np.clip(u, -(half[a] - radius), half[a] - radius)
            center[:, b] = np.clip(v, -(half[b] - radius), half[b] - radius)
            rows.append(np.column_stack([center, radius]))
    for k in range(3):  # edges along axis k
        t = np.clip(_axis_points(half[k], spacing / edge_split), -(half[k] - edge_radius),
                    half[k] - edge_radius)
        for sa, sb in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
            center = np.empty((len(t), 3))
            center[:, k] = t
            center[:, (k + 1) % 3] = sa * (half[(k + 1) % 3] - edge_radius)
            center[:, (k + 2) % 3] = sb * (half[(k + 2) % 3] - edge_radius)
            rows.append(np.column_stack([center, np.full(len(t), edge_radius)]))
    # round before merging so that twins built from two faces are one sphere
    spheres = np.unique(np.round(np.concatenate(rows), 12), axis=0)
    return spheres[:, :3], spheres[:, 3]


def box_spheres(size, max_spheres: int = 256,
                edge_radius: float | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Mirror-symmetric packing of a box centred at the origin, axes along x, y, z.

    The face grids are as fine as the budget and ``MAX_FACE_SPHERES`` allow
    (one spacing for all faces, from the edges inwards). Where that grid is
    coarser than ``MAX_SPACING`` of the thinnest half extent (a thin plate, a
    budget under ~120 spheres for a 20 x 15 x 10 cm box) the result is None:
    the spheres would leave much of the inside empty.

    Args:
        size: (3,) extents, metres, all positive.
        max_spheres: sphere budget.
        edge_radius: radius of the edge and corner spheres, metres (default:
            ``EDGE_FRACTION`` of the smallest half extent; at most that half
            extent).
    Returns:
        centers (N, 3) and radii (N,), N <= max_spheres, or None (see above); the packing's bounding
        box is the box, and mirroring it in any of the planes x = 0, y = 0,
        z = 0 gives the same set of spheres.
    Raises:
        GeometryError: an edge radius that does not fit.
    """
    half = 0.5 * np.asarray(size, dtype=np.float64).reshape(3)
    thinnest = float(half.min())
    radius = EDGE_FRACTION * thinnest if edge_radius is None else float(edge_radius)
    if not 0 < radius <= thinnest:
        raise GeometryError(f"edge radius {radius:g} m does not fit a box {2 * thinnest:g} m thin")
    best = None
    spacing = 2.0 * float(half.max())
    while spacing > 0.25 * radius:  # finer than that adds nothing the edge spheres lack
        centers, radii = _face_spheres(half, spacing, radius, EDGE_SPLIT)
        on_face = [int(np.sum(np.isclose(np.abs(centers[:, k]) + radii, half[k], rtol=0, atol=1e-12))) // 2
                   for k in range(3)]
        if len(radii) > max_spheres or max(on_face) > MAX_FACE_SPHERES:
            break
        best = (centers, radii)
        spacing *= 0.98
    if best is None or spacing / 0.98 > MAX_SPACING * thinnest:
        return None
    return best
