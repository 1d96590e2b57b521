"""The flagship posterior: does `dejaview solve --samples N` converge, and how fast (issue 56)?

    dejaview bench posterior                                    # mug_off_counter.xml, 500 samples, seed 0
    dejaview bench posterior --seeds 0,1,2 --csv posterior.csv
    dejaview bench posterior --scenes mug_off_counter_prior:500,box_tossed_tracked:300
    python bench/posterior.py                                   # the same as the first

Each row runs the command a user runs, `dejaview solve SCENE -o DIR --samples N --seed S -q`, in
a fresh Python process (imports, the native engine's load, the search, the sampler and the
files written: the wall time a user waits), then reads its `result.json`: the search's rollouts
and Jacobians, the sampler's rollouts and tempering steps, the largest R-hat between its two
independent runs (`posterior.agreement.max_rhat`) with the parameter it belongs to, and the modes'
shares. Targets (issue 56, on the project's 2-core machine): the runs agree (R-hat at most
`ReportParams.rhat_limit`, 1.1) and the solve takes at most 30 s. Wall time depends on what
else the machine runs (the header prints the load average); the rollouts and R-hat do not.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "examples" / "scenes"
DEFAULT_SCENES = (("mug_off_counter", 500),)
TARGET_SECONDS = 30.0
"""Seconds per solve with --samples (issue 56: the flagship, mug_off_counter with 500 samples)."""


def target_rhat() -> float:
    from dejaview.inference.params import ReportParams

    return ReportParams.rhat_limit


def parse_scenes(text: str) -> tuple[tuple[str, int], ...]:
    """``"mug_off_counter:500,box_tossed_tracked:300"`` -> ((name, samples), ...); a name without
    ``:N`` takes 500 samples.

    Raises:
        ValueError: empty, an unknown scene, or a count that is not a positive integer.
    """
    out = []
    for item in (v for v in text.replace(" ", "").split(",") if v):
        name, _, count = item.partition(":")
        if not (SCENES / f"{name}.xml").is_file():
            raise ValueError(f"no scene {name!r} in {SCENES}")
        try:
            n = int(count) if count else 500
        except ValueError:
            n = 0
        if n < 1:
            raise ValueError(f"samples must be a positive integer, got {count!r} for {name}")
        out.append((name, n))
    if not out:
        raise ValueError(f"expected scenes as NAME[:SAMPLES],..., got {text!r}")
    return tuple(out)


def row_from_result(result: dict) -> dict:
    """The bench's numbers from a solve's ``result.json`` (parsed)."""
    search = result.get("search", {})
    post = result.get("posterior") or {}
    sampler = post.get("sampler", {})
    agreement = post.get("agreement") or {}
    rhats = {k: v["rhat"] for k, v in post.get("intervals", {}).items() if "rhat" in v}
    worst = max(rhats, key=rhats.get) if rhats else None
    return {"search_rollouts": search.get("rollouts"), "search_jacobians": search.get("jacobians"),
            "sampler_rollouts": sampler.get("rollouts"), "stages": sampler.get("stages"),
            "particles": sampler.get("particles"), "sampler_seconds": sampler.get("seconds"),
            "max_rhat": agreement.get("max_rhat"), "worst_parameter": worst,
            "modes": ";".join(f"{m['probability']:.3f}" for m in post.get("modes", []))}


def solve_once(scene_name: str, samples: int, seed: int) -> dict:
    """One `dejaview solve --samples` in a fresh process, timed; the row of the table."""
    with tempfile.TemporaryDirectory(prefix="dejaview-bench-posterior-") as tmp:
        out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "dejaview.cli", "solve", str(SCENES / f"{scene_name}.xml"), "-o", str(out),
               "--samples", str(samples), "--seed", str(seed), "-q"]
        t0 = time.perf_counter()
        before = os.times()
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        after = os.times()
        seconds = time.perf_counter() - t0
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr.strip()[-500:]}")
        result = json.loads((out / "result.json").read_text(encoding="utf-8"))
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    row = {"scene": scene_name, "samples": samples, "seed": seed, "seconds": seconds, "cpu_seconds": cpu,
           **row_from_result(result)}
    row["met"] = verdict(row)
    return row


def verdict(row: dict) -> bool:
    """Both targets: R-hat at most the limit, wall time at most ``TARGET_SECONDS``."""
    rhat = row.get("max_rhat")
    return rhat is not None and rhat <= target_rhat() and row["seconds"] <= TARGET_SECONDS


def format_row(row: dict) -> str:
    rollouts = (row["search_rollouts"] or 0) + (row["sampler_rollouts"] or 0)
    rhat = "-" if row["max_rhat"] is None else f"{row['max_rhat']:.3f} ({row['worst_parameter']})"
    return (f"{row['scene']:<24} {row['samples']:>5} {row['seed']:>4} {row['seconds']:>7.1f} "
            f"{row['cpu_seconds']:>7.1f} "
            f"{row['search_rollouts'] or 0:>7} {row['search_jacobians'] or 0:>5} {row['sampler_rollouts'] or 0:>8} "
            f"{rollouts:>8} {row['stages'] or 0:>6}  {rhat:<36} {'met' if row['met'] else 'missed'}")


def run(print_fn=print, scenes=DEFAULT_SCENES, seeds=(0,), solve_fn=None) -> list[dict]:
    """Every scene x seed: one timed solve each; prints a row per solve and the verdicts.

    ``solve_fn(scene, samples, seed) -> row``: ``solve_once`` (the tests pass a stand-in)."""
    from dejaview.cli.bench_table import load_average

    solve_fn = solve_once if solve_fn is None else solve_fn
    say = print_fn or (lambda *_: None)
    say(f"posterior bench: `dejaview solve SCENE --samples N`; {load_average()}")
    say(f"targets: R-hat <= {target_rhat():g} between the sampler's runs, <= {TARGET_SECONDS:g} s wall per solve")
    say(f"{'scene':<24} {'N':>5} {'seed':>4} {'wall s':>7} {'cpu s':>7} {'search':>7} {'jac':>5} {'sampler':>8} "
        f"{'rollouts':>8} {'stages':>6}  {'max R-hat (parameter)':<36} verdict")
    rows = []
    for name, samples in scenes:
        for seed in seeds:
            row = solve_fn(name, samples, seed)
            rows.append(row)
            say(format_row(row))
    met = sum(1 for r in rows if r["met"])
    say(f"{met} of {len(rows)} solves met both targets; {load_average()}")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="mug_off_counter:500", help="NAME[:SAMPLES],... bundled scenes")
    parser.add_argument("--seeds", default="0", help="comma-separated seeds")
    parser.add_argument("--csv", type=Path, default=None, help="also write the rows as CSV here")
    args = parser.parse_args(argv)
    rows = run(scenes=parse_scenes(args.scenes), seeds=tuple(int(s) for s in args.seeds.split(",") if s))
    if args.csv is not None:
        from dejaview.cli.bench_table import write_rows_csv

        write_rows_csv(rows, args.csv)
    return 0 if all(r["met"] for r in rows) else 1


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
