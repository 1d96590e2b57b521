"""Small measurements the docs quote: the cost of eager forward-mode AD per op, and of one exact
interpenetration query (python-fcl) per candidate pose.

    dejaview bench micro [--poses 100] [--csv FILE]

- ``forward-ops``: one elementwise product on a (1, 150, 3) float64 tensor (a mug's spheres at
  B = 1) plainly, and under ``torch.func.jvp`` with a constant operand (``x * c``: the constant
  gets an "efficient zero" tangent whose kernels size their output through Python meta
  functions) and with both operands carrying tangents (``x * x``). This is why eager forward
  mode loses to reverse mode on the torch engine (``dejaview.inference.local.default_gradient``).
- ``collision``: ``SceneCollision.penetration`` of each bundled scene's source at random poses
  around its scene pose (within 10 cm, any orientation), one pose per call, median and 90th
  percentile, and how many of the poses overlap something.
- ``threads``: ``THREAD_STEPS`` eager torch-engine steps of the mug scene at B = 1, with
  torch's intra-op pool at 1 thread and at one per core, on idle cores and with every core
  kept busy by another process (a Python spin loop per core): why ``DEJAVIEW_THREADS``
  defaults to 1 (``dejaview.cli.options.configure_torch``).
- ``divergence``: one native rollout (a tumbling box, 2000 steps) with and without the
  divergence check in the C++ loop (``dejaview.sim.divergence.native_limits``), best of 5
  each, interleaved: what the check costs (a few comparisons per body and step).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
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


THREAD_STEPS = 20


def threads(steps: int = THREAD_STEPS, repeats: int = 5, batch: int = 1) -> list[dict]:
    """Seconds per eager torch-engine step (mug, B = ``batch``) at 1 and ``os.cpu_count()`` intra-op
    threads, idle and with every core busy (one spinning process per core)."""
    import torch

    from dejaview.scene import Scene
    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import step
    from dejaview.sim.world import World

    scene = Scene.from_xml(ROOT / "examples" / "scenes" / "mug_off_counter.xml")
    world = World.from_scene(scene)
    state = initial_state(world, scene, batch_size=batch)

    def rollout():
        s = state
        with torch.no_grad():
            for _ in range(steps):
                s = step(world, s)

    cores = os.cpu_count() or 1
    before = torch.get_num_threads()
    rows = []
    try:
        for busy in (False, True):
            spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cores)] \
                if busy else []
            try:
                if busy:
                    time.sleep(0.5)  # the spinners are running
                for n in sorted({1, cores}):
                    torch.set_num_threads(n)
                    rows.append({"section": "threads", "case": f"{n} thread(s), {'busy' if busy else 'idle'} cores",
                                 "threads": n, "busy": busy, "seconds": _per_call(rollout, repeats) / steps})
            finally:
                for proc in spinners:
                    proc.kill()
                    proc.wait()
    finally:
        torch.set_num_threads(before)
    return rows


def divergence_check(steps: int = 2000, repeats: int = 5) -> list[dict]:
    """Best-of-``repeats`` seconds of one native rollout of a tumbling box without and with the
    divergence check, runs interleaved; [] where the native extension does not build."""
    import torch

    from dejaview.scene import Scene
    from dejaview.sim import divergence, native
    from dejaview.sim.build import initial_state
    from dejaview.sim.world import World

    if not native.available():  # no compiler here: nothing to measure
        return []
    ext = native.extension()
    scene = Scene.from_string('''<scene version="1" name="divergence-check" gravity="0 0 -9.81">
  <simulation dt="0.002" duration="1"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
  <object id="box" shape="box" size="0.2 0.15 0.1" mass="1"><pose position="0 0 0.3" orientation="1 0 0 0"/>
    <velocity linear="1 0 -0.5" angular="3 2 1"/></object></scene>''')
    world = World.from_scene(scene)
    init = torch.cat(initial_state(world, scene).tensors(), -1)
    tensors, floats, ints = native.pack_world(world)
    best = {"without": float("inf"), "with": float("inf")}
    for round_ in range(repeats + 1):  # round 0 warms up and is not counted
        for case, extra in (("without", []), ("with", divergence.native_limits())):
            t0 = time.perf_counter()
            ext.rollout(init, steps, 50, False, tensors, floats + extra, ints, 1)
            seconds = time.perf_counter() - t0
            if round_ > 0:
                best[case] = min(best[case], seconds)
    return [{"section": "divergence", "case": f"native rollout, {steps} steps, {case} the check",
             "seconds": seconds} for case, seconds in best.items()]


def run(print_fn=print, poses: int = 100) -> list[dict]:
    """Every section; prints a table of each."""
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
    trows = threads()
    say(f"\n{'eager torch step, mug, B = 1':<44} {'per step':>10} {'vs 1 thread':>12}")
    for r in trows:
        one = next(t for t in trows if t["busy"] == r["busy"] and t["threads"] == 1)["seconds"]
        say(f"{r['case']:<44} {r['seconds'] * 1e3:>8.2f}ms {r['seconds'] / one:>11.2f}x")
    drows = divergence_check()
    if drows:
        say(f"\n{'divergence check (C++ loop), best of 5':<44} {'per rollout':>11} {'vs without':>11}")
        for r in drows:
            say(f"{r['case']:<44} {r['seconds'] * 1e3:>9.2f}ms {r['seconds'] / drows[0]['seconds']:>10.3f}x")
    torch.set_num_threads(1)
    return rows + crows + trows + drows


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=100)
    args = parser.parse_args()
    run(poses=args.poses)
