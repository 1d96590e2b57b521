"""Where one loss + gradient spends its time: ``torch.profiler`` over a solver evaluation.

    python bench/op_profile.py                                   # the reference mug scene, eager
    python bench/op_profile.py --compile                         # compiled rollouts (first compile excluded)
    python bench/op_profile.py --scene examples/scenes/mug_off_counter.xml --steps 400 --rows 30

Profiles the torch engine (``engine="torch"``): the native engine is one C++
call per rollout, which ``perf`` profiles better than ``torch.profiler``.

Builds the scene's inference problem, runs one warm-up loss + gradient (which
compiles, with ``--compile``), then profiles ``--repeat`` more and prints the
``--rows`` ops with the most self CPU time, plus the time per evaluation.
Measured on ``mug_off_counter`` (0.8 s) with ``--compile``: 74 % of the time is
self time inside the two compiled graphs, 10 % extern ``mm``/``bmm`` (the
3 x 3 products), so Python overhead was not what kept the simulator issue's
targets out of reach for the torch engine.

Named ``op_profile``, not ``profile``: a ``profile.py`` on the path of a
benchmark script would shadow the standard library module that ``cProfile``
(and with it torch._dynamo) imports.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "examples" / "scenes" / "mug_thrown.xml"


def run(scene=None, steps: int | None = None, compile: bool = False, mode: str = "reverse",
        repeat: int = 1, rows: int = 20, print_fn=print) -> dict:
    """Profile ``repeat`` loss + gradient evaluations of the scene's initial guess.

    Returns:
        dict with ``seconds_per_evaluation``, ``warmup_s`` and ``table`` (the printed text).
    """
    import torch
    from torch.profiler import ProfilerActivity, profile

    from dejaview.backends.spheres import SpheresProblem
    from dejaview.scene import Scene

    say = print_fn or (lambda *_: None)
    sc = Scene.from_xml(scene or SCENE)
    problem = SpheresProblem.from_scene(sc, engine="torch")
    if steps is not None:
        problem.steps = int(steps)
    problem.compile = compile
    x = problem.layout.encode().to(torch.float64)
    t0 = time.perf_counter()
    problem.value_and_grad(x, mode)
    warmup = time.perf_counter() - t0
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        for _ in range(repeat):
            problem.value_and_grad(x, mode)
        per_eval = (time.perf_counter() - t0) / repeat
    table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)
    say(f"{Path(sc.path).name if sc.path else sc.name}: {problem.steps} steps, {mode} mode, "
        f"{'compiled' if compile else 'eager'}; warm-up {warmup:.2f} s; "
        f"{per_eval:.3f} s per loss + gradient under the profiler")
    say(table)
    return {"seconds_per_evaluation": per_eval, "warmup_s": warmup, "table": table}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default=None, help=f"scene file (default: {SCENE.relative_to(ROOT)})")
    parser.add_argument("--steps", type=int, default=None, help="rollout length (default: the scene's)")
    parser.add_argument("--compile", action="store_true", help="compiled rollouts")
    parser.add_argument("--mode", choices=("reverse", "forward"), default="reverse")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--rows", type=int, default=20)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from dejaview.cli.options import configure_torch

    configure_torch()
    run(scene=args.scene, steps=args.steps, compile=args.compile, mode=args.mode, repeat=args.repeat,
        rows=args.rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
