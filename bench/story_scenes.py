"""The stories' scenes: random everyday stories drawn from a seed, their truths simulated to rest
and written as scene files (``bench/stories.py`` solves them; its docstring says what a story is
and which seeds are held out).

How a story is drawn (``make_story``): the kind's start area (0.3-0.9 m wide in x and y, placed
at random, on a counter or table top at the height where the source stands on it, else in the
air at hand height, 0.2-0.5 m tall), then a true start drawn uniformly inside that area (the
area is not centred on it), a random heading and velocities of the kind's ranges (``KINDS``).
The truth is simulated by DejaView's own engine for ``HORIZON`` seconds; it is redrawn (area and
all) when its start interpenetrates a static object by more than the solver's ``PosteriorSettings.feasibility_margin``, when
it does not tell the kind's story (a mug knocked off the counter must end on the floor), when
it leaves the room (``ROOM_HALF``) or sinks through the floor, or when it has not come to rest
by ``MAX_REST`` seconds. At rest: the source's mean speed over ``REST_WINDOW`` (its centre of
mass's displacement over the window) below ``REST_SPEED`` and its mean spin (the rotation over
the window) below ``REST_SPIN``, in every window from then to the end of the horizon. The
scene's ``<simulation duration>`` is the rest time plus ``REST_MARGIN``, rounded up to 0.1 s,
and its target the source's pose at the end of that duration (object-frame origin and
orientation, as ``examples/make_scenes.py`` writes them). The scene's own ``<pose>`` of the
source is a guess: the area's centre, upright, at rest.

The ball: the bundled ball (``examples/packings/ball.spheres``) is one sphere, and the engine
has no rolling or spinning friction, so a ball that lands with any sideways speed or spin rolls
(or spins about the vertical) for ever: measured, a ball thrown onto the floor still rolls at
1.51 m/s and 30 rad/s after 5 s, one dropped with 5 rad/s about z spins at 5 rad/s after 5 s.
It never comes to rest unless it falls straight down without spin. The stories' ball is the
bundled mesh (mass, inertia, feasibility) with a knobbly packing instead (``knobbly_ball``:
a 4 cm core and 12 knobs of 1.5 cm at the corners of an icosahedron, reaching the mesh's 5 cm),
which rolls from knob to knob, loses energy at each, and comes to rest in 1-4 s.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
MESHES = ROOT / "examples" / "meshes"
PACKINGS = ROOT / "examples" / "packings"

DT = 0.002
HORIZON = 5.0
"""s simulated per drawn truth to find its rest."""
MAX_REST = 4.0
"""s: a truth not at rest by then is redrawn."""
REST_WINDOW = 0.1
"""s over which the mean speed and spin are taken."""
REST_SPEED = 0.01
"""m/s: mean speed below which the source lies still."""
REST_SPIN = 0.1
"""rad/s: mean spin below which the source lies still."""
REST_MARGIN = 0.5
"""s the scene's duration runs past the rest time (then rounded up to 0.1 s)."""
ROOM_HALF = 3.0
"""m: a truth whose source ends (or passes) farther than this from the origin in x or y has left
the room; one below ``-FLOOR_SINK`` has sunk through the floor."""
FLOOR_SINK = 0.02
MAX_DRAWS = 200
"""Draws per story before giving up (RuntimeError)."""

COUNTER = dict(mesh="counter", x=(-0.5, 0.5), y=(-0.3, 0.3), top=0.9)
TABLE = dict(mesh="table", x=(-0.6, 0.6), y=(-0.4, 0.4), top=0.75)
SOURCES = {  # mesh, packing (None: the knobbly ball), mass, height of the origin over what it stands on,
             # radius about the origin in x-y (turned any way about z), the scene's restitution
    "ball": dict(mesh="ball", spheres=None, mass=0.4, stand=0.05, reach=0.05, restitution=0.3),
    "mug": dict(mesh="mug", spheres="mug", mass=0.35, stand=0.05, reach=0.068, restitution=0.2),
    "box": dict(mesh="box", spheres="box", mass=0.8, stand=0.05, reach=0.125, restitution=0.2),
}
FRICTION = 0.5
AREA_WIDTH = (0.3, 0.9)
"""m: range of a start area's width in x and in y (on a top: at most what the top leaves)."""
AIR_Z = (0.5, 1.6)
"""m: an area in the air lies within these heights ..."""
AIR_HEIGHT = (0.2, 0.5)
"""m: ... and is this tall."""
AIR_XY = 0.8
"""m: an area in the air has its centre within this of the origin in x and y."""


