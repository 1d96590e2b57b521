"""The cross-engine bench's physics checks: the same start in DejaView and in the observing engines.

``fidelity``: the fidelity table (bounce, roll, slide, tumble, box-box hit; the distance between
DejaView's and each engine's centres after 0.5, 1.0 and 1.5 s, and between the two engines').
``timestep_study``: whether an engine and DejaView are converged at their steps. ``throws``: the
engines' gap on random box throws, with controls for chaos and steps.
"""

from __future__ import annotations

import numpy as np

from dejaview.cli.bench import bench_module

_cases, _engines = bench_module("crossengine_cases"), bench_module("crossengine_engines")
BALL_R, BOX, SUCCESS_TOL, TABLE_TOP = _cases.BALL_R, _cases.BOX, _cases.SUCCESS_TOL, _cases.TABLE_TOP
THROW_SPEED, THROW_SPIN = _cases.THROW_SPEED, _cases.THROW_SPIN
about, angle_deg, ball, box, check_seeds = _cases.about, _cases.angle_deg, _cases.ball, _cases.box, _cases.check_seeds
CASES, case_scene, make_scene, scene_text = _cases.CASES, _cases.case_scene, _cases.make_scene, _cases.scene_text
MUJOCO_TIMESTEP, dejaview_run, mujoco_run = _engines.MUJOCO_TIMESTEP, _engines.dejaview_run, _engines.mujoco_run
_dejaview_end = _engines._dejaview_end

FIDELITY_TOL = 0.02
"""Metres: the fidelity table's bar at 1.0 s."""
FIDELITY_TIMES = (0.5, 1.0, 1.5)
REFERENCE_ENGINES = ("mujoco", "bullet")
"""The engines the fidelity table holds DejaView to (the 2 cm bar): MuJoCo with DejaView's contact
mapped, and Bullet. MuJoCo at its own default contact is a world unlike DejaView's on purpose: shown
where asked for (``fidelity_engines``), not held to the bar."""

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


def fidelity(print_fn=print, names=None, times=FIDELITY_TIMES, engines=("mujoco", "bullet")) -> list[dict]:
    """The fidelity table: DejaView against each of ``engines`` (``ENGINES``' names) from the same
    start: the distance between the centres of mass and the angle between the orientations (the
    largest over the bodies) at ``times`` (s; the rows run to the last: a test reading 1.0 s stops
    there); a box's centre can agree while its turn does not. With two engines, also their gap to
    each other: where both agree and DejaView does not, DejaView is the outlier.

    Returns:
        rows: ``gap_<t>s_m`` and ``angle_<t>s_deg`` against MuJoCo, ``bullet_gap_<t>s_m`` and
        ``bullet_angle_<t>s_deg`` against Bullet, ``mujoco_bullet_gap_<t>s_m`` between the two,
        ``mujoco_default_gap_<t>s_m`` and ``mujoco_default_angle_<t>s_deg`` against MuJoCo at its
        default contact where ``engines`` names it (shown, not held to the 2 cm bar: it is a world
        unlike DejaView's on purpose).
    """
    engines = _engines.check_engines(engines)
    both = {"mujoco", "bullet"} <= set(engines)  # their gap to each other is shown too
    prefix = {"mujoco": "", "bullet": "bullet_", "mujoco-default": "mujoco_default_"}
    short = {"mujoco": "mj", "bullet": "bt", "mujoco-default": "md"}
    last = max(times)
    cols = [f"{short[n]} {t:g}s" for n in engines for t in times]
    if both:
        cols += [f"mj-bt {t:g}" for t in times]
    print_fn(f"{'motion':<44} " + " ".join(f"{c:>9}" for c in cols) + " "
             + " ".join(f"{short[n] + ' deg':>7}" for n in engines)
             + f"  (cm between the centres: DejaView and each engine, {'the engines, ' if len(engines) > 1 else ''}"
               f"deg between the orientations at {last:g} s; the largest over the bodies)")
    rows = []
    for name, objects, e in FIDELITY:
        if names and not any(n in name for n in names):
            continue
        scene = make_scene(scene_text(objects, last, restitution=e))
        ours = dejaview_run(scene, times)
        theirs = {n: _engines.ENGINES[n](scene, times) for n in engines}
        row = {"section": "fidelity", "motion": name}
        cells, turns = [], []
        for n in engines:
            b = theirs[n]
            for t in times:
                gap = float(np.linalg.norm(ours[t][0] - b[t][0], axis=-1).max())
                row[f"{prefix[n]}gap_{t:g}s_m"] = gap
                row[f"{prefix[n]}angle_{t:g}s_deg"] = max(
                    angle_deg(qa, qb) for qa, qb in zip(np.asarray(ours[t][1]).reshape(-1, 4), b[t][1]))
                cells.append(gap)
            turns.append(row[f"{prefix[n]}angle_{last:g}s_deg"])
        if both:
            for t in times:
                row[f"mujoco_bullet_gap_{t:g}s_m"] = gap = float(
                    np.linalg.norm(theirs["mujoco"][t][0] - theirs["bullet"][t][0], axis=-1).max())
                cells.append(gap)
        refs = [n for n in engines if n in REFERENCE_ENGINES]
        worst = max(row[f"{prefix[n]}gap_1s_m"] for n in refs) if 1.0 in times and refs else None
        if worst is not None:
            row["within_2cm_at_1s"] = worst <= FIDELITY_TOL
        rows.append(row)
        print_fn(f"{name:<44} " + " ".join(f"{100 * g:>9.2f}" for g in cells) + " "
                 + " ".join(f"{a:>7.1f}" for a in turns)
                 + ("" if worst is None or worst <= FIDELITY_TOL else "  > 2 cm at 1.0 s"))
    return rows


