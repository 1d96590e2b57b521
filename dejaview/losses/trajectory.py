"""Losses of a whole rollout against the observed states of one body.

``trajectory_loss`` scores the recorded states of the source body against the
scene's ``<target>`` (or several: a tracked source, their losses in quadrature)
with one of the per-record losses of ``LOSSES``. Which record each target is
compared with is ``dejaview.losses.targets``' (the scene-format spec's "how the
source was seen"):

- ``time`` given (argument, else ``target.time``): the record nearest that
  moment (the observation is pinned; ``evaluate`` is ignored);
- a target without time and velocities (seen at rest, the default): the last
  record, plus the rest term below, under both ``evaluate``s;
- a moving target (``moving=True`` or velocities given) without time:
  ``evaluate="final"`` the last record, ``evaluate="best"`` the minimum over all
  records (step 0 included). The hard minimum passes its gradient to the best
  record only (a subgradient); ``softmin_temperature=T`` uses
  ``-T logsumexp(-l / T)`` instead, which mixes the gradients of records within
  ~T of the best. It is smooth, lies at most ``T log(records)`` below the hard
  minimum and tends to it as T -> 0.

A target without ``orientation`` is compared by the ``position`` loss.

Frames: scene targets give the object frame's origin. The ``pose`` and ``add``
losses compare centres of mass, converting the target with the world
(``target COM = origin + R(target_q) com``): at zero error this is the same as
comparing origins, and away from it the position term does not depend on the
orientation. The ``position`` loss compares object origins, what was observed,
so an orientation that is not part of the loss does not leak into it.

Velocity terms (when the target has ``linear_velocity`` / ``angular_velocity``)
are added per record: ``velocity_weight * |v - v*|`` (COM velocity, m/s) and
``velocity_weight * orientation_weight * |w - w*|`` (world frame, rad/s).
``velocity_weight`` (seconds) is the horizon over which a velocity error turns
into a position error: the default 0.1 s makes 1 m/s cost 10 cm. Seen at rest
adds ``velocity_weight`` x (the mean speed + ``orientation_weight`` x the mean
spin) over the rest window's parts, averaged over the parts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from dejaview.errors import InferenceError
from dejaview.losses.add import add_error
from dejaview.losses.penalty import contact_penalty
from dejaview.losses.pose import (DEFAULT_ORIENTATION_WEIGHT, SMOOTH_EPS, position_error, pose_error,
                                  velocity_error)
from dejaview.scene.model import EVALUATES, InferenceSettings, Penalty, Target
from dejaview.sim.integrate import Trajectory
from dejaview.sim.rotation import normalize_quat, quat_rotate
from dejaview.sim.state import State

DEFAULT_VELOCITY_WEIGHT = 0.1
"""Seconds: metres of loss per m/s of velocity error (times ``orientation_weight`` per rad/s)."""


def _body_index(world, body: int | str) -> int:
    return world.body_index(body) if isinstance(body, str) else int(body)


def pose_record_loss(world, body: int, states: State, target_position: torch.Tensor,
                     target_orientation: torch.Tensor, *,
                     orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
                     points: torch.Tensor | None = None, eps: float = SMOOTH_EPS) -> torch.Tensor:
    """``pose``: COM position error and ``orientation_weight`` x geodesic angle in quadrature, per record.

    Args:
        world: the World.
        body: index of the movable body.
        states: State with leading dimensions (..., N, ...), e.g. (T, B, N, ...).
        target_position: (3,) target object-frame origin.
        target_orientation: (4,) target unit quaternion.
        orientation_weight: metres per radian.
        points: ignored (uniform signature of ``LOSSES``).
        eps: smoothing scale (see ``dejaview.losses.pose``).
    Returns:
        (...) losses in metres.
    """
    target_com = target_position + quat_rotate(target_orientation, world.com[body])
    return pose_error(states.position[..., body, :], states.orientation[..., body, :], target_com,
                      target_orientation, orientation_weight, eps)


def position_record_loss(world, body: int, states: State, target_position: torch.Tensor,
                         target_orientation: torch.Tensor, *,
                         orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
                         points: torch.Tensor | None = None, eps: float = SMOOTH_EPS) -> torch.Tensor:
    """``position``: distance between object-frame origins, per record (orientation ignored).

    Same arguments as ``pose_record_loss`` (``orientation_weight`` and
    ``points`` are ignored). Returns (...) losses in metres.
    """
    com = world.com[body].expand_as(states.position[..., body, :])
    origin = states.position[..., body, :] - quat_rotate(states.orientation[..., body, :], com)
    return position_error(origin, target_position, eps)


def add_record_loss(world, body: int, states: State, target_position: torch.Tensor,
                    target_orientation: torch.Tensor, *,
                    orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
                    points: torch.Tensor | None = None, eps: float = SMOOTH_EPS) -> torch.Tensor:
    """``add``: average distance of model points, per record.

    Same arguments as ``pose_record_loss``; ``points`` (M, 3) in the body's COM
    frame (``model_points`` / ``body_model_points``; default: the centres of
    its sphere packing, all of them);
    ``orientation_weight`` is ignored. Returns (...) losses in metres.
    """
    weights = None
    if points is None:  # the sphere centres, padding masked out by weight (no data-dependent shapes)
        points, weights = world.centers[body], world.mask[body]
    target_com = target_position + quat_rotate(target_orientation, world.com[body])
    return add_error(states.position[..., body, :], states.orientation[..., body, :], target_com,
                     target_orientation, points, eps, weights)


LOSSES = {
    "pose": pose_record_loss,
    "add": add_record_loss,
    "position": position_record_loss,
}
"""Per-record losses by scene name; each ``fn(world, body, states, target_position, target_orientation,
*, orientation_weight, points, eps) -> (...)``."""


def nearest_record(traj: Trajectory, time: float) -> int:
    """Index of the record nearest ``time`` (seconds).

    Raises:
        InferenceError: if ``time`` lies outside the recorded span by more than half a step.
    """
    steps = traj.steps.tolist()
    t = float(time) / traj.dt
    if not (steps[0] - 0.5 <= t <= steps[-1] + 0.5):
        raise InferenceError(f"target time {time} s is outside the trajectory "
                             f"[{steps[0] * traj.dt:g}, {steps[-1] * traj.dt:g}] s")
    return min(range(len(steps)), key=lambda k: abs(steps[k] - t))


def softmin(losses: torch.Tensor, temperature: float | None = None, dim: int = 0) -> torch.Tensor:
    """Hard (``temperature`` None or 0) or soft minimum ``-T logsumexp(-l / T)`` along ``dim``.

    Args:
        losses: (..., T, ...) values.
        temperature: T in the unit of the losses.
    Returns:
        the values with ``dim`` reduced.
    """
    if not temperature:
        return torch.amin(losses, dim=dim)
    if temperature < 0:
        raise ValueError(f"softmin temperature must be positive, got {temperature}")
    return -temperature * torch.logsumexp(-losses / temperature, dim=dim)


def _target_tensors(world, target: Target) -> tuple[torch.Tensor, torch.Tensor | None]:
    kw = dict(dtype=world.dtype, device=world.device)
    origin = torch.as_tensor(target.position, **kw)
    if target.orientation is None:
        return origin, None
    return origin, normalize_quat(torch.as_tensor(target.orientation, **kw))


def sighting_loss(world, traj: Trajectory, body: int, sighting, kind: str = "pose",
                  orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
                  points: torch.Tensor | None = None,
                  velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
                  softmin_temperature: float | None = None,
                  eps: float = SMOOTH_EPS) -> torch.Tensor:
    """How far a rollout's ``body`` comes from one observation (``dejaview.losses.targets.Sighting``).

    The per-record loss ``kind`` (``position`` where the target observed the position alone) at the
    sighting's record, or the (soft) minimum over all records where it takes the best; plus the
    target's velocity terms; plus, where lying still is observed, ``velocity_weight`` x the mean
    speed (and ``orientation_weight`` x the mean spin) over each part of the rest window, averaged.

    Returns:
        (B,) losses in metres.
    """
    from dejaview.losses.targets import record_index, rest_velocities

    target = sighting.target
    origin, q_target = _target_tensors(world, target)
    if q_target is None:
        kind, q_target = "position", torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=world.dtype, device=world.device)
    states = traj.states
    if sighting.step is not None:
        k = record_index(traj.steps, sighting.step)
        states = State(*(t[k:k + 1] for t in states.tensors()))
    per_record = LOSSES[kind](world, body, states, origin, q_target, orientation_weight=orientation_weight,
                              points=points, eps=eps)  # (T', B)
    kw = dict(dtype=world.dtype, device=world.device)
    if velocity_weight and target.linear_velocity is not None:
        v_target = torch.as_tensor(target.linear_velocity, **kw)
        per_record = per_record + velocity_weight * velocity_error(
            states.linear_velocity[..., body, :], v_target, eps)
    if velocity_weight and target.angular_velocity is not None:
        w_target = torch.as_tensor(target.angular_velocity, **kw)
        per_record = per_record + velocity_weight * orientation_weight * velocity_error(
            states.angular_velocity[..., body, :], w_target, eps)
    loss = per_record[0] if per_record.shape[0] == 1 else softmin(per_record, softmin_temperature, dim=0)
    if velocity_weight and sighting.at_rest:
        lin, ang = rest_velocities(traj, body, sighting)  # (B, parts, 3)
        zero = torch.zeros(3, **kw)
        rest = velocity_error(lin, zero, eps) + orientation_weight * velocity_error(ang, zero, eps)
        loss = loss + velocity_weight * rest.mean(-1)
    return loss


def trajectory_loss(world, traj: Trajectory, body: int | str, target, kind: str = "pose",
                    evaluate: str = "best", time: float | None = None,
                    orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT,
                    points: torch.Tensor | None = None,
                    velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
                    softmin_temperature: float | None = None,
                    eps: float = SMOOTH_EPS) -> torch.Tensor:
    """How far a rollout's ``body`` comes from the observed ``target`` (see the module docstring).

    Args:
        world: the World the trajectory was simulated in.
        traj: Trajectory with states (T, B, N, ...), starting at step 0 and ending at the scene's
            end (the duration's last step: where an untimed target seen at rest is compared).
        body: index or name of the movable source body.
        target: a ``dejaview.scene.model.Target`` (position = object-frame origin), or several
            (a tuple: their losses in quadrature).
        kind: ``"pose"`` | ``"add"`` | ``"position"`` (``LOSSES``).
        evaluate: ``"best"`` (minimum over records) | ``"final"``: for a target seen moving at a
            moment not known (``dejaview.losses.targets``).
        time: pin the comparison to the record nearest this time in seconds
            (default ``target.time``); must lie within the trajectory.
        orientation_weight: metres per radian (``pose`` and angular velocity).
        points: (M, 3) model points in the COM frame for ``add``.
        velocity_weight: seconds; weight of velocity terms when the target has
            velocities or is seen at rest (0 ignores them).
        softmin_temperature: None for the hard minimum of ``best``, else the
            soft-min temperature in metres of loss.
        eps: smoothing scale of every distance.
    Returns:
        (B,) losses in metres.
    """
    from dataclasses import replace

    from dejaview.losses.targets import resolve

    if kind not in LOSSES:
        raise InferenceError(f"unknown loss {kind!r}; choose one of {', '.join(LOSSES)}")
    if evaluate not in EVALUATES:
        raise InferenceError(f"unknown evaluate {evaluate!r}; choose one of {', '.join(EVALUATES)}")
    targets = tuple(target) if isinstance(target, (tuple, list)) else (target,)
    if time is not None:
        targets = tuple(replace(t, time=time) for t in targets)
    for t in targets:
        if t.time is not None:
            nearest_record(traj, t.time)  # a time outside the trajectory is an error
    end = int(traj.steps[-1])
    sightings = resolve(targets, evaluate, traj.dt, end)
    return sightings_loss(world, traj, _body_index(world, body), sightings, kind,
                          orientation_weight=orientation_weight, points=points,
                          velocity_weight=velocity_weight, softmin_temperature=softmin_temperature, eps=eps)


def sightings_loss(world, traj: Trajectory, body: int, sightings, kind: str = "pose", **options) -> torch.Tensor:
    """Every observation's ``sighting_loss`` (same options), in quadrature: (B,) metres."""
    losses = [sighting_loss(world, traj, body, s, kind, **options) for s in sightings]
    if len(losses) == 1:
        return losses[0]
    total = sum(v * v for v in losses)
    return torch.sqrt(total + torch.finfo(total.dtype).tiny)


@dataclass(frozen=True, eq=False)
class TrajectoryLoss:
    """The whole inference objective of a scene: target loss plus weighted contact penalties.

    ``loss(world, traj) = trajectory_loss(...) + sum_k weight_k * contact_penalty(world, traj, a_k, b_k)``.

    Attributes:
        body: name of the source body.
        target: the observed state, or several (a tuple of targets).
        kind, evaluate, orientation_weight, velocity_weight, softmin_temperature, eps:
            see ``trajectory_loss``.
        points: (M, 3) model points for ``add`` (None: sphere centres).
        penalties: ``<penalty>`` terms.
    """

    body: str
    target: object
    kind: str = "pose"
    evaluate: str = "best"
    orientation_weight: float = DEFAULT_ORIENTATION_WEIGHT
    velocity_weight: float = DEFAULT_VELOCITY_WEIGHT
    softmin_temperature: float | None = None
    eps: float = SMOOTH_EPS
    points: torch.Tensor | None = None
    penalties: tuple[Penalty, ...] = field(default=())

    def __post_init__(self):
        if self.kind not in LOSSES:
            raise InferenceError(f"unknown loss {self.kind!r}; choose one of {', '.join(LOSSES)}")
        if self.evaluate not in EVALUATES:
            raise InferenceError(f"unknown evaluate {self.evaluate!r}; choose one of {', '.join(EVALUATES)}")

    @classmethod
    def from_inference(cls, inference: InferenceSettings, points: torch.Tensor | None = None,
                       **options) -> "TrajectoryLoss":
        """The objective of an ``<inference>`` element; ``options`` override the other fields."""
        return cls(body=inference.source, target=tuple(inference.targets), kind=inference.loss,
                   evaluate=inference.evaluate, points=points, penalties=tuple(inference.penalties),
                   **options)

    def __call__(self, world, traj: Trajectory) -> torch.Tensor:
        """Total loss. traj: states (T, B, N, ...) -> (B,) losses."""
        total = trajectory_loss(world, traj, self.body, self.target, self.kind, self.evaluate,
                                orientation_weight=self.orientation_weight, points=self.points,
                                velocity_weight=self.velocity_weight,
                                softmin_temperature=self.softmin_temperature, eps=self.eps)
        for p in self.penalties:
            total = total + p.weight * contact_penalty(world, traj, p.between[0], p.between[1])
        return total
