r"""A box body's exact geometry against static planes and boxes: its corners, and a static box's
edges against its faces.

A box body's corners. Against a plane or a static box (``CORNER_KINDS``) a box
body's static contacts come from its 8 exact corners, spheres of radius
``BOX_CORNER_RADIUS`` (1 mm) centred that far inside each corner
(``box_corners``), in place of its sphere packing; the contact law is
unchanged (``dejaview.sim.contacts.static_contact_wrench``). Against a convex
box the deepest point of a flat surface is a corner, so the corners are the
box's whole contact geometry there; spheres, cylinders and grids keep the
packing (their curved surface can meet a face between the corners). The
packing stays for body pairs. Why: a packed face is a union of spheres whose
surfaces sink in turn as a tilted face lands, so a box dropped 5 deg off its
face hit the floor twice, 2.92 cm away from MuJoCo's box at 1.0 s; on its
corners 0.03 cm, and 29 % of random throws within 3 cm of MuJoCo against 21 %
(docs/physics-fidelity.md, "A box's corners"). The roll stick of a line
contact (``dejaview.sim.line_contact``), worked out on the packing's edge,
is off for box bodies: their corners do without it.

Static box edges. Where a box body (``BodySpec.box_half``) meets a static box (a table), points
along each of the static's 12 edges, ``EDGE_SPACING`` (5 mm) apart
(``static_edge_points``, made with the shape), meet the body's exact faces:
each point P inside the body's box is a contact of depth
delta = min_a (half_a - |l_a|) (l = R^T (P - x), the point in the body's frame;
a the nearest face), normal minus that face's normal, contact point P. They
join the body's static contact set in
``dejaview.sim.contacts.static_contact_wrench`` (the ``max_static_contacts``
deepest per static; the contact law is unchanged), and the body's corners
whose closest point on the static is on an edge or a corner are left out
(``on_static_edge``). A ball or a mesh packing keeps its spheres (their
surface is the body's).

Why: a packed face is a union of spheres up to 5 cm in radius, 2 cm apart, and
a sphere meeting a sharp edge is pushed along the line from the edge to its
centre, up to 11 deg off the face's normal, so a box sliding off a table
would roll over the edge on those curved sides and tip early, ahead of a
rigid flat box (docs/physics-fidelity.md, "Static box edges against a box's
faces", has the angles against the rigid reference ``bench/edge_tip.py`` and
MuJoCo, with and without the exact faces).

The native engine makes the same points and contacts (``native/box_edges.h``:
``edge_point``, ``select_edges``, ``edge_contact``) and their reverse mode
(``native/adjoint_static.h``).
"""

from __future__ import annotations

import torch

from dejaview.sim.rotation import small_matmul

BOX_CORNER_RADIUS = 1e-3
"""m: radius of the spheres at a box body's corners (``box_corners``); a box whose smallest half
extent is under 4 mm gets spheres of a quarter of that half extent."""

CORNER_KINDS = ("plane", "box")
"""Static shape kinds that a box body meets with its corners (``box_corners``) instead of its
packing: those whose surface is flat (a convex polytope's deepest point in them is a vertex)."""

EDGE_SPACING = 0.005
"""m: spacing of the points along a static box's edges that meet a box body's exact faces
(``static_edge_points``); a face lying across an edge touches it at a point every 5 mm."""


def static_edge_points(shape) -> torch.Tensor:
    """Points (E, 3) along the 12 edges of a static box (world frame), ``EDGE_SPACING`` apart
    (both ends included): per axis 0, 1, 2, the four edges along it at the other two axes' (-, -),
    (-, +), (+, -), (+, +) half extents, each from -half to +half. The native engine makes the same
    points (``native/box_edges.h``, ``edge_point``)."""
    half = [float(v) for v in shape.half]
    pts = []
    for axis in range(3):
        o1, o2 = [a for a in range(3) if a != axis]
        n = edge_point_count(half[axis])
        t = torch.arange(n, dtype=torch.float64) * (2.0 * half[axis] / (n - 1)) - half[axis]
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                p = torch.zeros(n, 3, dtype=torch.float64)
                p[:, axis] = t
                p[:, o1] = s1 * half[o1]
                p[:, o2] = s2 * half[o2]
                pts.append(p)
    local = torch.cat(pts).to(shape.rotation.dtype)
    return local @ shape.rotation.T + shape.translation


