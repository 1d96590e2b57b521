"""Cross-engine benchmark: answers that survive another engine's physics.

    dejaview bench crossengine                       # fidelity table, then every case
    dejaview bench crossengine --cases ball-bounce,box-tumble --no-warp
    python bench/crossengine.py --csv crossengine.csv

Three parts, printed as tables (docs/physics-fidelity.md has the measured ones):

1. **Physics fidelity** (``fidelity``): the same start simulated by DejaView
   (native engine, the scene's defaults) and by MuJoCo (the scene exported
   with ``dejaview.io.mjcf.export_mjcf``, whose ``contact_parameters`` map
   friction, restitution and contact stiffness; at ``MUJOCO_TIMESTEP``, a
   converged step), the distance between the
   two engines' centres of mass after 0.5, 1.0 and 1.5 s, for bounce, roll,
   slide, tumble and a box-box hit.
2. **Inference across engines** (``CASES``, >= 16): MuJoCo simulates a known
   start (balls and boxes, table and floor, sliding, bouncing, tumbling);
   DejaView gets only the end pose (``<target>``, ``evaluate="final"``), the start
   area, the source at the area's centre at rest (``start_guess``) and the cases'
   ``PRIOR``, and solves with ``dejaview.solve``'s defaults (``optimizer="auto"``), once as
   the scene is and once with ``<model-uncertainty friction restitution>``
   (``UNCERTAINTY``); MuJoCo, and Warp where it runs, re-simulate each
   answer. Success: the re-simulated end (object origin) within
   ``SUCCESS_TOL`` (3 cm) of MuJoCo's observation. Seconds per solve and the
   ratio with / without model uncertainty are printed too (not asserted).
   The floor cases' start areas are centred on the truth's x, y (a table
   case's is the table top); ``--area-offset DX DY`` (``offset_area``) moves
   them so that the guess is not the truth's position either. ``--random-cases N``
   (``random_cases``) solves N random tumbling boxes of the cases' kind, held out
   from every choice tuned on the cases.
3. **Random throws** (``throws``, ``--throws N``): the engines' gap on N boxes
   thrown at random, with controls that tell a model gap from chaos and from
   the steps: how typical the fidelity table's chosen rows are.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SUCCESS_TOL = 0.03
"""Metres: a re-simulated answer's end within this of the observation counts as solved."""
FIDELITY_TOL = 0.02
"""Metres: the fidelity table's bar at 1.0 s."""
FIDELITY_TIMES = (0.5, 1.0, 1.5)
MUJOCO_TIMESTEP = 5e-6
"""Seconds: MuJoCo's time step here, the reference's (docs/physics-fidelity.md, "MuJoCo's time
step", ``timestep_study``): within 2 mm of its run at 2 us on every fidelity row and every
inference case's true start but the box sliding off the table (1.7 cm at 1.0 s, 0.4 cm at 1.2 s),
which lands on its edge and tips on or falls back. At 50 us MuJoCo's end there was 65-78 cm from
its 2 us run, and with the pairs' friction at omega_0 it fell back at 50 and 10 us and tipped on at
the other steps (a start 1-10 mm/s faster or slower flipped it at 50 and 20 us, moved it by 1 cm
at 5 us); at the export's 0.5 ms it tipped the box over the table's edge twice as fast as a rigid
box."""
UNCERTAINTY = (0.2, 0.2)
"""Relative standard deviations (friction, restitution) of the runs with model uncertainty."""
TABLE_TOP = 0.7
BALL_R = 0.05
BOX = (0.2, 0.15, 0.1)


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


# ------------------------------------------------------------------ engines
def mujoco_run(scene, times, state: dict | None = None, timestep: float | None = None):
    """MuJoCo's object-frame origins and orientations of every movable object at ``times``, at
    ``timestep`` (default ``MUJOCO_TIMESTEP``).

    Returns:
        {t: (positions (N, 3), orientations (N, 4))}.
    """
    import mujoco

    from dejaview.io.mjcf import export_mjcf

    model = mujoco.MjModel.from_xml_string(export_mjcf(scene, state, timestep=timestep or MUJOCO_TIMESTEP))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    ids = [model.body(o.id).id for o in scene.movable]
    marks = {round(t / model.opt.timestep): t for t in times}
    out = {}
    for k in range(max(marks) + 1):
        if k in marks:
            out[marks[k]] = (data.xpos[ids].copy(), data.xquat[ids].copy())
        mujoco.mj_step(model, data)
    return out


