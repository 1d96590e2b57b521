"""A moving robot's links in the ``warp`` backend: kinematic bodies driven along their paths.

``warp.sim`` (1.9.1) has no static shape that moves, but a body of zero mass is kinematic: its
integration moves it at its own velocity (``integrate_rigid_body``, gravity masked), the contact
solvers move it by nothing (XPBD's ``apply_body_deltas`` passes it through) and the contacts see
its velocity (XPBD's relative displacement, the semi-implicit integrator's damping and friction).
Each link geometry of a moving robot (``dejaview.sim.motion``: the same forward kinematics as the
sphere simulator's, sampled at Warp's substep) becomes such a body, its one shape in collision
group -1 (it meets every environment's bodies; it is filtered against the static shapes and the
other links). Before every substep its pose and velocity are written into the state from its path
(outside the tape: the path is data), the velocity a forward difference over the substep, so that
Warp's own integration carries it onto the path's next pose.

Gradients: the tape's reverse pass sees the links' rows as inputs; a link's mass is zero, so no
body's gradient flows through a link's own update, and the bodies' gradients are those of the
bodies' states with the path held fixed, as in the sphere simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import warp as wp


@wp.kernel
def _set_rows(rows_q: wp.array(dtype=wp.transform), rows_qd: wp.array(dtype=wp.spatial_vector), first: int,
              offset: int, body_q: wp.array(dtype=wp.transform), body_qd: wp.array(dtype=wp.spatial_vector)):
    k = wp.tid()
    body_q[offset + k] = rows_q[first + k]
    body_qd[offset + k] = rows_qd[first + k]


@dataclass
class MovingLink:
    """One link geometry of a moving robot as a kinematic Warp body.

    Attributes:
        name: ``robot-id/link``; shape: ``(kind, params)`` as the static shapes'.
        q: (T, 7) its frame's poses at substeps j = 0..T-1, origin and x y z w quaternion.
        qd: (T, 6) angular and linear velocity over substep j (from row j to row j + 1; 0 in the
            last row, held after it).
    """

    name: str
    shape: tuple
    friction: float
    restitution: float
    q: np.ndarray
    qd: np.ndarray


def moving_links(scene, obj, h: float, friction: float, restitution: float, shape_of) -> list[MovingLink]:
    """The link geometries of a moving robot object, on their paths at Warp's substep ``h``.

    Args:
        shape_of: ``model._shape_of`` (a link part's shape as the static shapes have it).
    Raises:
        SceneError: a plane among the links (it has no pose a body can carry).
    """
    from scipy.spatial.transform import Rotation

    from dejaview.errors import SceneError
    from dejaview.scene import bounds
    from dejaview.scene.robot_links import link_objects
    from dejaview.sim.motion import RobotMotion

    paths = RobotMotion(scene, obj, bounds.max_steps()).paths(h)
    links = []
    for part in link_objects(scene, obj):
        shape = shape_of(scene, part.object, part.solid)
        if shape[0] == "plane":
            raise SceneError(f"robot {obj.id!r}: link {part.link!r} is a plane, which cannot move in the warp "
                             "backend", file=str(scene.path) if scene.path else None, line=obj.line,
                             element="object")
        path = paths[part.object.id]
        rot = Rotation.from_matrix(path.rotation.numpy())
        x = path.translation.numpy()
        qd = np.zeros((len(x), 6))
        if len(x) > 1:
            turn = (rot[1:] * rot[:-1].inv()).as_quat()  # x y z w, world frame, over one substep
            turn *= np.sign(turn[:, 3:4] + (turn[:, 3:4] == 0))
            # Warp turns a quaternion r by r + h/2 (w, 0) r, then normalises: w = 2 tan(angle/2) axis / h
            qd[:-1, :3] = 2.0 * turn[:, :3] / (turn[:, 3:4] * h)
            qd[:-1, 3:] = (x[1:] - x[:-1]) / h
        links.append(MovingLink(part.object.id, shape, friction, restitution,
                                np.concatenate([x, rot.as_quat()], 1), qd))
    return links


class LinkRows:
    """The links' rows of every substep on the device, written into a state before its substep."""

    def __init__(self, links: list[MovingLink], device):
        self.count = len(links)
        self.length = max(len(k.q) for k in links)
        held = lambda a: np.concatenate([a, np.repeat(a[-1:], self.length - len(a), 0)])  # noqa: E731
        q = np.stack([held(k.q) for k in links], 1).reshape(-1, 7)  # (T * L, 7), substep-major
        qd = np.stack([held(k.qd) for k in links], 1).reshape(-1, 6)
        self.q = wp.array(q.astype(np.float32), dtype=wp.transform, device=device)
        self.qd = wp.array(qd.astype(np.float32), dtype=wp.spatial_vector, device=device)

    def write(self, state, substep: int, offset: int) -> None:
        """Pose the links (bodies ``offset`` on) in ``state`` at substep number ``substep``."""
        first = min(substep, self.length - 1) * self.count
        wp.launch(_set_rows, dim=self.count, inputs=[self.q, self.qd, first, offset],
                  outputs=[state.body_q, state.body_qd], device=state.body_q.device, record_tape=False)
