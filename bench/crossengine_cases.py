"""The cross-engine bench's problems: the scenes, the cases, their held-out variants and worlds.

``crossengine.py`` (the bench and its command line) has the overview. Here: the scene every case
shares (a table on a floor, ``scene_text``), the ``CASES`` (balls and boxes on the table or the
floor), the variants nothing was tuned on (``random_cases``, ``perturbed_cases``), the problem
DejaView is given (``case_scene``), each case's kind (``kind``) and the mismatched world an
observing engine may simulate instead of the scene's (``mismatch``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

SUCCESS_TOL = 0.03
"""Metres: a re-simulated answer's end within this of the observation counts as solved."""
TABLE_TOP = 0.7
BALL_R = 0.05
BOX = (0.2, 0.15, 0.1)
THROW_SPEED = 0.8
"""m/s: standard deviation of each linear velocity component of a throw."""
THROW_SPIN = 3.0
"""rad/s: standard deviation of each angular velocity component of a throw."""


def _v(values) -> str:
    return " ".join(f"{float(x):.9g}" for x in values)


def ball(oid: str, position, linear=(0, 0, 0), angular=(0, 0, 0)) -> str:
    """A solid ball (5 cm, 0.4 kg)."""
    return (f'<object id="{oid}" shape="sphere" radius="{BALL_R}" mass="0.4"><pose position="{_v(position)}" '
            f'orientation="1 0 0 0"/><velocity linear="{_v(linear)}" angular="{_v(angular)}"/></object>')


def box(oid: str, position, linear=(0, 0, 0), angular=(0, 0, 0), orientation=(1, 0, 0, 0)) -> str:
    """A solid box (0.2 x 0.15 x 0.1 m, 1 kg)."""
    return (f'<object id="{oid}" shape="box" size="{_v(BOX)}" mass="1.0"><pose position="{_v(position)}" '
            f'orientation="{_v(orientation)}"/><velocity linear="{_v(linear)}" angular="{_v(angular)}"/>'
            f'</object>')


def about(axis, degrees: float) -> tuple:
    """Quaternion (w x y z) of a rotation by ``degrees`` about ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    h = math.radians(degrees) / 2
    return (math.cos(h), *(math.sin(h) * a))


def scene_text(objects: str, duration: float, restitution: float = 0.3, friction: float = 0.5,
               inference: str = "") -> str:
    """A scene: floor, a table (0.8 x 0.6 m, top at 0.7 m, centred at the origin), the objects."""
    return f"""<scene version="1" name="crossengine" gravity="0 0 -9.81">
  <simulation dt="0.002" duration="{duration}" friction="{friction}" restitution="{restitution}"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
  <object id="table" shape="box" size="0.8 0.6 {TABLE_TOP}" fixed="true">
    <pose position="0 0 {TABLE_TOP / 2}" orientation="1 0 0 0"/></object>
  {objects}
  {inference}
