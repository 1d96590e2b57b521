"""Semantic checks of a scene: what the schema cannot say.

The reader (:mod:`dejaview.scene.xml`) calls :func:`validate_scene` on every
scene it builds, passing the line of each element; scenes built in Python can
be checked the same way (errors then carry the object lines the scene has, or
none).

``lines`` keys name the elements: ``("scene",)``, ``("simulation",)``,
``("object", i)``, ``("object", i, "pose")``, ``("object", i, "velocity")``,
``("inference",)``, ``("target", j)``, ``("optimize",)``, ``("start-area",)``,
``("exploration",)``, ``("penalty", j)``, ``("heatmap",)``.
"""

from __future__ import annotations

import math
import numbers
import re
from pathlib import Path

from dejaview.errors import SceneError
from dejaview.geometry import MESH_SUFFIXES
from dejaview.scene import bounds as B
from dejaview.scene.inference_elements import INFERENCE_ELEMENTS
from dejaview.scene.model import (
    EVALUATES,
    GRADIENTS,
    LOSSES,
    OPTIMIZERS,
    SHAPES,
    Scene,
    SceneObject,
)

__all__ = ["MESH_SUFFIXES", "scene_problems", "validate_scene"]

# Attributes each primitive takes; the others do not apply to it.
_SHAPE_ATTRS = {
    "plane": (),
    "box": ("size",),
    "sphere": ("radius",),
    "cylinder": ("radius", "height"),
}
_UNIT_QUAT_TOLERANCE = 1e-6
_SIMULATION_ATTRS = ("dt", "duration", "friction", "restitution")
# An XML attribute name (no namespace) or a Clark-notation namespaced one.
_XML_NAME_RE = re.compile(r"(\{[^{}]+\})?[A-Za-z_][\w.\-]*\Z")

Lines = dict[tuple, "int | None"]


def validate_scene(scene: Scene, *, check_files: bool = True, lines: Lines | None = None,
                   file: str | None = None, max_steps: int | None = None) -> Scene:
    """Check a scene's meaning and return it unchanged.

    Args:
        scene: the scene to check.
        check_files: also check that mesh and sphere files exist (resolved
            with ``scene.resolve``, i.e. against the scene's folder).
        lines: line of each element, keyed as in the module docstring.
        file: file name for messages (default: ``scene.path`` or ``<scene>``).
        max_steps: step budget of a simulation of the scene (default ``bounds.max_steps()``).
    Returns:
        ``scene``.
    Raises:
        SceneError: the first problem in file order.
    """
    problems = scene_problems(scene, check_files=check_files, lines=lines, file=file, max_steps=max_steps)
    if problems:
        raise problems[0]
    return scene


def scene_problems(scene: Scene, *, check_files: bool = True, lines: Lines | None = None,
                   file: str | None = None, max_steps: int | None = None) -> list[SceneError]:
    """Every semantic problem of ``scene``, one :class:`SceneError` each, in file order.

    Arguments as for :func:`validate_scene`.
    """
    if file is None:
        file = str(scene.path) if scene.path is not None else "<scene>"
    checker = _Checker(scene, file, lines or {}, check_files, max_steps)
    checker.run()
    # Stable sort: by line, problems without a line last, otherwise in check order.
    return sorted(checker.problems, key=lambda e: (e.line is None, e.line or 0))


