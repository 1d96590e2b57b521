"""MuJoCo round trips: a DejaView scene as an MJCF model, and an MJCF model as a scene.

``export_mjcf(scene)`` writes a model MuJoCo loads as it is (meshes inline as
mesh assets), with the movable objects' initial state as the keyframe
``initial``; ``import_mjcf(path)`` reads a model with the ``mujoco`` package
(an optional dependency, imported only here) and writes a scene.

What carries over, and how (docs/robotics.md has the user-facing version):

* Geometry: plane, box, sphere, cylinder map one to one. A mesh becomes
  MuJoCo mesh assets: MuJoCo collides a mesh as its convex hull, so a
  non-convex mesh goes as its convex pieces (``load_or_build_pieces``, the
  same CoACD pieces the interpenetration tests use; they fill concavities a
  little, e.g. part of a mug's handle hole), one geom each, named
  ``id``, ``id#1``, ``id#2``... Importing, capsules and ellipsoids become meshes; height
  fields and SDF geoms are refused.
* Mass: each movable object gets an explicit ``<inertial>`` with DejaView's
  mass, centre of mass and inertia (uniform density), so both engines move the
  same body. Importing, a body's mass is the object's ``mass``.
* Contact (``contact_parameters``; the fidelity table in docs/physics-fidelity.md
  measures it): Coulomb friction ``mu`` is the geom's sliding friction with
  ``condim=3`` (no torsional or rolling friction, which DejaView lacks too)
  and an elliptic cone with ``impratio=10`` (close to hard Coulomb
  friction). The normal contact is MuJoCo's spring-damper in its direct form,
  ``solref="-k -b"`` with a constant impedance (``solimp="0.99 0.99 0.001"``,
  so k and b act as given): the stiffness is DejaView's, ``k = omega_0^2``
  (its contact frequency, mass-normalised like MuJoCo's), so impacts last as
  long in both engines; the damping ``b = 2 zeta omega_0`` is calibrated so
  that MuJoCo's contact, which pushes and never pulls, integrated at its time
  step, rebounds with DejaView's restitution e (``damping_ratio``). The
  classic ``zeta = -ln e / sqrt(pi^2 + ln^2 e)`` holds for a spring-damper that
  may pull; MuJoCo's may not, and that formula made balls rebound too high
  and lively ones diverge (docs/physics-fidelity.md, "Mapping"). Importing inverts the mapping for
  either solref form. Every two geoms of different bodies, one movable, also
  get an explicit ``<pair>`` (``_contact_pairs``): DejaView's combined
  material (friction by the geometric mean, restitution by the mean, where
  MuJoCo combines geoms' friction by their maximum and solref by the mean)
  and ``solreffriction="0 -2 omega_0"`` (``FRICTION_DAMPING``), the friction's
  own reference damping: by default MuJoCo damps a slip with the normal
  contact's b, too slowly to stop it within an impact as Coulomb friction does;
  a larger damping makes MuJoCo's convex soft contact take normal impulse away
  from a sticking impact (``_contact_pairs``).
* ``contact="mujoco"`` (``export-mjcf --contact mujoco``) writes none of that contact: MuJoCo's
  own defaults (``solref`` 0.02 1, default ``solimp``, pyramidal cone, Euler), only each pair's
  DejaView friction: the world of a MuJoCo user who writes no contact parameters (the cross-engine
  bench's ``mujoco-default`` observer).
* State: DejaView's linear velocity is the centre of mass's, world frame;
  a MuJoCo free joint's is the body origin's (world frame) and its angular
  velocity is in the body frame: both are converted.
* Not carried: DejaView's backend settings (substeps, contact stiffness),
  the ``<inference>`` element (exported as an XML comment only) and, on
  import, MuJoCo's actuators, tendons, equality constraints, joints other
  than free joints (bodies with them are fixed at their keyframe pose) and
  its time step (DejaView keeps its own).
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np

from dejaview.errors import DejaViewError, SceneError
from dejaview.io.mjcf_text import _num, _vec, _xml

# MuJoCo settings shared by the export, tests/sim/test_mujoco_crosscheck.py and bench/crossengine.py
MJ_TIMESTEP = 0.0005
DEFAULT_FREQUENCY = 250.0
"""rad/s: DejaView's default contact frequency (0.25 / (dt / substeps) at dt 2 ms, 2 substeps)."""
SOLIMP = (0.99, 0.99, 0.001)  # constant impedance: solref's stiffness and damping act as given
OPTION = {"integrator": "implicitfast", "cone": "elliptic", "impratio": "10"}
FRICTION_DAMPING = 2.0
"""A contact pair's friction decays a slip at this many times the contact frequency
(``solreffriction = (0, -FRICTION_DAMPING omega_0)``), in a third of an impact's loading phase:
the slip stops within the impact as with Coulomb friction, and the normal impulse stays Coulomb's
(``_contact_pairs`` has the measurements)."""


