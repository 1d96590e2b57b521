"""Print the demo's story: the answers of two solves beside the truth (scripts/demo).

    python scripts/demo_story.py TRUTH.json DIR [DIR ...]

Each DIR holds a solve's result.json. For each: the start it found, the prior it assumed, its
negative log posterior, how far its re-simulated end lies from the observation, and how many
distinct pasts (modes) the search found that explain the end.
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
        p, m, s = data["prior"], data["matched_pose"], data["search"]
        prior = ("flat" if p["speed"] is None and p["spin"] is None and p["tilt"] is None else
                 f"speed {p['speed']} m/s, spin {p['spin']} rad/s, tilt {p['tilt']} rad")
        print(f"{Path(name).name}: prior {prior}; -log posterior {s['neg_log_posterior']:.3g}; "
              f"end {m['position_error'] * 1000:.1f} mm / {m['angle_error_deg']:.1f} deg from the "
              f"observation; {len(s['modes'])} distinct pasts found that the search refined")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
