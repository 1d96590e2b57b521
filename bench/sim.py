"""Simulator benchmark on the reference scene ``examples/scenes/mug_thrown.xml``.

    python bench/sim.py               # full run (several minutes on 2 busy cores)
    python bench/sim.py --quick       # a few steps of everything (smoke test)
    python bench/sim.py --make-scene  # regenerate the reference scene and its truth

The reference scene: a mug packed with 150 spheres is thrown from above one
end of a table (top at 0.75 m, 1.2 x 0.8 m) across it; it lands on the table,
tumbles off the far end and falls to the floor. 1.5 s at dt = 2 ms (750 steps
of 2 substeps). Its ``<inference>`` frees all 12 parameters of the mug's
initial state (the start area has depth in x, y and z) and targets the
simulated final pose.

Printed, and returned as rows by ``run(print_fn=print, quick=False)``, for
both simulation engines (``engine`` key of each row): ``torch`` (eager
PyTorch, ``dejaview.sim.integrate``) and ``native`` (the same model in C++,
``dejaview.sim.native``; rows only where the extension builds):

* rollout without gradient: steps per second at B = 1 and B = 64, the time
  per candidate at B = 64 and the batch speed-up (64 times the B = 1 time
  over the B = 64 time); native rows also their speed-up over eager;
* one loss + gradient of all 12 parameters, forward and reverse mode, at
  B = 1 and per candidate at B = 64 (reverse mode at B = 64 is one batched
  backward): eager, native (always over the whole rollout), and compiled
  (``SpheresProblem.compile``, where the checkout offers it) only with
  ``compile=True`` / ``--compile``, each configuration in a fresh process
  with a time limit, since the first compile takes minutes;
* checks: eager forward vs reverse gradient, and native forward and reverse
  vs eager reverse (over the window, B = 1);
* peak memory of one reverse-mode loss + gradient, eager without and with
  checkpointing (``checkpoint_every``) and native, each in a fresh
  subprocess; on Linux the peak-RSS mark (VmHWM) is reset after set-up, so
  the figure is what the gradient itself adds.

Targets: one loss + gradient at B = 1 in <= 100 ms, and <= 10 ms per
candidate at B = 64 (the faster gradient mode of each).

Eager forward mode, and anything eager at B = 64 with a gradient, would take minutes over
the whole rollout, so they are timed over the first ``WINDOW`` steps and
scaled to the full 750 (every step costs the same: one body, no
data-dependent work); reverse mode at B = 1 is timed over the whole rollout
as well, which checks that scaling. Timings are wall clock on a shared
machine: the load average is printed with them.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "examples" / "scenes" / "mug_thrown.xml"

TARGET_B1_S = 0.100
TARGET_PER_CANDIDATE_S = 0.010
MODES = ("forward", "reverse")

# batch: the large batch; window: steps over which slow gradients are timed;
# full_steps: rollout length (None: the scene's); memory: (batch, steps, checkpoint_every)
# configurations, steps None meaning the full rollout and "window" the window; each runs
# in a fresh process (quick: all in one).
FULL = dict(batch=64, window=100, full_steps=None, repeats=2,
            memory=((1, None, None, "torch"), (1, None, 25, "torch"), (1, None, 150, "torch"),
                    (64, "window", None, "torch"), (64, "window", 25, "torch"),
                    (1, None, None, "native"), (64, None, None, "native")))
QUICK = dict(batch=4, window=3, full_steps=6, repeats=1,
             memory=((1, None, None, "torch"), (1, None, 2, "torch"), (1, None, None, "native")))


# ------------------------------------------------------------------ scene
def _make_scenes():
    """examples/make_scenes.py as a module (its helpers build scenes with a known truth)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_scenes", ROOT / "examples" / "make_scenes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def make_reference_scene() -> Path:
    """Write ``mug_thrown.xml`` and ``mug_thrown.truth.json`` into examples/scenes.

    The true throw is simulated and its final pose becomes the target; the
    scene file holds a deliberately wrong guess, as the other examples do.
    """
    from dejaview.scene import Exploration, InferenceSettings, Scene, SimulationSettings, StartArea, Target

    ms = _make_scenes()
    truth = ms.movable("mug", "mug", (-0.55, 0.05, 1.0), linear=(2.4, 0.1, 0.6), angular=(1.0, 2.0, 3.0),
                       mass=0.35)
    guess = ms.movable("mug", "mug", (-0.45, 0.0, 1.0), linear=(1.5, 0.0, 0.0), mass=0.35)
    scene = Scene(
        name="mug-thrown",
        objects=(ms.floor(), ms.furniture("table"), truth),
        simulation=SimulationSettings(dt=0.002, duration=1.5, friction=0.5, restitution=0.2),
        inference=InferenceSettings(
            source="mug", targets=(Target((0.0, 0.0, 0.0), moving=True),), iterations=150, optimizer="lbfgs",
            loss="pose", evaluate="best",
            # depth on every axis: all 12 parameters are free
            start_area=StartArea((-0.6, -0.3, 0.9), (-0.3, 0.3, 1.1)),
            exploration=Exploration(epsilon=0.2, patience=20)))
    scene, record = ms.with_truth(scene, truth, guess)
    note = ("A mug packed with 150 spheres thrown across a table: it lands on the table, tumbles off "
            "the far end and falls to the floor (reference scene of bench/sim.py).")
    SCENE.write_text(scene.to_xml().replace("?>\n", f"?>\n<!-- {note} -->\n", 1), encoding="utf-8")
    SCENE.with_suffix(".truth.json").write_text(json.dumps(record, indent=2), encoding="utf-8")
    Scene.from_xml(SCENE)  # validates
    return SCENE