class MJCFError(DejaViewError):
    """An MJCF model that cannot be imported, or a scene or state that cannot be exported."""


def _rebound(zeta: float, omega_h: float) -> float:
    """Restitution of MuJoCo's normal contact: unit mass and stiffness, damping ratio ``zeta``,
    a force that pushes and never pulls, semi-implicit Euler at step ``omega_h`` (omega_0 times
    MuJoCo's time step), approach speed 1."""
    x, v = 0.0, -1.0
    for _ in range(100000):
        a = max(0.0, -x - 2.0 * zeta * v) if x < 0.0 else 0.0
        v += omega_h * a
        x += omega_h * v
        if x >= 0.0 and v > 0.0:
            return v
    return 0.0


def _max_damping_ratio(omega_h: float) -> float:
    """Largest damping ratio used: half of what keeps the explicit damper stable (b h < 2)."""
    return 0.5 / omega_h


@functools.lru_cache(maxsize=256)
def damping_ratio(restitution: float, frequency: float = DEFAULT_FREQUENCY,
                  timestep: float = MJ_TIMESTEP) -> float:
    """Damping ratio of MuJoCo's contact (stiffness ``frequency^2``) that rebounds with ``restitution``.

    Bisection on ``_rebound`` (monotone in zeta). Restitutions below what the most damped
    stable contact gives (0.016 at the defaults) get that contact.

    Args:
        restitution: 0..1.
        frequency: contact natural frequency omega_0 (rad/s).
        timestep: MuJoCo's time step (s).
    Returns:
        zeta >= 0.
    """
    oh = frequency * timestep
    hi = _max_damping_ratio(oh)
    e = min(max(float(restitution), 0.0), 1.0)
    if e <= _rebound(hi, oh):
        return hi
    lo = 0.0
    if e >= _rebound(lo, oh):
        return lo
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if _rebound(mid, oh) > e:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def restitution_of(zeta: float, frequency: float = DEFAULT_FREQUENCY,
                   timestep: float = MJ_TIMESTEP) -> float:
    """Inverse of ``damping_ratio``: the restitution of MuJoCo's contact; 0 for the most damped
    stable contact and beyond."""
    oh = frequency * timestep
    if zeta >= _max_damping_ratio(oh) or not oh < 1.0:
        return 0.0
    return _rebound(max(float(zeta), 0.0), oh)


def solref_restitution(solref, timestep: float = MJ_TIMESTEP) -> float:
    """Restitution of a geom's ``solref``: ``(timeconst, dampratio)`` (MuJoCo's natural frequency
    is then 1 / (timeconst dampratio)) or ``(-stiffness, -damping)``."""
    a, b = float(solref[0]), float(solref[1])
    if a < 0.0 and b <= 0.0:
        omega = math.sqrt(-a)
        return restitution_of(-b / (2.0 * omega), omega, timestep)
    if a > 0.0 and b > 0.0:
        return restitution_of(b, 1.0 / (a * b), timestep)
    return 0.0


def contact_parameters(friction: float, restitution: float,
                       frequency: float = DEFAULT_FREQUENCY, timestep: float = MJ_TIMESTEP) -> dict[str, str]:
    """MJCF geom attributes for DejaView's friction and restitution (module docstring).

    Args:
        friction: Coulomb coefficient.
        restitution: 0..1.
        frequency: DejaView's contact frequency omega_0 (rad/s), the stiffness of both engines.
        timestep: MuJoCo's time step (s), which the damping that gives ``restitution`` depends on.
    Returns:
        ``{"condim", "friction", "solref", "solimp"}`` as attribute strings.
    """
    zeta = damping_ratio(float(restitution), float(frequency), float(timestep))
    return {"condim": "3", "friction": f"{_num(friction)} 0 0",
            "solref": f"{_num(-frequency ** 2)} {_num(-2.0 * zeta * frequency)}",
            "solimp": _vec(SOLIMP)}