def dejaview_run(scene, times):
    """DejaView's (native engine) object-frame origins and orientations at ``times``."""
    import torch

    from dejaview.sim import World, rollout
    from dejaview.sim.build import initial_state

    world = World.from_scene(scene)
    steps = round(max(times) / world.dt)
    with torch.no_grad():
        traj = rollout(world, initial_state(world, scene), steps=steps, engine="native")
    pos = world.object_position(_flat(traj.states))
    out = {}
    for t in times:
        k = round(t / world.dt)
        out[t] = (pos[k].numpy(), traj.states.orientation[k, 0].numpy())
    return out


def _flat(states):
    """States (T, 1, N, ...) as a batch (T, N, ...) for ``World.object_position``."""
    from dejaview.sim.state import State

    return State(*(t[:, 0] for t in states.tensors()))


def warp_end(scene):
    """Warp's (``dejaview.backends.warp``, its defaults) end origin of the source, or None
    where Warp cannot run here."""
    try:
        from dejaview.backends.warp import simulate_scene
    except Exception:  # the warp extra is not installed
        return None
    try:
        frames, traj = simulate_scene(scene)
    except Exception as exc:  # Warp cannot build or run its kernels here
        print(f"warp: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return None
    pos = frames.object_position(_flat(traj.states))[-1]
    return pos[frames.body_index(scene.inference.source)].numpy()


# ------------------------------------------------------------------ fidelity
FIDELITY = (
    ("bounce (ball dropped 0.5 m, e 0.3)", ball("ball", (1.0, 0, 0.5), (0.3, 0, 0)), 0.3),
    ("bounce high (ball dropped 0.5 m, e 0.7)", ball("ball", (1.0, 0, 0.5), (0.3, 0.1, 0)), 0.7),
    ("roll (ball rolling at 1 m/s)", ball("ball", (1.0, 0, BALL_R), (1.0, 0, 0), (0, 20.0, 0)), 0.3),
    ("slide to roll (ball launched without spin)", ball("ball", (1.0, 0, BALL_R), (1.5, 0.3, 0)), 0.3),
    ("ball rolls off the table", ball("ball", (-0.2, 0, TABLE_TOP + BALL_R), (1.2, 0, 0)), 0.3),
    ("slide (box at 2 m/s on the floor)", box("box", (1.0, 0, BOX[2] / 2), (2.0, 0, 0)), 0.3),
    ("slide and spin (box)", box("box", (1.0, 0, BOX[2] / 2), (1.5, 0.5, 0), (0, 0, 4.0)), 0.3),
    ("tumble (box dropped tilted, spinning)", box("box", (1.0, 0, 0.3), (0.8, 0, 0), (0, 4.0, 0),
                                                  about((0, 1, 0), 25)), 0.3),
    ("box lands on an edge (dropped tilted 35 deg)", box("box", (1.0, 0, 0.3), orientation=about((0, 1, 0), 35)),
     0.3),
    ("box dropped nearly flat (tilted 5 deg)", box("box", (1.0, 0, 0.26), orientation=about((0, 1, 0), 5)), 0.3),
    ("box thrown onto the floor (box-thrown)", box("box", (0.8, -0.4, 0.5), (1.5, 0.2, 0.5), (0, 2.0, 0)), 0.3),
    ("box bounces over corners (box-tumble-2)", box("box", (1.0, 0.6, 0.4), (0.3, -0.6, 0.5), (2.0, 1.0, 3.0),
                                                   about((1, 2, 0), 30)), 0.3),
    ("box slides off the table", box("box", (0.0, 0, TABLE_TOP + BOX[2] / 2), (3.0, 0, 0)), 0.3),
    ("box-box hit (sliding into a resting box)", box("box", (1.0, 0, BOX[2] / 2), (2.5, 0, 0))
     + box("box2", (1.5, 0, BOX[2] / 2)), 0.3),
    ("ball hits a resting box (ball-hits-box's start)", ball("ball", (0.8, 0, BALL_R), (2.0, 0, 0), (0, 40.0, 0))
     + box("box2", (1.3, 0, BOX[2] / 2)), 0.3),
    ("ball meets a box face 1 cm off centre", ball("ball", (0.8, 0.01, BALL_R), (2.0, 0, 0), (0, 40.0, 0))
     + box("box2", (1.3, 0, BOX[2] / 2)), 0.3),
)


def fidelity(print_fn=print, names=None, times=FIDELITY_TIMES) -> list[dict]:
    """The fidelity table: DejaView against MuJoCo from the same start (module docstring): the
    distance between the centres of mass and the angle between the orientations (the largest over
    the bodies) at ``times`` (s; the rows run to the last: a test reading 1.0 s stops there);
    a box's centre can agree while its turn does not."""
    rows = []
    print_fn(f"{'motion':<44} " + " ".join(f"{f'{t:g} s':>7}" for t in times) + " "
             + " ".join(f"{f'deg {t:g}':>8}" for t in times)
             + "  (cm between the centres, deg between the orientations; the largest over the bodies)")
    for name, objects, e in FIDELITY:
        if names and not any(n in name for n in names):
            continue
        scene = make_scene(scene_text(objects, max(times), restitution=e))
        a, b = dejaview_run(scene, times), mujoco_run(scene, times)
        gap = {t: float(np.linalg.norm(a[t][0] - b[t][0], axis=-1).max()) for t in times}
        turn = {t: max(angle_deg(qa, qb) for qa, qb in zip(np.asarray(a[t][1]).reshape(-1, 4), b[t][1]))
                for t in times}
        row = {"section": "fidelity", "motion": name,
               **{f"gap_{t:g}s_m": gap[t] for t in times},
               **{f"angle_{t:g}s_deg": turn[t] for t in times}}
        if 1.0 in gap:
            row["within_2cm_at_1s"] = gap[1.0] <= FIDELITY_TOL
        rows.append(row)
        print_fn(f"{name:<44} " + " ".join(f"{100 * gap[t]:>7.2f}" for t in times) + " "
                 + " ".join(f"{turn[t]:>8.1f}" for t in times)
                 + ("" if row.get("within_2cm_at_1s", True) else "  > 2 cm at 1.0 s"))
    return rows


TIMESTEP_STUDY = (5e-4, 1e-4, 5e-5, 2e-5, 1e-5, 5e-6)
"""MuJoCo steps compared with ``STUDY_REFERENCE`` in ``timestep_study``."""
STUDY_REFERENCE = 2e-6
SUBSTEP_STUDY = (2, 4, 8)
"""DejaView substeps per 2 ms step compared with ``SUBSTEP_REFERENCE`` (same contact stiffness)."""
SUBSTEP_REFERENCE = 16


def _dejaview_end(world, scene, t: float) -> np.ndarray:
    import torch

    from dejaview.sim import rollout
    from dejaview.sim.build import initial_state

    with torch.no_grad():
        traj = rollout(world, initial_state(world, scene), steps=round(t / world.dt), engine="native")
    return world.object_position(_flat(traj.states))[-1].numpy()


def timestep_study(print_fn=print, steps=TIMESTEP_STUDY, reference=STUDY_REFERENCE,
                   substeps=SUBSTEP_STUDY, cases: bool = True, names=None) -> list[dict]:
    """Are the engines converged at their steps? Per fidelity row (at 1.0 s) and, with ``cases``,
    per inference case's true start (at the case's duration, the observation), the end (cm, the
    largest over the bodies) of MuJoCo at each of ``steps`` against MuJoCo at ``reference``, and
    of DejaView at each of ``substeps`` against DejaView at ``SUBSTEP_REFERENCE`` substeps (the
    same contact stiffness): how ``MUJOCO_TIMESTEP`` was chosen, and how much of each row's gap
    is the steps' rather than the models' (docs/physics-fidelity.md, "MuJoCo's time step").
    ``names``: only the rows whose motion contains one of them.

    Returns:
        rows: ``motion`` (a fidelity row's name or "case <name>"), ``gap_<ms>ms_m`` per MuJoCo
        step, ``dv_gap_<k>_substeps_m`` per DejaView substep count.
    """
    from dejaview.sim import World

    runs = [(name, make_scene(scene_text(objects, 1.0, restitution=e)), 1.0) for name, objects, e in FIDELITY]
    if cases:
        runs += [(f"case {c.name}", case_scene(c), c.duration) for c in CASES]
    if names:
        runs = [r for r in runs if any(n in r[0] for n in names)]
    rows = []
    print_fn(f"{'motion':<44} " + " ".join(f"{'mj ' + format(1e3 * dt, 'g') + 'ms':>10}" for dt in steps)
             + " " + " ".join(f"{'dv ' + str(k) + ' sub':>9}" for k in substeps)
             + f"  (cm at 1.0 s or the case's end: MuJoCo from its {1e3 * reference:g} ms run, DejaView "
               f"from its {SUBSTEP_REFERENCE} substeps)")
    for name, scene, t in runs:
        ref = mujoco_run(scene, (t,), timestep=reference)[t][0]
        gaps = [float(np.linalg.norm(mujoco_run(scene, (t,), timestep=dt)[t][0] - ref, axis=-1).max())
                for dt in steps]
        dv = []
        if substeps:
            world = World.from_scene(scene)
            dv_ref = _dejaview_end(world.with_substeps(SUBSTEP_REFERENCE), scene, t)
            dv = [float(np.linalg.norm(_dejaview_end(world.with_substeps(k), scene, t) - dv_ref, axis=-1).max())
                  for k in substeps]
        rows.append({"section": "timestep", "motion": name,
                     **{f"gap_{1e3 * dt:g}ms_m": g for dt, g in zip(steps, gaps)},
                     **{f"dv_gap_{k}_substeps_m": g for k, g in zip(substeps, dv)}})
        print_fn(f"{name:<44} " + " ".join(f"{100 * g:>10.2f}" for g in gaps)
                 + " " + " ".join(f"{100 * g:>9.2f}" for g in dv))
    return rows


def check_seeds(seeds) -> tuple:
    """``seeds`` as a non-empty tuple of whole numbers >= 0 (the solves' and the throws' seeds).

    Raises:
        ValueError: one line naming the seeds.
    """
    seeds = tuple(seeds)
    if not seeds or any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in seeds):
        raise ValueError(f"seeds must be whole numbers >= 0, got {seeds!r}")
    return seeds


