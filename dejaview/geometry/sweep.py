"""Where a moving robot's links pass through objects that stand (``dejaview validate``'s warnings).

A moving robot's links (``<joints time values>``, ``dejaview.sim.motion``) push the movable objects
and nothing pushes them back; the simulator has no contact between two pieces of static geometry,
so a link that the keyframes carry into a table passes through it as if it were not there. That is
almost always a keyframe mistake (a logged trajectory replayed beside furniture placed by hand),
and nothing in a rollout shows it: ``validate`` warns, one line per robot and object it passes
through, and the scene stays valid (the physics is well defined).

What is not warned about:

- Movable objects in a link's way, the source and its start area included: pushing them is what a
  moving robot is for (the bundled sweep knocks its mug off the table). Where the robot stands at
  time 0 is checked as for a robot that stands (``SceneCollision.interpenetrations``, an error),
  and so are the solve's starts (its feasibility check, ``dejaview.inference.start_area``).
- Overlaps a link already has at time 0 (a robot's base standing in the floor: two fixed objects
  may overlap): only a depth beyond the one at time 0 by more than the margin counts.
- The robot's own links (neighbours overlap at their joints) and other moving robots' links.

The links are posed every ``SAMPLE_INTERVAL`` from time 0 to the last keyframe and at each keyframe
(forward kinematics of the interpolated joints, as the simulator's paths), on the exact geometry
(python-fcl, ``SceneCollision``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SAMPLE_INTERVAL = 0.005
"""s between the poses checked: a link at 2 m/s moves 1 cm between two."""


@dataclass(frozen=True)
class SweptOverlap:
    """A moving robot passing through an object that stands.

    Attributes:
        robot: the robot object's id; other: the object (or a standing robot's link) passed through.
        link: the piece (``robot-id/link``) that goes deepest; depth: how deep (m) at ``time`` (s).
    """

    robot: str
    other: str
    link: str
    depth: float
    time: float


def swept_overlaps(scene, collision, margin: float) -> list[SweptOverlap]:
    """Objects that stand which a moving robot's links pass through (module docstring).

    Args:
        scene: the Scene; collision: its ``SceneCollision``.
        margin: depth (m) beyond the one at time 0 that counts.
    Returns:
        one ``SweptOverlap`` per moving robot and object it passes through, in file order.
    """
    from dejaview.geometry.robot import piece_transforms, robot_model

    moving = [o for o in scene.objects if o.moving]
    if not moving:
        return []
    links_of_moving = {o.id for o in moving}
    standing = [name for name in collision.ids
                if collision.is_fixed(name) and name.split("/", 1)[0] not in links_of_moving]
    found = []
    for obj in moving:
        times = np.union1d(np.arange(0.0, obj.keyframes[-1].time, SAMPLE_INTERVAL), [k.time for k in obj.keyframes])
        poses = piece_transforms(obj, robot_model(scene, obj), np.array([obj.joints_at(t) for t in times]))
        poses = {name: p for name, p in poses.items() if name in collision.ids}
        for other in standing:
            worst = None
            for name, pose in poses.items():
                depth = collision.depths(name, pose[:, :3, :3], pose[:, :3, 3], other)
                i = int(np.argmax(depth))
                if depth[i] > depth[0] + margin and (worst is None or depth[i] > worst.depth):
                    worst = SweptOverlap(obj.id, other, name, float(depth[i]), float(times[i]))
            if worst is not None:
                found.append(worst)
    return found
