"""Dataclasses of a DejaView scene (format version 1, see the scene-format spec).

These are plain data: no torch, no trimesh. Reading and writing XML lives in
``dejaview.scene.xml``; semantic checks in ``dejaview.scene.validate``.
Vectors are tuples of floats; quaternions are ``(w, x, y, z)`` and normalised
by the reader.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

SHAPES = ("plane", "box", "sphere", "cylinder")
OPTIMIZERS = ("auto", "gd", "adam", "lbfgs", "bfgs")
"""Optimiser names, the one list (scene, API, CLI, service). ``auto``, the default: the search for the
most probable past (``dejaview.inference.search``); the others: one local optimiser with restarts."""
GRADIENTS = ("forward", "reverse")
LOSSES = ("pose", "add", "position")
EVALUATES = ("best", "final")

DEFAULT_GRAVITY: Vec3 = (0.0, 0.0, -9.81)
DEFAULT_DENSITY = 1000.0


@dataclass(frozen=True)
class Pose:
    """Position (m) and orientation quaternion (w x y z) of an object's frame."""

    position: Vec3 = (0.0, 0.0, 0.0)
    orientation: Quat = (1.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Velocity:
    """Linear velocity (m/s) of the centre of mass and angular velocity (rad/s), world frame."""

    linear: Vec3 = (0.0, 0.0, 0.0)
    angular: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class JointKeyframe:
    """``<joints time values>`` inside a robot object: its joint values (radians or metres, in the
    order of the model's movable joints) at ``time`` (s from the start of the simulation)."""

    time: float
    values: tuple[float, ...]
    line: int | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class SceneObject:
    """One rigid body of the scene.

    Geometry is either a primitive (``shape`` with ``size``/``radius``/``height``),
    a mesh file (``mesh``) or a fixed robot (``urdf`` or ``mjcf``, posed by forward
    kinematics at the ``joints`` values, radians or metres in the order of the
    model's movable joints). A robot with ``keyframes`` moves: its joint values follow them,
    linearly interpolated in time, held before the first and after the last (``joints_at``).
    File names are kept as written in the file; ``Scene.resolve`` turns them into paths.
    """

    id: str
    pose: Pose = field(default_factory=Pose)
    velocity: Velocity = field(default_factory=Velocity)
    shape: str | None = None
    size: Vec3 | None = None
    radius: float | None = None
    height: float | None = None
    mesh: str | None = None
    spheres: str | None = None
    fixed: bool = False
    mass: float | None = None
    density: float | None = None
    friction: float | None = None
    restitution: float | None = None
    urdf: str | None = None
    mjcf: str | None = None
    joints: tuple[float, ...] | None = None
    keyframes: tuple[JointKeyframe, ...] = ()
    line: int | None = field(default=None, compare=False, repr=False)

    @property
    def moving(self) -> bool:
        """Whether this is a robot that moves (``<joints time values>`` children)."""
        return bool(self.keyframes)

    def joints_at(self, time: float) -> tuple[float, ...] | None:
        """The robot's joint values at ``time`` (s): ``joints`` for a robot that stands, else the
        keyframes linearly interpolated, held before the first and after the last."""
        if not self.keyframes:
            return self.joints
        keys = self.keyframes
        if time <= keys[0].time:
            return tuple(keys[0].values)
        for a, b in zip(keys, keys[1:]):
            if time < b.time:
                u = (time - a.time) / (b.time - a.time)
                return tuple(qa + u * (qb - qa) for qa, qb in zip(a.values, b.values))
        return tuple(keys[-1].values)

    @property
    def geometry_kind(self) -> str:
        """``"mesh"``, ``"urdf"``, ``"mjcf"`` or the primitive's shape name."""
        if self.mesh is not None:
            return "mesh"
        if self.urdf is not None:
            return "urdf"
        if self.mjcf is not None:
            return "mjcf"
        return str(self.shape)

    @property
    def robot(self) -> str | None:
        """The robot model file (``urdf`` or ``mjcf``) as written, or None."""
        return self.urdf if self.urdf is not None else self.mjcf


@dataclass(frozen=True)
class SimulationSettings:
    """``<simulation>``: step, duration and contact material defaults.

    ``extra`` keeps backend-specific attributes (stiffness, damping, substeps...)
    as strings, so they survive a round trip unchanged.
    """

    dt: float = 0.002
    duration: float = 1.5
    friction: float = 0.5
    restitution: float = 0.2
    extra: dict[str, str] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        """Number of steps of length ``dt`` in ``duration`` (rounded; ``sys.maxsize`` where that
        overflows: the reader refuses such scenes, see ``dejaview.scene.bounds.MAX_STEPS``)."""
        import sys

        from dejaview.scene.bounds import step_count

        n = step_count(self.duration, self.dt)
        return int(n) if n < sys.maxsize else sys.maxsize


@dataclass(frozen=True)
class Target:
    """``<target>``: one observation of the source (scene-format spec, "how the source was seen").

    ``orientation`` None: the position alone was observed. ``time`` None: the observation's moment is
    not known (the end, or any moment for ``moving``). ``moving``: ``True`` the source was seen in
    motion, ``False`` lying still, None as the spec's default (``at_rest``).
    """

    position: Vec3
    orientation: Quat | None = None
    linear_velocity: Vec3 | None = None
    angular_velocity: Vec3 | None = None
    time: float | None = None
    moving: bool | None = None

    @property
    def at_rest(self) -> bool:
        """Whether the source was seen lying still: ``moving="false"``, or, by default, a target
        without a ``time`` and without velocities (it must have come to rest at the pose and stay)."""
        if self.moving is not None:
            return not self.moving
        return self.time is None and self.linear_velocity is None and self.angular_velocity is None


def last_target(targets) -> Target:
    """The last observation of several: the target without a ``time`` (seen at the end), else the
    one with the latest time (the first of them where several share it)."""
    untimed = [t for t in targets if t.time is None]
    if untimed:
        return untimed[0]
    return max(targets, key=lambda t: t.time)


@dataclass(frozen=True)
class Optimize:
    """``<optimize>``: which parts of the source's initial state are free."""

    position: bool = True
    orientation: bool = True
    linear_velocity: bool = True
    angular_velocity: bool = True

    def any(self) -> bool:
        return self.position or self.orientation or self.linear_velocity or self.angular_velocity


@dataclass(frozen=True)
class StartArea:
    """``<start-area>``: axis-aligned box bounding the initial position (``line``: where it was read,
    for messages)."""

    min: Vec3
    max: Vec3
    line: int | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Exploration:
    """``<exploration>``: epsilon-greedy restarts."""

    epsilon: float = 0.2
    patience: int = 25


@dataclass(frozen=True)
class Penalty:
    """``<penalty>``: pull objects ``between[0]`` and ``between[1]`` into contact."""

    between: tuple[str, str]
    weight: float = 1.0


@dataclass(frozen=True)
class HeatmapSettings:
    """``<heatmap>``: start-position heatmap over the start area's x-y extent."""

    cells: tuple[int, int] = (16, 16)
    samples: int = 4
    sigma: float = 0.02


@dataclass(frozen=True)
class Prior:
    """``<prior speed spin tilt>``: standard deviations of zero-mean normal priors on each component
    of the initial linear velocity (m/s) and angular velocity (rad/s), and of the initial
    orientation's rotation away from the ``<pose>`` orientation (rad). None: flat within the
    backend's bounds (``dejaview.inference.posterior``)."""

    speed: float | None = None
    spin: float | None = None
    tilt: float | None = None


@dataclass(frozen=True)
class Observation:
    """``<observation sigma angle-sigma rest-speed rest-spin>``: standard deviations of the observed
    pose's noise, position (m) and orientation (rad), and of the speed (m/s) and spin (rad/s) with
    which "at rest" is observed. None: the defaults of ``dejaview.inference.posterior``."""

    sigma: float | None = None
    angle_sigma: float | None = None
    rest_speed: float | None = None
    rest_spin: float | None = None


@dataclass(frozen=True)
class ModelUncertainty:
    """``<model-uncertainty friction restitution>``: relative standard deviations (0.1 = 10 %) of the
    physics parameters that the likelihood averages over (``dejaview.inference.posterior``). None: the
    parameter is taken as exact."""

    friction: float | None = None
    restitution: float | None = None


@dataclass(frozen=True)
class PhysicsPrior:
    """``<physics-prior friction restitution stiffness>``: relative standard deviations (0.3 = 30 %)
    of log-normal priors around the scene's friction, restitution (kept within 0 and 1) and contact
    stiffness, inferred with the start (``dejaview.sim.physics``). None: the parameter is known."""

    friction: float | None = None
    restitution: float | None = None
    stiffness: float | None = None


@dataclass(frozen=True)
class PosteriorRequest:
    """``<posterior samples>``: how many samples of the posterior a solve draws (0: the most probable
    start alone)."""

    samples: int = 0


@dataclass(frozen=True)
class InferenceSettings:
    """``<inference>``: what to infer and how. ``targets``: every ``<target>``, in file order
    (one, or several with times: a tracked source)."""

    source: str
    targets: tuple[Target, ...]
    iterations: int = 200
    seed: int = 0
    optimizer: str = "auto"
    gradient: str | None = None  # None: the faster for the problem
    loss: str = "pose"
    evaluate: str = "best"
    optimize: Optimize = field(default_factory=Optimize)
    start_area: StartArea | None = None
    exploration: Exploration | None = None
    penalties: tuple[Penalty, ...] = ()
    heatmap: HeatmapSettings | None = None
    prior: Prior | None = None
    observation: Observation | None = None
    model_uncertainty: ModelUncertainty | None = None
    physics_prior: PhysicsPrior | None = None
    posterior: PosteriorRequest | None = None

    @property
    def target(self) -> Target:
        """The last observation (``last_target``)."""
        return last_target(self.targets)

    @property
    def infers_physics(self) -> bool:
        """Whether ``<physics-prior>`` makes any physics parameter an unknown (a deviation above 0)."""
        p = self.physics_prior
        return p is not None and any((v or 0.0) > 0 for v in (p.friction, p.restitution, p.stiffness))


@dataclass(frozen=True)
class Scene:
    """A whole scene file.

    ``base_dir`` is the folder relative file names resolve against (the scene
    file's folder); ``path`` the file it was read from. Neither takes part in
    equality, so a scene read back from its own XML compares equal.
    """

    objects: tuple[SceneObject, ...]
    version: int = 1
    name: str | None = None
    gravity: Vec3 = DEFAULT_GRAVITY
    simulation: SimulationSettings = field(default_factory=SimulationSettings)
    inference: InferenceSettings | None = None
    base_dir: Path | None = field(default=None, compare=False, repr=False)
    path: Path | None = field(default=None, compare=False, repr=False)
    root: Path | None = field(default=None, compare=False, repr=False)
    """Where given, the folder a robot's ``package://`` URIs resolve inside (the service's scene
    root); None: the search path of ``dejaview.geometry.packages.resolve_package``."""

    # -- construction and output (implemented in dejaview.scene.xml) --------
    @classmethod
    def from_xml(cls, path: str | Path, **kwargs) -> "Scene":
        """Read, validate and return the scene in the XML file ``path``.

        Raises:
            SceneError: naming file, line and element of the first problem.
        """
        from dejaview.scene.xml import read_scene_file

        return read_scene_file(path, **kwargs)

    @classmethod
    def from_string(cls, text: str | bytes, base_dir: str | Path | None = None,
                    filename: str = "<string>", **kwargs) -> "Scene":
        """Parse and validate scene XML text; relative files resolve against ``base_dir``."""
        from dejaview.scene.xml import read_scene_string

        return read_scene_string(text, base_dir=base_dir, filename=filename, **kwargs)

    def to_xml(self) -> str:
        """The scene as XML text (UTF-8 declaration included)."""
        from dejaview.scene.writer import scene_to_xml

        return scene_to_xml(self)

    def write(self, path: str | Path) -> None:
        """Write ``to_xml()`` to ``path``."""
        Path(path).write_text(self.to_xml(), encoding="utf-8")

    # -- queries -------------------------------------------------------------
    def object(self, object_id: str) -> SceneObject:
        """The object with id ``object_id`` (KeyError if absent)."""
        for obj in self.objects:
            if obj.id == object_id:
                return obj
        raise KeyError(object_id)

    @property
    def movable(self) -> tuple[SceneObject, ...]:
        """Objects that are not fixed, in file order."""
        return tuple(o for o in self.objects if not o.fixed)

    @property
    def fixed(self) -> tuple[SceneObject, ...]:
        """Fixed (static) objects, in file order."""
        return tuple(o for o in self.objects if o.fixed)

    def resolve(self, name: str | None) -> Path | None:
        """Resolve a file name from the scene (mesh, spheres, urdf, mjcf) against ``base_dir``."""
        if name is None:
            return None
        p = Path(name)
        if not p.is_absolute() and self.base_dir is not None:
            p = self.base_dir / p
        return p

    def replace(self, **changes) -> "Scene":
        """A copy with some fields changed (dataclasses.replace)."""
        return replace(self, **changes)

    def with_object(self, obj: SceneObject) -> "Scene":
        """A copy where the object with ``obj.id`` is replaced by ``obj``."""
        objs = tuple(obj if o.id == obj.id else o for o in self.objects)
        return replace(self, objects=objs)


def dataclass_fields(cls) -> list[str]:
    """Names of a dataclass's fields (used by the XML writer and tests)."""
    return [f.name for f in fields(cls)]