# ------------------------------------------------------------------ random throws
THROW_AREA = ((1.2, -0.5, 0.2), (2.0, 0.5, 0.5))
"""(min, max) start position of ``throws``' boxes: above the floor, clear of the table."""
THROW_SPEED = 0.8
"""m/s: standard deviation of each linear velocity component of a throw."""
THROW_SPIN = 3.0
"""rad/s: standard deviation of each angular velocity component of a throw."""
THROW_TIMES = (0.5, 1.0)
THROW_NUDGE = 0.001
"""m: the start offset (along x) of the throws' chaos control."""


def random_throw(rng) -> dict:
    """One box thrown onto the floor, as ``box``'s keyword arguments: orientation uniform, start
    uniform in ``THROW_AREA``, velocities normal (``THROW_SPEED``, ``THROW_SPIN``); numpy ``rng``."""
    q = rng.normal(size=4)
    lo, hi = (np.asarray(v) for v in THROW_AREA)
    return {"position": rng.uniform(lo, hi), "linear": rng.normal(size=3) * THROW_SPEED,
            "angular": rng.normal(size=3) * THROW_SPIN, "orientation": q / np.linalg.norm(q)}


def throws(print_fn=print, count: int = 40, seed: int = 0, times=THROW_TIMES) -> list[dict]:
    """How far the engines part on boxes in general, not on the fidelity table's chosen rows.

    ``count`` random throws (``random_throw``, seeded), each simulated by DejaView and MuJoCo as
    in ``fidelity``: the distance between the two centres (and the angle between the
    orientations) at ``times``, and at the last time three controls that tell a model gap from
    chaos and steps: MuJoCo at half its step (is it converged?), each engine from the start moved
    by ``THROW_NUDGE`` (how far a millimetre carries), and DejaView at four times its substeps
    (same stiffness; ``World.with_substeps``).

    Raises:
        ValueError: a seed that is not a whole number >= 0.
    Returns:
        rows (``section`` "throws"): ``gap_<t>s_m``, ``angle_<t>s_deg``, ``mujoco_half_step_m``,
        ``mujoco_nudged_m``, ``dejaview_nudged_m``, ``dejaview_4x_substeps_m``; then printed: the
        median and the share within ``SUCCESS_TOL`` of each.
    """
    from dejaview.sim import World

    check_seeds((seed,))
    rng = np.random.default_rng(seed)
    t_end = max(times)
    rows = []
    for i in range(int(count)):
        start = random_throw(rng)
        scene = make_scene(scene_text(box("box", **start), t_end))
        moved = make_scene(scene_text(box("box", **{**start, "position": start["position"]
                                                    + np.array([THROW_NUDGE, 0.0, 0.0])}), t_end))
        a, b = dejaview_run(scene, times), mujoco_run(scene, times)
        end = b[t_end][0][0]
        world = World.from_scene(scene)
        row = {"section": "throws", "throw": i,
               **{f"gap_{t:g}s_m": float(np.linalg.norm(a[t][0][0] - b[t][0][0])) for t in times},
               **{f"angle_{t:g}s_deg": angle_deg(a[t][1][0], b[t][1][0]) for t in times},
               "mujoco_half_step_m": float(np.linalg.norm(
                   mujoco_run(scene, (t_end,), timestep=MUJOCO_TIMESTEP / 2)[t_end][0][0] - end)),
               "mujoco_nudged_m": float(np.linalg.norm(mujoco_run(moved, (t_end,))[t_end][0][0] - end)),
               "dejaview_nudged_m": float(np.linalg.norm(dejaview_run(moved, (t_end,))[t_end][0][0]
                                                         - a[t_end][0][0])),
               "dejaview_4x_substeps_m": float(np.linalg.norm(
                   _dejaview_end(world.with_substeps(4 * world.substeps), scene, t_end)[0] - a[t_end][0][0]))}
        rows.append(row)
    keys = [k for k in rows[0] if k.endswith("_m")] if rows else []
    print_fn(f"{count} random box throws (seed {seed}): median cm, share within {100 * SUCCESS_TOL:g} cm")
    for k in keys:
        v = np.array([r[k] for r in rows])
        print_fn(f"  {k:<26} {100 * np.median(v):7.2f} cm  {np.mean(v <= SUCCESS_TOL):5.0%}")
    return rows


