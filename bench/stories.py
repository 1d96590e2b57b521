"""Stories: random everyday scenes, each solved from where its source was seen lying still.

    python bench/stories.py                        # seed 0, 7 stories (one of each kind), prints the table
    python bench/stories.py --seed 0 --count 14    # two of each kind
    python bench/stories.py --csv out/bench/stories.csv --out out/bench/stories
    python bench/stories.py --kinds mug_off_counter,box_thrown
    dejaview bench stories --seed 0                # the same through the CLI

Issue 56: "hidden stories solved with no settings: at least 6 of 7 end within 1 cm / 5 deg of
where the source was seen". The maintainers' hidden stories are scene files of a few kinds
(a ball thrown, bounced or rolled to rest on the floor, a mug knocked off a kitchen counter,
tossed onto the floor or slid off a desk, a box thrown onto the floor), each with the source's
resting pose as its ``<target position orientation>`` (no velocities, no time), a start area and
no other inference setting: no ``<prior>``, no ``<observation>``, no ``evaluate``, ``loss`` or
``seed`` attribute. This bench writes stories of the same kinds, from a seed, and solves each
with ``dejaview.solve(scene)`` and nothing else.

**Seed policy.** Seed 0 is the development set; seeds 100 and up are held out: run them to
check a change, never to make one (nothing may be tuned on them, nor on one story of seed 0).

The stories are drawn and written by ``bench/story_scenes.py`` (how a story is drawn, the
knobbly ball the ball stories use).

Measured per story (``solve_story``): the answer re-simulated (``result.final_pose()``, the end
of the solve's own re-simulation; ``resim_mm``: an independent rollout of its initial state from
the scene file, against it), its end's position error (mm, object-frame origins) and angle error
(deg, geodesic) against the observed pose, ``solved``: within ``POSITION_TOL`` and
``ANGLE_TOL`` (both required, every kind: the default loss is ``pose``); the answer's own mean
speed and spin over the last ``story_scenes.REST_WINDOW`` (a flyby moves at the end); the error at the record
the solver matched (``result.matched_pose()``, for comparison: ``evaluate="best"`` matches a
moment of a flyby); solve wall time and rollouts.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

POSITION_TOL = 0.01
"""m: the issue's 1 cm."""
ANGLE_TOL = 5.0
"""deg: the issue's 5 degrees."""
DEFAULT_COUNT = 7
"""Stories in a run: one of each kind."""
HELD_OUT_FROM = 100
"""Seeds from here on are held out (module docstring)."""


def story_scenes():
    """``bench/story_scenes.py``, the stories' generator (loaded as ``dejaview bench`` loads a bench)."""
    from dejaview.cli.bench import bench_module

    return bench_module("story_scenes")


def solve_story(path: Path | str) -> dict:
    """Solve the scene file ``path`` with ``dejaview.solve``'s defaults and measure the answer (module
    docstring); the row of the table (truth from ``<path>.truth.json`` where present)."""
    import torch

    import dejaview
    from dejaview.scene import Scene
    from dejaview.sim.rotation import geodesic_angle

    path = Path(path)
    scene = Scene.from_xml(path)
    truth_path = path.with_name(path.name[:-len(".xml")] + ".truth.json")
    truth = json.loads(truth_path.read_text(encoding="utf-8")) if truth_path.is_file() else {}
    target = scene.inference.target
    t_pos = torch.tensor(target.position, dtype=torch.float64)
    t_q = torch.tensor(target.orientation, dtype=torch.float64)

    def errors(pos, q) -> tuple[float, float]:
        pos, q = torch.as_tensor(pos, dtype=torch.float64), torch.as_tensor(q, dtype=torch.float64)
        return (1000.0 * float(torch.linalg.vector_norm(pos - t_pos)),
                math.degrees(float(geodesic_angle(q / q.norm(), t_q / t_q.norm()))))

    t0 = time.perf_counter()
    result = dejaview.solve(scene)
    seconds = time.perf_counter() - t0
    end_pos, end_q = result.final_pose()
    end_mm, end_deg = errors(end_pos, end_q)
    matched = result.matched_pose()
    matched_mm, matched_deg = errors(matched["position"], matched["orientation"])
    answer = result.initial_state
    start = dict(position=answer["position"], orientation=answer["orientation"],
                 linear=answer["linear_velocity"], angular=answer["angular_velocity"])
    scenes = story_scenes()
    world, traj, source = scenes.simulate(scene, start)
    resim_pos = world.object_position(traj.final)[0, source]
    resim_mm = 1000.0 * float(torch.linalg.vector_norm(resim_pos - torch.as_tensor(end_pos, dtype=resim_pos.dtype)))
    speed, spin = scenes.mean_motion(world, traj, source)
    search = result.settings.get("search") or {}
    truth_start = (truth.get("initial_state") or {}).get("position")
    return {
        "story": path.name[:-len(".xml")], "kind": truth.get("kind", ""),
        "solved": bool(end_mm <= 1000.0 * POSITION_TOL and end_deg <= ANGLE_TOL),
        "end_mm": end_mm, "end_deg": end_deg,
        "matched_mm": matched_mm, "matched_deg": matched_deg, "matched_time_s": matched["time"],
        "duration_s": scene.simulation.duration, "rest_time_s": truth.get("rest_time"),
        "end_speed": float(speed[-1]), "end_spin": float(spin[-1]), "resim_mm": resim_mm,
        "start_error_m": (float(np.linalg.norm(np.asarray(answer["position"]) - np.asarray(truth_start)))
                          if truth_start else None),
        "seconds": seconds, "rollouts": search.get("rollouts"), "jacobians": search.get("jacobians"),
        "evaluate": getattr(result.problem, "evaluate", ""),
        "answer": json.dumps(answer),
    }


