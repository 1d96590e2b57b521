"""Static shapes that move on a known path: the links of a moving robot.

A robot object with ``<joints time values>`` keyframes (scene-format spec, "Robots as users have
them") moves kinematically: its joint values follow the keyframes, linearly interpolated, held
before the first and after the last, and its links push the bodies while nothing pushes them back.
The simulator sees each link as a static shape with a ``ShapePath``: its pose and velocity at
every substep time ``j h`` (j = 0, 1, ...; the last row held after the path's end), computed here
once by forward kinematics. Substep j's contacts read row j (``World.posed``), and a contact's
relative velocity takes off the link's velocity at the contact point,
``v_link + w_link x (p - x_link)``, so that friction and the loading/unloading switch see the
slip and the approach between the two surfaces. The path is data, not a parameter: gradients
flow through the bodies' states only (exactly, in both engines).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np
import torch

VELOCITY_STEP = 1e-6
"""s: the half-width of the central difference (in time, along the segment's joint velocity) that
gives a link's velocity; round-off leaves it about 1e-10 off (m/s, rad/s), far below the contact
model's error."""


@dataclass(frozen=True)
class ShapePath:
    """A moving static shape's pose and velocity at substep times ``j h``, j = 0..T-1.

    Attributes:
        rotation: (T, 3, 3) world-from-shape rotations.
        translation: (T, 3) shape origins in the world (m).
        velocity: (T, 3) velocity of the shape's origin (m/s).
        angular_velocity: (T, 3) angular velocity (rad/s, world frame).
    """

    rotation: torch.Tensor
    translation: torch.Tensor
    velocity: torch.Tensor
    angular_velocity: torch.Tensor
    motion: "RobotMotion | None" = field(default=None, repr=False, compare=False)
    """What the path was sampled from (to sample it again at another substep), if known."""

    def __len__(self) -> int:
        return int(self.translation.shape[0])

    def row(self, j: int) -> int:
        """The row of substep number ``j``: j itself, the last one after the path's end."""
        return min(int(j), len(self) - 1)

    def rows(self) -> torch.Tensor:
        """(T, 18) rows as the native engine reads them (``schema.PATH_COLUMNS``)."""
        t = len(self)
        return torch.cat([self.rotation.reshape(t, 9), self.translation, self.velocity,
                          self.angular_velocity], 1)

    def to(self, device=None, dtype=None) -> "ShapePath":
        return replace(self, **{f.name: getattr(self, f.name).to(device=device, dtype=dtype)
                                for f in fields(self) if f.name != "motion"})


class RobotMotion:
    """A moving robot's keyframed motion, as its links' paths are sampled from it: ``paths(h)`` samples
    them at another substep ``h`` (``World.with_substeps``). A plain class with a repr naming the
    robot and its keyframes (what ``amortised.model.fingerprint`` hashes of it).

    Args:
        scene: the Scene; obj: the robot's SceneObject (with keyframes).
        limit: the step budget in substeps (no path runs past it).
    """

    def __init__(self, scene, obj, limit: int):
        self.scene, self.obj, self.limit = scene, obj, int(limit)

    def paths(self, h: float) -> dict[str, "ShapePath"]:
        """Each link geometry's path at substep times ``j h`` (``robot_paths``)."""
        times = np.arange(path_length(self.obj.keyframes, h, self.limit)) * h
        return robot_paths(self.scene, self.obj, times, motion=self)

    def __repr__(self) -> str:
        return f"RobotMotion({self.obj.id!r}, {self.obj.keyframes!r}, limit={self.limit})"


def resampled(statics, h: float) -> tuple:
    """``statics`` with each moving one's path sampled again at substep ``h`` (from its
    ``ShapePath.motion``, one forward kinematics per robot), posed at substep 0.

    Raises:
        SimulationError: a moving static whose path knows no motion (built by hand).
    """
    from dejaview.errors import SimulationError

    sampled = {}
    for s in statics:
        if s.path is not None:
            if s.path.motion is None:
                raise SimulationError(f"static {s.name!r} moves on a path given as data, sampled at the world's "
                                      "substep; build the world again at the other substep")
            sampled.setdefault(id(s.path.motion), s.path.motion.paths(h))
    return tuple(s if s.path is None else
                 replace(s, path=sampled[id(s.path.motion)][s.name].to(s.translation.device,
                                                                       s.translation.dtype)).at(0)
                 for s in statics)


def static_point_velocity(shapes, position: torch.Tensor, arm: torch.Tensor) -> torch.Tensor:
    """Velocity (B, N, K, C, 3) of each contact point ``x + arm`` moving with its static shape, the
    K groups' ``shapes`` (posed: ``StaticShape.at``; a shape that stands moves with 0).

    Args:
        position: (B, N, 3) centres of mass; arm: (B, N, K, C, 3) contact points' lever arms.
    """
    zero = torch.zeros(3, dtype=arm.dtype, device=arm.device)
    lin = torch.stack([zero if s.velocity is None else s.velocity for s in shapes])[:, None, :]  # (K, 1, 3)
    ang = torch.stack([zero if s.angular_velocity is None else s.angular_velocity for s in shapes])[:, None, :]
    origin = torch.stack([s.translation for s in shapes])[:, None, :]
    point = position[:, :, None, None, :] + arm
    return lin + torch.linalg.cross(ang.expand_as(point), point - origin, dim=-1)


def joint_path(keyframes, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint values and velocities of a keyframed robot at ``times``.

    Args:
        keyframes: ``dejaview.scene.JointKeyframe`` s, times increasing.
        times: (T,) s.
    Returns:
        q (T, J): linearly interpolated, held before the first keyframe and after the last;
        qdot (T, J): the segment's slope (the segment starting at t, where t is a keyframe's
        time), 0 where held.
    """
    t_key = np.array([k.time for k in keyframes], dtype=np.float64)
    q_key = np.array([k.values for k in keyframes], dtype=np.float64).reshape(len(keyframes), -1)
    times = np.asarray(times, dtype=np.float64)
    q = np.stack([np.interp(times, t_key, q_key[:, i]) for i in range(q_key.shape[1])], 1) \
        if q_key.shape[1] else np.zeros((len(times), 0))
    qdot = np.zeros_like(q)
    if len(t_key) > 1:
        seg = np.searchsorted(t_key, times, side="right") - 1  # keyframe i with t_i <= t < t_i+1
        inside = (seg >= 0) & (seg < len(t_key) - 1)
        s = seg[inside]
        qdot[inside] = (q_key[s + 1] - q_key[s]) / (t_key[s + 1] - t_key[s])[:, None]
    return q, qdot


def path_length(keyframes, h: float, limit: int) -> int:
    """Rows of a path covering the keyframes at substep ``h``: up to the last keyframe's time (held
    after), at most ``limit`` (the step budget: no rollout reaches further)."""
    last = keyframes[-1].time if keyframes else 0.0
    return max(1, min(int(limit) + 1, int(math.ceil(last / h - 1e-9)) + 1))


def _rotation_vector(r: np.ndarray) -> np.ndarray:
    """(T, 3) rotation vectors of rotation matrices (T, 3, 3) (small angles: what a velocity's
    central difference makes)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_rotvec()


