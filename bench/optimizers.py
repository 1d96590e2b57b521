"""Optimiser comparison: best loss after N iterations, and time per iteration.

    python bench/optimizers.py                          # 100, 500, 1000 iterations
    python bench/optimizers.py --iterations 10,50,100 --csv optimizers.csv
    python bench/optimizers.py --scene examples/scenes/ball_off_table.xml
    python bench/optimizers.py --make-scene             # regenerate the default scene

Reproduces the original work's comparison of optimisers (gradient descent,
Adam, L-BFGS, BFGS) and gradient modes (forward, reverse): for each pair,
one ``dejaview.solve`` of max(iterations) iterations from the scene's initial
guess, then the best loss after each iteration count (``Progress.best_loss``
of that iteration), the mean wall time per iteration and the loss + gradient
evaluations per iteration (L-BFGS's line search may take several; an L-BFGS
iteration that cannot move takes none, as the loop answers a repeated point
from its cache, so its mean time per iteration can look cheap). Restarts
(``<exploration>``) are switched off, so the optimisers are compared alone.

The default scene, ``examples/scenes/ball_rolled.xml``, is deliberately
cheap: a ball (one sphere) bowled across the floor with spin, 0.4 s in 40
steps of 10 ms, 11 free parameters. So long a step needs two contact
settings: ``contact-frequency="60"`` (the default, 0.25 / h = 25 rad/s, would
let the resting ball sink 3 cm; 60 rad/s: under 5 mm) and
``unload-velocity="0.1"`` m/s, about g h (with the default 0.01 m/s a resting
contact flips between loading and unloading every step and the ball chatters
at +-5 cm/s). One loss + gradient of the bundled examples (dt = 2 ms,
0.6-1.5 s, up to 150 spheres) costs seconds in reverse mode and tens of
seconds in forward mode on a CPU, so 8 runs of 1000 iterations there take
days; choose such a scene with ``scene=`` / ``--scene`` and fewer iterations.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "examples" / "scenes" / "ball_rolled.xml"
ITERATIONS = (100, 500, 1000)
MODES = ("forward", "reverse")
OPTIMIZERS = ("gd", "adam", "lbfgs", "bfgs")


def make_default_scene() -> Path:
    """Write ``ball_rolled.xml`` and ``ball_rolled.truth.json`` into examples/scenes
    (the true start is simulated and its final pose becomes the target)."""
    import importlib.util

    from dejaview.scene import InferenceSettings, Scene, SimulationSettings, StartArea, Target

    spec = importlib.util.spec_from_file_location("make_scenes", ROOT / "examples" / "make_scenes.py")
    ms = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ms)
    truth = ms.movable("ball", "ball", (-0.3, 0.05, 0.05), linear=(2.0, 0.3, 0.0), angular=(4.0, -20.0, 3.0),
                       mass=0.4)
    guess = ms.movable("ball", "ball", (-0.2, 0.0, 0.05), linear=(1.0, 0.0, 0.0), mass=0.4)
    scene = Scene(
        name="ball-rolled",
        objects=(ms.floor(), truth),
        simulation=SimulationSettings(dt=0.01, duration=0.4, friction=0.5, restitution=0.3,
                                      extra={"substeps": "1", "contact-frequency": "60",
                                             "unload-velocity": "0.1"}),
        inference=InferenceSettings(
            source="ball", targets=(Target((0.0, 0.0, 0.0), moving=True),), iterations=100, optimizer="lbfgs",
            loss="pose", evaluate="final",
            start_area=StartArea((-0.5, -0.2, 0.05), (0.0, 0.2, 0.05))))
    scene, record = ms.with_truth(scene, truth, guess)
    note = ("A ball bowled across the floor with backspin and side spin: it skids, then rolls "
            "(0.4 s in 10 ms steps: the cheap default scene of bench/optimizers.py).")
    SCENE.write_text(scene.to_xml().replace("?>\n", f"?>\n<!-- {note} -->\n", 1), encoding="utf-8")
    SCENE.with_suffix(".truth.json").write_text(json.dumps(record, indent=2), encoding="utf-8")
    Scene.from_xml(SCENE)  # validates
    return SCENE


def _load() -> str:
    from dejaview.cli.bench_table import load_average

    return load_average()


def _fmt(v: float) -> str:
    return f"{v:.3e}" if math.isfinite(v) else str(v)


def run(print_fn=print, iterations=ITERATIONS, modes=MODES, optimizers=OPTIMIZERS, scene=None,
        csv_path=None) -> list[dict]:
    """Run the comparison.

    Args:
        print_fn: where the table goes (None: silent).
        iterations: iteration counts to report the best loss at (each run lasts the largest).
        modes: gradient modes, ``forward`` and/or ``reverse``.
        optimizers: any of ``gd``, ``adam``, ``lbfgs``, ``bfgs``.
        scene: scene file (or Scene) with an ``<inference>`` section (default ``SCENE``).
        csv_path: also write the rows here as CSV.
    Returns:
        One dict per (optimizer, mode): scene, optimizer, mode, params, iterations (run),
        ``best_loss_<n>`` for each n in ``iterations``, final_best_loss,
        ms_per_iteration, evaluations_per_iteration, ms_per_evaluation,
        idle_iterations (iterations that computed no evaluation), seconds (whole run).
    """
    import torch

    from dejaview.backends.spheres import SpheresProblem
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
    problem = SpheresProblem.from_scene(sc)
    problem.value_and_grad(problem.layout.encode(), "reverse")  # warm-up outside the timings
    say(f"scene: {name} ({problem.steps} steps of {1000 * problem.world.dt:g} ms, "
        f"{problem.world.substeps} substep(s); {problem.num_params} parameters; loss "
        f"{problem.loss_kind}, evaluate {problem.evaluate}); restarts off; start: the scene's guess")
    say(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); {_load()}")
    head = f"{'optimizer':<9} {'mode':<8} " + " ".join(f"{'best@' + str(n):>10}" for n in counts)
    say(head + f" {'ms/iter':>9} {'evals/iter':>10} {'ms/eval':>8} {'idle':>5}")
    rows = []
    for opt in optimizers:
        for mode in modes:
            # loss + gradient evaluations actually computed, per iteration (the loop's cache
            # answers a repeated point, so an L-BFGS iteration that cannot move costs none)
            per_iteration = []
            seen = [problem.evaluations]

            def tally(progress, per_iteration=per_iteration, seen=seen):
                per_iteration.append(problem.evaluations - seen[0])
                seen[0] = problem.evaluations

            result = solve(sc, SolveParams(iterations=counts[-1], optimizer=opt, gradient=mode, epsilon=0.0),
                           problem=problem, callback=tally)
            evaluations = sum(per_iteration)
            history = result.iterations
            row = {"scene": name, "optimizer": opt, "mode": mode, "params": problem.num_params,
                   "iterations": len(history)}
            for n in counts:
                # a run that stopped early keeps its best loss
                row[f"best_loss_{n}"] = history[min(n, len(history)) - 1].best_loss
            seconds = history[-1].elapsed_s
            row.update(final_best_loss=result.loss, ms_per_iteration=1000 * seconds / len(history),
                       evaluations_per_iteration=evaluations / len(history),
                       ms_per_evaluation=1000 * seconds / evaluations if evaluations else math.nan,
                       idle_iterations=sum(1 for e in per_iteration if e == 0), seconds=seconds)
            rows.append(row)
            say(f"{opt:<9} {mode:<8} " + " ".join(f"{_fmt(row[f'best_loss_{n}']):>10}" for n in counts)
                + f" {row['ms_per_iteration']:>9.1f} {row['evaluations_per_iteration']:>10.2f}"
                  f" {row['ms_per_evaluation']:>8.1f} {row['idle_iterations']:>5}")
    say("best@n: best loss within the first n iterations; evals: loss + gradient evaluations computed; "
        "idle: iterations that computed none (L-BFGS could not move, e.g. a failed line search)")
    say(_load())
    if csv_path is not None:
        write_csv(rows, csv_path)
        say(f"wrote {csv_path}")
    return rows


def write_csv(rows: list[dict], path) -> Path:
    """Write ``run``'s rows as CSV (one line per optimizer and mode)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["optimizer"],
                                lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return path


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", default=",".join(map(str, ITERATIONS)),
                        help="comma-separated iteration counts")
    parser.add_argument("--scene", default=None, help="scene file (default: %(default)s)")
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--optimizers", default=",".join(OPTIMIZERS))
    parser.add_argument("--csv", default=None, help="write the rows as CSV")
    parser.add_argument("--make-scene", action="store_true", help="regenerate the default scene")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    if args.make_scene:
        print(make_default_scene())
        return 0
    from dejaview.cli.bench_table import parse_counts, parse_names
    from dejaview.cli.options import configure_torch

    configure_torch()
    try:
        iterations = parse_counts(args.iterations)
        modes, optimizers = parse_names(args.modes, MODES), parse_names(args.optimizers, OPTIMIZERS)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    run(iterations=iterations, modes=modes, optimizers=optimizers, scene=args.scene, csv_path=args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