# ------------------------------------------------------------------ inference
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


def case_scene(case: Case, target=None, uncertainty=None, seed: int = 0, prior: bool = True):
    """The case's scene. With ``target`` (origin, orientation): the problem DejaView solves, the
    ``<inference>`` section (the search's ``seed``, ``PRIOR`` unless ``prior`` is False) and the
    source at ``start_guess`` instead of the truth; without it, the truth."""
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


def solve_case(case: Case, uncertainty, warp: bool, print_fn=print, seed: int = 0, prior: bool = True) -> dict:
    """Observe the case in MuJoCo, solve (the search's ``seed``; ``PRIOR`` unless ``prior`` is False),
    re-simulate the answer in MuJoCo (and Warp)."""
    import dejaview

    truth = case_scene(case)
    end = mujoco_run(truth, (case.duration,))[case.duration]
    target = (end[0][0], end[1][0])
    scene = case_scene(case, target, uncertainty, seed, prior)
    t0 = time.perf_counter()
    result = dejaview.solve(scene)
    seconds = time.perf_counter() - t0
    initial = result.initial_state
    state = {"source": "source", "initial_state": initial}
    back = mujoco_run(scene, (case.duration,), state)[case.duration]
    mj_err = float(np.linalg.norm(back[0][0] - target[0]))
    own = float(np.linalg.norm(_own_end(result) - target[0]))
    search = result.settings.get("search", {})
    row = {"section": "inference", "case": case.name, "seed": int(seed),
           "model_uncertainty": "off" if uncertainty is None else f"{uncertainty[0]:g} {uncertainty[1]:g}",
           "prior": PRIOR["ball" if case.ball else "box"] if prior else "flat",
           "seconds": seconds, "rollouts": search.get("rollouts"), "jacobians": search.get("jacobians"),
           "own_end_error_m": own, "mujoco_end_error_m": mj_err,
           "mujoco_angle_error_deg": angle_deg(back[1][0], target[1]),
           "success": mj_err <= SUCCESS_TOL,
           "start_error_m": float(np.linalg.norm(np.asarray(initial["position"]) - _truth_start(truth)))}
    if warp:
        w = warp_end(with_start(scene, initial))
        row["warp_end_error_m"] = None if w is None else float(np.linalg.norm(w - target[0]))
        row["warp_success"] = None if w is None else row["warp_end_error_m"] <= SUCCESS_TOL
    print_fn(f"{case.name:<22} {seed:>4} {row['model_uncertainty']:<8} {seconds:>7.1f} {1000 * own:>8.1f} "
             f"{1000 * mj_err:>8.1f} {'yes' if row['success'] else 'no':<4}"
             + ("" if row.get("warp_end_error_m") is None else f" {1000 * row['warp_end_error_m']:>8.1f}"))
    return row


