"""Small measurements the docs quote: the cost of eager forward-mode AD per op, and of one exact
interpenetration query (python-fcl) per candidate pose.

    dejaview bench micro [--poses 100] [--csv FILE]

- ``forward-ops``: one elementwise product on a (1, 150, 3) float64 tensor (a mug's spheres at
  B = 1) plainly, and under ``torch.func.jvp`` with a constant operand (``x * c``: the constant
  gets an "efficient zero" tangent whose kernels size their output through Python meta
  functions) and with both operands carrying tangents (``x * x``). This is why eager forward
  mode loses to reverse mode on the torch engine (``dejaview.inference.solve.default_gradient``).
- ``collision``: ``SceneCollision.penetration`` of each bundled scene's source at random poses
  around its scene pose (within 10 cm, any orientation), one pose per call, median and 90th
  percentile, and how many of the poses overlap something.
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("ball_off_table", "box_along_shelf", "mug_off_counter", "box_among_boxes")


def _per_call(fn, repeats: int) -> float:
    """Median seconds per call of ``fn`` over ``repeats`` calls (after one warm-up)."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def forward_ops(repeats: int = 200) -> list[dict]:
    """Seconds per elementwise product: plain, and under ``torch.func.jvp`` (x * c and x * x)."""
    import torch

    x = torch.randn(1, 150, 3, dtype=torch.float64)
    c = torch.randn(1, 150, 3, dtype=torch.float64)
    v = torch.randn_like(x)
    cases = {
        "x * c, no AD": lambda: x * c,
        "x * x, jvp": lambda: torch.func.jvp(lambda y: y * y, (x,), (v,)),
        "x * c, jvp (constant operand)": lambda: torch.func.jvp(lambda y: y * c, (x,), (v,)),
    }
    return [{"section": "forward-ops", "case": name, "seconds": _per_call(fn, repeats)}
            for name, fn in cases.items()]


def collision(poses: int = 100, seed: int = 0) -> list[dict]:
    """Seconds per ``SceneCollision.penetration`` query of one pose, per bundled scene."""
    import numpy as np

    from dejaview.geometry.collision import SceneCollision
    from dejaview.scene import Scene

    rng = np.random.default_rng(seed)
    rows = []
    for name in SCENES:
        scene = Scene.from_xml(ROOT / "examples" / "scenes" / f"{name}.xml")
        source = scene.inference.source
        t0 = time.perf_counter()
        checker = SceneCollision(scene)
        build = time.perf_counter() - t0
        pose = np.asarray(next(o for o in scene.objects if o.id == source).pose.position)
        times, hits = [], 0
        for _ in range(poses):
            p = pose + rng.uniform(-0.1, 0.1, 3)
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            t0 = time.perf_counter()
            hit, _, _ = checker.penetration(source, p, q)
            times.append(time.perf_counter() - t0)
            hits += int(bool(np.asarray(hit).reshape(-1)[0]))
        times.sort()
        rows.append({"section": "collision", "case": name, "seconds": statistics.median(times),
                     "p90_seconds": times[int(0.9 * (len(times) - 1))], "overlapping": hits, "poses": poses,
                     "build_seconds": build})
    return rows


def run(print_fn=print, poses: int = 100) -> list[dict]:
    """Both sections; prints a table of each."""
    import torch

    torch.set_num_threads(1)
    say = print_fn
    load = " ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    say(f"micro benchmarks; torch {torch.__version__}, 1 thread; load average {load}")
    rows = forward_ops()
    base = rows[0]["seconds"]
    say(f"{'elementwise product, (1, 150, 3) float64':<44} {'per call':>10} {'vs plain':>9}")
    for r in rows:
        say(f"{r['case']:<44} {r['seconds'] * 1e6:>8.1f}us {r['seconds'] / base:>8.1f}x")
    crows = collision(poses)
    say(f"\n{'collision query (one pose)':<28} {'median':>9} {'p90':>9} {'overlapping':>12} {'build':>8}")
    for r in crows:
        say(f"{r['case']:<28} {r['seconds'] * 1e3:>7.1f}ms {r['p90_seconds'] * 1e3:>7.1f}ms "
            f"{r['overlapping']:>5} of {r['poses']:<4} {r['build_seconds']:>7.1f}s")
    return rows + crows


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=100)
    args = parser.parse_args()
    run(poses=args.poses)
