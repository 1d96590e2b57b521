"""Free parameters of the source object's initial state.

The parameter vector ``x`` (shape ``(B, P)``) holds, in this order, the parts
that ``<optimize>`` frees:

- position (3): ``p = lo + (hi - lo) * sigmoid(u)`` per axis inside
  ``<start-area>`` (a reparameterisation, so every optimiser stays inside
  the box without projection); axes with ``lo == hi`` are fixed and take no
  parameter. Without a start area the position is free: ``p = p0 + s_p u``.
- orientation (3): a rotation vector applied on top of the given orientation,
  ``q = exp(r) * q0``, in radians.
- linear velocity (3), m/s, and angular velocity (3), rad/s, world frame.
- physics (F, last): with ``<physics-prior>``, a standard normal per inferred friction,
  restitution or stiffness (``dejaview.sim.physics``), in that order; not part of the start.

Each block is scaled (``scale``) so a unit step means a comparable change in
every block (defaults: 0.1 m, 0.5 rad, 1 m/s, 5 rad/s); plain gradient
descent and L-BFGS behave much better that way.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from dejaview.sim.physics import PhysicsModel
from dejaview.sim.rotation import quat_multiply, rotvec_to_quat

BLOCKS = ("position", "orientation", "linear_velocity", "angular_velocity")
DEFAULT_SCALE = {"position": 0.1, "orientation": 0.5, "linear_velocity": 1.0, "angular_velocity": 5.0}


@dataclass(frozen=True)
class ParameterLayout:
    """How the free vector maps to the source's initial state.

    Attributes:
        free: which blocks are free, in BLOCKS order.
        position_axes: (A,) indices of the free position axes (start area with width).
        lo, hi: (3,) start-area bounds (None without a start area), or (B, 3) per-candidate
            boxes (the heatmap gives each candidate its cell; ``decode`` then wants B rows).
        base_position: (3,) given object-frame position (fixed axes take it, clamped into the area).
        base_orientation: (4,) given orientation.
        base_linear, base_angular: (3,) given velocities (used when not free).
        scale: per-block scale.
        max_speed, max_spin: bounds for random restarts (m/s, rad/s).
        physics: the ``<physics-prior>``'s ``PhysicsModel`` (``dejaview.sim.physics``) or None: one
            standard-normal column per inferred parameter after the start's.
    """

    free: dict
    position_axes: tuple[int, ...]
    lo: torch.Tensor | None
    hi: torch.Tensor | None
    base_position: torch.Tensor
    base_orientation: torch.Tensor
    base_linear: torch.Tensor
    base_angular: torch.Tensor
    scale: dict
    max_speed: float = 3.0
    max_spin: float = 10.0
    physics: PhysicsModel | None = None

    @property
    def start_size(self) -> int:
        """The free parameters of the start (P less the physics')."""
        n = 0
        if self.free["position"]:
            n += len(self.position_axes)
        for block in BLOCKS[1:]:
            n += 3 if self.free[block] else 0
        return n

    @property
    def size(self) -> int:
        """P, the number of free parameters."""
        return self.start_size + len(self.physics_names)

    @property
    def physics_names(self) -> tuple[str, ...]:
        """The inferred physics parameters (``dejaview.sim.physics.NAMES``), in column order."""
        return () if self.physics is None else self.physics.names

    def physics_values(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3) friction, restitution and stiffness of parameters x (B, P)
        (``PhysicsModel.values``); None without inferred physics."""
        return None if self.physics is None else self.physics.values(self.physics_z(x))

    def physics_z(self, x: torch.Tensor) -> torch.Tensor:
        """(B, F) the physics columns of parameters x (B, P)."""
        return x[:, self.start_size:self.size]

    def names(self) -> list[str]:
        """Names of the P parameters, e.g. ``position.x``, ``orientation.rx``."""
        out = []
        if self.free["position"]:
            out += [f"position.{'xyz'[a]}" for a in self.position_axes]
        if self.free["orientation"]:
            out += ["orientation.rx", "orientation.ry", "orientation.rz"]
        if self.free["linear_velocity"]:
            out += ["linear_velocity.x", "linear_velocity.y", "linear_velocity.z"]
        if self.free["angular_velocity"]:
            out += ["angular_velocity.x", "angular_velocity.y", "angular_velocity.z"]
        return out + [f"physics.{n}" for n in self.physics_names]

    def block_slice(self, block: str) -> slice:
        """Columns of ``x`` that hold a free block (``BLOCKS`` or ``physics``; empty when it is not
        free)."""
        if block == "physics":
            return slice(self.start_size, self.size)
        start = 0
        for b in BLOCKS:
            width = (len(self.position_axes) if b == "position" else 3) if self.free[b] else 0
            if b == block:
                return slice(start, start + width)
            start += width
        raise KeyError(block)

    @functools.cached_property
    def _identity_base(self) -> bool:
        """Whether the given orientation is the identity (exp(r) * q0 is then exp(r))."""
        return bool(torch.equal(self.base_orientation.detach(),
                                self.base_orientation.new_tensor([1.0, 0.0, 0.0, 0.0])))

    # --------------------------------------------------------------- mapping
    def decode(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """Initial state of the source from parameters.

        Args:
            x: (B, P) parameters.
        Returns:
            dict with ``position`` (B, 3) object-frame origin, ``orientation`` (B, 4),
            ``linear_velocity`` (B, 3), ``angular_velocity`` (B, 3).
        """
        b = x.shape[0]
        i = 0
        pos = self.base_position.expand(b, 3)
        if self.free["position"] and self.position_axes:
            a = len(self.position_axes)
            u = x[:, i:i + a]
            i += a
            axes = list(self.position_axes)
            every = a == 3  # every axis free: no column indexing (a rollout's few microseconds)
            if self.lo is not None:
                lo, hi = (self.lo, self.hi) if every else (self.lo[..., axes], self.hi[..., axes])
                vals = lo + (hi - lo) * torch.sigmoid(u)
            else:
                vals = (self.base_position if every else self.base_position[axes]) + self.scale["position"] * u
            if every:
                pos = vals
            else:
                cols = [pos[:, k:k + 1] for k in range(3)]
                for j, axis in enumerate(axes):
                    cols[axis] = vals[:, j:j + 1]
                pos = torch.cat(cols, -1)
        if self.free["orientation"]:
            r = self.scale["orientation"] * x[:, i:i + 3]
            i += 3
            q = rotvec_to_quat(r)
            if not self._identity_base:
                q = quat_multiply(q, self.base_orientation.expand(b, 4))
        else:
            q = self.base_orientation.expand(b, 4)
        if self.free["linear_velocity"]:
            v = self.scale["linear_velocity"] * x[:, i:i + 3]
            i += 3
        else:
            v = self.base_linear.expand(b, 3)
        if self.free["angular_velocity"]:
            w = self.scale["angular_velocity"] * x[:, i:i + 3]
            i += 3
        else:
            w = self.base_angular.expand(b, 3)
        return {"position": pos, "orientation": q, "linear_velocity": v, "angular_velocity": w}

    def encode(self, position=None, linear_velocity=None, angular_velocity=None,
               orientation=None) -> torch.Tensor:
        """Parameters (1, P) of a given start (orientation (4,), w x y z: default the base one,
        rotation vector 0; else the rotation vector from the base one, angle at most pi).

        Positions are clamped just inside the start area.
        """
        dt = self.base_position.dtype
        parts = []
        if self.free["position"] and self.position_axes:
            p = torch.as_tensor(position if position is not None else self.base_position, dtype=dt)
            axes = list(self.position_axes)
            if self.lo is not None:
                width = self.hi[axes] - self.lo[axes]
                frac = ((p[axes] - self.lo[axes]) / width).clamp(1e-3, 1 - 1e-3)
                parts.append(torch.logit(frac))
            else:
                parts.append((p[axes] - self.base_position[axes]) / self.scale["position"])
        if self.free["orientation"]:
            if orientation is None:
                parts.append(torch.zeros(3, dtype=dt))
            else:
                from dejaview.sim.rotation import normalize_quat, quat_conjugate, quat_multiply, quat_to_rotvec

                q = normalize_quat(torch.as_tensor(orientation, dtype=dt))
                rel = quat_multiply(q, quat_conjugate(self.base_orientation.to(dt)))
                parts.append(quat_to_rotvec(rel) / self.scale["orientation"])
        if self.free["linear_velocity"]:
            v = torch.as_tensor(linear_velocity if linear_velocity is not None else self.base_linear, dtype=dt)
            parts.append(v / self.scale["linear_velocity"])
        if self.free["angular_velocity"]:
            w = torch.as_tensor(angular_velocity if angular_velocity is not None else self.base_angular, dtype=dt)
            parts.append(w / self.scale["angular_velocity"])
        parts.append(torch.zeros(len(self.physics_names), dtype=dt))  # the scene's physics
        return torch.cat(parts).unsqueeze(0)

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """Random starts (n, P): position uniform in the start area (or +-scale around the
        given one), a random rotation vector (angle up to pi), velocities uniform in a ball
        of radius ``max_speed`` / ``max_spin``."""
        dt = self.base_position.dtype
        parts = []

        def rand(*shape):
            return torch.rand(*shape, generator=generator, dtype=dt)

        def ball(radius):
            d = torch.randn(n, 3, generator=generator, dtype=dt)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            return d * radius * rand(n, 1) ** (1.0 / 3.0)

        if self.free["position"] and self.position_axes:
            a = len(self.position_axes)
            if self.lo is not None:
                parts.append(torch.logit(rand(n, a).clamp(1e-3, 1 - 1e-3)))
            else:
                parts.append(2.0 * rand(n, a) - 1.0)
        if self.free["orientation"]:
            parts.append(ball(torch.pi) / self.scale["orientation"])
        if self.free["linear_velocity"]:
            parts.append(ball(self.max_speed) / self.scale["linear_velocity"])
        if self.free["angular_velocity"]:
            parts.append(ball(self.max_spin) / self.scale["angular_velocity"])
        if self.physics_names:  # their prior
            parts.append(torch.randn(n, len(self.physics_names), generator=generator, dtype=dt))
        return torch.cat(parts, -1)


def layout_from_scene(scene, dtype=torch.float64, scale: dict | None = None,
                      max_speed: float = 3.0, max_spin: float = 10.0, physics: PhysicsModel | None = None
                      ) -> ParameterLayout:
    """The parameter layout of a scene's ``<inference>`` (source, optimize, start-area), with
    ``physics`` (a ``PhysicsModel``) inferred beside the start."""
    inf = scene.inference
    src = scene.object(inf.source)
    t = lambda v: torch.tensor(v, dtype=dtype)  # noqa: E731
    free = {b: bool(getattr(inf.optimize, b)) for b in BLOCKS}
    lo = hi = None
    axes = (0, 1, 2)
    base = t(src.pose.position)
    if inf.start_area is not None:
        lo, hi = t(inf.start_area.min), t(inf.start_area.max)
        axes = tuple(a for a in range(3) if hi[a] > lo[a])
        base = torch.minimum(torch.maximum(base, lo), hi)
    q0 = t(src.pose.orientation)
    q0 = q0 / q0.norm()
    return ParameterLayout(free=free, position_axes=axes, lo=lo, hi=hi, base_position=base,
                           base_orientation=q0, base_linear=t(src.velocity.linear),
                           base_angular=t(src.velocity.angular),
                           scale={**DEFAULT_SCALE, **(scale or {})}, max_speed=max_speed,
                           max_spin=max_spin, physics=physics)
