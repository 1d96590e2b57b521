"""Backend comparison (Table I of the original work): each backend x each optimiser.

    python bench/backends.py                               # 100, 500, 1000 iterations
    python bench/backends.py --iterations 10,50,100 --csv backends.csv
    python bench/backends.py --scene examples/scenes/ball_off_table.xml --iterations 5,20

For each backend (``spheres``: DejaView's sphere-packing simulator on
PyTorch; ``warp``: NVIDIA Warp's ``warp.sim``, XPBD by default) and each
optimiser (gradient descent, Adam, L-BFGS, BFGS), one ``dejaview.solve`` of
max(iterations) iterations from the scene's initial guess, in reverse mode
(the one mode both backends offer), restarts off; then the best loss after
each iteration count, the mean wall time per iteration and per loss +
gradient evaluation. Both backends run in the same process, one after the
other, so the ratio of their times per iteration (and per evaluation, which
does not depend on how many evaluations an optimiser's line search takes) is
measured under the same load.

Default scene: ``examples/scenes/ball_rolled.xml`` (the cheap scene of
``bench/optimizers.py``: a mesh ball bowled across the floor with spin, 40
steps of 10 ms, 11 free parameters). Its target was simulated by the sphere
backend, so the Warp backend cannot reach it exactly (its icosphere rolls as
a polyhedron and rests 4 mm higher on XPBD's hard contact than on the penalty
contact): compare Warp's best losses with that floor in mind.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "examples" / "scenes" / "ball_rolled.xml"
ITERATIONS = (100, 500, 1000)
BACKENDS = ("spheres", "warp")
OPTIMIZERS = ("gd", "adam", "lbfgs", "bfgs")


def _load() -> str:
    from dejaview.cli.bench_table import load_average

    return load_average()


def _fmt(v: float) -> str:
    return f"{v:.3e}" if math.isfinite(v) else str(v)


def run(print_fn=print, iterations=ITERATIONS, backends=BACKENDS, optimizers=OPTIMIZERS, scene=None,
        csv_path=None, warp_options: dict | None = None) -> list[dict]:
    """Run the comparison.

    Args:
        print_fn: where the table goes (None: silent).
        iterations: iteration counts to report the best loss at (each run lasts the largest).
        backends: any of ``spheres``, ``warp``.
        optimizers: any of ``gd``, ``adam``, ``lbfgs``, ``bfgs``.
        scene: scene file (or Scene) with an ``<inference>`` section (default ``SCENE``).
        csv_path: also write the rows here as CSV.
        warp_options: options of the warp backend (``integrator``, ``substeps``, ...).
    Returns:
        One dict per (backend, optimizer): scene, backend, optimizer, params, iterations (run),
        ``best_loss_<n>`` for each n, final_best_loss, s_per_iteration, evaluations_per_iteration,
        s_per_evaluation, seconds; then one row per optimiser (and one ``all``) with
        ``backend="warp/spheres"`` holding the ratios of s_per_iteration and s_per_evaluation
        (when both backends ran).
    Raises:
        InferenceError: a backend that cannot be used (e.g. warp not installed).
    """
    import time

    import torch

    from dejaview.backends import make_problem
    from dejaview.inference import solve
    from dejaview.inference.solve import SolveParams
    from dejaview.scene import Scene

    say = print_fn or (lambda *_: None)
    counts = sorted({int(n) for n in iterations})
    if not counts or counts[0] < 1:
        raise ValueError(f"iterations must be positive integers, got {iterations!r}")
    scene = scene if scene is not None else SCENE
    sc = scene if hasattr(scene, "objects") else Scene.from_xml(scene)
    if sc.inference is None:
        raise ValueError(f"{scene}: the scene has no <inference> section")
    name = Path(sc.path).name if sc.path else sc.name
    problems = {}
    for backend in backends:
        problem = make_problem(sc, backend, **((warp_options or {}) if backend == "warp" else {}))
        t0 = time.perf_counter()
        problem.value_and_grad(problem.layout.encode(), "reverse")  # warm-up (Warp compiles kernels)
        problems[backend] = problem
        say(f"{backend}: {problem.simulation_settings()} (warm-up {time.perf_counter() - t0:.1f} s)")
    first = next(iter(problems.values()))
    say(f"scene: {name} ({first.steps} steps of {1000 * first.dt:g} ms; {first.num_params} parameters; "
        f"loss {first.loss_kind}, evaluate {first.evaluate}); reverse mode; restarts off; "
        f"start: the scene's guess")
    say(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); {_load()}")
    head = (f"{'optimizer':<9} {'backend':<8} " + " ".join(f"{'best@' + str(n):>10}" for n in counts)
            + f" {'s/iter':>8} {'evals/iter':>10} {'s/eval':>8}")
    say(head)
    rows = []
    for opt in optimizers:
        for backend, problem in problems.items():
            per_iteration = []
            seen = [problem.evaluations]

            def tally(progress, problem=problem, per_iteration=per_iteration, seen=seen):
                per_iteration.append(problem.evaluations - seen[0])
                seen[0] = problem.evaluations

            result = solve(sc, SolveParams(iterations=counts[-1], optimizer=opt, gradient="reverse",
                           epsilon=0.0), problem=problem, callback=tally)
            history = result.iterations
            evaluations = sum(per_iteration)
            seconds = history[-1].elapsed_s
            row = {"scene": name, "backend": backend, "optimizer": opt, "params": problem.num_params,
                   "iterations": len(history)}
            for n in counts:
                row[f"best_loss_{n}"] = history[min(n, len(history)) - 1].best_loss
            row.update(final_best_loss=result.loss, s_per_iteration=seconds / len(history),
                       evaluations_per_iteration=evaluations / len(history),
                       s_per_evaluation=seconds / evaluations if evaluations else math.nan, seconds=seconds)
            rows.append(row)
            say(f"{opt:<9} {backend:<8} " + " ".join(f"{_fmt(row[f'best_loss_{n}']):>10}" for n in counts)
                + f" {row['s_per_iteration']:>8.3f} {row['evaluations_per_iteration']:>10.2f}"
                  f" {row['s_per_evaluation']:>8.3f}")
    if "spheres" in problems and "warp" in problems:
        say("ratio warp / spheres (same run):")
        for opt in (*optimizers, "all"):
            pick = lambda b: [r for r in rows if r["backend"] == b and opt in (r["optimizer"], "all")]  # noqa: E731
            w, s = pick("warp"), pick("spheres")
            ratio = {"s_per_iteration": (sum(r["seconds"] for r in w) / sum(r["iterations"] for r in w))
                     / (sum(r["seconds"] for r in s) / sum(r["iterations"] for r in s))}
            ev = lambda rs: sum(r["seconds"] for r in rs) / max(1e-12, sum(  # noqa: E731
                r["evaluations_per_iteration"] * r["iterations"] for r in rs))
            ratio["s_per_evaluation"] = ev(w) / ev(s)
            rows.append({"scene": name, "backend": "warp/spheres", "optimizer": opt, **ratio})
            say(f"  {opt:<6} s/iteration x{ratio['s_per_iteration']:.2f}, "
                f"s/evaluation x{ratio['s_per_evaluation']:.2f}")
    say("best@n: best loss (m) within the first n iterations; evals: loss + gradient evaluations computed")
    say(_load())
    if csv_path is not None:
        write_csv(rows, csv_path)
        say(f"wrote {csv_path}")
    return rows


def write_csv(rows: list[dict], path) -> Path:
    """Write ``run``'s rows as CSV (one column per key, blank where a row has none)."""
    from dejaview.cli.bench_table import write_rows_csv

    return write_rows_csv(rows, path)


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", default=",".join(map(str, ITERATIONS)),
                        help="comma-separated iteration counts (default: %(default)s)")
    parser.add_argument("--scene", default=None, help=f"scene file (default: {SCENE.relative_to(ROOT)})")
    parser.add_argument("--backends", default=",".join(BACKENDS))
    parser.add_argument("--optimizers", default=",".join(OPTIMIZERS))
    parser.add_argument("--integrator", default=None, choices=("xpbd", "semi-implicit"),
                        help="warp integrator (default: the scene's, else xpbd)")
    parser.add_argument("--csv", default=None, help="write the rows as CSV")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from dejaview.cli.bench_table import parse_counts, parse_names
    from dejaview.cli.options import configure_torch
    from dejaview.errors import DejaViewError

    configure_torch()
    try:
        run(iterations=parse_counts(args.iterations), backends=parse_names(args.backends, BACKENDS),
            optimizers=parse_names(args.optimizers, OPTIMIZERS), scene=args.scene, csv_path=args.csv,
            warp_options={"integrator": args.integrator} if args.integrator else None)
    except (ValueError, DejaViewError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
