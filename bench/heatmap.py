"""Heatmap speed: a 16 x 16 grid with 4 samples per cell, batched versus one at a time.

    python bench/heatmap.py                     # 16 x 16 x 4 on examples/scenes/ball_down_ramp.xml
    python bench/heatmap.py --cells 4x4 --samples 1 --iterations 3 --serial 2   # smoke test
    python bench/heatmap.py --serial 0          # batched only

The per-cell optimisations of the ``basins`` method (``compute_heatmap(method="basins")``; the
default heatmap, the posterior's marginal, is timed by ``dejaview heatmap`` itself, see
docs/benchmarks.md, "Posterior"). Batched: ``compute_heatmap`` as the CLI runs it (all candidates of a chunk as
one batch, ``--batch-size`` candidates per chunk, ``--workers`` processes running
chunks at once), the whole pipeline (optimisation, deduplication, basin
measurement, weighting).

One at a time: the same optimisation (same optimiser, iterations and guesses)
of each candidate alone, a batch of one, as a loop over candidates would run
it. Running all 1024 that way takes hours here, so ``--serial N`` runs the
first N candidates and extrapolates their mean time to the whole grid (the
printed figure says so); ``--serial -1`` runs them all. The ratio compares the
optimisation phases, which is where the time goes.

The reference scene is ``examples/scenes/ball_down_ramp.xml`` (a ball let go
on a ramp, 240 steps of 5 ms, 2 free parameters): its heatmap is the one the
tests check against the known start. Target: the batched 16 x 16 x 4 under
5 minutes on this 2-core machine.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "examples" / "scenes" / "ball_down_ramp.xml"
TARGET_S = 300.0


def _load() -> str:
    from dejaview.cli.bench_table import load_average

    return load_average()


def serial_seconds(scene, cells, samples, iterations, count, seed=0) -> tuple[float, int]:
    """Time of optimising the first ``count`` candidates of the grid one at a time.

    Returns:
        (seconds, candidates run).
    """
    import torch

    from dejaview.backends import make_problem
    from dejaview.heatmap.search import DEFAULT_ADAM_LR, cell_boxes, with_layout
    from dejaview.inference.optimize import optimize
    from dejaview.backends.base import objective_to_loss

    problem = make_problem(scene)
    layout = problem.layout
    lo, hi = cell_boxes(layout.lo, layout.hi, *cells)
    gen = torch.Generator().manual_seed(seed)
    total = cells[0] * cells[1] * samples
    count = total if count < 0 else min(count, total)
    start = time.perf_counter()
    for n in range(count):
        c = n // samples
        one = with_layout(problem, replace(layout, lo=lo[c:c + 1], hi=hi[c:c + 1]))
        x0 = one.layout.sample(1, gen).to(problem.dtype)
        optimize(one.objective_and_grad, x0, optimizer="adam", iterations=iterations, gradient="reverse",
                 lr=DEFAULT_ADAM_LR, report=objective_to_loss)
    return time.perf_counter() - start, count


def run(print_fn=print, scene=None, cells=(16, 16), samples=4, iterations=30, workers=2,
        batch_size=1024, serial=8, csv_path=None) -> list[dict]:
    """Run the benchmark; returns rows (``name``, ``value``, ``unit``, ``note``)."""
    import torch

    from dejaview.heatmap import compute_heatmap
    from dejaview.scene import Scene

    say = print_fn or (lambda *a, **k: None)
    path = Path(scene) if scene else SCENE
    sc = Scene.from_xml(path)
    nx, ny = cells
    total = nx * ny * samples
    say(f"heatmap bench: {path.name}, {nx} x {ny} cells x {samples} samples = {total} optimisations, "
        f"{iterations} Adam iterations each, reverse mode")
    say(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op thread(s), {workers} worker "
        f"process(es), batch {batch_size}; {_load()}")
    rows = []
    t0 = time.perf_counter()
    c0 = time.process_time()
    phases = {}

    def progress(p):
        phases.setdefault(p.phase, time.perf_counter())

    result = compute_heatmap(sc, cells=cells, samples=samples, iterations=iterations, workers=workers,
                             batch_size=batch_size, callback=progress, method="basins")
    batched = time.perf_counter() - t0
    cpu = time.process_time() - c0
    optimise = phases.get("robustness", time.perf_counter()) - t0
    rows.append({"name": "batched total", "value": batched, "unit": "s",
                 "note": f"{len(result.solutions)} distinct solutions, entropy {result.entropy_bits():.2f} bits"})
    rows.append({"name": "batched CPU time", "value": cpu, "unit": "s",
                 "note": "this process only (not the worker processes)"})
    rows.append({"name": "batched optimisation", "value": optimise, "unit": "s", "note": ""})
    rows.append({"name": "batched per candidate", "value": optimise / total, "unit": "s",
                 "note": "optimisation phase / candidates"})
    rows.append({"name": "target", "value": TARGET_S, "unit": "s",
                 "note": "met" if batched <= TARGET_S else "missed"})
    if serial:
        c1 = time.process_time()
        secs, n = serial_seconds(sc, cells, samples, iterations, serial)
        serial_cpu = time.process_time() - c1
        per = secs / n
        whole = per * total
        how = "measured" if n == total else f"extrapolated from {n} candidates"
        rows.append({"name": "one at a time per candidate", "value": per, "unit": "s",
                     "note": f"CPU {serial_cpu / n:.3f} s"})
        rows.append({"name": "one at a time optimisation", "value": whole, "unit": "s", "note": how})
        rows.append({"name": "ratio one-at-a-time / batched", "value": whole / optimise, "unit": "x",
                     "note": "optimisation phases"})
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        say(f"{r['name']:<{width}}  {r['value']:10.3f} {r['unit']:<2} {r['note']}")
    if csv_path:
        from dejaview.cli.bench_table import write_rows_csv

        write_rows_csv(rows, csv_path)
        say(f"wrote {csv_path}")
    return rows


def main(argv=None) -> int:
    import torch

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=None)
    parser.add_argument("--cells", default="16x16")
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--serial", type=int, default=8, help="candidates run one at a time (-1: all)")
    parser.add_argument("--csv", default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(int(os.environ.get("DEJAVIEW_THREADS", "1")))
    nx, ny = (int(v) for v in args.cells.split("x"))
    run(scene=args.scene, cells=(nx, ny), samples=args.samples, iterations=args.iterations,
        workers=args.workers, batch_size=args.batch_size, serial=args.serial, csv_path=args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