COLUMNS = [  # key, header, format
    ("story", "story", "{:<26}"), ("solved", "solved", "{!s:<6}"),
    ("end_mm", "end_mm", "{:>9.1f}"), ("end_deg", "end_deg", "{:>7.1f}"),
    ("matched_mm", "match_mm", "{:>8.1f}"), ("matched_deg", "match_deg", "{:>9.1f}"),
    ("matched_time_s", "match_t", "{:>7.2f}"), ("duration_s", "dur_s", "{:>5.1f}"),
    ("end_speed", "end_v", "{:>6.3f}"), ("seconds", "seconds", "{:>7.1f}"), ("rollouts", "rollouts", "{:>8}"),
]


def format_header() -> str:
    return "  ".join(h.ljust(len(fmt.format("" if k == "story" else False))) if k in ("story", "solved")
                     else h.rjust(len(fmt.format(0))) for k, h, fmt in COLUMNS)


def format_row(row: dict) -> str:
    return "  ".join(fmt.format(row[k] if row[k] is not None else "") for k, _, fmt in COLUMNS)


def write_csv(rows: list[dict], path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["story"], lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return path


def run(print_fn=print, seed: int = 0, count: int = DEFAULT_COUNT, out: Path | str = "out/bench/stories",
        kinds=None, csv_path=None, solve: bool = True) -> list[dict]:
    """Write the stories of ``seed`` into ``out/seed<seed>`` and solve each (module docstring).

    Args:
        print_fn: where the table goes (None: nowhere).
        seed, count, kinds: ``make_stories``'.
        out: folder of the stories' folders.
        csv_path: also write the rows there (after every story).
        solve: False: only write the stories (rows without the solve's columns).
    Returns:
        one dict per story.
    """
    import torch

    torch.set_num_threads(int(os.environ.get("DEJAVIEW_THREADS", "1")))
    say = print_fn or (lambda *_: None)
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    if seed < 0:
        raise ValueError(f"seed must be at least 0, got {seed}")
    folder = Path(out) / f"seed{seed}"
    t0 = time.perf_counter()
    scenes = story_scenes()
    stories = scenes.make_stories(seed, count, folder, kinds)
    for story in stories:
        scenes.write_story(story, folder)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    say(f"stories: seed {seed}{' (held out)' if seed >= HELD_OUT_FROM else ' (development)'}, {count} "
        f"written to {folder} in {time.perf_counter() - t0:.1f} s; solved with dejaview.solve's defaults; "
        f"solved = the answer's end within {POSITION_TOL * 100:g} cm and {ANGLE_TOL:g} deg of the observed "
        f"pose (load average {load:.1f})")
    if not solve:
        rows = [{"story": s.name, "kind": s.kind, "draws": s.draws, "rest_time_s": s.truth["rest_time"],
                 "duration_s": s.truth["duration"], "path": str(s.path)} for s in stories]
        for r in rows:
            say(f"{r['story']:<26} draws {r['draws']:3d}  rest {r['rest_time_s']:.2f} s  duration "
                f"{r['duration_s']:.1f} s")
        if csv_path is not None:
            write_csv(rows, csv_path)
        return rows
    say(format_header())
    rows = []
    for story in stories:
        row = solve_story(story.path)
        row["draws"] = story.draws
        rows.append(row)
        say(format_row(row))
        if csv_path is not None:
            write_csv(rows, csv_path)
    ok = sum(r["solved"] for r in rows)
    say(f"solved {ok}/{len(rows)}, {sum(r['seconds'] for r in rows):.0f} s solving")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Random stories solved from where the source was seen lying "
                                                 "still (issue 56); module docstring: bench/stories.py")
    parser.add_argument("--seed", type=int, default=0, help="seed of the stories (0: development; "
                        f"{HELD_OUT_FROM} and up: held out)")
    parser.add_argument("--count", type=int, default=DEFAULT_COUNT, help="stories (one of each kind in turn)")
    parser.add_argument("--kinds", default=None, help=f"comma-separated kinds (default: all: {', '.join(story_scenes().KINDS)})")
    parser.add_argument("--out", type=Path, default=Path("out/bench/stories"), help="folder of the stories")
    parser.add_argument("--csv", type=Path, default=None, help="also write the rows as CSV here")
    parser.add_argument("--no-solve", action="store_true", help="only write the stories")
    args = parser.parse_args(argv)
    kinds = [k for k in args.kinds.replace(" ", "").split(",") if k] if args.kinds else None
    try:
        rows = run(seed=args.seed, count=args.count, out=args.out, kinds=kinds, csv_path=args.csv,
                   solve=not args.no_solve)
    except ValueError as exc:
        parser.error(str(exc))
    return 0 if args.no_solve or all(r["solved"] for r in rows) else 1


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
