"""A tracked source against its last observation alone: how much the extra moments tell.

    python bench/tracked.py                    # examples/scenes/box_tossed_tracked.xml, 300 samples
    python bench/tracked.py --samples 500 --seed 1
    dejaview bench tracked                     # the same through the CLI

Issue 56: "the tracked example: its posterior's 90 % intervals of the start's velocity are
narrower than from its last observation alone (report both), and the truth lies within them."
The example (``examples/make_scenes.py``, ``box_tossed_tracked``) is a box tossed onto the floor,
seen at 0.15 s and 0.35 s (position only), at 0.6 s (pose) and lying still at 1.2 s, with a
tracker's noise (1 cm, 0.1 rad) drawn once into the observations. The bench solves it twice with
``--samples N`` and the truth (``--truth``): as it is, and with its last target alone (the same
noise, the same prior and start area), and prints, per free parameter, the two 90 % intervals,
their widths' ratio and whether each holds the truth, plus the truth's credible level and the
sampler's agreement (R-hat) of each.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "examples" / "scenes" / "box_tossed_tracked.xml"


def solve_both(scene_path: Path = SCENE, samples: int = 300, seed: int = 0) -> dict:
    """The tracked scene and its last observation alone, each solved with ``samples`` posterior
    samples and its truth placed in the posterior.

    Returns:
        ``{"tracked": result, "last": result, "truth": initial_state}`` (``SolveResult`` each).
    """
    from dejaview.inference import solve
    from dejaview.inference.solve import SolveParams
    from dejaview.scene import Scene

    scene = Scene.from_xml(scene_path)
    truth = json.loads(scene_path.with_suffix("").with_suffix(".truth.json").read_text())["initial_state"]
    last = replace(scene, inference=replace(scene.inference, targets=(scene.inference.target,)))
    out = {"truth": truth}
    for name, sc in (("tracked", scene), ("last", last)):
        t0 = time.perf_counter()
        out[name] = solve(sc, SolveParams(samples=samples, seed=seed), truth=truth)
        out[name].settings["wall_s"] = time.perf_counter() - t0
    return out


def rows(results: dict) -> list[dict]:
    """One row per free parameter: both 90 % intervals, the ratio of their widths and whether each
    holds the truth."""
    tracked, last = (results[k].settings for k in ("tracked", "last"))
    out = []
    for name, iv in tracked["posterior"]["intervals"].items():
        other = last["posterior"]["intervals"][name]
        w_t, w_l = iv["90%"][1] - iv["90%"][0], other["90%"][1] - other["90%"][0]
        out.append({"parameter": name, "tracked_lo": iv["90%"][0], "tracked_hi": iv["90%"][1],
                    "last_lo": other["90%"][0], "last_hi": other["90%"][1],
                    "width_ratio": w_t / w_l if w_l > 0 else float("nan"),
                    "truth_in_tracked": tracked["truth"]["in_90"][name],
                    "truth_in_last": last["truth"]["in_90"][name]})
    return out


def run(print_fn=print, samples: int = 300, seed: int = 0, scene_path: Path = SCENE) -> list[dict]:
    """Solve both, print the table and a summary; returns the rows (the velocity rows decide)."""
    results = solve_both(scene_path, samples, seed)
    table = rows(results)
    print_fn(f"{'parameter':22s} {'tracked 90 %':>22s} {'last alone 90 %':>22s} {'width':>7s}  truth in")
    for r in table:
        lo, hi = r["tracked_lo"], r["tracked_hi"]
        lo2, hi2 = r["last_lo"], r["last_hi"]
        print_fn(f"{r['parameter']:22s} [{lo:8.3f}, {hi:8.3f}]   [{lo2:8.3f}, {hi2:8.3f}]  {r['width_ratio']:6.2f}x  "
                 f"{'yes' if r['truth_in_tracked'] else 'NO':>3s} / {'yes' if r['truth_in_last'] else 'NO'}")
    for name in ("tracked", "last"):
        s = results[name].settings
        agree = s["posterior"].get("agreement") or {}
        evidence = ", ".join(f"{v:.1f}" for v in s["posterior"]["sampler"].get("log_evidence", []))
        print_fn(f"{name:8s}: {s['posterior']['samples']} samples, R-hat {agree.get('max_rhat', float('nan')):.3f} "
                 f"(the runs' log evidence {evidence}), truth at the {100 * s['truth']['credible_level']:.0f} % "
                 f"credible level, {s['posterior']['sampler']['rollouts']} rollouts "
                 f"({s['posterior']['sampler'].get('rollouts_by_length', 0):.0f} counted by length), "
                 f"answer -log posterior {s['search']['neg_log_posterior']:.2f}"
                 + (f" (a sample refined; the search's {s['search']['from_samples']['search_neg_log_posterior']:.2f})"
                    if "from_samples" in s["search"] else "") + f", {s['wall_s']:.1f} s")
    velocity = [r for r in table if r["parameter"].startswith("linear_velocity")]
    narrower = sum(r["width_ratio"] < 1 for r in velocity)
    held = sum(r["truth_in_tracked"] for r in velocity)
    print_fn(f"start velocity: {narrower} of {len(velocity)} intervals narrower tracked than from the last "
             f"observation alone (mean width ratio {sum(r['width_ratio'] for r in velocity) / len(velocity):.2f}); "
             f"the truth inside {held} of {len(velocity)} tracked intervals")
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    table = run(samples=args.samples, seed=args.seed)
    velocity = [r for r in table if r["parameter"].startswith("linear_velocity")]
    ok = all(r["width_ratio"] < 1 and r["truth_in_tracked"] for r in velocity)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
