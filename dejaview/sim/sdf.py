"""Signed distance functions of static geometry, in torch, with their gradients.

Every function takes query points in the shape's own frame and returns the
signed distance (negative inside) and its spatial gradient (the outward
normal of the nearest surface). Gradients are written out analytically rather
than taken with autograd, so the functions compose with ``torch.func`` and
``torch.compile``; their own derivatives (needed for contact-force gradients)
come from autograd through these expressions.

Shapes: plane (z = 0, normal +z), box (half extents), sphere, cylinder (axis z)
and a regular grid of samples with trilinear interpolation (meshes).
"""

from __future__ import annotations

import torch

from dejaview.sim.epsilons import GRID_OUTSIDE, NORMAL_EPS2


def _safe_normalize(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3) -> (unit vectors, norms (...)); zero vectors give a zero direction, no NaN."""
    sq = (v * v).sum(-1)
    norm = torch.sqrt(sq + NORMAL_EPS2)
    return v / norm.unsqueeze(-1), norm


def sdf_plane(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Half-space z <= 0. p: (..., 3) -> distance (...), normal (..., 3)."""
    n = torch.zeros_like(p)
    n = n + p.new_tensor([0.0, 0.0, 1.0])
    return p[..., 2], n


def sdf_sphere(p: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Sphere of ``radius`` at the origin. p: (..., 3) -> distance (...), normal (..., 3)."""
    n, norm = _safe_normalize(p)
    return norm - radius, n


def sdf_box(p: torch.Tensor, half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Axis-aligned box with half extents ``half`` (3,) at the origin.

    p: (..., 3) -> distance (...), normal (..., 3). Inside, the normal points
    through the nearest face; outside, towards the point from the nearest
    surface point.
    """
    sign = torch.where(p < 0, -1.0, 1.0).to(p.dtype)
    q = p.abs() - half
    outside = q.clamp(min=0.0)
    out_dir, out_len = _safe_normalize(outside)
    qmax, axis = q.max(dim=-1)
    inside_dist = qmax.clamp(max=0.0)
    is_out = qmax > 0
    face = torch.nn.functional.one_hot(axis, 3).to(p.dtype)
    normal = torch.where(is_out.unsqueeze(-1), out_dir, face) * sign
    dist = torch.where(is_out, out_len, inside_dist)
    return dist, normal


def sdf_cylinder(p: torch.Tensor, radius: float, half_height: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Solid cylinder along z, centred at the origin.

    p: (..., 3) -> distance (...), normal (..., 3).
    """
    radial, rlen = _safe_normalize(torch.cat([p[..., :2], torch.zeros_like(p[..., :1])], -1))
    dr = rlen - radius
    dz = p[..., 2].abs() - half_height
    zdir = torch.zeros_like(p)
    zdir = zdir + p.new_tensor([0.0, 0.0, 1.0])
    zdir = zdir * torch.where(p[..., 2:3] < 0, -1.0, 1.0).to(p.dtype)
    # outside both: corner region, distance to the rim circle
    corner = torch.stack([dr.clamp(min=0.0), dz.clamp(min=0.0)], -1)
    cdir, clen = _safe_normalize(torch.cat([corner, torch.zeros_like(corner[..., :1])], -1))
    corner_normal = radial * cdir[..., :1] + zdir * cdir[..., 1:2]
    in_dist = torch.maximum(dr, dz).clamp(max=0.0)
    in_normal = torch.where((dr > dz).unsqueeze(-1), radial, zdir)
    is_out = (dr > 0) | (dz > 0)
    dist = torch.where(is_out, clen, in_dist)
    normal = torch.where(is_out.unsqueeze(-1), corner_normal, in_normal)
    return dist, normal


_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.float64)


def sdf_grid(p: torch.Tensor, values: torch.Tensor, origin: torch.Tensor,
             spacing: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Trilinear interpolation of a sampled signed distance field, with its gradient.

    Points outside the grid are clamped to it and the distance to the grid
    box is added, so far-away points read as far away (never as inside).
    The eight cell corners are gathered in one indexing op and weighted by
    their trilinear weights (the per-op overhead dominates a rollout).

    Args:
        p: (..., 3) query points in the grid's frame.
        values: (nx, ny, nz) samples; node (i, j, k) sits at origin + spacing * (i, j, k).
        origin: (3,) position of node (0, 0, 0).
        spacing: node spacing in metres.
    Returns:
        distance (...), gradient (..., 3) (not normalised; close to unit length).
    """
    nx, ny, nz = values.shape
    size = torch.tensor([nx - 1, ny - 1, nz - 1], dtype=p.dtype, device=p.device)
    u = (p - origin) / spacing
    u_in = torch.minimum(torch.maximum(u, torch.zeros_like(u)), size)
    excess = (u - u_in) * spacing
    i0 = torch.minimum(u_in.detach().floor(), size - 1).clamp(min=0)
    f = (u_in - i0).unsqueeze(-2)  # (..., 1, 3)
    corners = _CORNERS.to(p)  # (8, 3)
    strides = torch.tensor([ny * nz, nz, 1], dtype=p.dtype, device=p.device)
    index = ((i0.unsqueeze(-2) + corners) * strides).sum(-1).long()  # (..., 8)
    c = values.reshape(-1)[index]  # (..., 8)
    # per-axis weights of each corner: f where the corner is 1, (1 - f) where 0
    axis_w = corners * f + (1.0 - corners) * (1.0 - f)  # (..., 8, 3)
    axis_dw = 2.0 * corners - 1.0  # d(axis weight)/df
    wx, wy, wz = axis_w.unbind(-1)
    d = (c * wx * wy * wz).sum(-1)
    gx = (c * axis_dw[:, 0] * wy * wz).sum(-1)
    gy = (c * wx * axis_dw[:, 1] * wz).sum(-1)
    gz = (c * wx * wy * axis_dw[:, 2]).sum(-1)
    grad = torch.stack([gx, gy, gz], -1) / spacing
    ex_dir, ex_len = _safe_normalize(excess)
    outside = (ex_len > GRID_OUTSIDE).unsqueeze(-1)
    grad = torch.where(outside, ex_dir, grad)
    return d + ex_len, grad