def scene_frequency(scene) -> float:
    """DejaView's contact frequency of a scene (``<simulation contact-frequency>``, else
    0.25 / (dt / substeps): ``dejaview.sim.build.step_settings``), rad/s."""
    from dejaview.sim.build import step_settings
    from dejaview.sim.world import DEFAULT_OMEGA_H

    substeps, frequency = step_settings(scene)
    return float(frequency) if frequency else DEFAULT_OMEGA_H * substeps / scene.simulation.dt


# -------------------------------------------------------------------- export
def _initial_states(scene, state: dict | None) -> dict[str, dict]:
    """Initial state per movable object: the scene's, with ``state`` (result.json) for its source."""
    out = {}
    for obj in scene.movable:
        out[obj.id] = {"position": obj.pose.position, "orientation": obj.pose.orientation,
                       "linear_velocity": obj.velocity.linear,
                       "angular_velocity": obj.velocity.angular}
    if state is not None:
        source = state.get("source") or (scene.inference.source if scene.inference else None)
        initial = state.get("initial_state")
        if source not in out or not isinstance(initial, dict):
            raise MJCFError("state: expected a result.json with 'source' (a movable object of the "
                            "scene) and 'initial_state'")
        merged = dict(out[source])
        for key in merged:
            if key in initial:
                value = np.asarray(initial[key], dtype=np.float64)
                if value.shape != np.shape(merged[key]) or not np.all(np.isfinite(value)):
                    raise MJCFError(f"state: initial_state.{key} must be {len(merged[key])} finite numbers")
                merged[key] = tuple(value.tolist())
        out[source] = merged
    return out


def _geom(scene, obj, assets: list[str], timestep: float = MJ_TIMESTEP, owner: str = "",
          record: list | None = None, part=None, mode: str = "mapped") -> list[str]:
    """The ``<geom>`` elements of one object (its own frame); mesh assets go to ``assets``, and
    ``(geom name, owner, friction, restitution)`` of each geom to ``record`` (``_contact_pairs``;
    ``owner`` the body's name, "" for the world); ``part``: the robot ``LinkPart`` of a link's ``obj``;
    ``mode``: ``export_mjcf``'s ``contact``."""
    sim = scene.simulation
    mu = sim.friction if obj.friction is None else obj.friction
    e = sim.restitution if obj.restitution is None else obj.restitution
    contact = (contact_parameters(mu, e, scene_frequency(scene), timestep) if mode == "mapped"
               else {"friction": f"{_num(mu)} 0.005 0.0001"})  # "mujoco": MuJoCo's default contact
    geoms = _geom_elements(scene, obj, assets, contact, part)
    if record is not None:
        record.extend((name, owner, float(mu), float(e)) for name, _ in geoms)
    return [text for _, text in geoms]


def _geom_elements(scene, obj, assets: list[str], contact: dict, part=None) -> list[tuple[str, str]]:
    """(name, ``<geom>`` element) of each of one object's geoms (``part`` as in ``_geom``)."""
    attrs = {"name": obj.id}
    kind = obj.geometry_kind
    if kind == "plane":
        attrs.update(type="plane", size="0 0 1")
    elif kind == "box":
        attrs.update(type="box", size=_vec(0.5 * np.asarray(obj.size)))
    elif kind == "sphere":
        attrs.update(type="sphere", size=_num(obj.radius))
    elif kind == "cylinder":
        attrs.update(type="cylinder", size=f"{_num(obj.radius)} {_num(0.5 * obj.height)}")
    elif kind == "mesh":
        from dejaview.geometry.convex_pieces import load_or_build_pieces

        # MuJoCo collides a mesh as its convex hull: a non-convex one goes as its convex pieces
        if part is None:
            pieces = load_or_build_pieces(scene.resolve(obj.mesh))
        elif part.hull or part.solid.is_convex:  # a robot's mesh that collides as its hull, or is convex
            pieces = [part.solid]
        else:  # the pieces of the file's mesh, scaled as the link's
            pieces = [p.copy().apply_scale(part.scale) if part.scale != 1.0 else p
                      for p in load_or_build_pieces(scene.resolve(obj.mesh))]
        geoms = []
        for i, piece in enumerate(pieces):
            name = obj.id if i == 0 else f"{obj.id}#{i}"
            assets.append(f'<mesh name="mesh_{_xml(name)}" vertex="{_vec(piece.vertices.ravel())}" '
                          f'face="{" ".join(str(int(k)) for k in piece.faces.ravel())}"/>')
            geoms.append((name, _geom_text(dict(attrs, name=name, type="mesh", mesh=f"mesh_{name}"),
                                           contact, obj.fixed)))
        return geoms
    else:
        raise MJCFError(f"object {obj.id!r}: geometry {kind!r} has no MJCF export")
    return [(obj.id, _geom_text(attrs, contact, obj.fixed))]