@dataclass(frozen=True)
class Kind:
    """One kind of story: the source, where it starts (``stand``: on a top, else None: in the air)
    and its velocity ranges (m/s, rad/s)."""

    name: str
    story: str
    source: str
    stand: dict | None
    speed: tuple[float, float]
    """horizontal speed, at a uniformly random heading"""
    vz: tuple[float, float] = (0.0, 0.0)
    spin: float = 0.0
    """each component of the angular velocity uniform in +-spin (a top: x and y only, see spin_z)"""
    spin_z: float | None = None
    """on a top: the spin about z (else ``spin``)"""
    rolling: bool = False
    """the ball rolls: its spin about the horizontal axes matches its speed (w = z x v / r)"""
    any_orientation: bool = False
    """uniformly random orientation (thrown); else upright, turned about z at random"""
    leaves_top: bool = False
    """the story: it ends on the floor, not on its top"""


KINDS = {k.name: k for k in (
    Kind("ball_thrown", "a ball thrown in an arc onto the floor, rolling to rest", "ball", None,
         speed=(1.0, 3.5), vz=(-0.5, 2.0), spin=5.0, any_orientation=True),
    Kind("ball_bounced", "a ball thrown down at the floor, bouncing and rolling to rest", "ball", None,
         speed=(0.0, 1.5), vz=(-4.0, -1.0), spin=5.0, any_orientation=True),
    Kind("ball_off_table", "a ball rolled off a table onto the floor", "ball", TABLE,
         speed=(0.5, 2.0), spin_z=3.0, rolling=True, any_orientation=True, leaves_top=True),
    Kind("mug_off_counter", "a mug knocked off a kitchen counter onto the floor", "mug", COUNTER,
         speed=(0.5, 2.5), spin=1.0, spin_z=3.0, leaves_top=True),
    Kind("mug_tossed", "a mug tossed onto the floor", "mug", None,
         speed=(0.5, 3.0), vz=(-0.5, 2.0), spin=5.0, any_orientation=True),
    Kind("mug_off_desk", "a mug slid off a desk onto the floor", "mug", TABLE,
         speed=(0.5, 2.5), spin=0.5, spin_z=3.0, leaves_top=True),
    Kind("box_thrown", "a box thrown onto the floor", "box", None,
         speed=(1.0, 3.5), vz=(-0.5, 2.0), spin=5.0, any_orientation=True),
)}
KNOBBLY = "ball_knobbly.spheres"


def knobbly_ball(core: float = 0.04, knob: float = 0.015, reach: float = 0.05) -> np.ndarray:
    """The stories' ball packing (module docstring): (13, 4) rows x y z r in the ball mesh's frame,
    a core sphere and 12 knobs at an icosahedron's corners reaching ``reach``."""
    p = (1 + 5 ** 0.5) / 2
    corners = []
    for a in (-1.0, 1.0):
        for b in (-p, p):
            corners += [(0.0, a, b), (a, b, 0.0), (b, 0.0, a)]
    c = np.asarray(corners)
    c = c / np.linalg.norm(c, axis=1, keepdims=True) * (reach - knob)
    return np.vstack([[0.0, 0.0, 0.0, core], np.hstack([c, np.full((12, 1), knob)])])


