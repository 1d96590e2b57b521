"""Cross-engine benchmark: answers that survive another engine's physics.

    dejaview bench crossengine                       # fidelity table, then every case in MuJoCo
    dejaview bench crossengine --engines bullet --perturbed-seed 100 --no-warp
    dejaview bench crossengine --mismatched 100 --cases ball-bounce,box-tumble
    python bench/crossengine.py --csv crossengine.csv

Three parts, printed as tables (docs/physics-fidelity.md has the measured ones):

1. **Physics fidelity** (``crossengine_fidelity.fidelity``): the same start simulated by DejaView
   (native engine, the scene's defaults), by MuJoCo (the scene exported with
   ``dejaview.io.mjcf.export_mjcf``, at ``MUJOCO_TIMESTEP``, a converged step) and by Bullet
   (``bullet_engine``: friction and restitution mapped through Bullet's product rule, no
   damping, a converged step), the distance between DejaView's and each engine's centres of
   mass, and between the two engines', after 0.5, 1.0 and 1.5 s, for bounce, roll, slide, tumble
   and a box-box hit.
2. **Inference across engines** (``crossengine_cases.CASES``, >= 16): an observing engine
   (``--engines``: MuJoCo, Bullet) simulates a known start (balls and boxes, table and floor,
   sliding, bouncing, tumbling); DejaView gets only the end pose (``<target>``,
   ``evaluate="final"``), the start area, the source at the area's centre at rest
   (``start_guess``) and the cases' ``PRIOR``, and solves with ``dejaview.solve``'s defaults, once
   as the scene is and once with ``<model-uncertainty friction restitution>`` (``UNCERTAINTY``),
   and with ``--inference-xml`` once more with that XML added to ``<inference>`` (a
   ``<physics-prior>``); the observing engine, and Warp where it runs, re-simulate each answer.
   Success: the re-simulated end (object origin) within ``SUCCESS_TOL`` (3 cm) of the
   observation. Counts per engine, per setting and per kind (``kind``). ``--mismatched S``: the
   observing engine simulates a world whose friction is the scene's times 0.7-1.4 and whose
   restitution is 0-0.3 (``mismatch``, seeded by S), as a real table's would be, while DejaView
   solves the scene as written. Held out: the cases perturbed (``--perturbed-seed``) and worlds
   mismatched by seeds from ``HELD_OUT_SEED`` (100) up; below it, and the cases themselves, are
   the tuning set. ``--area-offset`` moves the floor cases' start areas off the truth;
   ``--random-cases N`` adds random tumbling boxes.
3. **Random throws** (``crossengine_fidelity.throws``, ``--throws N``): the engines' gap on N boxes
   thrown at random, with controls that tell a model gap from chaos and from the steps.

The parts live in ``crossengine_cases.py`` (scenes, cases, variants, worlds),
``crossengine_engines.py`` and ``bullet_engine.py`` (the engines) and ``crossengine_fidelity.py``;
this module re-exports their names, solves and reports.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from dejaview.cli.bench import bench_module  # noqa: E402

# The parts, loaded as bench_module loads this one, their names re-exported for the bench's users.
_parts = [bench_module(n) for n in ("crossengine_cases", "crossengine_engines", "crossengine_fidelity")]
globals().update({k: v for m in _parts for k, v in vars(m).items() if not k.startswith("__")})
_cases, _engines, _fidelity = _parts

UNCERTAINTY = (0.2, 0.2)
"""Relative standard deviations (friction, restitution) of the runs with model uncertainty."""


def settings(uncertainty=UNCERTAINTY, baseline: bool = True, extra: str = "") -> list[tuple]:
    """The solves' settings, ``(label, uncertainty or None, extra XML)``: without model uncertainty
    ("off", unless not ``baseline``), with it (its relative standard deviations), and with
    ``extra`` added to ``<inference>`` ("xml", where given; the scene's physics otherwise as is).

    Raises:
        ValueError: ``extra`` that is not XML elements, in one line.
    """
    import xml.etree.ElementTree as ET

    try:
        ET.fromstring(f"<inference>{extra}</inference>")
    except ET.ParseError as exc:
        raise ValueError(f"inference-xml: {extra!r} is not XML elements ({exc})") from None
    out = [("off", None, "")] if baseline else []
    out.append((f"{uncertainty[0]:g} {uncertainty[1]:g}", tuple(uncertainty), ""))
    return out + ([("xml", None, extra)] if extra else [])


def solve_case(case, uncertainty, warp: bool, print_fn=print, seed: int = 0, prior: bool = True,
               engine: str = "mujoco", world=None, extra: str = "", label: str | None = None) -> dict:
    """Observe the case in ``engine`` (in ``world``, ``in_world``: the scene's physics where None),
    solve (the search's ``seed``; ``PRIOR`` unless ``prior`` is False; ``uncertainty`` and ``extra``
    as ``case_scene`` takes them), re-simulate the answer in ``engine`` in the same world (and Warp)."""
    import dejaview

    run_engine, name = _engines.ENGINES[engine], _engines.ENGINE_NAMES[engine]
    truth = _cases.case_scene(case)
    end = run_engine(_cases.in_world(truth, world), (case.duration,))[case.duration]
    target = (end[0][0], end[1][0])
    scene = _cases.case_scene(case, target, uncertainty, seed, prior, extra)
    t0 = time.perf_counter()
    result = dejaview.solve(scene)
    seconds = time.perf_counter() - t0
    initial = result.initial_state
    back = run_engine(_cases.in_world(scene, world), (case.duration,),
                      {"source": "source", "initial_state": initial})[case.duration]
    err = float(np.linalg.norm(back[0][0] - target[0]))
    own = float(np.linalg.norm(_own_end(result) - target[0]))
    search = result.settings.get("search", {})
    if label is None:
        label = "off" if uncertainty is None else f"{uncertainty[0]:g} {uncertainty[1]:g}"
    row = {"section": "inference", "case": case.name, "kind": _cases.kind(case), "engine": engine,
           "world": "scene" if world is None else f"friction x{world[0]:.3f} restitution {world[1]:.3f}",
           "seed": int(seed), "model_uncertainty": label, "inference_xml": extra,
           "prior": _cases.PRIOR["ball" if case.ball else "box"] if prior else "flat",
           "seconds": seconds, "rollouts": search.get("rollouts"), "jacobians": search.get("jacobians"),
           "own_end_error_m": own, f"{engine}_end_error_m": err,
           f"{engine}_angle_error_deg": _cases.angle_deg(back[1][0], target[1]),
           "success": err <= _cases.SUCCESS_TOL,
           "start_error_m": float(np.linalg.norm(np.asarray(initial["position"]) - _cases._truth_start(truth)))}
    if warp:
        w = _engines.warp_end(_cases.in_world(_cases.with_start(scene, initial), world))
        row["warp_end_error_m"] = None if w is None else float(np.linalg.norm(w - target[0]))
        row["warp_success"] = None if w is None else row["warp_end_error_m"] <= _cases.SUCCESS_TOL
    print_fn(f"{case.name:<25} {name:<6} {seed:>4} {label:<8} {seconds:>7.1f} {1000 * own:>8.1f} "
             f"{1000 * err:>8.1f} {'yes' if row['success'] else 'no':<4}"
             + ("" if row.get("warp_end_error_m") is None else f" {1000 * row['warp_end_error_m']:>8.1f}"))
    return row


def _own_end(result) -> np.ndarray:
    """DejaView's end (object origin) of the answer: the last record of the solve's trajectory."""
    problem = result.problem
    pos = problem.world.object_position(_engines._flat(result.trajectory.states))
    return pos[-1, problem.source].numpy()


def run(print_fn=print, cases=None, uncertainty=UNCERTAINTY, warp: bool = True,
        with_fidelity: bool = True, baseline: bool = True, seeds=(0,), prior: bool = True,
        area_offset=(0.0, 0.0), extra_cases=(), perturb: int | None = None, engines=("mujoco",),
        mismatched: int | None = None, extra: str = "") -> list[dict]:
    """Fidelity table and the inference cases in each setting (``settings``) and engine (module docstring).

    Args:
        cases: case names (default all of ``CASES``, or none where ``extra_cases`` are given).
        uncertainty: (friction, restitution) relative standard deviations of the runs with it.
        warp: also re-simulate the answers in Warp (where it is installed).
        with_fidelity: print the fidelity table first (against MuJoCo and Bullet).
        baseline: also solve without model uncertainty.
        seeds: the search's seeds (``<inference seed>``), one solve each per case and setting
            (the same observation): several cases land within a few mm of the 3 cm bar, and
            which side they land on changes with the search's path, so one seed's count is a
            noisy estimate of the rate.
        prior: the solves' ``<prior>`` is ``PRIOR`` (False: flat within the backend's bounds).
        area_offset: (dx, dy) m, the floor cases' start areas moved off the truth (``offset_area``).
        extra_cases: more ``Case``s solved after the chosen ones (``random_cases``).
        perturb: a seed: the chosen cases' truths perturbed by it (``perturbed_cases``) instead.
        engines: the observing engines (``ENGINES``' names), each observing every case.
        mismatched: a seed: each case observed in a world drawn by it (``mismatch``) instead of the scene's.
        extra: XML added to ``<inference>`` in one more setting (``settings``).
    Returns:
        rows (dicts) of both parts.
    """
    from dejaview.cli.bench import load_average

    seeds, engines = _cases.check_seeds(seeds), _engines.check_engines(engines)
    solves = settings(uncertainty, baseline, extra)
    if mismatched is not None:
        _cases.check_seeds((mismatched,))
    chosen = [c for c in _cases.CASES if (not cases and not extra_cases) or c.name in (cases or ())]
    if perturb is not None:
        chosen = list(_cases.perturbed_cases(perturb, chosen))
    chosen = [_cases.offset_area(c, area_offset) for c in chosen]
    chosen += [_cases.offset_area(c, area_offset) for c in extra_cases]
    unknown = set(cases or ()) - {c.name for c in _cases.CASES}
    if unknown:
        raise ValueError(f"unknown case(s) {', '.join(sorted(unknown))}; cases: "
                         f"{', '.join(c.name for c in _cases.CASES)}")
    held = {"perturbed": None if perturb is None else _cases.held_out(perturb),
            "mismatched": None if mismatched is None else _cases.held_out(mismatched)}
    rows = []
    print_fn(f"# cross-engine benchmark ({load_average()})")
    if with_fidelity:
        print_fn("## fidelity: DejaView vs MuJoCo and Bullet from the same start")
        rows += _fidelity.fidelity(print_fn, engines=_fidelity.fidelity_engines(engines))
    names = " and ".join(_engines.ENGINE_NAMES[e] for e in engines)
    print_fn(f"## inference: {names} observe{'s' if len(engines) == 1 else ''}, DejaView solves, the observer"
             f"{' and Warp re-simulate' if warp else ' re-simulates'} (success: within {100 * _cases.SUCCESS_TOL:g} cm)"
             + (f"; the floor cases' start areas moved by {area_offset[0]:g} {area_offset[1]:g} m off the truth"
                if any(area_offset) else ""))
    told = ("cases: the bench's own (tuning set)" if perturb is None else
            f"cases: perturbed by seed {perturb} ({'held out' if held['perturbed'] else 'tuning set'})")
    if mismatched is not None:
        told += (f"; worlds mismatched by seed {mismatched} ({'held out' if held['mismatched'] else 'tuning set'}): "
                 f"friction x{_cases.MISMATCH_FRICTION[0]:g}-{_cases.MISMATCH_FRICTION[1]:g}, restitution "
                 f"{_cases.MISMATCH_RESTITUTION[0]:g}-{_cases.MISMATCH_RESTITUTION[1]:g}")
    print_fn(told + (f"; {len(extra_cases)} random boxes" if extra_cases else ""))
    print_fn(f"{'case':<25} {'engine':<6} {'seed':>4} {'model-u':<8} {'seconds':>7} {'own mm':>8} {'end mm':>8} ok  "
             + ("warp mm" if warp else ""))
    for case in chosen:
        world = None if mismatched is None else _cases.mismatch(case, mismatched)
        for engine in engines:
            for label, u, xml in solves:
                for seed in seeds:
                    rows.append({**solve_case(case, u, warp, print_fn, seed, prior, engine, world, xml, label),
                                 "area_offset": f"{area_offset[0]:g} {area_offset[1]:g}",
                                 "perturbed_seed": perturb, "mismatched_seed": mismatched,
                                 "held_out": bool(held["perturbed"] or held["mismatched"])})
    summary(rows, print_fn)
    return rows


def summary(rows, print_fn=print) -> None:
    """Per engine and setting: the share within ``SUCCESS_TOL``, the mean seconds, Warp's share, the
    cases every seed solved; then per kind, and each setting's cost against the solve without."""
    inf = [r for r in rows if r["section"] == "inference"]
    groups = {}
    for r in inf:
        groups.setdefault((r.get("engine", "mujoco"), r["model_uncertainty"]), []).append(r)
    secs = {}
    for (engine, key), rs in groups.items():
        ok = sum(r["success"] for r in rs)
        secs[engine, key] = sum(r["seconds"] for r in rs) / len(rs)
        line = (f"model uncertainty {key}: {_engines.ENGINE_NAMES[engine]} {ok}/{len(rs)} within "
                f"{100 * _cases.SUCCESS_TOL:g} cm ({100 * ok / len(rs):.0f} %), "
                f"mean {secs[engine, key]:.1f} s per solve")
        w = [r for r in rs if r.get("warp_success") is not None]
        if w:
            line += f"; Warp {sum(r['warp_success'] for r in w)}/{len(w)}"
        print_fn(line)
        if len({r.get("seed", 0) for r in rs}) > 1:
            per_case = {}
            for r in rs:
                per_case.setdefault(r["case"], []).append(r["success"])
            print_fn(f"  over {len({r.get('seed', 0) for r in rs})} seeds, cases solved by every seed: "
                     f"{sum(all(v) for v in per_case.values())}/{len(per_case)}; by some: "
                     f"{sum(any(v) for v in per_case.values())}/{len(per_case)}")
    kinds = sorted({r["kind"] for r in inf if "kind" in r})
    if kinds:
        print_fn("per kind (solved/solves): " + "; ".join(
            f"{_engines.ENGINE_NAMES[e]} {k}" for e, k in groups))
        for kind_ in kinds:
            cells = []
            for rs in groups.values():
                mine = [r["success"] for r in rs if r.get("kind") == kind_]
                cells.append(f"{sum(mine)}/{len(mine)}" if mine else "-")
            print_fn(f"  {kind_:<16} " + " ".join(f"{c:>7}" for c in cells))
    for (engine, key), s in secs.items():
        if key != "off" and (engine, "off") in secs:
            pairs = [(a, b) for a in groups[engine, "off"] for b in groups[engine, key]
                     if (a["case"], a.get("seed")) == (b["case"], b.get("seed"))]
            ratio = np.median([b["seconds"] / a["seconds"] for a, b in pairs])
            print_fn(f"cost with model uncertainty {key} ({_engines.ENGINE_NAMES[engine]}): mean "
                     f"{s / secs[engine, 'off']:.2f}x, median per case {ratio:.2f}x the solve without it")


def command(print_fn=print, cases: str = "", uncertainty=UNCERTAINTY, no_baseline: bool = False, seeds=(0,),
            no_warp: bool = False, no_fidelity: bool = False, fidelity_only: bool = False, flat_prior: bool = False,
            area_offset=(0.0, 0.0), timestep_study: bool = False, throws: int = 0, random_cases: int = 0,
            random_seed: int = 0, perturbed_seed: int | None = None, engines: str = "mujoco",
            mismatched: int | None = None, inference_xml: str = "") -> list[dict]:
    """One run of the bench as ``dejaview bench crossengine`` and ``main`` ask for it (their options,
    by name): the time-step study of the first engine, the throws, the fidelity table or the
    inference cases.

    Raises:
        ValueError: a bad option, in one line naming it.
    """
    names = _engines.check_engines(engines)
    if timestep_study:
        return _fidelity.timestep_study(print_fn, engine=names[0])
    if throws:
        return _fidelity.throws(print_fn, count=throws, seed=seeds[0] if seeds else 0)
    if fidelity_only:
        return _fidelity.fidelity(print_fn, engines=_fidelity.fidelity_engines(names))
    return run(print_fn=print_fn, cases=tuple(c for c in cases.replace(" ", "").split(",") if c),
               uncertainty=uncertainty, warp=not no_warp, with_fidelity=not no_fidelity, baseline=not no_baseline,
               seeds=seeds, prior=not flat_prior, area_offset=tuple(area_offset),
               extra_cases=_cases.random_cases(random_cases, random_seed), perturb=perturbed_seed, engines=names,
               mismatched=mismatched, extra=inference_xml)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    parser.add_argument("--engines", default="mujoco", help="comma-separated observing engines: mujoco, bullet")
    parser.add_argument("--no-warp", action="store_true")
    parser.add_argument("--no-fidelity", action="store_true")
    parser.add_argument("--fidelity-only", action="store_true")
    parser.add_argument("--csv", type=Path, default=None)
    parser.add_argument("--no-baseline", action="store_true")
    parser.add_argument("--seeds", default="0", help="comma-separated search seeds, one solve each per case")
    parser.add_argument("--flat-prior", action="store_true", help="solve without the cases' PRIOR")
    parser.add_argument("--area-offset", type=float, nargs=2, default=(0.0, 0.0), metavar=("DX", "DY"),
                        help="move the floor cases' start areas off the truth by DX DY m (offset_area)")
    parser.add_argument("--timestep-study", action="store_true", help="only the first engine's step convergence")
    parser.add_argument("--throws", type=int, default=0, metavar="N",
                        help="only the engines' gap on N random box throws (throws; seeded by --seeds' first)")
    parser.add_argument("--random-cases", type=int, default=0, metavar="N",
                        help="N random tumbling boxes (random_cases), instead of the cases unless --cases names some")
    parser.add_argument("--random-seed", type=int, default=0, help="the seed of --random-cases' draw")
    parser.add_argument("--perturbed-seed", type=int, default=None, metavar="S",
                        help="the cases' truths perturbed by seed S (perturbed_cases; S >= 100 held out)")
    parser.add_argument("--mismatched", type=int, default=None, metavar="S",
                        help="observe in worlds drawn by seed S (mismatch; S >= 100 held out)")
    parser.add_argument("--inference-xml", default="", help="also solve with this XML added to <inference>")
    args = vars(parser.parse_args(argv))
    csv_path = args.pop("csv")
    args["seeds"] = tuple(int(v) for v in args["seeds"].split(",") if v)
    rows = command(print, **args)
    if csv_path is not None:
        from dejaview.cli.bench import write_rows_csv

        write_rows_csv(rows, csv_path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
