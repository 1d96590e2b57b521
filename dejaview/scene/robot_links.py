"""A fixed robot's posed collision geometry as fixed scene objects, for the consumers that know scene
objects (``export-mjcf``, the warp backend), and the lines ``dejaview validate`` prints about its
meshes. Reading and posing are ``dejaview.geometry.robot``'s.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from dejaview.geometry.robot import robot_model, robot_pieces
from dejaview.scene.model import Pose, SceneObject

__all__ = ["LinkPart", "hull_notes", "link_objects"]


@dataclass(frozen=True)
class LinkPart:
    """One collision geometry of a fixed robot as a fixed scene object, for consumers that know scene
    objects (MJCF export, the warp backend).

    Attributes:
        object: a fixed SceneObject named ``robot-id/link``, posed in the world, with the robot's
            material: a primitive, or ``mesh`` naming the file.
        link: the link's name.
        solid: a mesh's solid, scaled, vertices (V, 3) and faces (F, 3) in the object's frame; None
            for a primitive. What consumers collide, never the file's mesh as it stands.
        hull: whether the convex hull stands in for the file's surface.
        scale: a mesh's uniform scale.
    """

    object: object
    link: str
    solid: object = None
    hull: bool = False
    scale: float = 1.0


def link_objects(scene, obj) -> list[LinkPart]:
    """A fixed robot's link geometry as :class:`LinkPart` s, posed in the world.

    Raises:
        SceneError: naming the scene object, for any problem of the robot file or its joints.
        GeometryError: a mesh that cannot be read.
    """
    parts = []
    for p in robot_pieces(scene, obj):
        solid, hull = p.solid() if p.kind == "mesh" else (None, False)
        part = SceneObject(id=p.name, pose=Pose(p.position, p.orientation), fixed=True,
                           shape=None if p.kind == "mesh" else p.kind,
                           mesh=None if p.mesh is None else str(p.mesh), size=p.size, radius=p.radius,
                           height=p.height, friction=obj.friction, restitution=obj.restitution, line=obj.line)
        parts.append(LinkPart(part, p.link, solid, hull, p.scale))
    return parts


def hull_notes(scene, obj) -> list[str]:
    """One line per collision mesh of a robot object that has holes and so takes part as its convex
    hull (``dejaview validate`` prints them; nothing fails).

    Raises:
        SceneError: the robot file cannot be read (``dejaview validate`` has reported it already).
        GeometryError: a mesh that cannot be read.
    """
    from dejaview.geometry.mesh import collision_solid

    notes, seen = [], set()
    for g in robot_model(scene, obj).geometry:
        if g.kind != "mesh" or g.convex_hull or (g.mesh, g.scale) in seen:
            continue
        seen.add((g.mesh, g.scale))
        if collision_solid(g.mesh, g.scale)[1]:
            notes.append(f"robot {obj.id!r}: link {g.link!r}: mesh {_shown(g.mesh, scene)} is not watertight; "
                         "it collides as its convex hull (as in MuJoCo and Bullet)")
    return notes


def _shown(path: Path, scene) -> str:
    """A mesh path relative to the scene's folder where it lies below it."""
    try:
        return str(Path(os.path.abspath(path)).relative_to(Path(os.path.abspath(scene.base_dir))))
    except (ValueError, TypeError):
        return str(path)
