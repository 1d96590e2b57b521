"""Depths of overlap between placed convex pieces, numpy only (``dejaview.geometry.collision``).

A body (``collision._Body``: the ``body``, ``a`` and ``b`` arguments below) is a list of convex
pieces with their polytope vertices and face normals (``shapes``) or a closed-form support
(spheres, cylinders). These functions place them
(rotation (3, 3) and position (3,), or a batch of them) and measure how deep two of them
overlap: by projections onto separating axes (``piece_depth``), by a mesh's deepest vertex in a
convex polytope (``vertex_depth``), or below a plane (``below_plane``).
"""

from __future__ import annotations

import numpy as np


def support(body, piece: int, rot: np.ndarray, pos: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Largest ``axis . x`` over one convex piece placed at (rot, pos).

    Args:
        axes: (K, 3) unit vectors, world frame.
    Returns:
        (K,) support values, metres.
    """
    base = axes @ pos
    local = axes @ rot  # the axes in the object frame
    shape = body.shapes[piece]
    if shape is not None:
        return base + (local @ shape[0].T).max(axis=1)
    if body.kind == "sphere":
        return base + body.size[0]
    radius, height = body.size
    along = np.abs(local[:, 2])
    return base + 0.5 * height * along + radius * np.sqrt(np.clip(1.0 - along ** 2, 0.0, None))


def piece_depth(a, p: int, rot: np.ndarray, pos: np.ndarray, b, q: int,
                contact, limit: float | None = None) -> float:
    """Penetration depth of two overlapping convex pieces (fcl found them overlapping).

    ``contact`` is fcl's contact where a piece is a sphere or cylinder (its
    normal is one more axis), None for two polytopes.

    fcl's EPA depth is unreliable for polytopes (measured: two 20 x 15 x 10 cm
    boxes 3 cm apart, 10 cm deep, reported 17 cm), so the depth is the
    smallest overlap of the two pieces' projections onto a set of axes: the
    face normals of both and EPA's normal (curved pieces). Every axis gives an upper bound of
    the minimum translation that separates them; face normals give it exactly
    unless the deepest direction is an edge against an edge. Pairs of boxes
    and spheres keep fcl's own answer (closed-form routines, exact) where smaller.

    ``limit``: only whether the depth exceeds it matters (``penetration``'s margin). The axes
    are tried a group at a time, the piece with fewer faces first, and the first group that
    shows an overlap at or below ``limit`` ends the search: the value returned is then an
    upper bound of the depth, at most ``limit`` (a resting mesh ball of 1000 faces on a
    table top: one axis instead of 1000).
    """
    groups = [] if contact is None else [np.asarray(contact.normal, dtype=np.float64)[None]]
    pieces = [(body, piece, r) for body, piece, r in ((a, p, rot), (b, q, b.rotation))
              if body.shapes[piece] is not None]
    pieces.sort(key=lambda t: len(t[0].shapes[t[1]][1]))
    groups += [body.shapes[piece][1] @ r.T for body, piece, r in pieces]
    depth = np.inf
    for axes in groups:
        axes = axes[np.linalg.norm(axes, axis=1) > 0.5]
        if not len(axes):
            continue
        overlap = np.minimum(
            support(a, p, rot, pos, axes) + support(b, q, b.rotation, b.position, -axes),
            support(b, q, b.rotation, b.position, axes) + support(a, p, rot, pos, -axes))
        depth = min(depth, float(overlap.min()))
        if limit is not None and depth <= limit:
            break
    if not np.isfinite(depth):
        depth = abs(contact.penetration_depth)
    if contact is not None and a.kind in ("box", "sphere") and b.kind in ("box", "sphere"):
        depth = min(depth, abs(contact.penetration_depth))
    return max(0.0, depth)


def vertex_depth(a, rot: np.ndarray, pos: np.ndarray, b) -> float:
    """A lower bound of the depth of a concave mesh's overlap with a convex polytope (0 where
    the pair is not one): the deepest of the mesh's vertices inside the polytope, measured to
    its nearest face. Every translation that separates the two moves that vertex out."""
    if a.concave and not b.concave and len(b.shapes) == 1 and b.shapes[0] is not None:
        mesh, m_rot, m_pos, solid, s_rot, s_pos = a, rot, pos, b, b.rotation, b.position
    elif b.concave and not a.concave and len(a.shapes) == 1 and a.shapes[0] is not None:
        mesh, m_rot, m_pos, solid, s_rot, s_pos = b, b.rotation, b.position, a, rot, pos
    else:
        return 0.0
    normals = solid.shapes[0][1] @ s_rot.T  # (K, 3) world frame
    offsets = support(solid, 0, s_rot, s_pos, normals)  # (K,)
    verts = np.asarray(mesh.mesh.vertices) @ m_rot.T + m_pos  # (V, 3)
    inside = (offsets[None] - verts @ normals.T).min(axis=1)  # (V,) > 0 inside
    return max(0.0, float(inside.max()))


def below_plane(body, rot: np.ndarray, pos: np.ndarray, plane_rot: np.ndarray,
                plane_pos: np.ndarray) -> np.ndarray:
    """How far (m) a solid at B poses reaches below a plane (the half-space z <= 0 of its frame).

    Returns:
        (B,) depths, 0 where the solid lies above.
    """
    normal = plane_rot[:, 2]
    return np.maximum(0.0, plane_pos @ normal - body.lowest(rot, pos, normal))
