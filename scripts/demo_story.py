"""Print the demo's story: the answers of two solves beside the truth (scripts/demo).

    python scripts/demo_story.py TRUTH.json DIR [DIR ...]

Each DIR holds a solve's result.json. For each: the start it found, the prior it assumed, its
negative log posterior, how far its re-simulated END lies from where the mug was seen lying (and
when it came to rest), how many distinct pasts (modes) the search found that explain the end, and,
where the solve drew posterior samples with ``--truth``, the truth's credible level.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path


def fmt(v) -> str:
    return "(" + ", ".join(f"{x:5.2f}" for x in v) + ")"


def tilt_deg(q) -> float:
    """Angle (degrees) between the object's z axis and the world's z axis."""
    w, x, y, _ = q
    return math.degrees(math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (x * x + y * y)))))


def main(argv: list[str]) -> int:
    truth = json.loads(Path(argv[0]).read_text())["initial_state"]
    rows = [("truth", truth, None)]
    for d in argv[1:]:
        rows.append((d, json.loads((Path(d) / "result.json").read_text())["initial_state"],
                     json.loads((Path(d) / "result.json").read_text())))
    print(f"{'':<18} {'start position m':<22} {'velocity m/s':<22} {'spin rad/s':<22} {'tilt':>6}")
    for name, s, _ in rows:
        print(f"{Path(name).name:<18} {fmt(s['position']):<22} {fmt(s['linear_velocity']):<22} "
              f"{fmt(s['angular_velocity']):<22} {tilt_deg(s['orientation']):5.1f}d")
    for name, _, data in rows[1:]:
        p, e, s = data["prior"], data["end_error"], data["search"]
        prior = ("flat" if p["speed"] is None and p["spin"] is None and p["tilt"] is None else
                 f"speed {p['speed']} m/s, spin {p['spin']} rad/s, tilt {p['tilt']} rad")
        came = data.get("rest", {}).get("came_to_rest_s")
        rest = f"at rest from {came:.2f} s" if came is not None else "still moving at the end"
        print(f"{Path(name).name}: prior {prior}; -log posterior {s['neg_log_posterior']:.3g}; its end "
              f"(t = {e['time']:.2f} s) lies {e['position_error'] * 1000:.1f} mm / {e['angle_error_deg']:.1f} deg "
              f"from where the mug was seen lying ({rest}); {len(s['modes'])} distinct pasts refined")
        truth = data.get("truth")
        if truth is not None and "credible_level" in truth:
            post = data["posterior"]
            agree = post.get("agreement") or {}
            print(f"{'':<{len(Path(name).name)}}  posterior: {post['samples']} samples (R-hat "
                  f"{agree.get('max_rhat', float('nan')):.2f}); the truth (-log posterior "
                  f"{truth['neg_log_posterior']:.3g}) at the {100 * truth['credible_level']:.0f} % credible level "
                  f"(the posterior mass more probable than it; spread evenly over 0-100 % where the samples "
                  f"are calibrated): {sum(truth['in_90'].values())} of {len(truth['in_90'])} parameters inside "
                  f"their 90 % intervals")
        for w in data.get("warnings", []):
            print(f"{'':<{len(Path(name).name)}}  warning: {w}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