def _geom_text(attrs: dict, contact: dict, fixed: bool) -> str:
    attrs = dict(attrs, **contact)
    if not fixed:
        attrs["mass"] = "0"  # the body's <inertial> carries mass and inertia
    return "<geom " + " ".join(f'{k}="{_xml(v)}"' for k, v in attrs.items()) + "/>"


def _mass_properties(scene, obj):
    from dejaview.geometry.mesh import load_mesh, mass_properties, primitive_mass_properties

    density = obj.density if obj.density is not None else 1000.0
    if obj.mesh is not None:
        return mass_properties(load_mesh(scene.resolve(obj.mesh)), mass=obj.mass, density=density)
    return primitive_mass_properties(obj.shape, size=obj.size, radius=obj.radius, height=obj.height,
                                     mass=obj.mass, density=density)


def export_mjcf(scene, state: dict | None = None, timestep: float = MJ_TIMESTEP, contact: str = "mapped") -> str:
    """The scene as MJCF text that ``mujoco.MjModel.from_xml_string`` loads as it is.

    Args:
        scene: a validated Scene (mesh files must exist).
        state: optional parsed ``result.json`` of a solve: its ``initial_state``
            replaces the source's pose and velocity in the keyframe.
        timestep: MuJoCo's time step (s); the contacts' damping is mapped for it.
        contact: ``"mapped"`` (DejaView's contact carried over: the module docstring) or
            ``"mujoco"``: MuJoCo's own defaults (soft, critically damped ``solref`` 0.02 1, default
            ``solimp``, pyramidal cone, Euler), only the friction carried (each pair's DejaView
            combined coefficient), the restitution not (MuJoCo's default contact hardly rebounds):
            the world a MuJoCo user who writes no contact parameters simulates.
    Returns:
        MJCF XML. Fixed objects are world geoms, movable ones bodies with a free
        joint (named after the object); the keyframe ``initial`` holds their
        initial state, also written as the bodies' poses.
    Raises:
        MJCFError: a state that does not fit the scene.
        GeometryError: a mesh that cannot be read.
    """
    from dejaview.geometry.transforms import quat_to_matrix

    if contact not in ("mapped", "mujoco"):
        raise MJCFError(f"contact: expected 'mapped' or 'mujoco', got {contact!r}")
    states = _initial_states(scene, state)
    assets: list[str] = []
    geoms: list[tuple] = []
    world, qpos, qvel = [], [], []
    mocap: list[str] = []  # a moving robot's link geometries, as mocap bodies (dejaview.io.mjcf_motion)
    for obj in scene.objects:
        if obj.fixed and obj.moving:
            from dejaview.io.mjcf_motion import mocap_bodies
            from dejaview.scene.robot_links import link_objects

            parts = link_objects(scene, obj)
            world.extend(mocap_bodies([(p.object, _geom(scene, p.object, assets, timestep, "", geoms, p, contact))
                                       for p in parts]))
            mocap.extend(p.object.id for p in parts)
            continue
        if obj.fixed:
            from dejaview.scene.robot_links import link_objects

            # a robot: its links' collision geometry, posed by forward kinematics, as world geoms
            for part in link_objects(scene, obj) if obj.robot is not None else [None]:
                one = obj if part is None else part.object
                for geom in _geom(scene, one, assets, timestep, "", geoms, part, contact):
                    world.append(geom.replace("<geom ", f'<geom pos="{_vec(one.pose.position)}" '
                                                        f'quat="{_vec(one.pose.orientation)}" ', 1))
            continue
        s = states[obj.id]
        props = _mass_properties(scene, obj)
        inertia = props.inertia
        full = (inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2])
        world.append(f'<body name="{_xml(obj.id)}" pos="{_vec(s["position"])}" '
                     f'quat="{_vec(s["orientation"])}"><freejoint name="{_xml(obj.id)}"/>'
                     f'<inertial pos="{_vec(props.center_of_mass)}" mass="{_num(props.mass)}" '
                     f'fullinertia="{_vec(full)}"/>{"".join(_geom(scene, obj, assets, timestep, obj.id, geoms, mode=contact))}'
                     '</body>')
        rot = quat_to_matrix(s["orientation"])
        omega = np.asarray(s["angular_velocity"], dtype=np.float64)
        # free joint: velocity of the body origin (world), angular velocity in the body frame
        v_origin = np.asarray(s["linear_velocity"]) - np.cross(omega, rot @ props.center_of_mass)
        quat = np.asarray(s["orientation"], dtype=np.float64)
        qpos.extend([*s["position"], *(quat / np.linalg.norm(quat))])
        qvel.extend([*v_origin, *(rot.T @ omega)])
    option = " ".join(f'{k}="{v}"' for k, v in OPTION.items()) if contact == "mapped" else ""
    comment = ""
    if scene.inference is not None:
        comment = (f"\n  <!-- DejaView inference source: {_xml(scene.inference.source)}; "
                   "the <inference> element has no MJCF counterpart -->")
    motion, keys = "", []
    if mocap:  # where the links stand at each time, and at the start
        from dejaview.io.mjcf_motion import motion_keys

        motion, keys = motion_keys(scene, mocap)
    keyframe = ("\n  <keyframe>\n    " + "\n    ".join(
        [f'<key name="initial" qpos="{_vec(qpos)}" qvel="{_vec(qvel)}"{motion}/>'] + keys)
        + "\n  </keyframe>" if qpos else "")
    asset = ("\n  <asset>\n    " + "\n    ".join(assets) + "\n  </asset>") if assets else ""
    body = "\n    ".join(world)
    pairs = _contact_pairs(scene, geoms, timestep, contact)
    contact_xml = ("\n  <contact>\n    " + "\n    ".join(pairs) + "\n  </contact>") if pairs else ""
    return f"""<mujoco model="{_xml(scene.name or 'dejaview-scene')}">{comment}
  <compiler angle="radian"/>
  <option timestep="{_num(timestep)}" gravity="{_vec(scene.gravity)}" {option}/>{asset}
  <worldbody>
    {body}
  </worldbody>{contact_xml}{keyframe}
</mujoco>
"""


