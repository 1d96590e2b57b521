"""What inferring the physics costs: a solve with `<physics-prior>` against the same solve without.

    dejaview bench physics                                   # three bundled scenes, seed 0
    dejaview bench physics --scenes box_along_shelf,ball_off_table --prior "0.3 0.3 0"

Each scene is solved twice in this process with the default search (no samples): as it is, and
with `<physics-prior friction restitution stiffness>` (the relative standard deviations given)
added; the rows print the wall time, the rollouts (a Jacobian counts as the search counts it),
the end's distance from the observation and the ratio of the times. Target (issue 58): at most
3x. Wall times depend on the machine's load (the header prints it); the rollouts do not.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "examples" / "scenes"
DEFAULT_SCENES = ("box_along_shelf", "ball_off_table", "box_tossed_tracked")
TARGET_RATIO = 3.0
"""Most a solve with a physics prior may cost over the solve without (issue 58)."""


def _solve(scene):
    from dejaview.inference import solve

    t0 = time.perf_counter()
    result = solve(scene)
    seconds = time.perf_counter() - t0
    search = result.settings.get("search", {})
    return seconds, int(search.get("rollouts", 0)), float(result.loss), result.settings.get("physics")


def run(print_fn=print, scenes=DEFAULT_SCENES, prior=(0.3, 0.3, 0.0)) -> list[dict]:
    """One row per scene: seconds and rollouts without and with the physics prior, their ratio."""
    from dejaview.cli.bench_table import load_average
    from dejaview.scene import PhysicsPrior, Scene

    print_fn(f"physics prior friction {prior[0]:g}, restitution {prior[1]:g}, stiffness {prior[2]:g}; "
             f"load average {load_average()}")
    print_fn(f"{'scene':22s} {'plain s':>8s} {'rollouts':>9s} {'loss m':>9s} {'physics s':>10s} {'rollouts':>9s} "
             f"{'loss m':>9s} {'ratio':>6s}  friction restitution")
    rows = []
    for name in scenes:
        scene = Scene.from_xml(SCENES / f"{name}.xml")
        plain = replace(scene, inference=replace(scene.inference, physics_prior=None))
        given = PhysicsPrior(*(v or None for v in prior))
        with_prior = replace(scene, inference=replace(scene.inference, physics_prior=given))
        s0, r0, l0, _ = _solve(plain)
        s1, r1, l1, physics = _solve(with_prior)
        mp = physics["most_probable"]
        row = {"scene": name, "plain_seconds": s0, "plain_rollouts": r0, "plain_loss": l0, "physics_seconds": s1,
               "physics_rollouts": r1, "physics_loss": l1, "ratio": s1 / s0, "friction": mp["friction"],
               "restitution": mp["restitution"], "met": s1 / s0 <= TARGET_RATIO}
        rows.append(row)
        print_fn(f"{name:22s} {s0:8.1f} {r0:9d} {l0:9.4f} {s1:10.1f} {r1:9d} {l1:9.4f} {s1 / s0:6.2f}  "
                 f"{mp['friction']:.3f}    {mp['restitution']:.3f}")
    return rows


if __name__ == "__main__":
    run()
