"""Warp 1.9.1 as a differentiable backend: its gradients against finite differences, and rolling.

    python bench/warp_limits.py
    dejaview bench warp-limits [--scenes ball_rolled,ball_off_table] [--eps 1e-3] [--quick]

What docs/benchmarks.md says of Warp's limits, measured by one command. Both backends run
in the same process on the same scenes (the spheres backend, DejaView's own, is the control):

1. **Gradients against central differences.** At each scene's initial guess ``x0``, the
   backend's reverse-mode gradient of the loss beside central differences of the same loss,
   ``(L(x0 + eps e_i) - L(x0 - eps e_i)) / (2 eps)`` per parameter ``i`` (parameters in the
   layout's own units). Per backend and scene: how many components disagree in sign, and the
   largest ratio ``max(|g / fd|, |fd / g|)`` over the components where either is not tiny
   (``> 1e-3`` of the largest). Warp runs in float32: ``eps`` is large enough for its loss's
   round-off (``1e-3`` changes a loss of centimetres by ~1e-4 m, against ~1e-7 of round-off).
2. **Rolling.** The ball of ``ball_rolled.xml`` (bowled across the floor at 1 m/s without
   spin: friction turns slip into rolling within ~0.1 s, at 5/7 of the speed for a solid ball)
   simulated by each backend: its horizontal speed once rolling (``ROLL_FROM``) and 1 s later,
   and the fraction lost in that second (a ball rolling on a level floor keeps its speed but
   for rolling resistance, which neither model has).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENES = ("ball_rolled", "ball_off_table")
BACKENDS = ("spheres", "warp")
EPS = 1e-3
TINY = 1e-3  # components below this fraction of the largest are not ratioed
ROLL_SCENE = "ball_rolled"
ROLL_SECONDS = 1.0
ROLL_FROM = 0.2  # s: the slip phase is over


def gradient_check(scene_name: str, backend: str, eps: float = EPS, steps: int | None = None) -> dict:
    """Reverse-mode gradient against central differences at the scene's initial guess.

    Returns:
        dict: scene, backend, params (names), exact and fd (the P numbers, space-separated),
        wrong_signs, compared (components not tiny), worst_ratio, loss.
    """
    import torch

    from dejaview.backends import make_problem
    from dejaview.scene import Scene

    scene = Scene.from_xml(ROOT / "examples" / "scenes" / f"{scene_name}.xml")
    problem = make_problem(scene, backend)
    if steps is not None:
        problem.steps = min(problem.steps, steps)
    x0 = problem.layout.encode().to(problem.dtype)
    loss, grad = problem.value_and_grad(x0, "reverse")
    exact = grad[0].double()
    fd = torch.empty_like(exact)
    with torch.no_grad():
        for i in range(x0.shape[1]):
            e = torch.zeros_like(x0)
            e[0, i] = eps
            fd[i] = (float(problem.loss(x0 + e)[0]) - float(problem.loss(x0 - e)[0])) / (2 * eps)
    scale = max(float(exact.abs().max()), float(fd.abs().max()), 1e-300)
    big = (exact.abs() > TINY * scale) | (fd.abs() > TINY * scale)
    wrong = int(((torch.sign(exact) != torch.sign(fd)) & big).sum())
    ratios = [max(abs(g / f) if f else math.inf, abs(f / g) if g else math.inf)
              for g, f in zip(exact[big].tolist(), fd[big].tolist())]
    return {"scene": scene_name, "backend": backend, "params": " ".join(problem.layout.names()),
            "exact": " ".join(f"{g:.6g}" for g in exact.tolist()), "fd": " ".join(f"{f:.6g}" for f in fd.tolist()),
            "wrong_signs": wrong, "compared": int(big.sum()),
            "worst_ratio": max(ratios, default=1.0), "loss": float(loss[0])}


def rolling(backend: str, seconds: float = ROLL_SECONDS, start: float = ROLL_FROM) -> dict:
    """The ball of ``ROLL_SCENE`` from its start: horizontal speed at ``start`` and ``seconds``
    later (m/s), and the fraction lost in between."""
    from dejaview.backends import make_problem
    from dejaview.scene import Scene

    scene = Scene.from_xml(ROOT / "examples" / "scenes" / f"{ROLL_SCENE}.xml")
    problem = make_problem(scene, backend)
    dt = scene.simulation.dt
    first, steps = round(start / dt), round((start + seconds) / dt)
    x0 = problem.layout.encode().to(problem.dtype)
    traj = problem.simulate(x0, steps=steps, record_every=1)
    v = traj.states.linear_velocity[:, 0, problem.source, :2].double().norm(dim=-1)  # (T,)
    a, b = float(v[first]), float(v[steps])
    return {"backend": backend, "initial_speed": float(v[0]), "from_s": first * dt, "seconds": (steps - first) * dt,
            "speed_from": a, "speed_end": b, "lost": 1.0 - b / a if a > 0 else math.nan}


def run(print_fn=print, scenes=SCENES, backends=BACKENDS, eps: float = EPS, quick: bool = False) -> list[dict]:
    """Both measurements (module docstring); rows ``section`` gradients | rolling."""
    from dejaview.backends import REGISTRY as KNOWN
    from dejaview.cli.bench_table import load_average

    say = print_fn or (lambda *_: None)
    usable = []
    for b in backends:
        reason = KNOWN[b].available()
        if reason:
            say(f"{b}: not available ({reason}); skipped")
        else:
            usable.append(b)
    say(f"Warp limits: gradients against central differences (eps {eps:g}) and a rolling ball; {load_average()}")
    rows: list[dict] = []
    say("")
    say(f"{'scene':<16} {'backend':<8} {'loss':>10} {'wrong signs':>12} {'worst ratio':>12}")
    for name in scenes:
        for b in usable:
            r = gradient_check(name, b, eps, steps=20 if quick else None)
            rows.append({"section": "gradients", **r})
            say(f"{name:<16} {b:<8} {r['loss']:>10.4g} {r['wrong_signs']:>5} of {r['compared']:<4} "
                f"{r['worst_ratio']:>12.3g}")
    say("")
    for b in usable:
        r = rolling(b, 0.1 if quick else ROLL_SECONDS)  # 0.3 s in all when quick
        rows.append({"section": "rolling", **r})
        say(f"rolling ball ({ROLL_SCENE}, {b}): bowled at {r['initial_speed']:.3f} m/s, rolling at "
            f"{r['speed_from']:.4f} m/s at {r['from_s']:g} s and {r['speed_end']:.4f} m/s {r['seconds']:g} s later "
            f"({100 * r['lost']:.1f} % lost)")
    return rows


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--eps", type=float, default=EPS)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    run(scenes=tuple(s for s in args.scenes.split(",") if s), eps=args.eps, quick=args.quick)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
