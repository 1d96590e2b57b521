"""What each ``<target>`` of a scene observes, resolved once for every loss and likelihood.

Scene-format spec, "how the source was seen": a scene holds one ``<target>`` or several with
times (a tracked source). Each becomes a ``Sighting``: the record of a rollout it is compared with
and whether it says the source lay still.

- A target with a ``time`` observes the pose at that moment (the record nearest it); with
  ``moving="false"`` it adds that the source lay still then.
- A target without ``time`` and without velocities observes the source **at rest** (the default):
  an explanation brings the source to rest at the pose and leaves it there, so it is compared with
  the last record, under ``evaluate`` ``best`` and ``final`` alike, and its rest is observed.
- ``moving="true"`` (or velocities given) without ``time``: ``evaluate`` decides, ``best`` the
  record that fits best (version 1's meaning, a moment not known), ``final`` the last one.

**At rest, observed.** Lying still is observed as the source's mean velocities over the last
``REST_WINDOW`` seconds before the compared moment, in ``REST_PARTS`` parts: the centre of mass's
displacement over each part (m/s) and the rotation over it (its rotation vector, rad/s), zero with
standard deviations ``rest_speed`` and ``rest_spin`` (``<observation rest-speed rest-spin>``).
Means, not the last instant's velocity: a mug on its side rocks at 0.3 rad/s for a second after it
has settled (millimetres), which nobody would call moving, while a flyby, a bounce's apex or a
box balanced on an edge for an instant moves centimetres within the window (an apex at the end:
``g W / (2 parts)``, 0.5 m/s over the last 0.1 s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import reduce

import torch

from dejaview.sim.rotation import normalize_quat, quat_conjugate, quat_multiply, quat_to_rotvec

REST_WINDOW = 0.2
"""Seconds before the compared moment over which "at rest" is observed."""
REST_PARTS = 2
"""Parts of ``REST_WINDOW`` whose mean velocities are each observed (over the last 0.1 s and the
0.1 s before)."""


@dataclass(frozen=True)
class Sighting:
    """One ``<target>`` resolved against a rollout's steps (module docstring).

    Attributes:
        target: the scene's ``Target``.
        step: the step of the record it is compared with; None: the best-fitting record
            (a moving target without a time under ``evaluate="best"``).
        at_rest: whether lying still is observed (``rest_steps`` then holds the window).
        rest_steps: steps bounding the rest window's parts, first to last (the last is ``step``).
    """

    target: object
    step: int | None
    at_rest: bool = False
    rest_steps: tuple[int, ...] = ()

    @property
    def orientation_observed(self) -> bool:
        return self.target.orientation is not None

    @property
    def time(self) -> float | None:
        return self.target.time


def rest_window_steps(step: int, dt: float) -> tuple[int, ...]:
    """Steps bounding the ``REST_PARTS`` parts of the rest window that ends at ``step`` (clipped at
    step 0; a part of no length is observed by the velocity at its end)."""
    out = []
    for i in range(REST_PARTS + 1):
        back = int(round(REST_WINDOW * (REST_PARTS - i) / REST_PARTS / dt))
        out.append(max(0, step - back))
    return tuple(out)


def resolve(targets, evaluate: str, dt: float, duration_steps: int) -> tuple[Sighting, ...]:
    """The sightings of a scene's targets.

    Args:
        targets: the ``<inference>``'s targets (``InferenceSettings.targets``).
        evaluate: ``best`` | ``final``.
        dt: the step (s).
        duration_steps: steps of the scene's duration.
    Returns:
        one ``Sighting`` per target, in file order.
    """
    out = []
    for t in targets:
        if t.time is not None:
            step = min(max(int(round(float(t.time) / dt)), 0), duration_steps)
        elif t.at_rest or evaluate == "final":
            step = duration_steps
        else:
            step = None
        rest = bool(t.at_rest) and step is not None
        out.append(Sighting(target=t, step=step, at_rest=rest,
                            rest_steps=rest_window_steps(step, dt) if rest else ()))
    return tuple(out)


def rollout_steps(sightings, duration_steps: int) -> int:
    """Steps a rollout needs to show every sighting: up to the latest one where each has a time,
    else the scene's duration."""
    if all(s.time is not None for s in sightings):
        return max(1, max(s.step for s in sightings))
    return duration_steps