</scene>"""


def make_scene(text: str):
    from dejaview.scene import Scene

    return Scene.from_string(text, base_dir=ROOT)


def check_seeds(seeds) -> tuple:
    """``seeds`` as a non-empty tuple of whole numbers >= 0 (the solves' and the throws' seeds).

    Raises:
        ValueError: one line naming the seeds.
    """
    seeds = tuple(seeds)
    if not seeds or any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in seeds):
        raise ValueError(f"seeds must be whole numbers >= 0, got {seeds!r}")
    return seeds


@dataclass(frozen=True)
class Case:
    """One inference problem: the truth (objects XML, the source first), what is free, where.

    Attributes:
        name: case id.
        objects: objects XML; the source is the object called ``source``.
        area: (min (3,), max (3,)) start area of the source.
        orientation: whether the start orientation is free (else the truth's is given).
        duration: seconds MuJoCo simulates before the end is observed.
        restitution: the scene's.
    """

    name: str
    objects: str
    area: tuple
    orientation: bool = False
    duration: float = 1.2
    restitution: float = 0.3

    @property
    def ball(self) -> bool:
        """Whether the source (the first object) is a ball."""
        return 'shape="sphere"' in self.objects.split("</object>")[0]


TABLE_AREA = ((-0.35, -0.25), (0.35, 0.25))
"""(min, max) x, y of the table cases' start area: the table top, 5 cm in from its edges."""


def _on_table(z):
    return TABLE_TOP + z


def _floor_area(x, y, z0, z1) -> tuple:
    """A floor case's start area: 0.6 x 0.6 m centred on (x, y), heights z0..z1."""
    return ((x - 0.3, y - 0.3, z0), (x + 0.3, y + 0.3, z1))


def _cases() -> tuple[Case, ...]:
    zb, zx = _on_table(BALL_R), _on_table(BOX[2] / 2)
    tab = lambda z: ((*TABLE_AREA[0], z), (*TABLE_AREA[1], z))  # noqa: E731
    floor = _floor_area
    tilt = about((1, 2, 0), 30)
    return (
        Case("ball-off-table", ball("source", (-0.2, 0.05, zb), (1.2, 0.1, 0)), tab(zb)),
        Case("ball-off-table-2", ball("source", (0.0, -0.1, zb), (0.9, -0.4, 0), (4, 2, 0)), tab(zb)),
        Case("ball-off-table-side", ball("source", (0.1, 0.0, zb), (0.1, 1.1, 0)), tab(zb), duration=1.0),
        Case("ball-on-table", ball("source", (-0.25, -0.1, zb), (0.6, 0.3, 0)), tab(zb), duration=0.8),
        Case("ball-slide-floor", ball("source", (1.0, 0.0, BALL_R), (1.5, 0.2, 0)),
             floor(1.0, 0.0, BALL_R, BALL_R), duration=1.0),
        Case("ball-roll-floor", ball("source", (1.0, 0.5, BALL_R), (-0.8, 0.6, 0), (-12, -16, 0)),
             floor(1.0, 0.5, BALL_R, BALL_R), duration=1.0),
        Case("ball-bounce", ball("source", (1.0, 0.5, 0.4), (1.0, 0.0, 1.0)), floor(1.0, 0.5, 0.3, 0.5),
             restitution=0.5),
        Case("ball-bounce-2", ball("source", (0.8, -0.6, 0.6), (0.5, 0.5, 0)), floor(0.8, -0.6, 0.5, 0.7),
             restitution=0.6),
        Case("ball-bounce-table", ball("source", (-0.2, 0.0, 1.0), (0.8, 0.2, 0)), tab(1.0), restitution=0.5),
        Case("box-slide-floor", box("source", (1.0, 0.0, BOX[2] / 2), (2.0, 0, 0)),
             floor(1.0, 0.0, BOX[2] / 2, BOX[2] / 2), duration=1.0),
        Case("box-slide-spin-floor", box("source", (1.0, -0.5, BOX[2] / 2), (1.5, 0.5, 0), (0, 0, 4.0)),
             floor(1.0, -0.5, BOX[2] / 2, BOX[2] / 2), duration=1.0),
        Case("box-slide-table", box("source", (-0.2, 0.0, zx), (1.5, 0.2, 0)), tab(zx), duration=0.8),
        Case("box-off-table", box("source", (0.0, 0.0, zx), (3.0, 0.0, 0)), tab(zx)),
        Case("box-tumble", box("source", (1.0, 0.0, 0.3), (0.8, 0, 0), (0, 4.0, 0), about((0, 1, 0), 25)),
             floor(1.0, 0.0, 0.2, 0.4), orientation=True),
        Case("box-tumble-2", box("source", (1.0, 0.6, 0.4), (0.3, -0.6, 0.5), (2.0, 1.0, 3.0), tilt),
             floor(1.0, 0.6, 0.3, 0.5), orientation=True),
        Case("box-thrown", box("source", (0.8, -0.4, 0.5), (1.5, 0.2, 0.5), (0, 2.0, 0)),
             floor(0.8, -0.4, 0.4, 0.6), orientation=True),
        Case("box-hits-box", box("source", (1.0, 0.0, BOX[2] / 2), (2.5, 0, 0))
             + box("other", (1.5, 0.0, BOX[2] / 2)),
             floor(1.0, 0.0, BOX[2] / 2, BOX[2] / 2), duration=1.0),
        Case("ball-hits-box", ball("source", (0.8, 0.0, BALL_R), (2.0, 0.0, 0), (0, 40.0, 0))
             + box("other", (1.3, 0.0, BOX[2] / 2)), floor(0.8, 0.0, BALL_R, BALL_R), duration=1.0),
    )


CASES = _cases()


def _compose(a, b) -> list:
    """The rotation ``a`` after ``b``: (4,) quaternions (w x y z), their product as a list."""
    import torch

    from dejaview.sim.rotation import quat_multiply

    return quat_multiply(torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)).tolist()


def _on_table_top(lo, hi) -> bool:
    """Whether a start area ((3,) min and max) spans the table top's x, y (``TABLE_AREA``): a table case's."""
    return bool(np.allclose((np.asarray(lo)[:2], np.asarray(hi)[:2]), TABLE_AREA))