def write_knobbly(folder: Path) -> Path:
    path = Path(folder) / KNOBBLY
    lines = ["# DejaView sphere packing: one sphere per line, 'x y z r' in metres, in the mesh's frame",
             "# source: examples/meshes/ball.obj (bench/story_scenes.py knobbly_ball: a core and 12 knobs)",
             f"# spheres: {len(knobbly_ball())}"]
    lines += [" ".join(f"{v:.9f}" for v in row) for row in knobbly_ball()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# ------------------------------------------------------------------ drawing
def _yaw_quat(angle: float) -> list[float]:
    from dejaview.scene.xml import normalize_quaternion

    return list(normalize_quaternion([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]))


def _random_quat(rng) -> list[float]:
    from dejaview.scene.xml import normalize_quaternion

    q = rng.normal(size=4)
    q = q if q[0] >= 0 else -q
    return list(normalize_quaternion([float(v) for v in q]))


def draw_area(rng, kind: Kind) -> tuple[list[float], list[float]]:
    """(min, max) of a start area of ``kind`` (module docstring)."""
    src = SOURCES[kind.source]
    if kind.stand is not None:
        top = kind.stand
        z = round(top["top"] + src["stand"], 6)
        lo, hi = [], []
        for axis in ("x", "y"):
            a, b = top[axis][0] + src["reach"], top[axis][1] - src["reach"]
            width = round(float(rng.uniform(AREA_WIDTH[0], min(AREA_WIDTH[1], b - a))), 3)
            start = round(float(rng.uniform(a, b - width)), 3)
            lo.append(start)
            hi.append(round(start + width, 3))
        return [*lo, z], [*hi, z]
    lo, hi = [], []
    for _ in range(2):
        width = round(float(rng.uniform(*AREA_WIDTH)), 3)
        start = round(float(rng.uniform(-AIR_XY, AIR_XY)) - width / 2, 3)
        lo.append(start)
        hi.append(round(start + width, 3))
    height = round(float(rng.uniform(*AIR_HEIGHT)), 3)
    bottom = round(float(rng.uniform(AIR_Z[0], AIR_Z[1] - height)), 3)
    return [*lo, bottom], [*hi, round(bottom + height, 3)]


def draw_start(rng, kind: Kind, area) -> dict:
    """A true start of ``kind`` uniformly inside ``area`` (position, orientation (w x y z), linear,
    angular: lists of floats)."""
    lo, hi = area
    position = [float(rng.uniform(a, b)) if b > a else float(a) for a, b in zip(lo, hi)]
    orientation = _random_quat(rng) if kind.any_orientation else _yaw_quat(rng.uniform(-math.pi, math.pi))
    speed, heading = float(rng.uniform(*kind.speed)), float(rng.uniform(-math.pi, math.pi))
    linear = [speed * math.cos(heading), speed * math.sin(heading), float(rng.uniform(*kind.vz))]
    if kind.rolling:
        r = SOURCES[kind.source]["stand"]
        angular = [-linear[1] / r, linear[0] / r, float(rng.uniform(-kind.spin_z, kind.spin_z))]
    else:
        spin_z = kind.spin if kind.spin_z is None else kind.spin_z
        angular = [float(rng.uniform(-kind.spin, kind.spin)), float(rng.uniform(-kind.spin, kind.spin)),
                   float(rng.uniform(-spin_z, spin_z))]
    return dict(position=position, orientation=orientation, linear=linear, angular=angular)


# ------------------------------------------------------------------ scenes
def _rel(path: Path, folder: Path) -> str:
    """``path`` as the scene in ``folder`` names it: relative where ``folder`` lies in this checkout,
    else absolute."""
    path, folder = Path(path).resolve(), Path(folder).resolve()
    if folder == ROOT or ROOT in folder.parents:
        return os.path.relpath(path, folder).replace(os.sep, "/")
    return str(path)


def base_scene(kind: Kind, area, folder: Path, duration: float = HORIZON):
    """The story's scene with its source at the guess (the area's centre, upright, at rest) and a
    placeholder target; relative file names resolve against ``folder``."""
    from dejaview.scene import (
        InferenceSettings,
        Pose,
        Scene,
        SceneObject,
        SimulationSettings,
        StartArea,
        Target,
    )

    src = SOURCES[kind.source]
    objects = [SceneObject(id="floor", shape="plane", fixed=True)]
    if kind.stand is not None:
        objects.append(SceneObject(id=kind.stand["mesh"], mesh=_rel(MESHES / f"{kind.stand['mesh']}.obj", folder),
                                   fixed=True))
    spheres = KNOBBLY if src["spheres"] is None else _rel(PACKINGS / f"{src['spheres']}.spheres", folder)
    centre = tuple(round((a + b) / 2, 6) for a, b in zip(*area))
    objects.append(SceneObject(id=kind.source, mesh=_rel(MESHES / f"{src['mesh']}.obj", folder), spheres=spheres,
                               mass=src["mass"], pose=Pose(centre)))
    return Scene(name=kind.name.replace("_", "-"), objects=tuple(objects),
                 simulation=SimulationSettings(dt=DT, duration=duration, friction=FRICTION,
                                               restitution=src["restitution"]),
                 inference=InferenceSettings(source=kind.source, targets=(Target((0.0, 0.0, 0.0)),),
                                             start_area=StartArea(tuple(area[0]), tuple(area[1]))),
                 base_dir=Path(folder))


def with_start(scene, start: dict):
    """The scene with its source starting at ``start`` (a truth dict: position, orientation,
    linear, angular)."""
    from dejaview.scene import Pose, Velocity

    src = scene.object(scene.inference.source)
    return scene.with_object(replace(src, pose=Pose(tuple(start["position"]), tuple(start["orientation"])),
                                     velocity=Velocity(tuple(start["linear"]), tuple(start["angular"]))))


def simulate(scene, start: dict, steps: int | None = None):
    """(world, trajectory of every step, source index): ``start`` rolled out on the native engine
    (``auto``) for ``steps`` (default: the scene's)."""
    import torch

    from dejaview.sim import World
    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import rollout

    true_scene = with_start(scene, start)
    world = World.from_scene(true_scene)
    with torch.no_grad():
        traj = rollout(world, initial_state(world, true_scene), steps=steps, engine="auto")
    return world, traj, world.body_index(scene.inference.source)


def mean_motion(world, traj, source: int, window: float = REST_WINDOW):
    """(speed (T,), spin (T,)) of the source: its mean speed (m/s, the centre of mass's
    displacement) and mean spin (rad/s, the rotation) over the ``window`` seconds before each
    record (from the first record for the first ones)."""
    import torch

    from dejaview.sim.rotation import geodesic_angle

    dt = traj.dt * float(traj.steps[1] - traj.steps[0])
    n = max(1, int(round(window / dt)))
    com = traj.states.position[:, 0, source]
    q = traj.states.orientation[:, 0, source]
    back = torch.clamp(torch.arange(len(com)) - n, min=0)
    span = (torch.arange(len(com)) - back).clamp(min=1).to(com.dtype) * dt
    speed = torch.linalg.vector_norm(com - com[back], dim=-1) / span
    spin = geodesic_angle(q, q[back]) / span
    return speed, spin


def rest_time(world, traj, source: int) -> float | None:
    """The first time from which the source stays at rest (module docstring) to the end of
    ``traj``: the end of its first resting window; None: moving at the end."""
    speed, spin = mean_motion(world, traj, source)
    still = ((speed < REST_SPEED) & (spin < REST_SPIN)).tolist()
    if not still[-1]:
        return None
    k = len(still) - 1
    while k > 0 and still[k - 1]:
        k -= 1
    return float(traj.steps[k]) * traj.dt


def story_duration(rest: float) -> float:
    """``rest`` plus ``REST_MARGIN``, rounded up to 0.1 s."""
    return round(math.ceil(round((rest + REST_MARGIN) * 10.0, 6)) / 10.0, 1)


@dataclass
class Story:
    """One drawn story: its scene (target set, duration set), the truth record and draws needed."""

    name: str
    kind: str
    scene: object
    truth: dict
    draws: int
    path: Path | None = None
    notes: dict = field(default_factory=dict)


def _rejection(kind: Kind, world, traj, source: int) -> str | None:
    """Why a simulated truth is not a story of ``kind`` (None: it is)."""
    origins = world.object_position(traj.states)[:, 0, source]  # (T, 3)
    if float(origins[:, :2].abs().max()) > ROOM_HALF:
        return "left the room"
    if float(origins[:, 2].min()) < -FLOOR_SINK:
        return "sank through the floor"
    if kind.leaves_top and float(origins[-1, 2]) > 0.3:
        return "stayed on the top"
    return None


def make_story(kind_name: str, rng, folder: Path, name: str | None = None) -> Story:
    """Draw one story of ``kind_name`` with ``rng`` (module docstring); relative file names of its
    scene resolve against ``folder`` (``write_story`` writes it there; the knobbly ball's packing
    must be there, ``write_knobbly``).

    Raises:
        RuntimeError: no draw in ``MAX_DRAWS`` made a story.
    """
    from dejaview.geometry.collision import SceneCollision
    from dejaview.inference.posterior import PosteriorSettings
    from dejaview.scene import Target
    from dejaview.scene.xml import normalize_quaternion

    kind = KINDS[kind_name]
    folder = Path(folder)
    if SOURCES[kind.source]["spheres"] is None and not (folder / KNOBBLY).is_file():
        write_knobbly(folder)
    collision = {}
    reasons: dict[str, int] = {}
    for draw in range(1, MAX_DRAWS + 1):
        area = draw_area(rng, kind)
        start = draw_start(rng, kind, area)
        scene = base_scene(kind, area, folder)
        key = kind.stand["mesh"] if kind.stand else None
        if key not in collision:
            collision[key] = SceneCollision(scene)
        hit, _, _ = collision[key].penetration(kind.source, np.asarray(start["position"]),
                                               np.asarray(start["orientation"]), margin=PosteriorSettings.feasibility_margin,
                                               decide_only=True)
        if bool(np.asarray(hit).reshape(-1)[0]):
            reasons["start interpenetrates"] = reasons.get("start interpenetrates", 0) + 1
            continue
        world, traj, source = simulate(scene, start)
        why = _rejection(kind, world, traj, source)
        rest = None
        if why is None:
            rest = rest_time(world, traj, source)
            if rest is None or rest > MAX_REST:
                why = "not at rest by %g s" % MAX_REST
        if why is not None:
            reasons[why] = reasons.get(why, 0) + 1
            continue
        duration = story_duration(rest)
        steps = int(round(duration / DT))
        end_pos = world.object_position(traj.states)[steps, 0, source].tolist()
        end_q = traj.states.orientation[steps, 0, source].tolist()
        target = Target(position=tuple(round(v, 9) for v in end_pos),
                        orientation=normalize_quaternion([round(v, 9) for v in end_q]))
        scene = replace(scene, simulation=replace(scene.simulation, duration=duration),
                        inference=replace(scene.inference, targets=(target,)))
        truth = {"source": kind.source, "kind": kind.name, "story": kind.story,
                 "initial_state": {"position": start["position"], "orientation": start["orientation"],
                                   "linear_velocity": start["linear"], "angular_velocity": start["angular"]},
                 "final_pose": {"position": end_pos, "orientation": end_q},
                 "rest_time": rest, "duration": duration,
                 "start_area": {"min": list(area[0]), "max": list(area[1])},
                 "draws": draw, "rejected": reasons}
        return Story(name=name or kind.name, kind=kind.name, scene=scene, truth=truth, draws=draw)
    raise RuntimeError(f"{kind_name}: no story in {MAX_DRAWS} draws ({reasons})")


def story_kinds(count: int, kinds=None) -> list[str]:
    """The kinds of ``count`` stories: one of each of ``kinds`` (default: every kind) in turn."""
    kinds = list(KINDS) if kinds is None else list(kinds)
    return [kinds[i % len(kinds)] for i in range(count)]


def make_stories(seed: int, count: int, folder: Path | str = "out/bench/stories", kinds=None) -> list[Story]:
    """``count`` stories of seed ``seed`` (story i of kind ``story_kinds(count, kinds)[i]``, drawn
    with ``numpy.random.default_rng([seed, i])``: a story does not depend on the others)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = story_kinds(count, kinds)
    bad = [k for k in names if k not in KINDS]
    if bad:
        raise ValueError(f"unknown kind {bad[0]!r}; known: {', '.join(KINDS)}")
    return [make_story(kind, np.random.default_rng([seed, i]), folder, name=f"s{seed}-{i:02d}-{kind}")
            for i, kind in enumerate(names)]


def scene_xml(story: Story) -> str:
    """The story's scene file: the source's resting pose as the target, a start area and no other
    inference setting (the ``<inference>`` element's ``loss``, ``evaluate`` and ``seed``, which
    the writer always writes, are dropped, so the reader's defaults apply)."""
    from lxml import etree

    root = etree.fromstring(story.scene.to_xml().encode("utf-8"))
    inference = root.find("inference")
    for attr in ("loss", "evaluate", "seed", "iterations", "optimizer", "gradient"):
        inference.attrib.pop(attr, None)
    root.addprevious(etree.Comment(f" {story.truth['story']} (bench/stories.py, {story.name}) "))
    text = etree.tostring(root.getroottree(), pretty_print=True, xml_declaration=True, encoding="UTF-8")
    return text.decode("utf-8")


def write_story(story: Story, folder: Path | str) -> Path:
    """Write ``<name>.xml`` and ``<name>.truth.json`` into ``folder`` (the story's folder: its
    relative file names resolve there); the scene path."""
    folder = Path(folder)
    path = folder / f"{story.name}.xml"
    path.write_text(scene_xml(story), encoding="utf-8")
    (folder / f"{story.name}.truth.json").write_text(json.dumps(story.truth, indent=2), encoding="utf-8")
    story.path = path
    return path
