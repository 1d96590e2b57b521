"""The default search against the seed's pipeline, in one run: wall time and answer per solve.

    python bench/search.py                         # mug_off_counter and box_among_boxes, seeds 0-2
    python bench/search.py --scenes mug_off_counter --seeds 0
    dejaview bench search                          # the same

Each row solves one bundled scene (the file as shipped: full duration, its own packings and
target) with one pipeline and one seed:

- ``auto``: ``dejaview.solve(scene, seed=s)``, the defaults (the search of
  ``dejaview.inference.search``: CMA-ES over the prior, Levenberg-Marquardt on exact Jacobians);
- ``seed-pipeline``: what the recovery suite needed before (``SEED_PIPELINE``): 64 screened
  guesses, four L-BFGS candidates with epsilon-greedy restarts (epsilon 0.5, patience 8), at
  most 300 iterations and 1000 evaluations, early stop at a 3 mm pose loss.

Reported: wall time of the ``solve`` call, the error at the matched record (position, angle),
success (the recovery suite's: 1 cm and 5 degrees; position alone for a ``position`` loss) and the ratio of the wall
times. Targets (issue 19): mug_off_counter <= 10 s, box_among_boxes <= 60 s per solve with the
defaults, on the project's 2-core machine.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "examples" / "scenes"
DEFAULT_SCENES = ("mug_off_counter", "box_among_boxes")
TARGET_SECONDS = {"mug_off_counter": 10.0, "box_among_boxes": 60.0}
SEED_PIPELINE = dict(optimizer="lbfgs", multistart=4, screen=64, epsilon=0.5, patience=8, iterations=300,
                     tolerance=0.003)
SEED_MAX_EVALUATIONS = 1000


def solve_once(scene_name: str, pipeline: str, seed: int) -> dict:
    """One solve; the row of the table."""
    from dejaview.cli.bench import bench_module
    from dejaview.inference.solve import SolveParams, solve
    from dejaview.scene import Scene

    recovery = bench_module("recovery")  # its success criterion, one place
    scene = Scene.from_xml(SCENES / f"{scene_name}.xml")
    options: dict = {"seed": seed}
    hooks: dict = {}
    if pipeline == "seed-pipeline":
        spent = [0]
        options.update(SEED_PIPELINE)
        hooks = dict(callback=lambda p: spent.__setitem__(0, p.evaluations),
                     should_stop=lambda: spent[0] >= SEED_MAX_EVALUATIONS)
    t0 = time.perf_counter()
    result = solve(scene, SolveParams(**options), **hooks)
    seconds = time.perf_counter() - t0
    errors = recovery.pose_errors(result)
    return {"scene": scene_name, "pipeline": pipeline, "seed": seed, "seconds": seconds,
            "success": recovery.explains_the_end(result, errors),
            "position_error_m": errors["position_error_m"], "angle_error_deg": errors["angle_error_deg"],
            "iterations": len(result.iterations),
            "evaluations": result.iterations[-1].evaluations if result.iterations else 0}


def run(print_fn=print, scenes=DEFAULT_SCENES, seeds=(0, 1, 2), pipelines=("auto", "seed-pipeline")) -> list[dict]:
    """Solve every scene x seed x pipeline; print the table and the time ratios."""
    import torch

    torch.set_num_threads(int(os.environ.get("DEJAVIEW_THREADS", "1")))
    say = print_fn or (lambda *_: None)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    say(f"search: {', '.join(scenes)}; seeds {', '.join(map(str, seeds))}; load average {load:.1f}")
    say(f"{'scene':<16} {'pipeline':<14} {'seed':>4} {'seconds':>8} {'pos_mm':>8} {'ang_deg':>8} "
        f"{'ok':<5} {'iters':>5} {'evals':>6}")
    rows = []
    for name in scenes:
        for seed in seeds:
            for pipeline in pipelines:
                row = solve_once(name, pipeline, seed)
                rows.append(row)
                say(f"{name:<16} {pipeline:<14} {seed:>4} {row['seconds']:>8.1f} "
                    f"{row['position_error_m'] * 1000:>8.2f} {row['angle_error_deg']:>8.2f} "
                    f"{'yes' if row['success'] else 'no':<5} {row['iterations']:>5} {row['evaluations']:>6}")
    for name in scenes:
        per = {p: [r for r in rows if r["scene"] == name and r["pipeline"] == p] for p in pipelines}
        if not all(per.values()):
            continue
        mean = {p: sum(r["seconds"] for r in v) / len(v) for p, v in per.items()}
        solved = {p: sum(r["success"] for r in v) for p, v in per.items()}
        line = (f"{name}: " + ", ".join(f"{p} {mean[p]:.1f} s mean, {solved[p]}/{len(per[p])} solved"
                                        for p in pipelines))
        if "auto" in mean and "seed-pipeline" in mean:
            line += f"; seed-pipeline / auto time ratio {mean['seed-pipeline'] / mean['auto']:.1f}"
        if "auto" in mean and name in TARGET_SECONDS:
            worst = max(r["seconds"] for r in per["auto"])
            line += (f"; auto worst {worst:.1f} s vs target {TARGET_SECONDS[name]:g} s -> "
                     f"{'met' if worst <= TARGET_SECONDS[name] else 'missed'}")
        say(line)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default=",".join(DEFAULT_SCENES), help="comma-separated bundled scenes")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    parser.add_argument("--pipelines", default="auto,seed-pipeline", help="auto and/or seed-pipeline")
    parser.add_argument("--csv", type=Path, default=None, help="also write the rows as CSV here")
    args = parser.parse_args(argv)
    rows = run(scenes=tuple(args.scenes.split(",")), seeds=tuple(int(s) for s in args.seeds.split(",")),
               pipelines=tuple(args.pipelines.split(",")))
    if args.csv is not None:
        from dejaview.cli.bench_table import write_rows_csv

        write_rows_csv(rows, args.csv)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