def box_corners(half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A box body's corner spheres: centres (N, 8, 3) in body axes and radii (N, 8).

    Corner j has sign +1 along axis i where bit i of j is set, -1 otherwise; its sphere, of radius
    r = min(BOX_CORNER_RADIUS, min(half) / 4), is centred at ``sign * (half - r)``, so its surface
    reaches the corner. The native engine makes the same spheres (``native/box_edges.h``, ``static_point``).

    Args:
        half: (N, 3) half extents (``World.box_half``; 0 for a body that is not a box: its corners
            are all at the centre, radius 0).
    """
    r = torch.clamp(0.25 * half.min(-1).values, max=BOX_CORNER_RADIUS)  # (N,)
    bits = torch.arange(8, device=half.device).unsqueeze(-1) >> torch.arange(3, device=half.device)
    sign = torch.where(bits & 1 == 1, 1.0, -1.0).to(half.dtype)  # (8, 3)
    return sign * (half - r.unsqueeze(-1)).unsqueeze(-2), r.unsqueeze(-1).expand(-1, 8)


def edge_point_count(half: float) -> int:
    """Points along one static box edge of half length ``half`` (m): at least its two ends."""
    return max(2, int(round(2.0 * half / EDGE_SPACING)) + 1)


def on_static_edge(shape, points: torch.Tensor) -> torch.Tensor:
    """(...) whether a static box's closest point to each world point (..., 3) is on one of its
    edges or corners (the point outside the box along two or three of its axes)."""
    local = small_matmul(points - shape.translation, shape.rotation)
    return ((local.abs() - shape.half) > 0).sum(-1) >= 2


def static_edge_contacts(world, state, shape, rot: torch.Tensor, is_box: torch.Tensor, cap: int):
    """A static box's edge points inside the box bodies: depth (B, N, C), normal (B, N, C, 3)
    (pointing out of the static into the body: minus the body's face normal) and arm (B, N, C, 3)
    of the ``cap`` deepest per body (zero depth for a body that is not a box)."""
    pts = shape.edge_points.to(state.position.dtype)  # (E, 3), made with the shape (static_edge_points)
    b, nb = state.position.shape[:2]
    rel = pts[None, None] - state.position.unsqueeze(-2)  # (B, N, E, 3)
    local = small_matmul(rel, rot)  # R^T (P - x)
    room = world.box_half[None, :, None, :] - local.abs()
    inner, axis = room.min(-1)  # (B, N, E): the depth inside the body's box, through face ``axis``
    inside = (inner > 0) & is_box[None, :, None]
    depth = torch.where(inside, inner, torch.zeros_like(inner))
    # the cap deepest (a selection, no gradient), in the points' order as the native engine's picks
    idx = torch.topk(depth.detach(), min(cap, depth.shape[-1]), dim=-1, sorted=False).indices.sort(-1).values
    depth, axis = depth.gather(-1, idx), axis.gather(-1, idx)
    local, rel = (t.gather(2, idx.unsqueeze(-1).expand(*idx.shape, 3)) for t in (local, rel))
    sign = torch.where(local.gather(-1, axis.unsqueeze(-1)) < 0, -1.0, 1.0).to(local.dtype)
    face = torch.nn.functional.one_hot(axis, 3).to(local.dtype) * sign  # the body's face, body axes
    normal = -small_matmul(face, rot.transpose(-1, -2))  # world: -R face
    return depth, normal, rel