def _contact_pairs(scene, geoms: list[tuple], timestep: float, contact: str = "mapped") -> list[str]:
    """``<pair>`` elements for every two geoms of different bodies, one of them movable, from
    ``geoms`` ((name, owner, friction, restitution), owner "" for the world).

    Each pair has DejaView's combined material (friction by the geometric mean, restitution by
    the mean; MuJoCo's own rule for geoms takes the larger friction) and its friction's
    reference acceleration ``solreffriction = (0, -FRICTION_DAMPING omega_0)``: a slip decays in
    half of 1 / omega_0, a third of an impact's loading phase. MuJoCo otherwise damps the
    friction dimensions with the normal contact's damping b = 2 zeta omega_0 (61 /s at e = 0.7),
    and a ball dropped 0.5 m with 0.3 m/s sideways left the floor still slipping at 0.14 m/s,
    where Coulomb friction (and DejaView) stops the slip within the impact. The factor
    (docs/physics-fidelity.md, "The friction's damping at 2 omega_0", MuJoCo at its 5 us): MuJoCo's
    contact is a convex soft constraint, whose friction's reference feeds into the normal force;
    a ball landing at 2 m/s with 2.5 m/s of backspin (e 0.3), whose rebound Coulomb friction
    leaves as it is, rebounds 0.010 m/s slower than without spin at factor 2, 0.088 at 4, 0.19
    at 8, while at 1 its slip is not stopped (7 % short of rolling). A box landing on its front
    edge (40 deg, 2.2 m/s forward, 3.6 down, turning at 110 deg/s) turns on at 84 deg/s after a
    rigid impact with Coulomb friction, 87 in DejaView, and in MuJoCo at factors 1, 2, 4, 8 at
    -6, 72, 99, 126. An explicit pair replaces MuJoCo's automatic contact of the same two geoms.
    """
    frequency = scene_frequency(scene)
    out = []
    for i, (name_a, owner_a, mu_a, e_a) in enumerate(geoms):
        for name_b, owner_b, mu_b, e_b in geoms[i + 1:]:
            if owner_a == owner_b:  # one body's own geoms, or two world geoms
                continue
            mu = math.sqrt(mu_a * mu_b)
            pair, friction = f'<pair geom1="{_xml(name_a)}" geom2="{_xml(name_b)}"', f'friction="{_num(mu)} {_num(mu)} 0 0 0"'
            if contact == "mujoco":  # MuJoCo's default contact, DejaView's combined friction
                out.append(f"{pair} {friction}/>")
                continue
            c = contact_parameters(mu, 0.5 * (e_a + e_b), frequency, timestep)
            out.append(f'{pair} condim="{c["condim"]}" {friction} solref="{c["solref"]}" '
                       f'solimp="{c["solimp"]}" solreffriction="0 {_num(-FRICTION_DAMPING * frequency)}"/>')
    return out