class _Checker:
    def __init__(self, scene: Scene, file: str, lines: Lines, check_files: bool, max_steps: int):
        self.scene = scene
        self.max_steps = B.max_steps(max_steps)
        self.file = file
        self.lines = lines
        self.check_files = check_files
        self.problems: list[SceneError] = []

    # -- reporting -----------------------------------------------------------
    def line(self, key: tuple) -> int | None:
        if key in self.lines:
            return self.lines[key]
        if key[0] == "object":
            objects = self.scene.objects
            if 0 <= key[1] < len(objects) and objects[key[1]].line is not None:
                return objects[key[1]].line
            return self.lines.get(("scene",))
        if key[0] in ("target", "optimize", "start-area", "exploration", "penalty", "heatmap"):
            return self.lines.get(("inference",), self.lines.get(("scene",)))
        return self.lines.get(("scene",))

    def report(self, key: tuple, reason: str) -> None:
        element = key[2] if key[0] == "object" and len(key) > 2 else key[0]
        self.problems.append(SceneError(reason, self.file, self.line(key), element))

    # -- value checks (each returns True when fine) ----------------------------
    def number(self, key, name, value, *, positive=False, nonnegative=False,
               unit_interval=False, optional=False, minimum=None, limit=None, unit="") -> bool:
        if value is None:
            if not optional:
                self.report(key, f"'{name}' is missing")
            return False
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            self.report(key, f"'{name}' must be a number, not {type(value).__name__}")
            return False
        if not math.isfinite(value):
            self.report(key, f"'{name}' is not finite ({value!r})")
            return False
        if positive and not value > 0:
            self.report(key, f"'{name}' must be positive, got {value!r}")
            return False
        if nonnegative and not value >= 0:
            self.report(key, f"'{name}' must be >= 0, got {value!r}")
            return False
        if unit_interval and not 0 <= value <= 1:
            self.report(key, f"'{name}' must be between 0 and 1, got {value!r}")
            return False
        if minimum is not None and value < minimum:
            self.report(key, f"'{name}' {value!r}{unit} is below the smallest meaningful value, {minimum:g}{unit}")
            return False
        if limit is not None and abs(value) > limit:
            self.report(key, f"'{name}' {value!r}{unit} is beyond the limit of {limit:g}{unit}")
            return False
        return True

    def vector(self, key, name, value, n=3, *, positive=False, optional=False, minimum=None, limit=None,
               norm=None, unit="") -> bool:
        if value is None:
            if not optional:
                self.report(key, f"'{name}' is missing")
            return False
        try:
            count = len(value)
        except TypeError:
            self.report(key, f"'{name}' must be {n} numbers")
            return False
        if count != n:
            self.report(key, f"'{name}' needs {n} numbers, got {count}")
            return False
        if not all([self.number(key, name, v, positive=positive, minimum=minimum, limit=limit, unit=unit)
                    for v in value]):
            return False
        if norm is not None:
            size = math.hypot(*(float(v) for v in value))
            if size > norm:
                self.report(key, f"'{name}' has magnitude {size:.4g}{unit}, beyond the limit of {norm:g}{unit}")
                return False
        return True

    def integer(self, key, name, value, minimum, maximum=None) -> bool:
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            self.report(key, f"'{name}' must be an integer, got {value!r}")
            return False
        if value < minimum:
            self.report(key, f"'{name}' must be >= {minimum}, got {value!r}")
            return False
        if maximum is not None and value > maximum:
            self.report(key, f"'{name}' {value!r} is over the limit of {maximum}")
            return False
        return True

    def quaternion(self, key, name, q) -> None:
        if not self.vector(key, name, q, 4):
            return
        n2 = sum(float(c) * float(c) for c in q)
        if n2 == 0.0:
            self.report(key, f"'{name}' is a zero quaternion")
        elif abs(math.sqrt(n2) - 1.0) > _UNIT_QUAT_TOLERANCE:
            self.report(key, f"'{name}' is not a unit quaternion (norm {math.sqrt(n2):.6g})")

    def choice(self, key, name, value, allowed, optional=False) -> None:
        if value is None and optional:
            return
        if value not in allowed:
            self.report(key, f"{name} {value!r} is not one of {', '.join(allowed)}")

    def file_exists(self, key, name, value) -> None:
        if not isinstance(value, str) or not value.strip():
            self.report(key, f"'{name}' names no file")
            return
        if not self.check_files:
            return
        path = self.scene.resolve(value)
        try:
            ok = Path(path).is_file()
        except (OSError, ValueError):
            ok = False
        if not ok:
            where = f" (looked for {path})" if str(path) != value else ""
            self.report(key, f"{name} file {value!r} not found{where}")

    # -- the checks ----------------------------------------------------------
    def run(self) -> None:
        scene = self.scene
        root = ("scene",)
        if scene.version != 1:
            self.report(root, f"unknown scene version {scene.version!r} "
                              "(this reader knows version 1)")
        self.vector(root, "gravity", scene.gravity, norm=B.MAX_GRAVITY, unit=" m/s^2")
        if not scene.objects:
            self.report(root, "scene has no objects")
        self.simulation()
        first_line: dict[str, int] = {}
        for i, obj in enumerate(scene.objects):
            self.object(i, obj, first_line)
        if scene.inference is not None:
            self.inference()

    def simulation(self) -> None:
        s = self.scene.simulation
        key = ("simulation",)
        dt_ok = self.number(key, "dt", s.dt, positive=True, limit=B.MAX_DT, unit=" s")
        duration_ok = self.number(key, "duration", s.duration, positive=True, unit=" s")
        self.number(key, "friction", s.friction, nonnegative=True, limit=B.MAX_FRICTION)
        self.number(key, "restitution", s.restitution, unit_interval=True)
        extras = {}
        for name, value in s.extra.items():
            if not isinstance(name, str) or not _XML_NAME_RE.match(name) or name in _SIMULATION_ATTRS:
                self.report(key, f"extra setting name {name!r} is not a usable attribute name")
            elif not isinstance(value, str):
                self.report(key, f"extra setting '{name}' must be text, not {type(value).__name__}")
            elif name in B.SIM_EXTRAS:  # the sphere simulator's own settings: what it would refuse
                parsed, reason = B.parse_extra(name, value)
                if reason:
                    self.report(key, reason)
                else:
                    extras[name] = parsed
        substeps = extras.get("substeps", B.default_substeps(self.scene))
        if dt_ok and "contact-frequency" in extras:
            h = s.dt / substeps
            omega = extras["contact-frequency"]
            if omega * h > B.MAX_CONTACT_OMEGA_H:
                self.report(key, f"simulation attribute contact-frequency={s.extra['contact-frequency']!r} "
                                 f"is unstable with substeps of {h:.4g} s (contact-frequency x dt / substeps "
                                 f"= {omega * h:.4g}, over {B.MAX_CONTACT_OMEGA_H:g})")
        if dt_ok and duration_ok and ("substeps" in extras or "substeps" not in s.extra):
            reason = B.budget_problem(B.step_count(s.duration, s.dt), substeps, self.max_steps,
                                      f"duration / dt = {s.duration!r} s / {s.dt!r} s")
            if reason:
                self.report(key, reason)

    def object(self, i: int, obj: SceneObject, first_line: dict[str, int]) -> None:
        key = ("object", i)
        # identity
        if not isinstance(obj.id, str) or not obj.id:
            self.report(key, "'id' is empty")
        elif any(c.isspace() for c in obj.id):
            self.report(key, f"id {obj.id!r} contains whitespace (penalties list ids "
                             "separated by spaces)")
        elif obj.id in first_line:
            seen = first_line[obj.id]
            where = f" (first used on line {seen})" if seen is not None else ""
            self.report(key, f"duplicate id {obj.id!r}{where}")
        else:
            first_line[obj.id] = self.line(key)

        # geometry: exactly one of shape, mesh, urdf and mjcf
        given = [name for name in ("shape", "mesh", "urdf", "mjcf") if getattr(obj, name, None) is not None]
        if len(given) > 1:
            both = f"both {given[0]} and {given[1]}" if len(given) == 2 else ", ".join(given[:-1]) + f" and {given[-1]}"
            self.report(key, f"object {obj.id!r} has {both}; give one geometry")
        elif not given:
            self.report(key, f"object {obj.id!r} has no geometry; give shape=..., mesh=..., urdf=... or mjcf=...")
        elif obj.shape is not None:
            self.primitive(key, obj)
        elif obj.mesh is not None:
            self.mesh(key, obj)
        else:
            self.robot(key, obj)
        if obj.joints is not None and obj.urdf is None and obj.mjcf is None:
            self.report(key, "'joints' applies to a robot only (urdf=... or mjcf=...)")
        if obj.keyframes and obj.urdf is None and obj.mjcf is None:
            self.report(key + ("joints", 0), "<joints> keyframes apply to a robot only (urdf=... or mjcf=...)")
        if obj.spheres is not None:
            self.file_exists(key, "spheres", obj.spheres)

        if not isinstance(obj.fixed, bool):
            self.report(key, f"'fixed' must be a boolean, got {obj.fixed!r}")
        self.number(key, "mass", obj.mass, positive=True, optional=True, minimum=B.MIN_MASS,
                    limit=B.MAX_MASS, unit=" kg")
        density_ok = self.number(key, "density", obj.density, positive=True, optional=True,
                                 minimum=B.MIN_DENSITY, limit=B.MAX_DENSITY, unit=" kg/m^3")
        if obj.mass is None and (obj.density is None or density_ok):
            self.primitive_mass(key, obj)
        self.number(key, "friction", obj.friction, nonnegative=True, optional=True, limit=B.MAX_FRICTION)
        self.number(key, "restitution", obj.restitution, unit_interval=True, optional=True)

        pose_key = ("object", i, "pose")
        self.vector(pose_key, "position", obj.pose.position, limit=B.MAX_LENGTH, unit=" m")
        self.quaternion(pose_key, "orientation", obj.pose.orientation)
        vel_key = ("object", i, "velocity")
        self.vector(vel_key, "linear", obj.velocity.linear, norm=B.MAX_SPEED, unit=" m/s")
        self.vector(vel_key, "angular", obj.velocity.angular, norm=B.MAX_SPIN, unit=" rad/s")

    def primitive_mass(self, key, obj: SceneObject) -> None:
        """A movable primitive without a mass gets density x volume: that must be in range too."""
        if obj.fixed or obj.mass is not None or obj.mesh is not None or obj.shape not in ("box", "sphere",
                                                                                         "cylinder"):
            return
        dims = list(obj.size or ()) if obj.shape == "box" else [obj.radius] + ([obj.height] if obj.shape == "cylinder" else [])
        if not all(isinstance(d, numbers.Real) and B.MIN_SIZE <= d <= B.MAX_LENGTH for d in dims):
            return  # reported by the shape checks
        try:
            if obj.shape == "box":
                volume = math.prod(float(v) for v in obj.size)
            elif obj.shape == "sphere":
                volume = 4.0 / 3.0 * math.pi * float(obj.radius) ** 3
            else:
                volume = math.pi * float(obj.radius) ** 2 * float(obj.height)
        except (TypeError, ValueError, OverflowError):
            return  # reported by the shape checks
        density = obj.density if obj.density is not None else 1000.0
        mass = density * volume
        if math.isfinite(mass) and not B.MIN_MASS <= mass <= B.MAX_MASS:
            self.report(key, f"object {obj.id!r} would weigh {mass:.4g} kg (density x volume), outside "
                             f"{B.MIN_MASS:g}..{B.MAX_MASS:g} kg; give a 'mass' or another density")

    def primitive(self, key, obj: SceneObject) -> None:
        if obj.shape not in SHAPES:
            self.report(key, f"shape {obj.shape!r} is not one of {', '.join(SHAPES)}")
            return
        takes = _SHAPE_ATTRS[obj.shape]
        for name in ("size", "radius", "height"):
            value = getattr(obj, name)
            if name not in takes:
                if value is not None:
                    self.report(key, f"'{name}' does not apply to a {obj.shape}")
            elif value is None:
                self.report(key, f"a {obj.shape} needs '{name}'")
            elif name == "size":
                self.vector(key, "size", value, positive=True, minimum=B.MIN_SIZE, limit=B.MAX_LENGTH,
                            unit=" m")
            else:
                self.number(key, name, value, positive=True, minimum=B.MIN_SIZE, limit=B.MAX_LENGTH, unit=" m")
        if obj.shape == "plane" and obj.fixed is not True:
            self.report(key, f"plane {obj.id!r} must be fixed (add fixed=\"true\")")

    def mesh(self, key, obj: SceneObject) -> None:
        for name in ("size", "radius", "height"):
            if getattr(obj, name) is not None:
                self.report(key, f"'{name}' does not apply to a mesh (the mesh gives the size)")
        if not isinstance(obj.mesh, str):
            self.report(key, "'mesh' must be a file name")
            return
        suffix = Path(obj.mesh).suffix.lower()
        if suffix not in MESH_SUFFIXES:
            self.report(key, f"mesh {obj.mesh!r} has unsupported suffix {suffix or '(none)'!r} "
                             f"(use one of {', '.join(MESH_SUFFIXES)})")
            return
        self.file_exists(key, "mesh", obj.mesh)

    def robot(self, key, obj: SceneObject) -> None:
        """A URDF or MJCF robot: fixed, no size or mass, its file readable, one value per movable
        joint and each inside its limits, the meshes it names present."""
        kind = "urdf" if obj.urdf is not None else "mjcf"
        for name in ("size", "radius", "height", "spheres", "mass", "density"):
            if getattr(obj, name) is not None:
                self.report(key, f"'{name}' does not apply to a robot (its {kind.upper()} file gives the geometry)")
        if obj.fixed is not True:
            self.report(key, f"robot {obj.id!r} must be fixed (add fixed=\"true\"): its links are static "
                             "geometry posed by 'joints'")
        if obj.joints is not None:
            for q in obj.joints:
                if not self.number(key, "joints", q, limit=B.MAX_LENGTH):
                    return
        if not self.keyframe_times(key, obj):
            return
        value = obj.robot
        if not isinstance(value, str) or not value.strip():
            self.report(key, f"'{kind}' names no file")
            return
        before = len(self.problems)
        self.file_exists(key, kind, value)
        if not self.check_files or len(self.problems) > before:
            return
        from dejaview.geometry.robot import joint_problems, robot_model

        try:
            model = robot_model(self.scene, obj)
        except SceneError as exc:
            self.report(key, f"{kind} {value!r}: {exc}")
            return
        if obj.joints is not None or not obj.keyframes:  # a moving robot may leave 'joints' out
            for reason in joint_problems(model, obj.joints):
                self.report(key, f"robot {obj.id!r}: {reason}")
        for j, frame in enumerate(obj.keyframes):
            for reason in joint_problems(model, frame.values, what=f"<joints time=\"{frame.time:g}\">"):
                self.report(key + ("joints", j), f"robot {obj.id!r}: {reason}")
        for path in model.files:
            try:
                ok = Path(path).is_file()
            except (OSError, ValueError):
                ok = False
            if not ok:
                self.report(key, f"robot {obj.id!r}: mesh file {str(path)!r} named by {value!r} not found")

    def keyframe_times(self, key, obj: SceneObject) -> bool:
        """A moving robot's ``<joints time values>``: finite times from 0 on, increasing, finite
        values (the spec's "Robots as users have them"); False where one is not."""
        previous = None
        for j, frame in enumerate(obj.keyframes):
            where = key + ("joints", j)
            if not self.number(where, "time", frame.time, nonnegative=True, limit=B.MAX_LENGTH, unit=" s"):
                return False
            for q in frame.values:
                if not self.number(where, "values", q, limit=B.MAX_LENGTH):
                    return False
            if previous is not None and not frame.time > previous:
                self.report(where, f"robot {obj.id!r}: <joints> times must increase: {frame.time:g} s "
                                   f"follows {previous:g} s")
                return False
            previous = frame.time
        return True

    def inference(self) -> None:
        inf = self.scene.inference
        key = ("inference",)
        ids = {o.id: o for o in self.scene.objects}
        source = ids.get(inf.source)
        if source is None:
            self.report(key, f"source {inf.source!r} is not an object of the scene")
        elif source.fixed:
            self.report(key, f"source {inf.source!r} is fixed; the source must be movable")
        self.integer(key, "iterations", inf.iterations, 1, B.MAX_ITERATIONS)
        self.integer(key, "seed", inf.seed, 0, B.MAX_SEED)
        self.choice(key, "optimizer", inf.optimizer, OPTIMIZERS)
        self.choice(key, "gradient", inf.gradient, GRADIENTS, optional=True)
        self.choice(key, "loss", inf.loss, LOSSES)
        self.choice(key, "evaluate", inf.evaluate, EVALUATES)

        self.targets(inf)

        if not inf.optimize.any():
            self.report(("optimize",), "nothing to optimize: every part of the initial "
                                       "state is held fixed")

        area = inf.start_area
        if area is not None:
            akey = ("start-area",)
            min_ok = self.vector(akey, "min", area.min, limit=B.MAX_LENGTH, unit=" m")
            max_ok = self.vector(akey, "max", area.max, limit=B.MAX_LENGTH, unit=" m")
            if min_ok and max_ok:
                bad = [ax for ax, lo, hi in zip("xyz", area.min, area.max) if lo > hi]
                if bad:
                    self.report(akey, f"'min' is greater than 'max' along {', '.join(bad)}")

        for j, pen in enumerate(inf.penalties):
            pkey = ("penalty", j)
            if len(pen.between) != 2:
                self.report(pkey, f"'between' needs two object ids, got {len(pen.between)}")
            else:
                a, b = pen.between
                robots = {k for k, o in ids.items() if getattr(o, "robot", None) is not None}
                missing = [x for x in (a, b) if x not in ids and not (isinstance(x, str) and "/" in x
                                                                       and x.split("/", 1)[0] in robots)]
                whole = [x for x in (a, b) if x in robots]
                if whole:
                    self.report(pkey, f"'between' names robot {whole[0]!r}: name one of its links "
                                      f"('{whole[0]}/LINK', e.g. the link it should touch)")
                elif missing:
                    self.report(pkey, "'between' names unknown object "
                                      + ", ".join(repr(x) for x in missing))
                elif a == b:
                    self.report(pkey, f"'between' names {a!r} twice; give two distinct objects")

        if inf.heatmap is not None:
            self.heatmap(area)
        self.ranges(inf)

    def ranges(self, inf) -> None:
        """The plain numbers of ``<inference>``'s children, each held to its row's range in
        ``INFERENCE_ELEMENTS`` (``check``: ``number``'s keywords, or an integer's (min, max))."""
        for spec in INFERENCE_ELEMENTS:
            value = getattr(inf, spec.field)
            items = list(enumerate(value)) if spec.repeated else ([] if value is None else [(None, value)])
            for j, item in items:
                key = (spec.tag,) if j is None else (spec.tag, j)
                for a in spec.attributes:
                    if isinstance(a.check, tuple):
                        self.integer(key, a.xml, getattr(item, a.field), *a.check)
                    elif a.check is not None:
                        self.number(key, a.xml, getattr(item, a.field), **a.check)

    def targets(self, inf) -> None:
        """Each ``<target>`` (key ``("target", j)``), and how several go together: every one of
        several observations has a ``time`` but at most one (the end, seen at rest or moving)."""
        untimed = []
        duration = self.scene.simulation.duration
        if not inf.targets:
            self.report(("inference",), "no <target>: an inference needs at least one observation")
        for j, t in enumerate(inf.targets):
            tkey = ("target", j)
            self.vector(tkey, "position", t.position, limit=B.MAX_LENGTH, unit=" m")
            if t.orientation is not None:
                self.quaternion(tkey, "orientation", t.orientation)
            self.vector(tkey, "linear-velocity", t.linear_velocity, optional=True, norm=B.MAX_SPEED,
                        unit=" m/s")
            self.vector(tkey, "angular-velocity", t.angular_velocity, optional=True, norm=B.MAX_SPIN,
                        unit=" rad/s")
            if self.number(tkey, "time", t.time, nonnegative=True, optional=True):
                if isinstance(duration, numbers.Real) and t.time > duration:
                    self.report(tkey, f"'time' {t.time!r} is after the end of the simulation "
                                      f"(duration {duration!r})")
            else:
                untimed.append(j)
            if t.moving is False and (t.linear_velocity is not None or t.angular_velocity is not None):
                self.report(tkey, "a target seen at rest (moving=\"false\") observes no velocities: "
                                  "drop linear-velocity and angular-velocity or moving")
        if len(inf.targets) > 1 and len(untimed) > 1:
            self.report(("target", untimed[1]), f"{len(untimed)} targets have no 'time': of several "
                                                f"observations each needs the moment it was made "
                                                f"(at most one, the end, may leave it out)")

    def heatmap(self, area) -> None:
        h, key = self.scene.inference.heatmap, ("heatmap",)
        if area is None:
            self.report(key, "a heatmap needs a <start-area> to cover")
        elif all(isinstance(v, numbers.Real) and math.isfinite(v) for v in (*area.min, *area.max)):
            if not (area.max[0] > area.min[0] and area.max[1] > area.min[1]):
                self.report(key, "the start area has no x-y extent to cover with a heatmap")
        try:
            cells = tuple(h.cells)
        except TypeError:
            cells = ()
        if len(cells) != 2:
            self.report(key, f"'cells' needs 2 integers, got {len(cells)}")
        else:
            for c in cells:
                self.integer(key, "cells", c, 1, B.MAX_HEATMAP_CELLS)
        self.integer(key, "samples", h.samples, 1, B.MAX_HEATMAP_SAMPLES)
        self.number(key, "sigma", h.sigma, positive=True, limit=B.MAX_LENGTH, unit=" m")
