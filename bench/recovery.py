"""Recovery suite: does ``dejaview.solve`` find a past that explains a known end?

    python bench/recovery.py                       # every case, prints the table
    python bench/recovery.py --csv recovery.csv    # also write the rows as CSV
    python bench/recovery.py --cases ball_off_table-0,box_along_shelf-1
    python bench/recovery.py --verbose             # also every iteration of the solver

Each case takes one bundled scene (``examples/scenes``), draws a known random
initial state of its source (seeded; inside the scene's start area; with
velocities that keep the scene's story, e.g. the ball still rolls off the
table; the bodies of each ``<penalty>`` touch: each draw is simulated and
redrawn until the story holds), simulates it
with DejaView and gives the solver only the source's final pose as the
``<target>``. The solver is ``dejaview.solve`` with its defaults and nothing
else: the most probable past under the scene's priors (the default search,
``dejaview.inference.search``), on the native simulation engine.

Success: the best solution, re-simulated, comes within ``POSITION_TOL`` (1 cm)
and ``ANGLE_TOL`` (5 degrees) of the target pose, both measured at the
trajectory record that matches the target best by the solver's own per-record
loss (``evaluate="best"``, the setting of every bundled scene: the target is
compared with the best-matching moment, not with the last record). Positions
are object-frame origins, as the target gives them; the angle is the geodesic
angle between orientations. Where the scene's loss is ``position`` (the ball:
a sphere's orientation is neither observed nor part of its loss) the angle is
reported but not required. The start-position error (solution vs. true start)
is reported too, never required: different starts can end alike.

Scene variants (built in code with ``dataclasses.replace``; the files are not
touched) keep the suite short:

- every duration is shortened to what the story needs (``DURATIONS``);
- in ``box_among_boxes`` the four boxes use a coarse packing
  (``tests/fixtures/inference/box_coarse.spheres``: a regular 4 x 3 x 2 grid of
  24 equal spheres touching the faces) instead of the bundled 128 spheres. The
  simulator's body-pair contact tests every sphere of one body against every
  sphere of the other (128 x 128 per pair; forces for the deepest 64 only),
  and its broadphase (bounding spheres of radius 0.126 m) runs it for the
  resting box0 and box1, 0.20 m apart, at every substep: with dense pair
  forces a 0.6 s rollout of a thrown box among them took 35-40 s with the
  bundled packing (one loss + gradient ~100 s), 5-6 s with the coarse one.

The budget is the solver's own (its defaults); ``seconds`` is the wall time of the
whole ``solve`` call, screening and the final re-simulation included.

Rows (one per case): ``case``, ``scene``, ``success``, ``position_error_m``,
``angle_error_deg``, ``start_error_m``, ``loss``, ``iterations``,
``evaluations``, ``seconds``, plus the drawn truth and the solution.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "examples" / "scenes"

POSITION_TOL = 0.01
ANGLE_TOL = 5.0
COARSE_BOX = ROOT / "tests" / "fixtures" / "inference" / "box_coarse.spheres"

DURATIONS = {"ball_off_table": 0.8, "mug_off_counter": 0.8, "box_along_shelf": 0.5,
             "box_among_boxes": 0.6, "ball_down_ramp": None, "box_down_ramp": None}
"""Simulated seconds per scene (None: the scene's own)."""
CASES_PER_SCENE = 4
MAX_DRAWS = 50


@dataclass(frozen=True)
class Case:
    """One recovery problem: a bundled scene and the seed of its true initial state."""

    scene: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.scene}-{self.seed}"


ALL_CASES = tuple(Case(scene, seed) for scene in DURATIONS for seed in range(CASES_PER_SCENE))


# ----------------------------------------------------------------- the truths
def _rotvec_quat(rotvec) -> tuple[float, ...]:
    """(w, x, y, z) of a rotation vector."""
    r = np.asarray(rotvec, dtype=float)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    axis = r / angle
    return (math.cos(angle / 2), *(math.sin(angle / 2) * axis))


def _in_area(rng, scene) -> list[float]:
    area = scene.inference.start_area
    return [float(rng.uniform(lo, hi)) for lo, hi in zip(area.min, area.max)]


def _heading(speed: float, angle: float, vz: float = 0.0) -> list[float]:
    return [speed * math.cos(angle), speed * math.sin(angle), vz]