RANDOM_AREA = ((1.0, -0.6, 0.3), (1.8, 0.6, 0.5))
"""(min, max) true start of ``random_cases``' boxes: above the floor, clear of the table."""
RANDOM_TILT = 40.0
"""deg: ``random_cases``' boxes start tilted up to this much (about a random horizontal axis)."""


def random_cases(count: int, seed: int = 0) -> tuple[Case, ...]:
    """``count`` tumbling boxes of the kind of box-tumble, box-tumble-2 and box-thrown that no
    one tuned anything for (``--random-cases``): the start uniform in ``RANDOM_AREA``, any
    heading, tilted about a random horizontal axis by ``RANDOM_TILT`` sqrt(u) (u uniform: the tilt
    vector uniform over a disc), velocities normal (``THROW_SPEED``,
    ``THROW_SPIN``: within the cases' ``PRIOR``), the orientation free, the area the floor cases'
    around the truth (0.2 m of height), observed at 1.2 s. Named ``box-random-<seed>-<i>``;
    ``seed`` seeds numpy's generator, so the same seed gives the same cases.

    Raises:
        ValueError: a count or seed that is not a whole number >= 0.
    """
    if int(count) != count or count < 0:
        raise ValueError(f"random cases: {count!r} is not a whole number >= 0")
    check_seeds((seed,))
    rng = np.random.default_rng(seed)
    out = []
    for i in range(int(count)):
        position = rng.uniform(*(np.asarray(v) for v in RANDOM_AREA))
        axis = rng.normal(size=2)
        tilt = about((axis[0], axis[1], 0.0), RANDOM_TILT * math.sqrt(rng.uniform()))
        heading = about((0.0, 0.0, 1.0), rng.uniform(0.0, 360.0))
        orientation = _compose(tilt, heading)
        linear, angular = rng.normal(size=3) * THROW_SPEED, rng.normal(size=3) * THROW_SPIN
        x, y, z = position
        out.append(Case(f"box-random-{seed}-{i}", box("source", position, linear, angular, orientation),
                        _floor_area(x, y, z - 0.1, z + 0.1), orientation=True))
    return tuple(out)


PERTURB_SHIFT = 0.05
"""m: ``perturbed_cases`` moves a true start by up to this in x and y (uniform), and in z where the
start height is free (the start area's heights are a range)."""
PERTURB_SCALE = 0.2
"""``perturbed_cases`` scales each velocity component by a factor uniform in 1 -/+ this (a zero stays
zero: a slide stays a slide, a head-on hit head-on)."""
PERTURB_TURN = 15.0
"""deg: ``perturbed_cases`` turns a free start orientation about a random axis, and a given one (a
box flat on a surface) about the vertical, by up to this."""


def perturb_case(case: Case, rng) -> Case:
    """``case`` with its true start moved, its velocity scaled and its orientation turned by draws
    from ``rng`` (``PERTURB_SHIFT``, ``PERTURB_SCALE``, ``PERTURB_TURN``); the rest of the scene, what
    is free and the observation time are the case's. A floor case's start area (centred on the
    truth) moves with the start; a table case's (the table top) stays and the start is kept on it.

    Raises:
        ValueError: the moved start is not clear of the floor.
    """
    import torch

    from dejaview.sim.rotation import quat_to_matrix

    source = case_scene(case).object("source")
    p = np.asarray(source.pose.position, dtype=np.float64)
    lo, hi = (np.asarray(v, dtype=np.float64) for v in case.area)
    free_z = hi[2] > lo[2]
    d = rng.uniform(-PERTURB_SHIFT, PERTURB_SHIFT, 3)
    d[2] = d[2] if free_z else 0.0
    q = p + d
    if _on_table_top(lo, hi):
        q[:2] = np.clip(q[:2], lo[:2], hi[:2])
    else:
        lo, hi = lo + (q - p), hi + (q - p)
    linear = np.asarray(source.velocity.linear) * rng.uniform(1 - PERTURB_SCALE, 1 + PERTURB_SCALE, 3)
    angular = np.asarray(source.velocity.angular) * rng.uniform(1 - PERTURB_SCALE, 1 + PERTURB_SCALE, 3)
    axis = rng.normal(size=3) if case.orientation else np.array([0.0, 0.0, 1.0])
    turn = about(axis, rng.uniform(-PERTURB_TURN, PERTURB_TURN))
    orientation = _compose(turn, source.pose.orientation)
    rest = case.objects.split("</object>", 1)[1]
    moved = (ball("source", q, linear, angular) if case.ball
             else box("source", q, linear, angular, orientation)) + rest
    if case.ball:
        bottom = q[2] - BALL_R
    else:  # the box's half extent along world z: its rotation's last row (world z in body axes)
        row = quat_to_matrix(torch.tensor(orientation, dtype=torch.float64))[2].numpy()
        bottom = q[2] - float(np.abs(row) @ np.asarray(BOX)) / 2
    if bottom < -1e-9:
        raise ValueError(f"perturbed case {case.name}: the source's start sinks {-bottom:.3f} m into the floor")
    return replace(case, objects=moved, area=(tuple(lo.tolist()), tuple(hi.tolist())))