def read_state(path) -> dict:
    """A solve's ``result.json`` (the keys export uses: ``source``, ``initial_state``)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise MJCFError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except ValueError as exc:
        raise MJCFError(f"{path}: not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise MJCFError(f"{path}: expected a JSON object (a solve's result.json)")
    return data


# -------------------------------------------------------------------- import
_GEOM_NAMES = {0: "plane", 1: "hfield", 2: "sphere", 3: "capsule", 4: "ellipsoid", 5: "cylinder",
               6: "box", 7: "mesh", 8: "sdf"}


def import_mjcf(path, out_path, key: str | None = None) -> "object":
    """Write a DejaView scene from an MJCF model.

    World geoms become fixed objects; every body with a free joint (it must
    have exactly one geom) a movable object whose initial pose and velocity
    come from ``qpos0`` or the keyframe ``key``. Meshes (and capsules,
    ellipsoids) are written as .obj files into ``meshes/`` beside the scene (a mesh
    with holes as its convex hull, as MuJoCo collides it). Mesh files are found as a robot's
    (``dejaview.geometry.mjcf_files``: meshdir, relative, absolute, ``file://``, ``package://``).

    Args:
        path: the MJCF file.
        out_path: the scene file to write.
        key: name of a keyframe (default: the model's ``qpos0``, zero velocity).
    Returns:
        The Scene written (read back and validated).
    Raises:
        MJCFError: MuJoCo cannot load the model, a mesh file not found (where it was looked for:
            ``dejaview.geometry.mjcf_files``), an unknown keyframe, geometry DejaView cannot
            represent; the message names the body or geom.
    """
    import mujoco

    from dejaview.scene import Scene
    from dejaview.scene.model import Pose, SceneObject, SimulationSettings

    from dejaview.geometry.mjcf_files import compile_mjcf, read_mjcf

    path, out_path = Path(path), Path(out_path)
    try:  # mesh files by the robot files' rule (meshdir, file://, package://): one reader for both
        model = compile_mjcf(read_mjcf(path))
    except SceneError as exc:
        raise MJCFError(str(exc)) from None
    data = mujoco.MjData(model)
    if key is not None:
        kid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, key)
        if kid < 0:
            names = [model.key(i).name for i in range(model.nkey)]
            raise MJCFError(f"{path}: no keyframe {key!r} (keyframes: {', '.join(names) or 'none'})")
        mujoco.mj_resetDataKeyframe(model, data, kid)
    mujoco.mj_forward(model, data)

    mesh_dir = out_path.parent / "meshes"
    objects, used = [], set()
    frictions, restitutions = [], []

    def unique(name: str) -> str:
        base = name or "object"
        name, n = base, 1
        while name in used:
            n += 1
            name = f"{base}_{n}"
        used.add(name)
        return name

    for g in range(model.ngeom):
        body = int(model.geom_bodyid[g])
        root = int(model.body_rootid[body])
        free = _free_joint(model, root) if body else None
        if body and free is None:
            fixed = True  # a body without a free joint: frozen at this pose
        elif body:
            fixed = False
        else:
            fixed = True
        gname = model.geom(g).name or (model.body(body).name if body else f"geom{g}")
        where = f"{path}: geom {gname!r}"
        if not fixed:
            n_geoms = int(model.body_geomnum[body])
            if body != root or n_geoms != 1:
                raise MJCFError(f"{path}: body {model.body(root).name!r} has {n_geoms} geoms or child "
                                "bodies; a DejaView object has one geometry (merge them into one mesh)")
            gname = model.body(body).name or gname
        oid = unique(gname)
        geometry = _geometry(model, g, where, mesh_dir, oid, out_path.parent)
        pos = tuple(float(v) for v in data.geom_xpos[g])
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, data.geom_xmat[g])
        friction = float(model.geom_friction[g][0])
        restitution = solref_restitution(model.geom_solref[g], float(model.opt.timestep))
        frictions.append(friction)
        restitutions.append(restitution)
        kwargs = dict(geometry, id=oid, fixed=fixed, friction=friction, restitution=round(restitution, 6),
                      pose=Pose(pos, tuple(float(v) for v in quat)))
        if not fixed:
            kwargs["mass"] = float(model.body_mass[body])
            kwargs["velocity"] = _velocity(mujoco, model, data, body, np.asarray(pos))
        objects.append(SceneObject(**kwargs))
    if not any(not o.fixed for o in objects):
        raise MJCFError(f"{path}: no body with a free joint (DejaView needs a movable object)")
    planes_first = sorted(objects, key=lambda o: (o.shape != "plane", not o.fixed))
    friction = max(set(frictions), key=frictions.count)
    restitution = max(set(restitutions), key=restitutions.count)
    scene = Scene(objects=tuple(planes_first), name=path.stem,
                  gravity=tuple(float(v) for v in model.opt.gravity),
                  simulation=SimulationSettings(friction=friction, restitution=round(restitution, 6)),
                  base_dir=out_path.parent)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    text = scene.to_xml()
    try:
        written = Scene.from_string(text, base_dir=out_path.parent, filename=str(out_path))
    except SceneError as exc:
        raise MJCFError(f"{path}: the imported scene is not valid: {exc}") from exc
    out_path.write_text(text, encoding="utf-8")
    return written


def _free_joint(model, body: int):
    """Index of the free joint of a body, or None."""
    for j in range(int(model.body_jntadr[body]), int(model.body_jntadr[body] + model.body_jntnum[body])):
        if j >= 0 and int(model.jnt_type[j]) == 0:  # mjJNT_FREE
            return j
    return None


def _velocity(mujoco, model, data, body: int, origin: np.ndarray):
    """DejaView velocity of a free body: centre-of-mass velocity and angular velocity, world frame."""
    from dejaview.scene.model import Velocity

    vel = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, vel, 0)  # [rot, lin] at the COM
    return Velocity(tuple(float(v) for v in vel[3:]), tuple(float(v) for v in vel[:3]))


def _geometry(model, g: int, where: str, mesh_dir: Path, oid: str, scene_dir: Path) -> dict:
    """SceneObject geometry fields of one geom (meshes written to ``mesh_dir``)."""
    import trimesh

    kind = _GEOM_NAMES.get(int(model.geom_type[g]), "unknown")
    size = np.asarray(model.geom_size[g], dtype=np.float64)
    if kind == "plane":
        return {"shape": "plane"}
    if kind == "box":
        return {"shape": "box", "size": tuple(float(v) for v in 2.0 * size)}
    if kind == "sphere":
        return {"shape": "sphere", "radius": float(size[0])}
    if kind == "cylinder":
        return {"shape": "cylinder", "radius": float(size[0]), "height": float(2.0 * size[1])}
    if kind == "capsule":
        mesh = trimesh.creation.capsule(height=2.0 * size[1], radius=size[0], count=[32, 32])
    elif kind == "ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
        mesh.apply_scale(size)
    elif kind == "mesh":
        m = int(model.geom_dataid[g])
        start, count = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
        fstart, fcount = int(model.mesh_faceadr[m]), int(model.mesh_facenum[m])
        mesh = trimesh.Trimesh(np.asarray(model.mesh_vert[start:start + count], dtype=np.float64),
                               np.asarray(model.mesh_face[fstart:fstart + fcount], dtype=np.int64))
        if not mesh.is_watertight:  # holes: its convex hull, which is what MuJoCo collides anyway
            mesh = mesh.convex_hull
    else:
        raise MJCFError(f"{where}: geom type {kind!r} has no DejaView counterpart")
    mesh_dir.mkdir(parents=True, exist_ok=True)
    file = mesh_dir / f"{oid}.obj"
    mesh.export(file)
    return {"mesh": str(file.relative_to(scene_dir))}