def draw_ball_off_table(rng, scene) -> dict:
    """Rolled (no slip: w = z x v / r) towards +x at 1.2-2.2 m/s, +-15 degrees, some side spin."""
    v = _heading(rng.uniform(1.2, 2.2), rng.uniform(-0.26, 0.26))
    r = 0.05
    return dict(position=_in_area(rng, scene), orientation=None, linear=v,
                angular=[-v[1] / r, v[0] / r, float(rng.uniform(-3.0, 3.0))])


def draw_mug_off_counter(rng, scene) -> dict:
    """Slid towards the counter's +x edge at 1.8-2.8 m/s, +-12 degrees, turned up to +-30 degrees
    about z and spinning up to 3 rad/s about z."""
    p = _in_area(rng, scene)
    p[0] = float(rng.uniform(0.0, 0.45))  # close enough to the edge to leave the counter
    return dict(position=p, orientation=_rotvec_quat([0.0, 0.0, rng.uniform(-0.52, 0.52)]),
                linear=_heading(rng.uniform(1.8, 2.8), rng.uniform(-0.2, 0.2)),
                angular=[0.0, 0.0, float(rng.uniform(-3.0, 3.0))])


def draw_box_along_shelf(rng, scene) -> dict:
    """Slid along the board (friction 0.4) fast enough to reach the side panel, not much more."""
    p = _in_area(rng, scene)
    to_wall = 0.38 - p[0]  # the box's centre stops 0.1 m short of the panel's inner face at 0.48
    v_min = math.sqrt(2 * 0.4 * 9.81 * to_wall)
    return dict(position=p, orientation=None,
                linear=_heading(rng.uniform(v_min + 0.1, v_min + 0.8), rng.uniform(-0.05, 0.05)),
                angular=[0.0, 0.0, 0.0])


def draw_box_among_boxes(rng, scene) -> dict:
    """Thrown towards box0 (x = 0.75) from the start area, tumbling a little."""
    return dict(position=_in_area(rng, scene), orientation=_rotvec_quat(rng.uniform(-0.3, 0.3, 3)),
                linear=[float(rng.uniform(1.3, 1.9)), float(rng.uniform(-0.15, 0.15)),
                        float(rng.uniform(0.0, 0.6))],
                angular=[float(v) for v in rng.uniform(-2.0, 2.0, 3)])


def draw_on_ramp(rng, scene) -> dict:
    """Released at rest anywhere in the start area (only the position is free)."""
    return dict(position=_in_area(rng, scene), orientation=None, linear=[0.0, 0.0, 0.0],
                angular=[0.0, 0.0, 0.0])


DRAWS = {"ball_down_ramp": draw_on_ramp, "box_down_ramp": draw_on_ramp,
         "ball_off_table": draw_ball_off_table, "mug_off_counter": draw_mug_off_counter,
         "box_along_shelf": draw_box_along_shelf, "box_among_boxes": draw_box_among_boxes}


def story_holds(name: str, world, traj, source: int) -> bool:
    """Does a simulated truth still tell the scene's story?"""
    import torch

    origins = world.object_position(traj.states)[:, 0]  # (T, N, 3)
    src = origins[:, source]
    dt = traj.dt * float(traj.steps[1] - traj.steps[0]) if len(traj.steps) > 1 else traj.dt
    last = max(1, int(round(0.1 / dt)))  # the last 0.1 s
    if name in ("ball_off_table", "mug_off_counter"):
        # it left the table / counter and is on the floor for the last 0.1 s
        return bool((src[-last:, 2] < 0.2).all())
    if name == "box_along_shelf":
        # it reached the side panel and is still on the board
        return bool(src[-1, 0] > 0.36 and abs(float(src[-1, 2]) - 1.05) < 0.01)
    if name in ("ball_down_ramp", "box_down_ramp"):
        # it rolled or slid down onto the floor
        return bool(src[-1, 2] < 0.2)
    if name == "box_among_boxes":
        # it knocked at least one of the other boxes by more than a centimetre
        moved = torch.linalg.vector_norm(origins[-1] - origins[0], dim=-1)
        others = [i for i in range(world.num_bodies) if i != source]
        return bool(moved[others].max() > 0.01)
    raise KeyError(name)


def penalties_met(scene, world, traj) -> bool:
    """Do the bodies of every ``<penalty>`` of the scene touch in a simulated truth?

    A penalty is the scene's prior knowledge (``box_among_boxes``: the thrown box hit box0);
    a truth that breaks it is not a story of that scene: its penalty would be positive at the
    truth, so the objective's minimum would lie elsewhere. (Measured: the first draw of
    ``box_among_boxes-1`` hit box1 only and ended 10.8 cm from box0: 10.8 mm of penalty.)
    """
    from dejaview.losses import contact_penalty

    return all(float(contact_penalty(world, traj, *p.between).max()) == 0.0
               for p in scene.inference.penalties)