def record_interval(sightings, steps: int, penalties: bool = False) -> int:
    """Record interval of a loss's rollouts of ``steps`` steps: the largest that records every step a
    sighting reads (the initial and final states are always recorded), 1 where a sighting takes the
    best of all records or a ``<penalty>`` reads every record."""
    if penalties or any(s.step is None for s in sightings):
        return 1
    needed = {s.step for s in sightings} | {k for s in sightings for k in s.rest_steps}
    needed = {k for k in needed if 0 < k < steps}
    return max(1, reduce(math.gcd, needed, max(steps, 1)))


def record_index(steps: torch.Tensor, step: int) -> int:
    """Index of the record (of a trajectory's ``steps`` (T,)) nearest ``step``."""
    return int(torch.argmin((steps.to(torch.float64) - float(step)).abs()))


def rest_velocities(traj, body: int, sighting: Sighting) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean velocities over the parts of a sighting's rest window.

    Args:
        traj: Trajectory (T, B, N, ...) recording the window's steps (``record_interval``).
        body: the source's index.
        sighting: a sighting with ``at_rest``.
    Returns:
        linear (B, REST_PARTS, 3) m/s of the centre of mass and angular (B, REST_PARTS, 3) rad/s
        (world frame); a part of no length gives the velocities at its end.
    """
    st = traj.states
    idx = [record_index(traj.steps, k) for k in sighting.rest_steps]
    lin, ang = [], []
    for a, b in zip(idx[:-1], idx[1:]):
        span = float(traj.steps[b] - traj.steps[a]) * traj.dt
        if span <= 0:
            lin.append(st.linear_velocity[b, :, body])
            ang.append(st.angular_velocity[b, :, body])
            continue
        lin.append((st.position[b, :, body] - st.position[a, :, body]) / span)
        qa, qb = normalize_quat(st.orientation[a, :, body]), normalize_quat(st.orientation[b, :, body])
        ang.append(quat_to_rotvec(quat_multiply(qb, quat_conjugate(qa))) / span)
    return torch.stack(lin, 1), torch.stack(ang, 1)


def rest_time(traj, body: int, rest_speed: float, rest_spin: float, index: int = 0) -> float | None:
    """When the source came to rest in a trajectory recorded at every step: its mean velocities
    over every ``REST_WINDOW / REST_PARTS`` after that stay within ``rest_speed`` and ``rest_spin``;
    within the last part that moved, the moment after its last instant faster than those. None
    where it is still moving at the end (or the trajectory is shorter than one part).

    Args:
        traj: Trajectory (T, B, N, ...), ``steps`` evenly spaced.
        body: the source's index; index: the candidate (batch entry).
    Returns:
        seconds from the start, or None.
    """
    steps = traj.steps
    if steps.numel() < 2:
        return None
    every = int(steps[1] - steps[0])
    lag = max(1, int(round(REST_WINDOW / REST_PARTS / (traj.dt * every))))
    if steps.numel() <= lag:
        return None
    st = traj.states
    pos, q = st.position[:, index, body], normalize_quat(st.orientation[:, index, body])
    span = lag * every * traj.dt
    v = (pos[lag:] - pos[:-lag]).norm(dim=-1) / span
    w = quat_to_rotvec(quat_multiply(q[lag:], quat_conjugate(q[:-lag]))).norm(dim=-1) / span
    moving = ((v > rest_speed) | (w > rest_spin)).nonzero().flatten()
    if moving.numel() == 0:
        return float(steps[0]) * traj.dt
    last = int(moving[-1])  # the part from record last to last + lag moved, none after it
    end = last + lag
    if end >= steps.numel() - 1:
        return None
    # within that part, the source rests from the record after its last fast instant
    fast = ((st.linear_velocity[last:end + 1, index, body].norm(dim=-1) > rest_speed)
            | (st.angular_velocity[last:end + 1, index, body].norm(dim=-1) > rest_spin)).nonzero().flatten()
    k = last + int(fast[-1]) + 1 if fast.numel() else last
    return float(steps[min(k, end)]) * traj.dt