def perturbed_cases(seed: int, cases=None) -> tuple[Case, ...]:
    """Every case of ``cases`` (default ``CASES``) perturbed (``perturb_case``) by a numpy generator
    seeded with ``seed``, named ``<case>-p<seed>``: cases of the bench's kinds (a ball rolling off the
    table, a box tumbling, ...) whose truths no one tuned anything for (``--perturbed-seed``). Each
    case draws from its own stream (``seed`` and its index in ``CASES``), so a case's perturbation does
    not depend on which others are chosen.

    Raises:
        ValueError: a seed that is not a whole number >= 0.
    """
    check_seeds((seed,))
    index = {c.name: i for i, c in enumerate(CASES)}
    out = []
    for case in (CASES if cases is None else cases):
        rng = np.random.default_rng((int(seed), index.get(case.name, len(index))))
        out.append(replace(perturb_case(case, rng), name=f"{case.name}-p{int(seed)}"))
    return tuple(out)


PRIOR = {"box": 'speed="2" spin="5"', "ball": 'speed="2"'}
"""``<prior>`` attributes of the cases' solves, by the source's shape: what is believed about a
start before looking at its end. The objects here are pushed, dropped or thrown by hand: each
velocity component within a few m/s (standard deviation 2 m/s; the truths' largest is 3 m/s), a
box's spin within a few turns a second (5 rad/s; the truths' 0-4). A ball's spin is left flat: a
ball rolling at 2 m/s spins at 40 rad/s. Not the orientation (``tilt``): it would be centred on the
guess's."""


def start_guess(case: Case, given_orientation) -> dict:
    """The source's start as the solve is given it (``initial_state`` terms): the start area's centre,
    at rest, upright where the orientation is free (``given_orientation``, (4,) w x y z, the truth's,
    where it is not). Nothing of the truth's position or velocity: the scene's own start seeds the
    search."""
    lo, hi = (np.asarray(v, dtype=np.float64) for v in case.area)
    return {"position": ((lo + hi) / 2).tolist(),
            "orientation": [1.0, 0.0, 0.0, 0.0] if case.orientation else list(given_orientation),
            "linear_velocity": [0.0, 0.0, 0.0], "angular_velocity": [0.0, 0.0, 0.0]}


def offset_area(case: Case, offset=(0.0, 0.0)) -> Case:
    """``case`` with its start area moved by ``offset`` ((dx, dy), m) where the area is centred on the
    truth's x, y (the floor cases), so that the start guess (the area's centre) is not the truth's
    position either. A table case's area is the table top (``TABLE_AREA``) and stays (box-off-table's
    truth starts at its centre).

    Raises:
        ValueError: the moved area no longer holds the truth's start.
    """
    dx, dy = (float(v) for v in offset)
    lo, hi = (np.asarray(v, dtype=np.float64) for v in case.area)
    truth = _truth_start(case_scene(case))
    if (dx == 0 and dy == 0) or _on_table_top(lo, hi) \
            or not np.allclose((lo[:2] + hi[:2]) / 2, truth[:2]):
        return case
    d = np.array([dx, dy, 0.0])
    lo, hi = lo + d, hi + d
    if np.any(truth < lo - 1e-12) or np.any(truth > hi + 1e-12):
        raise ValueError(f"area offset {dx:g} {dy:g} m moves case {case.name}'s start area off its true start "
                         f"({_v(truth[:2])}): at most half the area's width ({_v((hi - lo)[:2] / 2)} m)")
    return replace(case, area=(tuple(lo.tolist()), tuple(hi.tolist())))