def variant(name: str):
    """The bundled scene as the suite runs it (see the module docstring)."""
    from dejaview.scene import Scene

    scene = Scene.from_xml(SCENES / f"{name}.xml")
    if DURATIONS[name] is not None:
        scene = replace(scene, simulation=replace(scene.simulation, duration=DURATIONS[name]))
    if name == "box_among_boxes":
        scene = replace(scene, objects=tuple(replace(o, spheres=str(COARSE_BOX)) if o.spheres else o
                                             for o in scene.objects))
    return scene


def with_start(scene, start: dict):
    """The scene with its source starting at ``start`` (position, orientation (w x y z), linear,
    angular: sequences of floats, as a truth dict holds them)."""
    src = scene.object(scene.inference.source)
    obj = replace(src, pose=replace(src.pose, position=tuple(start["position"]),
                                    orientation=tuple(start["orientation"])),
                  velocity=replace(src.velocity, linear=tuple(start["linear"]),
                                   angular=tuple(start["angular"])))
    return scene.with_object(obj)


def make_case(case: Case):
    """(scene with the drawn truth's final pose as target, truth dict, draws needed).

    Raises:
        RuntimeError: no draw told the story in ``MAX_DRAWS`` tries.
    """
    import torch

    from dejaview.scene import Target
    from dejaview.sim import World
    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import rollout

    scene = variant(case.scene)
    src_obj = scene.object(scene.inference.source)
    rng = np.random.default_rng(case.seed)
    world = None
    for draw in range(1, MAX_DRAWS + 1):
        truth = DRAWS[case.scene](rng, scene)
        q = src_obj.pose.orientation if truth["orientation"] is None else truth["orientation"]
        truth["orientation"] = [float(v) for v in q]
        true_scene = with_start(scene, truth)
        world = world or World.from_scene(true_scene)
        with torch.no_grad():
            traj = rollout(world, initial_state(world, true_scene), record_every=1)
        source = world.body_index(src_obj.id)
        if story_holds(case.scene, world, traj, source) and penalties_met(true_scene, world, traj):
            end = world.object_position(traj.final)[0, source].tolist()
            q_end = traj.final.orientation[0, source].tolist()
            target = Target(position=tuple(end), orientation=tuple(q_end), moving=True)  # at rest or not
            truth["final_position"], truth["final_orientation"] = end, q_end
            return replace(scene, inference=replace(scene.inference, targets=(target,))), truth, draw
    raise RuntimeError(f"{case.name}: no draw in {MAX_DRAWS} told the story of {case.scene}")


# ----------------------------------------------------------------- measuring
def pose_errors(result) -> dict:
    """Errors of a SolveResult's re-simulated best solution at its best-matching record
    (``SolveResult.matched_pose``).

    Returns:
        dict with position_error_m (object-frame origins), angle_error_deg, record_time_s.
    """
    m = result.matched_pose()
    return dict(position_error_m=m["position_error"], angle_error_deg=m["angle_error_deg"],
                record_time_s=m["time"])


def explains_the_end(result, errors: dict | None = None) -> bool:
    """The suite's success: the answer re-simulated meets the target within ``POSITION_TOL`` and
    ``ANGLE_TOL`` (the angle not required for a ``position`` loss); ``errors``: ``pose_errors``."""
    errors = pose_errors(result) if errors is None else errors
    angle_required = result.problem.loss_kind != "position"
    return errors["position_error_m"] <= POSITION_TOL and (
        not angle_required or errors["angle_error_deg"] <= ANGLE_TOL)


def solve_case(case: Case, callback=None, **solve_options) -> dict:
    """Draw, simulate and solve one case with ``dejaview.solve``'s defaults (``solve_options``
    override them, e.g. for a comparison; ``callback``: solve's); the row of the table."""
    from dejaview.inference.solve import SolveParams, solve

    scene, truth, draws = make_case(case)
    t0 = time.perf_counter()
    result = solve(scene, SolveParams(**solve_options), callback=callback)
    seconds = time.perf_counter() - t0
    errors = pose_errors(result)
    start = np.asarray(result.initial_state["position"])
    angle_required = result.problem.loss_kind != "position"
    success = explains_the_end(result, errors)
    history = result.iterations
    return {
        "case": case.name, "scene": case.scene, "success": bool(success),
        "position_error_m": errors["position_error_m"], "angle_error_deg": errors["angle_error_deg"],
        "angle_required": angle_required,
        "start_error_m": float(np.linalg.norm(start - np.asarray(truth["position"]))),
        "loss": result.loss, "iterations": len(history),
        "evaluations": history[-1].evaluations if history else 0, "seconds": seconds,
        "record_time_s": errors["record_time_s"], "duration_s": scene.simulation.duration,
        "optimizer": result.settings["optimizer"], "gradient": result.settings["gradient"],
        "out_of_budget": result.optimization.stopped, "truth_draws": draws,
        "truth": json.dumps({k: truth[k] for k in ("position", "orientation", "linear", "angular")}),
        "solution": json.dumps(result.initial_state),
    }


