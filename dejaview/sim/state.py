"""The changing part of a simulation: an immutable, batched rigid-body state, and the recorded
states of a rollout (``Trajectory``, what both engines return)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
import torch.utils._pytree as pytree

STATE_LAYOUT = (
    ("position", 3, "centre of mass, world frame, m"),
    ("orientation", 4, "unit quaternion w x y z, body axes into the world"),
    ("linear_velocity", 3, "centre-of-mass velocity, world frame, m/s"),
    ("angular_velocity", 3, "angular velocity, world frame, rad/s"),
)
"""One body's state as a row of numbers: (field, width, meaning), in ``State``'s field order. Both
engines' flat states (the native engine's ``(B, N, STATE_WIDTH)`` arrays, ``schema.h``'s
``STATE_*`` offsets) are this row."""

STATE_WIDTH = sum(width for _, width, _ in STATE_LAYOUT)
"""Numbers per body in a flat state."""


def state_offsets() -> dict[str, tuple[int, int]]:
    """Field name -> (first index, width) in a body's flat state row."""
    out, at = {}, 0
    for name, width, _ in STATE_LAYOUT:
        out[name] = (at, width)
        at += width
    return out


@dataclass(frozen=True)
class State:
    """Batched state of all movable bodies.

    ``position`` is the centre of mass (not the object frame's origin; see
    ``World.object_pose`` for the conversion), ``orientation`` rotates the
    body frame (the object's axes) into the world, velocities are world-frame.

    Attributes:
        position: (B, N, 3) centre-of-mass positions, metres.
        orientation: (B, N, 4) unit quaternions, w x y z.
        linear_velocity: (B, N, 3) centre-of-mass velocities, m/s.
        angular_velocity: (B, N, 3) angular velocities, world frame, rad/s.
    """

    position: torch.Tensor
    orientation: torch.Tensor
    linear_velocity: torch.Tensor
    angular_velocity: torch.Tensor

    def replace(self, **changes) -> "State":
        """A copy with some fields replaced."""
        return replace(self, **changes)

    @property
    def batch_size(self) -> int:
        return self.position.shape[0]

    @property
    def num_bodies(self) -> int:
        return self.position.shape[1]

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """The four fields in order (position, orientation, linear, angular)."""
        return tuple(getattr(self, f.name) for f in fields(self))

    def flat(self) -> torch.Tensor:
        """(..., N, STATE_WIDTH) the fields side by side, in ``STATE_LAYOUT`` order."""
        return torch.cat(self.tensors(), -1)

    @staticmethod
    def from_flat(x: torch.Tensor) -> "State":
        """The State of (..., N, STATE_WIDTH) flat rows (``STATE_LAYOUT``); views of ``x``."""
        return State(*(x[..., first:first + width] for first, width in state_offsets().values()))

    def to(self, device=None, dtype=None) -> "State":
        return State(*(t.to(device=device, dtype=dtype) for t in self.tensors()))

    def detach(self) -> "State":
        return State(*(t.detach() for t in self.tensors()))

    def index(self, idx) -> "State":
        """Select along the batch dimension (``idx`` an int, slice or index tensor)."""
        if isinstance(idx, int):
            idx = slice(idx, idx + 1)
        return State(*(t[idx] for t in self.tensors()))

    @staticmethod
    def stack(states: list["State"], dim: int = 0) -> "State":
        """Stack states along a new leading dimension (e.g. time): (T, B, N, ...)."""
        return State(*(torch.stack(ts, dim=dim) for ts in zip(*(s.tensors() for s in states))))

    @staticmethod
    def cat(states: list["State"]) -> "State":
        """Concatenate along the batch dimension."""
        return State(*(torch.cat(ts, dim=0) for ts in zip(*(s.tensors() for s in states))))

    def is_finite(self) -> torch.Tensor:
        """(B,) bool: every number of the batch element is finite."""
        return torch.stack([t.isfinite().flatten(1).all(1) for t in self.tensors()]).all(0)


pytree.register_pytree_node(
    State,
    lambda s: (list(s.tensors()), None),
    lambda children, _: State(*children),
    serialized_type_name="dejaview.sim.state.State",
)


@dataclass(frozen=True)
class Trajectory:
    """Recorded states of a rollout.

    Attributes:
        states: State whose tensors have a leading time dimension, (T, B, N, ...).
        steps: (T,) step index of each record (0 is the initial state).
        dt: step length, so the time of record t is ``steps[t] * dt``.
    """

    states: State
    steps: torch.Tensor
    dt: float

    @property
    def times(self) -> torch.Tensor:
        """(T,) times in seconds."""
        return self.steps.to(self.states.position.dtype) * self.dt

    @property
    def final(self) -> State:
        """The last recorded State (B, N, ...)."""
        return State(*(t[-1] for t in self.states.tensors()))

    def select(self, idx) -> "Trajectory":
        """The records of the candidates ``idx`` (an index or mask of the batch dimension)."""
        return Trajectory(State(*(t[:, idx] for t in self.states.tensors())), self.steps, self.dt)

    def __len__(self) -> int:
        return self.steps.shape[0]