def pose_velocity(poses_minus: np.ndarray, poses_plus: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear (T, 3) and angular (T, 3) velocity of frames from their (T, 4, 4) poses ``dt`` before
    and after (central differences)."""
    v = (poses_plus[:, :3, 3] - poses_minus[:, :3, 3]) / (2.0 * dt)
    rel = poses_plus[:, :3, :3] @ np.swapaxes(poses_minus[:, :3, :3], 1, 2)  # world-frame turn
    return v, _rotation_vector(rel) / (2.0 * dt)


def robot_paths(scene, obj, times: np.ndarray, model=None, motion: RobotMotion | None = None
                ) -> dict[str, ShapePath]:
    """The path of every collision geometry of a moving robot object, by its piece name
    (``dejaview.geometry.robot.robot_pieces``' ``robot-id/link``), at ``times`` (T,) s (the
    simulator's: substep times ``j h``): one batched forward kinematics at the joint values then,
    and two more ``VELOCITY_STEP`` before and after along the joints' velocities for the
    velocities. ``motion``: what the paths carry as their source (``ShapePath.motion``)."""
    from dejaview.geometry.robot import piece_transforms, robot_model

    model = model or robot_model(scene, obj)
    q, qdot = joint_path(obj.keyframes, np.asarray(times, dtype=np.float64))
    at = piece_transforms(obj, model, q)
    minus = piece_transforms(obj, model, q - VELOCITY_STEP * qdot)
    plus = piece_transforms(obj, model, q + VELOCITY_STEP * qdot)
    paths = {}
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    for name, pose in at.items():  # (T, 4, 4)
        v, w = pose_velocity(minus[name], plus[name], VELOCITY_STEP)
        paths[name] = ShapePath(rotation=t(pose[:, :3, :3]), translation=t(pose[:, :3, 3]), velocity=t(v),
                                angular_velocity=t(w), motion=motion)
    return paths


def sample_times(last: float, interval: float) -> np.ndarray:
    """Times (s) every ``interval`` from 0 to ``last``, ``last`` included (what the viewer and the MJCF
    export sample a moving robot at)."""
    count = int(math.ceil(last / interval - 1e-9))
    return np.minimum(np.arange(count + 1) * interval, last)


def link_poses(scene, obj, times: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each link geometry's world position (T, 3) and orientation (T, 4, w x y z) at ``times``, by
    piece name (``robot-id/link``), for a moving robot object (``robot_paths``)."""
    from dejaview.geometry.transforms import matrix_to_quat

    return {name: (path.translation.numpy(), np.array([matrix_to_quat(r) for r in path.rotation.numpy()]))
            for name, path in robot_paths(scene, obj, times).items()}
