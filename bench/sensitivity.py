"""How sensitive is a recovery case's end to its start? (Why some cases resist the solver.)

    python bench/sensitivity.py                                  # the box_among_boxes cases
    python bench/sensitivity.py --cases mug_off_counter-1,box_along_shelf-1
    python bench/sensitivity.py --cases box_among_boxes-1 --around out/bench/recovery.csv

Two measurements per case of the recovery suite (``bench/recovery.py``: the
same scene variant and the same drawn truth):

1. **End vs. start.** The true start's position is moved by ``d`` (1 um to
   1 mm) in ``TRIALS`` random directions within the start area's free axes
   (an axis with ``min == max`` is fixed for the solver too), everything else
   kept, and the rollout's final source pose is compared with the truth's:
   the range of position (mm) and angle (degrees) changes over the trials.
   A smooth story (a box sliding along a shelf) moves its end by about ``d``;
   a chaotic one (four boxes colliding) by 10-1000 ``d``.
2. **The loss around a point.** ``TRIALS`` random perturbations of the
   parameter vector (all free parameters, normal with standard deviation
   ``sigma`` in the solver's scaled parameters; see
   ``dejaview.inference.params``) around the true start, or around the
   solution a recovery run found (``--around CSV``, its ``solution``
   column): the median and smallest loss (the solver's, metres). Around a
   true start the loss is 0; if the median is already centimetres at
   ``sigma = 0.02`` (a few millimetres, a fraction of a degree) the start is a
   needle that neither screening nor a gradient step can aim at.

The parameterisation is built from the scene with the point as its own
start (rotation vector 0 on the point's orientation), so ``sigma`` means
the same in every block as for the solver. Rollouts are eager, one thread,
without gradients: about a minute per case on the box scene.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DISTANCES = (1e-6, 1e-5, 1e-4, 1e-3)
SIGMAS = (0.001, 0.02, 0.05, 0.1)
TRIALS = 8
DEFAULT_CASES = ("box_among_boxes-0", "box_among_boxes-1", "box_among_boxes-2")


def _recovery():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from bench import recovery

    return recovery


def end_pose(world, scene, source: int):
    """(position (3,), orientation (4,)) of the source's object frame at the end of a rollout."""
    import torch

    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import rollout

    with torch.no_grad():
        final = rollout(world, initial_state(world, scene), record_every=50).final
    return world.object_position(final)[0, source], final.orientation[0, source]


def end_sensitivity(scene, truth: dict, distances=DISTANCES, trials: int = TRIALS,
                    seed: int = 0) -> list[dict]:
    """Rows (distance_m, end_moved_mm min/max, end_turned_deg min/max) for moved starts."""
    import torch

    from dejaview.backends.params import layout_from_scene
    from dejaview.sim import World
    from dejaview.sim.rotation import geodesic_angle

    recovery = _recovery()
    base = recovery.with_start(scene, truth)
    world = World.from_scene(base)
    source = world.body_index(scene.inference.source)
    ref_p, ref_q = end_pose(world, base, source)
    layout = layout_from_scene(scene)  # the solver's free position axes (start area with width)
    free = torch.zeros(3, dtype=torch.float64)
    free[list(layout.position_axes)] = 1.0
    gen = torch.Generator().manual_seed(seed)
    rows = []
    for d in distances:
        moved, turned = [], []
        for _ in range(trials):
            u = torch.randn(3, generator=gen, dtype=torch.float64) * free
            u = u / u.norm()
            start = dict(truth, position=[p + d * float(v) for p, v in zip(truth["position"], u)])
            p, q = end_pose(world, recovery.with_start(scene, start), source)
            moved.append(float(torch.linalg.vector_norm(p - ref_p)) * 1e3)
            turned.append(math.degrees(float(geodesic_angle(q, ref_q))))
        rows.append(dict(distance_m=d, moved_mm_min=min(moved), moved_mm_max=max(moved),
                         turned_deg_min=min(turned), turned_deg_max=max(turned)))
    return rows


def loss_around(scene, point: dict, sigmas=SIGMAS, trials: int = TRIALS, seed: int = 0) -> dict:
    """The solver's loss at ``point`` and the median / smallest over perturbations per sigma."""
    import torch

    from dejaview.backends import as_problem, make_problem

    problem = as_problem(make_problem(_recovery().with_start(scene, point)))
    x = problem.layout.encode().to(problem.dtype)
    gen = torch.Generator().manual_seed(seed)
    out = {"loss": float(problem.loss(x)[0]), "sigmas": []}
    for sigma in sigmas:
        xs = x + sigma * torch.randn(trials, x.shape[1], generator=gen, dtype=x.dtype)
        with torch.no_grad():
            losses = problem.loss(xs).tolist()
        out["sigmas"].append(dict(sigma=sigma, median=statistics.median(losses), min=min(losses)))
    return out


def solution_of(csv_path, case: str) -> dict:
    """The ``solution`` column of a recovery CSV row, as a start dict."""
    import csv

    with open(csv_path, newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            if row["case"] == case:
                sol = json.loads(row["solution"])
                return dict(position=sol["position"], orientation=sol["orientation"],
                            linear=sol["linear_velocity"], angular=sol["angular_velocity"])
    raise KeyError(f"{case} is not in {csv_path}")


def run(cases=DEFAULT_CASES, around=None, trials: int = TRIALS, print_fn=print) -> list[dict]:
    """Measure every case; print a block per case; return one dict per case."""
    import torch

    torch.set_num_threads(1)
    recovery = _recovery()
    results = []
    for case in recovery._resolve(cases):  # KeyError naming the known cases for a bad name
        name = case.name
        scene, truth, _ = recovery.make_case(case)
        ends = end_sensitivity(scene, truth, trials=trials)
        point = solution_of(around, name) if around else truth
        losses = loss_around(scene, point, trials=trials)
        print_fn(f"{name}: end vs. start ({trials} directions in the start area's free axes)")
        for r in ends:
            print_fn(f"  start moved {r['distance_m'] * 1e3:g} mm: end moved {r['moved_mm_min']:.3g}-"
                     f"{r['moved_mm_max']:.3g} mm, turned {r['turned_deg_min']:.3g}-{r['turned_deg_max']:.3g} deg")
        print_fn(f"  loss around the {'solution' if around else 'truth'} ({losses['loss'] * 1e3:.3g} mm there):")
        for r in losses["sigmas"]:
            print_fn(f"  sigma {r['sigma']:g}: median {r['median'] * 1e3:.3g} mm, smallest {r['min'] * 1e3:.3g} mm")
        results.append(dict(case=name, ends=ends, losses=losses))
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default=",".join(DEFAULT_CASES), help="comma-separated case names")
    parser.add_argument("--around", type=Path, default=None,
                        help="a recovery CSV: probe the loss around its solutions instead of the truths")
    parser.add_argument("--trials", type=int, default=TRIALS)
    args = parser.parse_args(argv)
    run(args.cases.split(","), around=args.around, trials=args.trials)
    return 0


if __name__ == "__main__":
    sys.exit(main())