# ------------------------------------------------------------------ helpers
def _best_time(fn, repeats: int = 1) -> float:
    best = math.inf
    for _ in range(max(1, repeats)):
        started = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - started)
    return best


def _load() -> str:
    from dejaview.cli.bench_table import load_average

    return load_average()


def _compile_offered() -> bool:
    """Whether SpheresProblem can run its rollouts through torch.compile."""
    import dataclasses

    from dejaview.backends.spheres import SpheresProblem

    return "compile" in {f.name for f in dataclasses.fields(SpheresProblem)}


def _candidates(problem, batch: int):
    """(1, P) the scene's guess and (batch, P) the guess plus random draws from the start area."""
    import torch

    x1 = problem.layout.encode().to(problem.world.dtype)
    draws = problem.layout.sample(batch - 1, torch.Generator().manual_seed(0)).to(x1.dtype)
    return x1, torch.cat([x1, draws], 0)


# ------------------------------------------------------------------ memory (subprocess)
def _status_kib(key: str) -> int | None:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _maxrss_kib() -> int:
    import resource

    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss // 1024 if sys.platform == "darwin" else rss  # bytes on macOS, KiB on Linux


def memory_probe(config: dict) -> dict:
    """Peak memory of one reverse-mode loss + gradient (run in a fresh process).

    Args:
        config: batch, steps (None: the scene's), checkpoint_every (None: off), threads,
            engine (``torch`` | ``native``; default torch).
    Returns:
        peak_growth_mib (peak RSS during the gradient minus RSS before it), baseline_mib,
        seconds, method (``VmHWM reset`` or ``ru_maxrss``, the latter a lower bound when
        set-up peaked higher).
    """
    from dataclasses import replace

    import torch

    from dejaview.backends.spheres import SpheresProblem
    from dejaview.scene import Scene

    torch.set_num_threads(int(config.get("threads", 1)))
    problem = SpheresProblem.from_scene(Scene.from_xml(SCENE), engine=config.get("engine", "torch"))
    steps = config.get("steps") or problem.steps
    problem = replace(problem, steps=steps, checkpoint_every=config.get("checkpoint_every"))
    _, x = _candidates(problem, int(config["batch"]))
    replace(problem, steps=2).value_and_grad(x, "reverse")  # warm-up: allocator, autograd
    method = "ru_maxrss"
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
            fh.write("5")  # resets VmHWM to the current RSS (Linux >= 4.0)
        base = _status_kib("VmRSS")
        method = "VmHWM reset" if base is not None else method
    except OSError:
        base = None
    if base is None:
        base = _maxrss_kib()
    started = time.perf_counter()
    loss, grad = problem.value_and_grad(x, "reverse")
    seconds = time.perf_counter() - started
    peak = _status_kib("VmHWM") if method == "VmHWM reset" else _maxrss_kib()
    finite = bool(torch.isfinite(loss).all() and torch.isfinite(grad).all())
    return {"peak_growth_mib": max(0, peak - base) / 1024, "baseline_mib": base / 1024,
            "seconds": seconds, "steps": steps, "method": method, "finite": finite}