def _own_end(result) -> np.ndarray:
    """DejaView's end (object origin) of the answer: the last record of the solve's trajectory."""
    problem = result.problem
    inner = problem
    src = inner.source
    pos = inner.world.object_position(_flat(result.trajectory.states))
    return pos[-1, src].numpy()


def _truth_start(scene) -> np.ndarray:
    return np.asarray(scene.object("source").pose.position)


def run(print_fn=print, cases=None, uncertainty=UNCERTAINTY, warp: bool = True,
        with_fidelity: bool = True, baseline: bool = True, seeds=(0,), prior: bool = True,
        area_offset=(0.0, 0.0), extra_cases=(), perturb: int | None = None) -> list[dict]:
    """Fidelity table and the inference cases with and without model uncertainty (module docstring).

    Args:
        cases: case names (default all of ``CASES``, or none where ``extra_cases`` are given).
        uncertainty: (friction, restitution) relative standard deviations of the runs with it.
        warp: also re-simulate the answers in Warp (where it is installed).
        with_fidelity: print the fidelity table first.
        baseline: also solve without model uncertainty.
        seeds: the search's seeds (``<inference seed>``), one solve each per case and setting
            (the same observation): several cases land within a few mm of the 3 cm bar, and
            which side they land on changes with the search's path, so one seed's count is a
            noisy estimate of the rate.
        prior: the solves' ``<prior>`` is ``PRIOR`` (False: flat within the backend's bounds).
        area_offset: (dx, dy) m, the floor cases' start areas moved off the truth (``offset_area``).
        extra_cases: more ``Case``s solved after the chosen ones (``random_cases``).
        perturb: a seed: the chosen cases' truths perturbed by it (``perturbed_cases``) instead.
    Returns:
        rows (dicts) of both parts.
    """
    from dejaview.cli.bench import load_average

    seeds = check_seeds(seeds)
    chosen = [c for c in CASES if (not cases and not extra_cases) or c.name in (cases or ())]
    if perturb is not None:
        chosen = list(perturbed_cases(perturb, chosen))
    chosen = [offset_area(c, area_offset) for c in chosen]
    chosen += [offset_area(c, area_offset) for c in extra_cases]
    unknown = set(cases or ()) - {c.name for c in CASES}
    if unknown:
        raise ValueError(f"unknown case(s) {', '.join(sorted(unknown))}; cases: "
                         f"{', '.join(c.name for c in CASES)}")
    rows = []
    print_fn(f"# cross-engine benchmark ({load_average()})")
    if with_fidelity:
        print_fn("## fidelity: DejaView vs MuJoCo from the same start")
        rows += fidelity(print_fn)
    settings = ([None] if baseline else []) + [tuple(uncertainty)]
    print_fn(f"## inference: MuJoCo observes, DejaView solves, MuJoCo{' and Warp' if warp else ''} "
             f"re-simulate (success: within {100 * SUCCESS_TOL:g} cm)"
             + (f"; the floor cases' start areas moved by {area_offset[0]:g} {area_offset[1]:g} m off the truth"
                if any(area_offset) else ""))
    print_fn(f"{'case':<22} {'seed':>4} {'model-u':<8} {'seconds':>7} {'own mm':>8} {'mujoco mm':>8} ok  "
             + ("warp mm" if warp else ""))
    for case in chosen:
        for u in settings:
            for seed in seeds:
                rows.append({**solve_case(case, u, warp, print_fn, seed, prior),
                             "area_offset": f"{area_offset[0]:g} {area_offset[1]:g}"})
    summary(rows, print_fn)
    return rows


