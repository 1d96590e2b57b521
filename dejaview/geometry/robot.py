"""Fixed robots in scenes: URDF and MJCF models posed by forward kinematics (pytorch-kinematics).

A scene object ``<object id="arm" urdf="robots/arm.urdf" joints="q1 q2 ..." fixed="true">`` (or
``mjcf="model.xml"``) stands for every link of the model, posed at the given joint values (radians
or metres, in the order of the model's movable joints) relative to the object's ``<pose>``. Each
link's collision geometry becomes one static piece of the world (``dejaview.sim.build``): boxes,
spheres and cylinders one to one, meshes as signed distance grids, MJCF capsules as a cylinder
and two spheres, MJCF meshes as their convex hulls (as MuJoCo collides them).

Reading is in two parts so that checks stay cheap:

* :func:`read_robot` parses the file (lxml, no torch): movable joints and their limits, and each
  link's collision geometry. The XML is untrusted: DOCTYPE and ENTITY declarations are refused
  before any parser sees the text, and no entity, DTD or network access is ever resolved.
  Mesh names resolve by one rule for both formats (``dejaview.geometry.packages.resolve_mesh``):
  relative to the file (an MJCF model's ``meshdir``), absolute, ``file://`` or ``package://``;
  an MJCF model's includes and mesh files are read by ``dejaview.geometry.mjcf_files``.
* :func:`robot_pieces` poses the geometry with pytorch-kinematics' forward kinematics
  (``build_chain_from_urdf`` / ``build_chain_from_mjcf``, imported here, lazily: it costs ~2 s).

Errors are :class:`~dejaview.errors.SceneError` naming the robot file, its line and element.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dejaview.errors import SceneError
from dejaview.geometry import MESH_SUFFIXES
from dejaview.geometry.transforms import matrix_to_quat, quat_to_matrix, rigid_transform, rpy_to_matrix

__all__ = ["LinkGeometry", "RobotJoint", "RobotModel", "RobotPiece", "joint_problems", "link_transforms",
           "link_transforms_batch", "read_robot", "robot_model", "robot_pieces"]

MAX_ROBOT_BYTES = 4 << 20
"""Largest URDF or MJCF file read (4 MiB)."""

MOVABLE_URDF_JOINTS = ("revolute", "continuous", "prismatic")
_REFUSED_URDF_JOINTS = ("floating", "planar")


@dataclass(frozen=True)
class RobotJoint:
    """A movable joint: ``kind`` revolute | continuous | prismatic; limits in rad or m (None: none)."""

    name: str
    kind: str
    lower: float | None = None
    upper: float | None = None


@dataclass(frozen=True)
class LinkGeometry:
    """One collision geometry of a link, in the link's frame.

    Attributes:
        link: link (URDF) or body (MJCF) name.
        kind: box | sphere | cylinder | mesh | plane.
        size: (3,) box edge lengths (m).
        radius, height: sphere and cylinder radius, cylinder height (m).
        mesh: the mesh file (resolved) and ``scale`` its uniform scale.
        convex_hull: the mesh collides as its convex hull whatever its shape (MJCF: as in MuJoCo);
            else as itself, or as its hull where it has holes (``dejaview.geometry.mesh.collision_solid``).
        origin: (4, 4) link-from-geometry transform.
        line: line of the element in the robot file.
    """

    link: str
    kind: str
    origin: np.ndarray
    size: tuple[float, float, float] | None = None
    radius: float | None = None
    height: float | None = None
    mesh: Path | None = None
    scale: float = 1.0
    convex_hull: bool = False
    line: int | None = None


@dataclass(frozen=True)
class RobotModel:
    """What :func:`read_robot` found in a URDF or MJCF file.

    Attributes:
        path: the file; format: ``urdf`` | ``mjcf``.
        joints: the movable joints, in the file's order (the order of a scene's ``joints``).
        geometry: every link's collision geometry.
        text: what the forward kinematics reads: a URDF's links (names only) and joints (origin, parent,
            child, axis, limit), the tags pytorch-kinematics' parser knows (it prints a line for every
            other); an MJCF model as ``dejaview.geometry.mjcf_files.read_mjcf`` makes it (one document).
        files: files the model names (meshes, MJCF includes), resolved.
        assets: an MJCF model's mesh files by the asset key ``text`` names them by
            (``dejaview.geometry.mjcf_files``).
    """

    path: Path
    format: str
    joints: tuple[RobotJoint, ...]
    geometry: tuple[LinkGeometry, ...]
    text: bytes = field(repr=False)
    files: tuple[Path, ...] = ()
    assets: tuple[tuple[str, Path], ...] = ()


@dataclass(frozen=True)
class RobotPiece:
    """One posed collision geometry of a robot, in the world.

    ``name``: ``robot-id/link`` (``#k`` appended for a link's k-th extra geometry); ``kind``: box |
    sphere | cylinder | mesh | plane; ``position`` (3,) and ``orientation`` (4,) w x y z of the
    geometry's frame; ``size``/``radius``/``height``/``mesh``/``scale``/``convex_hull`` as in
    :class:`LinkGeometry`.
    """

    name: str
    link: str
    kind: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    size: tuple[float, float, float] | None = None
    radius: float | None = None
    height: float | None = None
    mesh: Path | None = None
    scale: float = 1.0
    convex_hull: bool = False

    def solid(self):
        """The mesh piece's solid, scaled, and whether its convex hull stands in:
        ``dejaview.geometry.mesh.collision_solid``."""
        from dejaview.geometry.mesh import collision_solid

        return collision_solid(self.mesh, self.scale, self.convex_hull)


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------
def read_robot(path: str | Path, format: str, root: Path | None = None) -> RobotModel:
    """Parse a URDF (``format="urdf"``) or MJCF (``"mjcf"``) file's joints and collision geometry.

    Args:
        path: the robot file.
        format: ``urdf`` | ``mjcf``.
        root: where given, ``package://`` URIs resolve only inside this folder (the service's scene
            root); None: anywhere on the search path (``dejaview.geometry.packages``).
    Raises:
        SceneError: naming the robot file, line and element: unreadable, hostile or malformed XML,
            a joint type a fixed robot cannot have, geometry that is not supported, a mesh URI other
            than ``file://`` and ``package://``, or a package not found on the search path;
            ``dejaview.geometry.mjcf_files.MeshOutsideRoot`` for an MJCF file outside ``root``.
    """
    path = Path(path)
    if format == "mjcf":  # the model and the files it names: dejaview.geometry.mjcf_files
        return _read_mjcf(path, root)
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_ROBOT_BYTES + 1)
    except OSError as exc:
        raise SceneError(f"cannot read {format.upper()} file: {exc.strerror or exc}", str(path)) from None
    if len(data) > MAX_ROBOT_BYTES:
        raise SceneError(f"{format.upper()} file is over the {MAX_ROBOT_BYTES >> 20} MiB limit", str(path))
    from dejaview.untrusted_xml import parse_xml

    tree = parse_xml(data, filename=str(path), max_bytes=MAX_ROBOT_BYTES, what=f"{format.upper()} files")
    if format == "urdf":
        return _read_urdf(path, tree, root)
    raise ValueError(f"unknown robot format {format!r}")


def _err(path: Path, el, reason: str) -> SceneError:
    return SceneError(reason, str(path), getattr(el, "sourceline", None), getattr(el, "tag", None))


def _floats(path: Path, el, name: str, n: int, default=None) -> tuple[float, ...] | None:
    raw = el.get(name)
    if raw is None:
        return default
    try:
        values = tuple(float(t) for t in raw.split())
    except ValueError:
        values = ()
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise _err(path, el, f"attribute '{name}' needs {n} finite number{'s' if n > 1 else ''}, got {raw!r}")
    return values


def _positive(path: Path, el, name: str, value) -> float:
    if value is None:
        raise _err(path, el, f"missing attribute '{name}'")
    v = value[0] if isinstance(value, tuple) else value
    if not v > 0:
        raise _err(path, el, f"attribute '{name}' must be positive, got {v!r}")
    return float(v)


def _urdf_origin(path: Path, el) -> np.ndarray:
    origin = el.find("origin")
    if origin is None:
        return np.eye(4)
    xyz = _floats(path, origin, "xyz", 3, (0.0, 0.0, 0.0))
    rpy = _floats(path, origin, "rpy", 3, (0.0, 0.0, 0.0))
    return rigid_transform(rpy_to_matrix(rpy), xyz)


def _read_urdf(path: Path, root, confine: Path | None) -> RobotModel:
    if root.tag != "robot":
        raise _err(path, root, f"the root element is <{root.tag}>, a URDF's is <robot>")
    links = {}
    geometry, files = [], []
    for link in root.findall("link"):
        name = link.get("name")
        if not name:
            raise _err(path, link, "a <link> needs a 'name'")
        if name in links:
            raise _err(path, link, f"duplicate link name {name!r}")
        links[name] = link
        for col in link.findall("collision"):
            geom = col.find("geometry")
            shapes = [] if geom is None else [g for g in geom if isinstance(g.tag, str)]
            if len(shapes) != 1:
                raise _err(path, col, f"link {name!r}: a <collision> needs a <geometry> with one shape")
            g = shapes[0]
            origin = _urdf_origin(path, col)
            if g.tag == "box":
                size = _floats(path, g, "size", 3)
                for v in size or (None,):
                    _positive(path, g, "size", v)
                geometry.append(LinkGeometry(name, "box", origin, size=size, line=g.sourceline))
            elif g.tag == "sphere":
                r = _positive(path, g, "radius", _floats(path, g, "radius", 1))
                geometry.append(LinkGeometry(name, "sphere", origin, radius=r, line=g.sourceline))
            elif g.tag == "cylinder":  # URDF cylinders are along z, centred: ours too
                r = _positive(path, g, "radius", _floats(path, g, "radius", 1))
                h = _positive(path, g, "length", _floats(path, g, "length", 1))
                geometry.append(LinkGeometry(name, "cylinder", origin, radius=r, height=h, line=g.sourceline))
            elif g.tag == "mesh":
                mesh, scale = _urdf_mesh(path, g, confine)
                files.append(mesh)
                geometry.append(LinkGeometry(name, "mesh", origin, mesh=mesh, scale=scale, line=g.sourceline))
            else:
                raise _err(path, g, f"link {name!r}: collision geometry <{g.tag}> is not supported "
                                    "(box, sphere, cylinder, mesh)")
    if not links:
        raise _err(path, root, "the robot has no <link>")
    joints = []
    for joint in root.findall("joint"):
        name, kind = joint.get("name"), joint.get("type")
        if not name or not kind:
            raise _err(path, joint, "a <joint> needs a 'name' and a 'type'")
        if kind in _REFUSED_URDF_JOINTS:
            raise _err(path, joint, f"joint {name!r} is {kind}: a fixed robot's joints are revolute, "
                                    "continuous, prismatic or fixed")
        if kind not in MOVABLE_URDF_JOINTS + ("fixed",):
            raise _err(path, joint, f"joint {name!r} has unknown type {kind!r}")
        for end in ("parent", "child"):
            e = joint.find(end)
            if e is None or e.get("link") not in links:
                raise _err(path, joint, f"joint {name!r}: <{end} link=...> must name a link of the robot")
        if kind == "fixed":
            continue
        lower = upper = None
        limit = joint.find("limit")
        if kind != "continuous":
            if limit is None:
                raise _err(path, joint, f"{kind} joint {name!r} needs a <limit lower upper>")
            lower = _floats(path, limit, "lower", 1, (0.0,))[0]
            upper = _floats(path, limit, "upper", 1, (0.0,))[0]
            if lower > upper:
                raise _err(path, limit, f"joint {name!r}: lower limit {lower!r} is above upper {upper!r}")
        joints.append(RobotJoint(name, kind, lower, upper))
    return RobotModel(path=path, format="urdf", joints=tuple(joints), geometry=tuple(geometry),
                      text=_urdf_skeleton(root), files=tuple(files))


_SKELETON_JOINT_TAGS = ("origin", "parent", "child", "axis", "limit")


def _urdf_skeleton(root) -> bytes:
    """The URDF's kinematic tree alone: ``<link name>`` and ``<joint>`` with the children in
    ``_SKELETON_JOINT_TAGS`` (pytorch-kinematics prints "Unknown tag" for the rest)."""
    from lxml import etree

    robot = etree.Element("robot", name=root.get("name") or "robot")
    for el in root:
        if el.tag == "link":
            etree.SubElement(robot, "link", name=el.get("name"))
        elif el.tag == "joint":
            joint = etree.SubElement(robot, "joint", dict(el.attrib))
            for child in el:
                if child.tag in _SKELETON_JOINT_TAGS:
                    joint.append(etree.fromstring(etree.tostring(child)))
    return etree.tostring(robot)


def _urdf_mesh(path: Path, g, root: Path | None) -> tuple[Path, float]:
    name = g.get("filename")
    if not name:
        raise _err(path, g, "a <mesh> needs a 'filename'")
    if Path(name).suffix.lower() not in MESH_SUFFIXES:
        raise _err(path, g, f"mesh {name!r}: unsupported suffix (use one of {', '.join(MESH_SUFFIXES)})")
    scale = _floats(path, g, "scale", 3, (1.0, 1.0, 1.0))
    if not (scale[0] > 0 and scale[0] == scale[1] == scale[2]):
        raise _err(path, g, f"mesh {name!r}: scale {g.get('scale')!r} must be uniform and positive")
    from dejaview.geometry.packages import resolve_mesh

    try:
        return resolve_mesh(name, path, root=root), float(scale[0])
    except ValueError as exc:
        raise _err(path, g, f"mesh {name!r}: {exc}") from None


# MuJoCo geom types (mjtGeom) that make static pieces; others are refused.
_MJ_PLANE, _MJ_SPHERE, _MJ_CAPSULE, _MJ_CYLINDER, _MJ_BOX, _MJ_MESH = 0, 2, 3, 5, 6, 7
_MJ_NAMES = {0: "plane", 1: "hfield", 2: "sphere", 3: "capsule", 4: "ellipsoid", 5: "cylinder", 6: "box",
             7: "mesh", 8: "sdf"}


def _read_mjcf(path: Path, confine: Path | None) -> RobotModel:
    from dejaview.geometry.mjcf_files import compile_mjcf, read_mjcf

    source = read_mjcf(path, confine)
    model = compile_mjcf(source)
    files = dict(source.meshes)
    joints = []
    for j in range(model.njnt):
        jnt = model.joint(j)
        kind = {2: "prismatic", 3: "revolute"}.get(int(model.jnt_type[j]))
        if kind is None:
            what = {0: "a free joint", 1: "a ball joint"}.get(int(model.jnt_type[j]), "a joint")
            raise SceneError(f"joint {jnt.name or j!r} is {what}: a fixed robot's joints are hinges and "
                             "slides (free bodies: dejaview import-mjcf)", str(path), None, "joint")
        limited = bool(model.jnt_limited[j])
        lo, hi = (float(model.jnt_range[j][0]), float(model.jnt_range[j][1])) if limited else (None, None)
        joints.append(RobotJoint(jnt.name or f"joint{j}", kind if limited or kind == "prismatic" else "continuous",
                                 lo, hi))
    geometry = []
    for g in range(model.ngeom):
        if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0:
            continue  # a visual-only geom: MuJoCo collides nothing with it either
        body = model.body(int(model.geom_bodyid[g])).name
        if not body:
            raise SceneError(f"geom {g} is on a body without a name: name every body that carries geoms",
                             str(path), None, "body")
        kind, size = int(model.geom_type[g]), model.geom_size[g]
        origin = rigid_transform(quat_to_matrix(model.geom_quat[g]), model.geom_pos[g])
        if kind == _MJ_PLANE:
            geometry.append(LinkGeometry(body, "plane", origin))
        elif kind == _MJ_SPHERE:
            geometry.append(LinkGeometry(body, "sphere", origin, radius=float(size[0])))
        elif kind == _MJ_BOX:
            geometry.append(LinkGeometry(body, "box", origin, size=tuple(2.0 * float(s) for s in size[:3])))
        elif kind in (_MJ_CYLINDER, _MJ_CAPSULE):
            geometry.append(LinkGeometry(body, "cylinder", origin, radius=float(size[0]),
                                         height=2.0 * float(size[1])))
            if kind == _MJ_CAPSULE:  # a capsule is a cylinder with a sphere on each end
                for sign in (-1.0, 1.0):
                    geometry.append(LinkGeometry(body, "sphere", origin @ rigid_transform(None, (0, 0, sign * size[1])),
                                                 radius=float(size[0])))
        elif kind == _MJ_MESH:
            geometry.append(_mjcf_mesh(path, model, g, body, origin, files))
        else:
            name = model.geom(g).name or f"#{g}"
            raise SceneError(f"geom {name!r} is a {_MJ_NAMES.get(kind, kind)}: an MJCF robot's geoms are planes, "
                             "spheres, capsules, cylinders, boxes and meshes", str(path), None, "geom")
    return RobotModel(path=path, format="mjcf", joints=tuple(joints), geometry=tuple(geometry), text=source.text,
                      files=source.files, assets=source.assets)


def _mjcf_mesh(path: Path, model, g: int, body: str, origin: np.ndarray, files: dict) -> LinkGeometry:
    """A mesh geom as the mesh file, placed where MuJoCo puts it: MuJoCo moves a mesh's vertices
    into its inertial frame (``mesh_pos``, ``mesh_quat``: v' = R^T (s v - p)) and the geom's frame
    with them; the file's frame is the geom's times (R, p)^-1. It collides as its convex hull, as
    in MuJoCo."""
    m = int(model.geom_dataid[g])
    mesh_name = model.mesh(m).name
    name = model.geom(g).name or f"#{g}"
    if mesh_name not in files:
        raise SceneError(f"geom {name!r}: mesh {mesh_name!r} has no file (vertices given inline are not "
                         "supported: give a mesh file)", str(path), None, "geom")
    scale = np.asarray(model.mesh_scale[m], dtype=np.float64)
    if not (scale[0] > 0 and np.allclose(scale, scale[0], rtol=1e-9, atol=0)):
        raise SceneError(f"geom {name!r}: mesh {mesh_name!r} has scale {' '.join(map(repr, scale.tolist()))}; "
                         "it must be uniform and positive", str(path), None, "geom")
    inertial = rigid_transform(quat_to_matrix(model.mesh_quat[m]), model.mesh_pos[m])
    return LinkGeometry(body, "mesh", origin @ np.linalg.inv(inertial), mesh=files[mesh_name],
                        scale=float(scale[0]), convex_hull=True)


def joint_problems(model: RobotModel, values, what: str = "'joints'") -> list[str]:
    """Reasons the joint values do not fit the model (wrong count, outside limits); empty when they do.
    ``what``: how the messages name the values (a keyframe: ``<joints time="0.5">``)."""
    values = tuple(values or ())
    if len(values) != len(model.joints):
        names = " ".join(j.name for j in model.joints) or "none"
        return [f"{what} needs {len(model.joints)} values, one per movable joint of "
                f"{model.path.name} ({names}), got {len(values)}"]
    problems = []
    for joint, q in zip(model.joints, values):
        if joint.lower is not None and not joint.lower - 1e-9 <= q <= joint.upper + 1e-9:
            unit = "m" if joint.kind == "prismatic" else "rad"
            problems.append(f"joint {joint.name!r} = {q!r} {unit} is outside its limits "
                            f"[{joint.lower!r}, {joint.upper!r}] {unit}")
    return problems


# ---------------------------------------------------------------------------
# posing (pytorch-kinematics)
# ---------------------------------------------------------------------------
def link_transforms(model: RobotModel, values) -> dict[str, np.ndarray]:
    """Robot-frame (4, 4) transform of every link (URDF) or body (MJCF), by forward kinematics.

    Args:
        model: from :func:`read_robot`.
        values: one value per movable joint, in ``model.joints`` order.
    Raises:
        SceneError: wrong joint values, or a model pytorch-kinematics cannot build.
    """
    problems = joint_problems(model, values)
    if problems:
        raise SceneError(problems[0], str(model.path))
    values = np.asarray([tuple(values or ())], dtype=np.float64).reshape(1, len(model.joints))
    return {name: t[0] for name, t in link_transforms_batch(model, values).items()}


def link_transforms_batch(model: RobotModel, values: np.ndarray) -> dict[str, np.ndarray]:
    """Robot-frame transforms (T, 4, 4) of every link at T joint vectors ``values`` (T, J), in one
    batched forward kinematics (a moving robot's path); the values are not checked here."""
    if not model.joints and model.format == "urdf":  # no joint: one link (pk finds no root then)
        return {g.link: np.repeat(np.eye(4)[None], len(values), 0) for g in model.geometry}
    values = np.asarray(values, dtype=np.float64).reshape(-1, len(model.joints))
    import torch

    with torch.no_grad():
        try:
            import pytorch_kinematics as pk

            if model.format == "urdf":
                chain = pk.build_chain_from_urdf(model.text)
            else:
                chain = _mjcf_chain(pk, model)
            chain = chain.to(dtype=torch.float64)
            names = chain.get_joint_parameter_names()
            order = {j.name: i for i, j in enumerate(model.joints)}
            th = torch.as_tensor(values[:, [order[n] for n in names]], dtype=torch.float64)
            fk = chain.forward_kinematics(th)
        except Exception as exc:  # pytorch-kinematics' errors are of every kind
            raise SceneError(f"pytorch-kinematics cannot pose the robot: {' '.join(str(exc).split())}",
                             str(model.path)) from None
    return {name: t.get_matrix().numpy().copy() for name, t in fk.items()}


def piece_transforms(obj, model: RobotModel, values: np.ndarray) -> dict[str, np.ndarray]:
    """World transforms (T, 4, 4) of every collision geometry of a robot object at T joint vectors
    ``values`` (T, J), by piece name (``robot-id/link``, ``#k`` for a link's further geometries, as
    ``robot_pieces``), the object's ``<pose>`` placing the root (``link_transforms_batch``)."""
    links = link_transforms_batch(model, values)
    base = rigid_transform(quat_to_matrix(obj.pose.orientation), obj.pose.position)
    out, seen = {}, {}
    for g in model.geometry:
        k = seen.get(g.link, 0)
        seen[g.link] = k + 1
        out[f"{obj.id}/{g.link}" + (f"#{k}" if k else "")] = base @ links[g.link] @ g.origin
    return out


def _mjcf_chain(pk, model: RobotModel):
    """A pytorch-kinematics chain of an MJCF body tree, built from MuJoCo's compiled model.

    Not ``pk.build_chain_from_mjcf``: in pytorch-kinematics 0.10 it recognises no joint type under
    mujoco 3.2+ (its map is keyed by the enum, MuJoCo hands out integers), and it leaves out the
    joint's anchor (``pos``): a hinge turns the body about ``pos``, so the body's frame is
    ``body offset @ T(pos) @ R(q) @ T(-pos)``. Here the ``T(-pos)`` is a fixed frame after the joint's.
    """
    import torch
    from pytorch_kinematics import frame as pk_frame

    from dejaview.geometry.mjcf_files import MJCFSource, compile_mjcf

    m = compile_mjcf(MJCFSource(model.path, model.text, model.assets))

    def tf(pos=None, quat=None):  # float32 like pytorch-kinematics' own builders; the chain moves to float64
        return pk.Transform3d(pos=None if pos is None else torch.tensor(np.asarray(pos), dtype=torch.float32),
                              rot=None if quat is None else torch.tensor(np.asarray(quat), dtype=torch.float32))

    frames = {0: pk_frame.Frame(m.body(0).name, link=pk_frame.Link(m.body(0).name), joint=pk_frame.Joint())}
    for b in range(1, m.nbody):
        body = m.body(b)
        parent = frames[int(body.parentid[0])]
        if int(body.jntnum[0]) > 1:
            raise ValueError(f"body {body.name!r} has {int(body.jntnum[0])} joints; a robot's bodies have one at most")
        if int(body.jntnum[0]) == 0:
            f = pk_frame.Frame(body.name, link=pk_frame.Link(body.name, offset=tf(body.pos, body.quat)),
                               joint=pk_frame.Joint(body.name + "_fixed", offset=None))
            parent.children = parent.children + [f]
        else:
            j = int(body.jntadr[0])
            jnt = m.joint(j)
            kind = "revolute" if int(m.jnt_type[j]) == 3 else "prismatic"
            anchor = np.asarray(jnt.pos, dtype=np.float64)
            moving = pk_frame.Frame(body.name + "__anchor",
                                    link=pk_frame.Link(body.name + "__anchor", offset=tf(body.pos, body.quat)),
                                    joint=pk_frame.Joint(jnt.name, offset=tf(anchor), joint_type=kind,
                                                         axis=np.asarray(jnt.axis, dtype=np.float32)))
            f = pk_frame.Frame(body.name, link=pk_frame.Link(body.name),
                               joint=pk_frame.Joint(body.name + "_anchor_back", offset=tf(-anchor)))
            moving.children = [f]
            parent.children = parent.children + [moving]
        frames[b] = f
    return pk.Chain(frames[0])


def robot_model(scene, obj) -> RobotModel:
    """The robot model of a scene object (``urdf`` or ``mjcf``), its file resolved against the scene
    (``package://`` URIs only inside ``scene.root`` where the scene has one)."""
    fmt = "urdf" if obj.urdf is not None else "mjcf"
    return read_robot(scene.resolve(obj.robot), fmt, root=scene.root)


def robot_pieces(scene, obj, model: RobotModel | None = None, time: float = 0.0) -> list[RobotPiece]:
    """Every collision geometry of a robot object, posed in the world at ``time`` (s; a robot that
    stands: at its ``joints``, one that moves: at its keyframes' values then, ``obj.joints_at``).

    Args:
        scene: the Scene (files resolve against it).
        obj: a SceneObject with ``urdf`` or ``mjcf``; its ``<pose>`` places the robot's root.
        model: the object's model if already read.
    Raises:
        SceneError: naming the scene object, for any problem of the robot file or its joints.
    """
    try:
        model = model or robot_model(scene, obj)
        links = link_transforms(model, obj.joints_at(time))
    except SceneError as exc:
        raise SceneError(f"object {obj.id!r}: {exc}", str(scene.path) if scene.path else None, obj.line,
                         "object") from None
    base = rigid_transform(quat_to_matrix(obj.pose.orientation), obj.pose.position)
    pieces, seen = [], {}
    for g in model.geometry:
        if g.link not in links:
            raise SceneError(f"object {obj.id!r}: link {g.link!r} of {model.path.name} is not connected to the "
                             "robot's root", str(scene.path) if scene.path else None, obj.line, "object")
        world = base @ links[g.link] @ g.origin
        k = seen.get(g.link, 0)
        seen[g.link] = k + 1
        name = f"{obj.id}/{g.link}" + (f"#{k}" if k else "")
        pieces.append(RobotPiece(name=name, link=g.link, kind=g.kind, position=tuple(float(v) for v in world[:3, 3]),
                                 orientation=matrix_to_quat(world[:3, :3]), size=g.size, radius=g.radius,
                                 height=g.height, mesh=g.mesh, scale=g.scale, convex_hull=g.convex_hull))
    return pieces