COLUMNS = [  # key, header, format (the width is the header's or the format's)
    ("case", "case", "{:<18}"), ("success", "success", "{!s:<7}"),
    ("position_error_m", "pos_err_m", "{:>9.4f}"), ("angle_error_deg", "ang_deg", "{:>7.2f}"),
    ("start_error_m", "start_m", "{:>7.3f}"), ("loss", "loss", "{:>8.5f}"),
    ("iterations", "iters", "{:>5d}"), ("evaluations", "evals", "{:>5d}"),
    ("seconds", "seconds", "{:>7.1f}"),
]


def format_header() -> str:
    return "  ".join(h.ljust(len(fmt.format(0 if key != "case" else ""))) if key in ("case", "success")
                     else h.rjust(len(fmt.format(0))) for key, h, fmt in COLUMNS)


def format_row(row: dict) -> str:
    cells = [fmt.format(row[key]) for key, _, fmt in COLUMNS]
    if not row["angle_required"]:
        cells[3] = cells[3][1:] + "*"
    return "  ".join(cells)


def _resolve(cases) -> list[Case]:
    if cases is None:
        return list(ALL_CASES)
    by_name = {c.name: c for c in ALL_CASES}
    out = []
    for c in cases:
        if isinstance(c, Case):
            out.append(c)
        elif c in by_name:
            out.append(by_name[c])
        else:
            raise KeyError(f"unknown case {c!r}; known: {', '.join(by_name)}")
    return out


def run(print_fn=print, cases=None, csv_path=None, **solve_options) -> list[dict]:
    """Run the suite and print its table.

    Args:
        print_fn: where the table lines go (None: nowhere).
        cases: Case objects or names like ``"ball_off_table-0"`` (default: ``ALL_CASES``).
        csv_path: also write the rows there.
        **solve_options: ``callback`` and overrides of solve's defaults (``solve_case``).
    Returns:
        one dict per case (see the module docstring).
    """
    import os

    import torch

    torch.set_num_threads(int(os.environ.get("DEJAVIEW_THREADS", "1")))
    say = print_fn or (lambda *_: None)
    cases = _resolve(cases)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    settings = {k: v for k, v in solve_options.items() if k != "callback"}
    say(f"recovery: {len(cases)} cases, solve's {settings or 'defaults'}; success = within "
        f"{POSITION_TOL * 100:g} cm and {ANGLE_TOL:g} deg at the best-matching record "
        f"(load average {load:.1f})")
    say(format_header())
    rows = []
    for case in cases:
        row = solve_case(case, **solve_options)
        rows.append(row)
        say(format_row(row))
        if csv_path is not None:
            write_csv(rows, csv_path)
    ok = sum(r["success"] for r in rows)
    total = sum(r["seconds"] for r in rows)
    say(f"success {ok}/{len(rows)} ({100.0 * ok / max(1, len(rows)):.0f} %), {total:.0f} s solving"
        + ("; * angle not required (position loss)" if any(not r["angle_required"] for r in rows) else ""))
    return rows


def write_csv(rows: list[dict], path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["case"], lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--csv", type=Path, default=None, help="also write the rows as CSV here")
    parser.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    parser.add_argument("--verbose", action="store_true", help="print every iteration")
    args = parser.parse_args(argv)
    cases = args.cases.split(",") if args.cases else None

    def show(p):
        print(f"    {p.iteration:3d}  loss {p.loss:.5g}  best {p.best_loss:.5g}  evals {p.evaluations:5d}"
              f"  {p.elapsed_s:6.1f} s" + ("  restart" if p.restarted else ""), flush=True)

    rows = run(cases=cases, csv_path=args.csv, callback=show if args.verbose else None)
    return 0 if rows and all(r["success"] for r in rows) else 1


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