def compile_probe(config: dict) -> dict:
    """Time one compiled loss + gradient (run in a fresh process: the compile may take minutes).

    Args:
        config: mode, batch, steps, threads.
    Returns:
        first_s (the first call, compile included), seconds (the second call), finite.
    """
    from dataclasses import replace

    import torch

    from dejaview.backends.spheres import SpheresProblem
    from dejaview.scene import Scene

    torch.set_num_threads(int(config.get("threads", 1)))
    problem = SpheresProblem.from_scene(Scene.from_xml(SCENE), engine="torch")
    problem = replace(problem, steps=int(config["steps"]), compile=True)
    _, x = _candidates(problem, int(config["batch"]))
    started = time.perf_counter()
    problem.value_and_grad(x, config["mode"])
    first = time.perf_counter() - started
    started = time.perf_counter()
    loss, grad = problem.value_and_grad(x, config["mode"])
    seconds = time.perf_counter() - started
    return {"first_s": first, "seconds": seconds,
            "finite": bool(torch.isfinite(loss).all() and torch.isfinite(grad).all())}


def _in_subprocess(flag: str, configs: list[dict], timeout: float | None = None) -> list[dict]:
    """Run a probe (``--memory-probe`` / ``--compile-probe``) of each configuration, in order,
    in one fresh Python process.

    Raises:
        RuntimeError: the probe failed; subprocess.TimeoutExpired: it ran past ``timeout``.
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), flag, json.dumps(configs)],
                          capture_output=True, text=True, env=env, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"{flag} {configs} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------ benchmark
def run(print_fn=print, quick: bool = False, compile: bool = False,
        compile_timeout: float = 600.0) -> list[dict]:
    """Run the benchmark.

    Args:
        print_fn: where the tables and verdicts go (None: silent).
        quick: a few steps and a batch of 4 instead of the full rollout and 64 (smoke test).
        compile: also time compiled loss + gradients (``SpheresProblem.compile``), each
            configuration in a fresh process: the first compile takes minutes.
        compile_timeout: seconds allowed to each compiled configuration.
    Returns:
        Rows (dicts), each with ``section`` (rollout | loss+grad | check | memory | target),
        ``name``, ``batch``, ``mode``, ``value`` and ``unit`` (``value`` is None only for
        configurations not offered, with a ``note``), plus per section:

        - rollout: steps, seconds (one rollout), per_candidate_s, speedup_vs_b1;
        - loss+grad: seconds (one loss + gradient of the full rollout), per_candidate_s,
          measured_steps, measured_s, scaled (True when timed over the window); compiled
          rows also first_s (the first call of the fresh process, compile included);
        - memory: steps, checkpoint_every (0: off), seconds, method;
        - target: target, met.
    """
    from dataclasses import replace

    import torch

    from dejaview.backends.spheres import SpheresProblem
    from dejaview.scene import Scene
    from dejaview.sim.integrate import rollout

    cfg = QUICK if quick else FULL
    say = print_fn or (lambda *_: None)
    rows: list[dict] = []
    from dejaview.sim import native

    problem = SpheresProblem.from_scene(Scene.from_xml(SCENE), engine="torch")
    world = problem.world
    native_ok = native.available()
    full = cfg["full_steps"] or problem.steps
    problem = replace(problem, steps=full)
    window = min(cfg["window"], full)
    batch = cfg["batch"]
    repeats = cfg["repeats"]
    x1, xb = _candidates(problem, batch)
    p = problem.num_params
    spheres = int(world.centers.shape[-2])
    say(f"reference scene: {SCENE.relative_to(ROOT)} ({spheres} spheres; {full} steps of "
        f"{1000 * world.dt:g} ms, {world.substeps} substeps{'; quick: shortened' if quick else ''})")
    say(f"parameters: {p} ({', '.join(problem.layout.names())})")
    if not 11 <= p <= 12:
        say(f"  warning: expected 11-12 free parameters, the layout gives {p}")
    say(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), float64; native engine: "
        f"{str(native.threads()) + ' thread(s)' if native_ok else 'not built'}; {_load()}")

    # ---- rollout without gradient
    def simulate(x, steps):
        with torch.no_grad():
            rollout(world, problem.initial_state(x), steps=steps, record_every=steps)

    simulate(x1, 2)
    simulate(xb, 2)
    t1 = _best_time(lambda: simulate(x1, full), repeats)
    tb = _best_time(lambda: simulate(xb, full), 1)
    say("")
    say(f"{'rollout, no gradient':<34} {'B':>3} {'steps/s':>9} {'s/rollout':>10} "
        f"{'s/candidate':>12} {'speed-up':>9}")
    for b, t in ((1, t1), (batch, tb)):
        row = {"section": "rollout", "name": "eager", "engine": "torch", "batch": b, "mode": "none",
               "value": full / t, "unit": "steps/s", "steps": full, "seconds": t,
               "per_candidate_s": t / b, "speedup_vs_b1": t1 * b / t}
        rows.append(row)
        say(f"{'  eager':<34} {b:>3} {row['value']:>9.1f} {t:>10.3f} {t / b:>12.4f} "
            f"{row['speedup_vs_b1']:>8.1f}x")
    say(f"  at B = {batch}: {batch * full / tb:.0f} candidate-steps/s")
    if native_ok:
        def simulate_native(x, steps):
            with torch.no_grad():
                rollout(world, problem.initial_state(x), steps=steps, record_every=steps, engine="native")

        simulate_native(x1, 2)
        n1 = _best_time(lambda: simulate_native(x1, full), max(3, repeats))
        nb = _best_time(lambda: simulate_native(xb, full), max(2, repeats))
        for b, t in ((1, n1), (batch, nb)):
            row = {"section": "rollout", "name": "native", "engine": "native", "batch": b, "mode": "none",
                   "value": full / t, "unit": "steps/s", "steps": full, "seconds": t,
                   "per_candidate_s": t / b, "speedup_vs_b1": n1 * b / t, "speedup_vs_eager": (t1 if b == 1 else tb) / t}
            rows.append(row)
            say(f"{'  native':<34} {b:>3} {row['value']:>9.1f} {t:>10.4f} {t / b:>12.5f} "
                f"{row['speedup_vs_b1']:>8.1f}x  ({row['speedup_vs_eager']:.0f}x eager)")

    # ---- loss + gradient
    short = replace(problem, steps=window)
    for mode in MODES:
        replace(problem, steps=2).value_and_grad(x1, mode)  # warm-up
        replace(problem, steps=2).value_and_grad(xb, mode)
    say("")
    say(f"{'loss + gradient, ' + str(p) + ' parameters':<34} {'B':>3} {'s/full':>9} {'s/candidate':>12}  "
        f"timed over")
    measured = {}
    results = {}
    for mode in MODES:
        for b, x in ((1, x1), (batch, xb)):
            holder = {}

            def grad(x=x, mode=mode, holder=holder):
                holder["out"] = short.value_and_grad(x, mode)

            t = _best_time(grad, repeats if b == 1 else 1)
            results[(mode, b)] = holder["out"]
            measured[(mode, b)] = (t * full / window, t, window, window < full)
    # reverse mode at B = 1 over the whole rollout too: the headline figure and a check of the scaling
    if window < full:
        t_full = _best_time(lambda: problem.value_and_grad(x1, "reverse"), 1)
        scaled_estimate = measured[("reverse", 1)][0]
        measured[("reverse", 1)] = (t_full, t_full, full, False)
    for mode in MODES:
        for b in (1, batch):
            seconds, t, steps, scaled = measured[(mode, b)]
            row = {"section": "loss+grad", "name": f"{mode}, eager", "engine": "torch", "batch": b,
                   "mode": mode, "value": seconds, "unit": "s", "seconds": seconds, "per_candidate_s": seconds / b,
                   "measured_steps": steps, "measured_s": t, "scaled": scaled}
            rows.append(row)
            how = f"{steps} steps, x{full / steps:.1f}" if scaled else f"all {steps} steps"
            say(f"{'  ' + mode + ', eager':<34} {b:>3} {seconds:>9.3f} {seconds / b:>12.4f}  {how}")
    if compile and _compile_offered():
        for mode in MODES:
            for b in (1, batch):
                config = {"mode": mode, "batch": b, "steps": window, "threads": torch.get_num_threads()}
                row = {"section": "loss+grad", "name": f"{mode}, compiled", "engine": "torch", "batch": b,
                       "mode": mode, "value": None, "unit": "s"}
                try:
                    out = _in_subprocess("--compile-probe", [config], timeout=compile_timeout)[0]
                except subprocess.TimeoutExpired:
                    row["note"] = f"did not finish within {compile_timeout:.0f} s"
                except RuntimeError as exc:
                    row["note"] = "failed: " + str(exc).strip().splitlines()[-1][:120]
                else:
                    seconds = out["seconds"] * full / window
                    row.update(value=seconds, seconds=seconds, per_candidate_s=seconds / b,
                               measured_steps=window, measured_s=out["seconds"], scaled=window < full,
                               first_s=out["first_s"])
                rows.append(row)
                if row["value"] is None:
                    say(f"{'  ' + mode + ', compiled':<34} {b:>3} {row['note']}")
                else:
                    say(f"{'  ' + mode + ', compiled':<34} {b:>3} {seconds:>9.3f} {seconds / b:>12.4f}  "
                        f"{window} steps, x{full / window:.1f}; first call {out['first_s']:.0f} s")
    else:
        note = ("not offered" if not _compile_offered() else
                "offered (SpheresProblem.compile), not timed: the first compile takes minutes "
                "(run with --compile)")
        for mode in MODES:
            rows.append({"section": "loss+grad", "name": f"{mode}, compiled", "engine": "torch", "batch": None,
                         "mode": mode, "value": None, "unit": "s", "note": note})
            say(f"{'  ' + mode + ', compiled':<34} {'-':>3} {note}")
    native_results = {}
    if native_ok:
        nfull = replace(problem, engine="native")
        for mode in MODES:
            nfull.value_and_grad(x1, mode)  # warm-up
            for b, x in ((1, x1), (batch, xb)):
                holder = {}

                def grad(x=x, mode=mode, holder=holder):
                    holder["out"] = nfull.value_and_grad(x, mode)

                t = _best_time(grad, max(3, repeats) if b == 1 else max(2, repeats))
                row = {"section": "loss+grad", "name": f"{mode}, native", "engine": "native", "batch": b,
                       "mode": mode, "value": t, "unit": "s", "seconds": t, "per_candidate_s": t / b,
                       "measured_steps": full, "measured_s": t, "scaled": False}
                rows.append(row)
                say(f"{'  ' + mode + ', native':<34} {b:>3} {t:>9.3f} {t / b:>12.4f}  all {full} steps")
        for mode in MODES:
            native_results[mode] = replace(nfull, steps=window).value_and_grad(x1, mode)
    if window < full:
        say(f"  scaling check: reverse B = 1 over all {full} steps took {t_full:.3f} s; "
            f"{window} steps x{full / window:.1f} gave {scaled_estimate:.3f} s "
            f"(ratio {scaled_estimate / t_full:.2f})")
    (lf, gf), (lr, gr) = results[("forward", 1)], results[("reverse", 1)]
    diff = float((gf - gr).abs().max() / gr.abs().max().clamp_min(1e-300))
    rows.append({"section": "check", "name": "forward vs reverse gradient", "batch": 1, "mode": "both",
                 "value": diff, "unit": "max |difference| / max |gradient|", "steps": window,
                 "loss_difference": float((lf - lr).abs().max())})
    say(f"  forward vs reverse gradient (B = 1, {window} steps): max |difference| / max |gradient| "
        f"= {diff:.1e}")
    if native_results:
        for mode in MODES:
            ln, gn = native_results[mode]
            ndiff = float((gn - gr).abs().max() / gr.abs().max().clamp_min(1e-300))
            rows.append({"section": "check", "name": f"native {mode} vs eager reverse gradient", "batch": 1,
                         "mode": mode, "value": ndiff, "unit": "max |difference| / max |gradient|",
                         "steps": window, "loss_difference": float((ln - lr).abs().max())})
            say(f"  native {mode} vs eager reverse gradient (B = 1, {window} steps): {ndiff:.1e}")

    # ---- memory
    say("")
    say(f"{'reverse mode, peak memory':<34} {'B':>3} {'steps':>6} {'checkpoint':>11} {'peak growth':>12} "
        f"{'seconds':>8}")
    configs = [{"batch": min(b, batch), "steps": full if steps is None else window,
                "checkpoint_every": every, "threads": torch.get_num_threads(), "engine": engine}
               for b, steps, every, engine in cfg["memory"] if engine == "torch" or native_ok]
    if quick:  # one process for all: saves start-up time, the figures matter less
        outs = _in_subprocess("--memory-probe", configs)
    else:
        outs = [_in_subprocess("--memory-probe", [c])[0] for c in configs]
    for config, out in zip(configs, outs):
        b, steps, every = config["batch"], config["steps"], config["checkpoint_every"]
        engine = config["engine"]
        row = {"section": "memory", "name": f"reverse, {'eager' if engine == 'torch' else engine}",
               "engine": engine, "batch": b, "mode": "reverse",
               "value": out["peak_growth_mib"], "unit": "MiB", "steps": steps,
               "checkpoint_every": every or 0, "seconds": out["seconds"], "method": out["method"]}
        rows.append(row)
        say(f"{'  one loss + gradient, ' + row['name'].split(', ')[1]:<34} {b:>3} {steps:>6} "
            f"{('every ' + str(every)) if every else 'off':>11} "
            f"{row['value']:>8.0f} MiB {out['seconds']:>8.2f}")
    widest = [r for r in rows if r["section"] == "memory" and r["batch"] == batch and not r["checkpoint_every"]
              and r["engine"] == "torch"]
    if widest and widest[0]["steps"] < full:
        say(f"  (B = {batch} over all {full} steps without checkpointing: about "
            f"{widest[0]['value'] * full / widest[0]['steps'] / 1024:.1f} GiB by the same scaling)")
    say(f"  measured in a fresh process each: {rows[-1]['method']}")

    # ---- targets
    say("")
    say("targets")
    for name, key, b, target in (("loss + gradient at B = 1", "seconds", 1, TARGET_B1_S),
                                 (f"loss + gradient per candidate at B = {batch}", "per_candidate_s",
                                  batch, TARGET_PER_CANDIDATE_S)):
        cands = [r for r in rows if r["section"] == "loss+grad" and r["batch"] == b and r["value"] is not None]
        best = min(cands, key=lambda r: r[key])
        met = best[key] <= target
        rows.append({"section": "target", "name": name, "batch": b, "mode": best["mode"],
                     "value": best[key], "unit": "s", "target": target, "met": bool(met),
                     "best": best["name"]})
        verdict = "met" if met else f"NOT met ({best[key] / target:.0f}x over)"
        say(f"  {name} <= {1000 * target:.0f} ms: {1000 * best[key]:.0f} ms ({best['name']}) -> {verdict}")
    say(f"  {_load()}")
    return rows


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a few steps of everything")
    parser.add_argument("--make-scene", action="store_true", help="regenerate the reference scene")
    parser.add_argument("--compile", action="store_true",
                        help="also time compiled loss + gradients (minutes of compiling)")
    parser.add_argument("--memory-probe", metavar="JSON", help=argparse.SUPPRESS)
    parser.add_argument("--compile-probe", metavar="JSON", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    if args.memory_probe:
        print(json.dumps([memory_probe(c) for c in json.loads(args.memory_probe)]))
        return 0
    if args.compile_probe:
        print(json.dumps([compile_probe(c) for c in json.loads(args.compile_probe)]))
        return 0
    if args.make_scene:
        print(make_reference_scene())
        return 0
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = run(quick=args.quick, compile=args.compile)
    return 0 if all(r["met"] for r in rows if r["section"] == "target") else 1


if __name__ == "__main__":
    sys.exit(main())