TIMESTEP_STUDY = (5e-4, 1e-4, 5e-5, 2e-5, 1e-5, 5e-6)
"""MuJoCo steps compared with ``STUDY_REFERENCE`` in ``timestep_study``."""
STUDY_REFERENCE = 2e-6
SUBSTEP_STUDY = (2, 4, 8)
"""DejaView substeps per 2 ms step compared with ``SUBSTEP_REFERENCE`` (same contact stiffness)."""
SUBSTEP_REFERENCE = 16
BULLET_STUDY = ((2e-3, 1e-3, 5e-4, 2.5e-4, 1e-4), 5e-5)
"""Bullet's steps and its reference step in ``timestep_study(engine="bullet")``."""


def timestep_study(print_fn=print, steps=None, reference=None, substeps=SUBSTEP_STUDY, cases: bool = True,
                   names=None, engine: str = "mujoco") -> list[dict]:
    """Are the engines converged at their steps? Per fidelity row (at 1.0 s) and, with ``cases``,
    per inference case's true start (at the case's duration, the observation), the end (cm, the
    largest over the bodies) of MuJoCo at each of ``steps`` against MuJoCo at ``reference``, and
    of DejaView at each of ``substeps`` against DejaView at ``SUBSTEP_REFERENCE`` substeps (the
    same contact stiffness): how ``MUJOCO_TIMESTEP`` was chosen, and how much of each row's gap
    is the steps' rather than the models' (docs/physics-fidelity.md, "MuJoCo's time step").
    ``names``: only the rows whose motion contains one of them. ``engine`` "bullet": Bullet at
    ``BULLET_STUDY``'s steps instead of MuJoCo (how ``bullet_engine.BULLET_TIMESTEP`` was chosen).

    Returns:
        rows: ``motion`` (a fidelity row's name or "case <name>"), ``gap_<ms>ms_m`` per engine
        step, ``dv_gap_<k>_substeps_m`` per DejaView substep count.
    """
    from dejaview.sim import World

    steps = steps or (TIMESTEP_STUDY if engine == "mujoco" else BULLET_STUDY[0])
    reference = reference or (STUDY_REFERENCE if engine == "mujoco" else BULLET_STUDY[1])
    run_engine, tag = _engines.ENGINES[_engines.check_engines((engine,))[0]], {"mujoco": "mj"}.get(engine, "bt")
    runs = [(name, make_scene(scene_text(objects, 1.0, restitution=e)), 1.0) for name, objects, e in FIDELITY]
    if cases:
        runs += [(f"case {c.name}", case_scene(c), c.duration) for c in CASES]
    if names:
        runs = [r for r in runs if any(n in r[0] for n in names)]
    rows = []
    print_fn(f"{'motion':<44} " + " ".join(f"{tag + ' ' + format(1e3 * dt, 'g') + 'ms':>10}" for dt in steps)
             + " " + " ".join(f"{'dv ' + str(k) + ' sub':>9}" for k in substeps)
             + f"  (cm at 1.0 s or the case's end: {_engines.ENGINE_NAMES[engine]} from its "
               f"{1e3 * reference:g} ms run, DejaView "
               f"from its {SUBSTEP_REFERENCE} substeps)")
    for name, scene, t in runs:
        ref = run_engine(scene, (t,), timestep=reference)[t][0]
        gaps = [float(np.linalg.norm(run_engine(scene, (t,), timestep=dt)[t][0] - ref, axis=-1).max())
                for dt in steps]
        dv = []
        if substeps:
            world = World.from_scene(scene)
            dv_ref = _dejaview_end(world.with_substeps(SUBSTEP_REFERENCE), scene, t)
            dv = [float(np.linalg.norm(_dejaview_end(world.with_substeps(k), scene, t) - dv_ref, axis=-1).max())
                  for k in substeps]
        rows.append({"section": "timestep", "engine": engine, "motion": name,
                     **{f"gap_{1e3 * dt:g}ms_m": g for dt, g in zip(steps, gaps)},
                     **{f"dv_gap_{k}_substeps_m": g for k, g in zip(substeps, dv)}})
        print_fn(f"{name:<44} " + " ".join(f"{100 * g:>10.2f}" for g in gaps)
                 + " " + " ".join(f"{100 * g:>9.2f}" for g in dv))
    return rows


THROW_AREA = ((1.2, -0.5, 0.2), (2.0, 0.5, 0.5))
"""(min, max) start position of ``throws``' boxes: above the floor, clear of the table."""
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


def fidelity_engines(observers) -> tuple:
    """The fidelity table's engines: ``REFERENCE_ENGINES``, and the other observing engines that
    ``observers`` (the bench's ``--engines``) name."""
    return REFERENCE_ENGINES + tuple(n for n in observers if n not in REFERENCE_ENGINES)