def summary(rows, print_fn=print) -> None:
    inf = [r for r in rows if r["section"] == "inference"]
    groups = {}
    for r in inf:
        groups.setdefault(r["model_uncertainty"], []).append(r)
    secs = {}
    for key, rs in groups.items():
        ok = sum(r["success"] for r in rs)
        secs[key] = sum(r["seconds"] for r in rs) / len(rs)
        line = (f"model uncertainty {key}: MuJoCo {ok}/{len(rs)} within {100 * SUCCESS_TOL:g} cm "
                f"({100 * ok / len(rs):.0f} %), mean {secs[key]:.1f} s per solve")
        w = [r for r in rs if r.get("warp_success") is not None]
        if w:
            line += f"; Warp {sum(r['warp_success'] for r in w)}/{len(w)}"
        print_fn(line)
        seeds = sorted({r.get("seed", 0) for r in rs})
        if len(seeds) > 1:
            per_case = {}
            for r in rs:
                per_case.setdefault(r["case"], []).append(r["success"])
            print_fn(f"  over {len(seeds)} seeds, cases solved by every seed: "
                     f"{sum(all(v) for v in per_case.values())}/{len(per_case)}; by some: "
                     f"{sum(any(v) for v in per_case.values())}/{len(per_case)}")
    if "off" in secs and len(secs) > 1:
        for key in secs:
            if key != "off":
                pairs = [(a, b) for a in groups["off"] for b in groups[key]
                         if (a["case"], a.get("seed")) == (b["case"], b.get("seed"))]
                ratio = np.median([b["seconds"] / a["seconds"] for a, b in pairs])
                print_fn(f"cost with model uncertainty {key}: mean {secs[key] / secs['off']:.2f}x, "
                         f"median per case {ratio:.2f}x the solve without it")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    parser.add_argument("--no-warp", action="store_true")
    parser.add_argument("--no-fidelity", action="store_true")
    parser.add_argument("--csv", type=Path, default=None)
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--seeds", default="0", help="comma-separated search seeds, one solve each per case")
    parser.add_argument("--flat-prior", action="store_true", help="solve without the cases' PRIOR")
    parser.add_argument("--area-offset", type=float, nargs=2, default=(0.0, 0.0), metavar=("DX", "DY"),
                        help="move the floor cases' start areas off the truth by DX DY m (offset_area)")
    parser.add_argument("--timestep-study", action="store_true", help="only MuJoCo's step convergence")
    parser.add_argument("--throws", type=int, default=0, metavar="N",
                        help="only the engines' gap on N random box throws (throws; seeded by --seeds' first)")
    parser.add_argument("--random-cases", type=int, default=0, metavar="N",
                        help="N random tumbling boxes (random_cases), instead of the cases unless --cases names some")
    parser.add_argument("--random-seed", type=int, default=0, help="the seed of --random-cases' draw")
    parser.add_argument("--perturbed-seed", type=int, default=None, metavar="S",
                        help="the cases' truths perturbed by seed S (perturbed_cases) instead of the cases")
    args = parser.parse_args(argv)
    if args.timestep_study:
        rows = timestep_study()
    elif args.throws:
        rows = throws(count=args.throws, seed=int(args.seeds.split(",")[0]))
    else:
        rows = run(cases=tuple(c for c in args.cases.split(",") if c), warp=not args.no_warp,
                   with_fidelity=not args.no_fidelity, baseline=not args.no_baseline,
                   seeds=tuple(int(v) for v in args.seeds.split(",") if v), prior=not args.flat_prior,
                   area_offset=tuple(args.area_offset),
                   extra_cases=random_cases(args.random_cases, args.random_seed), perturb=args.perturbed_seed)
    if args.csv is not None:
        from dejaview.cli.bench import write_rows_csv

        write_rows_csv(rows, args.csv)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