def case_scene(case: Case, target=None, uncertainty=None, seed: int = 0, prior: bool = True, extra: str = ""):
    """The case's scene. With ``target`` (origin, orientation): the problem DejaView solves, the
    ``<inference>`` section (the search's ``seed``, ``PRIOR`` unless ``prior`` is False, ``uncertainty``'s
    ``<model-uncertainty>``, then ``extra``: XML as written, e.g. a ``<physics-prior>``) and the source
    at ``start_guess`` instead of the truth; without it, the truth."""
    if target is None:
        return make_scene(scene_text(case.objects, case.duration, restitution=case.restitution))
    lo, hi = case.area
    mu = ("" if uncertainty is None else
          f'<model-uncertainty friction="{uncertainty[0]}" restitution="{uncertainty[1]}"/>')
    belief = f"<prior {PRIOR['ball' if case.ball else 'box']}/>" if prior else ""
    inference = f"""<inference source="source" loss="{'position' if case.ball else 'pose'}" evaluate="final" seed="{int(seed)}">
    <target position="{_v(target[0])}" orientation="{_v(target[1])}" moving="true"/>
    <optimize position="true" orientation="{str(case.orientation).lower()}" linear-velocity="true" angular-velocity="true"/>
    <start-area min="{_v(lo)}" max="{_v(hi)}"/>
    {belief}
    {mu}
    {extra}
  </inference>"""
    scene = make_scene(scene_text(case.objects, case.duration, restitution=case.restitution, inference=inference))
    return with_start(scene, start_guess(case, scene.object("source").pose.orientation))


def with_start(scene, initial: dict):
    """``scene`` with the source's pose and velocity replaced by a solve's ``initial_state``."""
    from dejaview.scene.model import Pose, Velocity

    objs = []
    for o in scene.objects:
        if o.id == scene.inference.source:
            o = replace(o, pose=Pose(tuple(initial["position"]), tuple(initial["orientation"])),
                        velocity=Velocity(tuple(initial["linear_velocity"]), tuple(initial["angular_velocity"])))
        objs.append(o)
    return replace(scene, objects=tuple(objs))


def angle_deg(q1, q2) -> float:
    d = abs(float(np.dot(np.asarray(q1) / np.linalg.norm(q1), np.asarray(q2) / np.linalg.norm(q2))))
    return math.degrees(2 * math.acos(min(1.0, d)))


def _truth_start(scene) -> np.ndarray:
    return np.asarray(scene.object("source").pose.position)


HELD_OUT_SEED = 100
"""``perturbed_cases``' and ``mismatch``'s seeds from this one up are held out: run them to check
a change, never to make one (seeds below it are the tuning set: the docs' numbers at 0-5)."""


def held_out(seed) -> bool:
    """Whether a perturbation or mismatch ``seed`` (None: the cases themselves, tuned on) is held out."""
    return seed is not None and int(seed) >= HELD_OUT_SEED


MOTIONS = (("hit", ("hits-box",)), ("tumble", ("tumble", "thrown", "random")), ("bounce", ("bounce",)),
           ("off table", ("off-table",)), ("slide", ("slide",)), ("roll", ("roll", "on-table")))
"""A case's motion, by the first of these whose words its name holds."""


def kind(case: Case) -> str:
    """The case's kind for the per-kind counts: its source's shape and its motion (``MOTIONS``),
    e.g. "ball bounce", "box tumble"; the perturbed and random variants keep their case's."""
    motion = next((m for m, words in MOTIONS if any(w in case.name for w in words)), "other")
    return f"{'ball' if case.ball else 'box'} {motion}"


MISMATCH_FRICTION = (0.7, 1.4)
"""The mismatched world's friction: the scene's times a factor uniform in this range."""
MISMATCH_RESTITUTION = (0.0, 0.3)
"""The mismatched world's restitution: uniform in this range, whatever the scene says (a real
table's: wood, laminate, a floor)."""


def mismatch(case: Case, seed: int) -> tuple[float, float]:
    """The world an observing engine simulates for ``case`` in the mismatched mode: (friction factor,
    restitution), drawn from the case's own stream (``seed`` and its index in ``CASES``, as
    ``perturbed_cases``), so a case's world does not depend on which others are chosen."""
    check_seeds((seed,))
    index = {c.name: i for i, c in enumerate(CASES)}
    base = case.name.rsplit("-p", 1)[0] if case.name not in index else case.name
    rng = np.random.default_rng((int(seed), 1, index.get(base, len(index))))
    return float(rng.uniform(*MISMATCH_FRICTION)), float(rng.uniform(*MISMATCH_RESTITUTION))


def in_world(scene, world: tuple[float, float] | None):
    """``scene`` with its material replaced by ``world`` ((friction factor, restitution), from
    ``mismatch``; None: the scene as it is): every default and per-object friction scaled, every
    restitution set. What the observing engine simulates; DejaView solves the scene as written."""
    if world is None:
        return scene
    factor, e = world
    sim = scene.simulation
    objects = tuple(replace(o, friction=None if o.friction is None else o.friction * factor,
                            restitution=None if o.restitution is None else e) for o in scene.objects)
    return replace(scene, simulation=replace(sim, friction=sim.friction * factor, restitution=e), objects=objects)
