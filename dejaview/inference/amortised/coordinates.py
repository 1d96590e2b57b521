"""The flow's coordinates: the free parameters mapped one to one onto R^P.

A normalising flow is a density on all of R^P; the posterior's parameters x
(``ParameterLayout``) are not all unbounded:

- a start position inside a start area is already unbounded (the layout's logit coordinates);
- an orientation under a flat prior is a rotation vector of angle at most pi, a ball: it maps
  radially onto R^3 by ``u = r / |r| * atanh(|r| / R)`` (R the ball's radius in the layout's
  scale). Every rotation is reached once; the antipodal rotations on the ball's surface lie at
  infinity, where the Haar density in these coordinates falls like ``exp(-2 |u|)``;
- a velocity under a flat prior lies in the ball of its bound: the same radial map;
- a velocity or orientation under a normal prior, and the physics' standard normals, stay.

``to_flow`` and ``from_flow`` are each other's inverse; ``log_jacobian`` is ``log |dx/du|``, so a
density over u becomes one over x by ``log q(x) = log q(u) - log |dx/du|``.
"""

from __future__ import annotations

import math

import torch

from dejaview.errors import InferenceError


def balls(post) -> list[tuple[slice, float]]:
    """The blocks of ``post``'s layout that are balls (flat priors), as (columns, radius in the
    layout's scaled units)."""
    lay, s = post.layout, post.settings
    out = []
    cols = lay.block_slice("orientation")
    if cols.stop > cols.start and s.tilt is None:
        out.append((cols, math.pi / lay.scale["orientation"]))
    for block, sd, bound in (("linear_velocity", s.speed, s.speed_bound),
                             ("angular_velocity", s.spin, s.spin_bound)):
        cols = lay.block_slice(block)
        if cols.stop > cols.start and sd is None:
            out.append((cols, bound / lay.scale[block]))
    return out


def check_proper(post) -> None:
    """An amortised posterior is trained on draws from the prior: refuse an improper one."""
    lay = post.layout
    if lay.block_slice("position").stop > 0 and lay.lo is None:
        raise InferenceError("an amortised posterior is trained on draws from the prior, and a free position "
                             "without <start-area> has no proper prior: give the scene a <start-area>")


def to_flow(post, x: torch.Tensor) -> torch.Tensor:
    """Flow coordinates u (B, P) of parameters x (B, P) (inside the balls)."""
    u = x.clone()
    for cols, radius in balls(post):
        r = x[:, cols]
        rho = r.norm(dim=-1, keepdim=True)
        f = (rho / radius).clamp(max=1 - 1e-12)
        scale = torch.where(rho > 1e-12, torch.atanh(f) / rho.clamp_min(1e-300), torch.full_like(rho, 1 / radius))
        u[:, cols] = r * scale
    return u


def from_flow(post, u: torch.Tensor) -> torch.Tensor:
    """Parameters x (B, P) at flow coordinates u (B, P)."""
    x = u.clone()
    for cols, radius in balls(post):
        v = u[:, cols]
        s = v.norm(dim=-1, keepdim=True)
        scale = torch.where(s > 1e-12, radius * torch.tanh(s) / s.clamp_min(1e-300), torch.full_like(s, radius))
        x[:, cols] = v * scale
    return x


def log_jacobian(post, u: torch.Tensor) -> torch.Tensor:
    """``log |dx/du|`` (B,) at flow coordinates u (B, P): per ball, the radial map's
    ``log(R (1 - tanh^2 s)) + 2 log(R tanh(s) / s)`` at s = |u|."""
    out = torch.zeros(u.shape[0], dtype=u.dtype)
    for cols, radius in balls(post):
        s = u[:, cols].norm(dim=-1)
        t = torch.tanh(s)
        ratio = torch.where(s > 1e-6, t / s.clamp_min(1e-300), 1 - s * s / 3)
        # 1 - tanh^2 s = 4 / (e^s + e^-s)^2, written so it does not underflow to log 0 at large s
        log_sech2 = math.log(4.0) - 2 * (s + torch.log1p(torch.exp(-2 * s)))
        out = out + math.log(radius) + log_sech2 + 2 * (math.log(radius) + torch.log(ratio))
    return out


__all__ = ["balls", "check_proper", "from_flow", "log_jacobian", "to_flow"]
