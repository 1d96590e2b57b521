"""``dejaview bench``: run the benchmarks of the source checkout's ``bench/`` folder.

The benchmarks are scripts beside the package (they read the checkout's example scenes and
meshes), loaded by path from the checkout DejaView is installed from (``pip install -e .``).
"""

from __future__ import annotations

import json
from pathlib import Path

import click

# load_average: bench/crossengine.py imports it from here
from dejaview.cli.bench_table import load_average, parse_counts, parse_names, write_rows_csv  # noqa: F401
from dejaview.cli.bench_table import _comma_list, _finish, bench_module, check_option, csv_option  # noqa: F401


def _iterations(ctx, param, value):
    if value is None:
        return None
    try:
        return parse_counts(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


@click.group("bench", context_settings={"help_option_names": ["-h", "--help"]})
def command():
    """Benchmarks of the simulator, the sphere packing, the optimisers and the service.

    Timings are wall clock on whatever else the machine runs; each table is
    printed with the load average.
    """


@command.command("sim")
@click.option("--quick", is_flag=True, help="A few steps and a batch of 4 (smoke test).")
@click.option("--compile", "use_compile", is_flag=True,
              help="Also time compiled loss + gradients (each first compile takes minutes).")
@click.option("--compile-timeout", default=600.0, show_default=True, type=click.FloatRange(min=1),
              metavar="SECONDS", help="Time allowed to each compiled configuration.")
@csv_option
@check_option
def sim(quick, use_compile, compile_timeout, csv_path, check):
    """Simulator speed and memory on examples/scenes/mug_thrown.xml.

    A 150-sphere mug thrown across a table onto the floor, 1.5 s at dt = 2 ms:
    steps per second at B = 1 and 64, one loss + gradient of its 12
    parameters in forward and reverse mode, reverse-mode peak memory with and
    without checkpointing, against the targets (<= 100 ms at B = 1, <= 10 ms
    per candidate at B = 64). Several minutes without --quick.
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("sim").run(print_fn=click.echo, quick=quick, compile=use_compile,
                                   compile_timeout=compile_timeout)
    _finish(rows, csv_path, check, [r["met"] for r in rows if r["section"] == "target"])


@command.command("packing")
@click.option("-n", "--max-spheres", default=256, show_default=True, type=click.IntRange(min=1),
              help="Sphere budget for every mesh.")
@csv_option
@check_option
def packing(max_spheres, csv_path, check):
    """Sphere packing of the example box, ball and mug and a 10 000-triangle mesh.

    Coverage, how far spheres reach outside the mesh and build time, against
    the targets (>= 80 % coverage with <= 256 spheres, <= 2 mm outside,
    10 000 triangles in < 15 s).
    """
    rows = bench_module("packing").run(print_fn=click.echo, max_spheres=max_spheres)
    _finish(rows, csv_path, check, [rows[-1]["ok"]] if rows else [])


@command.command("profile")
@click.option("--scene", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Scene file (default: examples/scenes/mug_thrown.xml).")
@click.option("--steps", type=click.IntRange(min=1), default=None, help="Rollout length (default: the scene's).")
@click.option("--compile", "use_compile", is_flag=True, help="Compiled rollouts (first compile excluded).")
@click.option("--mode", type=click.Choice(["reverse", "forward"]), default="reverse", show_default=True)
@click.option("--rows", type=click.IntRange(min=1), default=20, show_default=True)
def profile(scene, steps, use_compile, mode, rows):
    """Where one loss + gradient spends its time (torch.profiler, top ops by self time)."""
    from dejaview.cli.options import configure_torch

    configure_torch()
    bench_module("op_profile").run(scene=scene, steps=steps, compile=use_compile, mode=mode, rows=rows,
                                print_fn=click.echo)


@command.command("micro")
@click.option("--poses", default=100, show_default=True, type=click.IntRange(min=1),
              help="Random poses per scene for the collision queries.")
@csv_option
def micro(poses, csv_path):
    """Eager forward-mode AD per op, and one exact interpenetration query per pose (fcl)."""
    rows = bench_module("micro").run(print_fn=click.echo, poses=poses)
    _finish(rows, csv_path, False, [])


@command.command("warp-limits")
@click.option("--scenes", default="ball_rolled,ball_off_table", show_default=True,
              help="Bundled scenes (names under examples/scenes) whose gradients are checked.")
@click.option("--eps", default=1e-3, show_default=True, type=click.FloatRange(min=0.0, min_open=True),
              help="Central-difference step, in the parameters' own units.")
@click.option("--quick", is_flag=True, help="20 steps per scene and 0.1 s of rolling (smoke test).")
@csv_option
def warp_limits(scenes, eps, quick, csv_path):
    """Warp 1.9.1's gradients against central differences, and a rolling ball, beside DejaView's."""
    from dejaview.cli.options import configure_torch

    configure_torch()
    import dejaview

    scenes_dir = Path(dejaview.__file__).resolve().parent.parent / "examples" / "scenes"
    names = tuple(s.strip() for s in scenes.split(",") if s.strip())
    missing = [n for n in names if not (scenes_dir / f"{n}.xml").is_file()]
    if missing:
        raise click.BadParameter(f"no bundled scene {', '.join(missing)}", param_hint="--scenes")
    rows = bench_module("warp_limits").run(print_fn=click.echo, scenes=names, eps=eps, quick=quick)
    _finish(rows, csv_path, False, [])


@command.command("optimizers")
@click.option("--iterations", default="100,500,1000", show_default=True, callback=_iterations,
              help="Comma-separated iteration counts to report the best loss at.")
@click.option("--scene", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Scene with an <inference> section [default: examples/scenes/ball_rolled.xml, "
                   "a cheap one].")
@click.option("--optimizers", "optimizers", default="gd,adam,lbfgs,bfgs", show_default=True,
              callback=_comma_list(("gd", "adam", "lbfgs", "bfgs")), help="Optimisers to compare.")
@click.option("--modes", default="forward,reverse", show_default=True,
              callback=_comma_list(("forward", "reverse")), help="Gradient modes to compare.")
@click.option("--quick", is_flag=True, help="Iterations 1,2 (smoke test).")
@csv_option
def optimizers(iterations, scene, optimizers, modes, quick, csv_path):
    """Best loss after N iterations and time per iteration of each optimiser and gradient mode.

    One solve per optimiser and mode, from the scene's initial guess, without
    restarts. Forward mode and the larger bundled scenes cost more per
    iteration: give those fewer --iterations.
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    module = bench_module("optimizers")
    module.run(print_fn=click.echo, iterations=(1, 2) if quick else iterations, modes=modes,
               optimizers=optimizers, scene=scene, csv_path=csv_path)


@command.command("heatmap")
@click.option("--scene", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Scene [default: examples/scenes/ball_down_ramp.xml].")
@click.option("--cells", default="16x16", show_default=True, help="Grid NXxNY.")
@click.option("--samples", default=4, show_default=True, type=click.IntRange(min=1))
@click.option("--iterations", default=30, show_default=True, type=click.IntRange(min=1))
@click.option("--workers", default=2, show_default=True, type=click.IntRange(min=1))
@click.option("--batch-size", default=1024, show_default=True, type=click.IntRange(min=1))
@click.option("--serial", default=8, show_default=True, type=int,
              help="Candidates run one at a time for the comparison (-1: all, 0: none).")
@click.option("--quick", is_flag=True, help="4x4 cells, 1 sample, 2 iterations, 1 serial (smoke test).")
@csv_option
def heatmap(scene, cells, samples, iterations, workers, batch_size, serial, quick, csv_path):
    """Time of a 16 x 16 x 4 heatmap, batched versus one at a time, and the ratio (target: < 5 min)."""
    from dejaview.cli.options import configure_torch

    configure_torch()
    try:
        nx, ny = (int(v) for v in cells.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected NXxNY, got {cells!r}", param_hint="--cells") from None
    if quick:
        nx, ny, samples, iterations, serial = 4, 4, 1, 2, 1
    bench_module("heatmap").run(print_fn=click.echo, scene=scene, cells=(nx, ny), samples=samples,
                                iterations=iterations, workers=workers, batch_size=batch_size,
                                serial=serial, csv_path=csv_path)


@command.command("backends")
@click.option("--iterations", default="100,500,1000", show_default=True, callback=_iterations,
              help="Comma-separated iteration counts to report the best loss at.")
@click.option("--scene", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Scene with an <inference> section [default: examples/scenes/ball_rolled.xml, "
                   "a cheap one].")
@click.option("--backends", "backends", default="spheres,warp", show_default=True,
              callback=_comma_list(("spheres", "warp")), help="Backends to compare.")
@click.option("--optimizers", "optimizers", default="gd,adam,lbfgs,bfgs", show_default=True,
              callback=_comma_list(("gd", "adam", "lbfgs", "bfgs")), help="Optimisers to compare.")
@click.option("--integrator", type=click.Choice(["xpbd", "semi-implicit"]), default=None,
              help="Warp integrator [default: the scene's warp-integrator, else xpbd].")
@click.option("--quick", is_flag=True, help="Iterations 1,2 (smoke test).")
@csv_option
def backends(iterations, scene, backends, optimizers, integrator, quick, csv_path):
    """Best loss after N iterations and seconds per iteration of each backend and optimiser.

    The original work's Table I: DejaView's sphere simulator (PyTorch) against
    NVIDIA Warp (warp.sim, needs pip install 'dejaview[warp]'), reverse mode,
    from the scene's initial guess without restarts, plus the ratio of their
    seconds per iteration measured in the same run.
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    bench_module("backends").run(print_fn=click.echo, iterations=(1, 2) if quick else iterations,
                                 backends=backends, optimizers=optimizers, scene=scene, csv_path=csv_path,
                                 warp_options={"integrator": integrator} if integrator else None)


@command.command("search")
@click.option("--scenes", default="mug_off_counter,box_among_boxes", show_default=True,
              help="Comma-separated bundled scenes.")
@click.option("--seeds", default="0,1,2", show_default=True, help="Comma-separated seeds.")
@click.option("--pipelines", default="auto,seed-pipeline", show_default=True,
              callback=_comma_list(("auto", "seed-pipeline")), help="Pipelines to compare.")
@csv_option
def search(scenes, seeds, pipelines, csv_path):
    """The default search beside the seed's pipeline: wall time and answer per solve.

    Solves each scene as shipped with `solve`'s defaults (auto) and with the settings the
    recovery suite needed before (screening, four L-BFGS candidates, restarts), in one run,
    and prints the time ratio and the targets (mug 10 s, box_among_boxes 60 s).
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("search").run(print_fn=click.echo, scenes=tuple(scenes.split(",")),
                                      seeds=tuple(int(s) for s in seeds.split(",")),
                                      pipelines=pipelines)
    _finish(rows, csv_path, False, [])


def _seeds(ctx, param, value):
    try:
        seeds = tuple(int(v) for v in value.replace(" ", "").split(",") if v)
    except ValueError:  # reported below
        seeds = ()
    if not seeds or min(seeds) < 0:
        raise click.BadParameter(f"expected comma-separated non-negative integers, got {value!r}")
    return seeds


def _scenes_with_samples(ctx, param, value):
    try:
        return bench_module("posterior").parse_scenes(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


@command.command("posterior")
@click.option("--scenes", default="mug_off_counter:500", show_default=True, callback=_scenes_with_samples,
              help="Comma-separated bundled scenes, each NAME[:SAMPLES] (500 samples without).")
@click.option("--seeds", default="0", show_default=True, callback=_seeds,
              help="Comma-separated seeds, one solve each.")
@csv_option
@check_option
def posterior(scenes, seeds, csv_path, check):
    """The flagship posterior timed: `dejaview solve SCENE --samples N` in a fresh process, its
    rollouts and largest R-hat against the targets (R-hat <= 1.1, <= 30 s on 2 cores)."""
    rows = bench_module("posterior").run(print_fn=click.echo, scenes=scenes, seeds=seeds)
    _finish(rows, csv_path, check, [r["met"] for r in rows])


@command.command("crossengine")
@click.option("--cases", default="", help="Comma-separated case names (default: all).")
@click.option("--uncertainty", nargs=2, type=click.FloatRange(min=0.0, max=1.0), default=(0.2, 0.2),
              show_default=True, metavar="FRICTION RESTITUTION",
              help="Relative standard deviations of the runs with model uncertainty.")
@click.option("--no-baseline", is_flag=True, help="Skip the solves without model uncertainty.")
@click.option("--seeds", "seed_list", default="0", show_default=True,
              help="Comma-separated search seeds, one solve each per case and setting (a rate, not one draw).")
@click.option("--no-warp", is_flag=True, help="Do not re-simulate the answers in Warp.")
@click.option("--no-fidelity", is_flag=True, help="Skip the fidelity table.")
@click.option("--fidelity-only", is_flag=True, help="Only the fidelity table.")
@click.option("--flat-prior", is_flag=True,
              help="Solve the cases under a flat prior instead of their <prior> (bench/crossengine.py PRIOR).")
@click.option("--area-offset", nargs=2, type=float, default=(0.0, 0.0), show_default=True, metavar="DX DY",
              help="Move the floor cases' start areas (centred on the truth's x, y) by DX DY m, so that "
                   "the guess at the area's centre is not the truth's position.")
@click.option("--timestep-study", is_flag=True,
              help="Only the first engine's time-step convergence on the fidelity rows and the cases' true starts.")
@click.option("--throws", default=0, type=click.IntRange(min=0), metavar="N",
              help="Only the engines' gap on N random box throws, with its controls (seeded by the first "
                   "of --seeds).")
@click.option("--random-cases", default=0, type=click.IntRange(min=0), metavar="N",
              help="Also solve N random tumbling boxes of the cases' kind (bench/crossengine_cases.py random_cases), "
                   "held out from every choice made on the cases; alone without --cases.")
@click.option("--random-seed", default=0, type=click.IntRange(min=0), show_default=True,
              help="The seed of --random-cases' draw.")
@click.option("--perturbed-seed", default=None, type=click.IntRange(min=0), metavar="S",
              help="Solve the cases with their truths perturbed by seed S (perturbed_cases: the start moved up to "
                   "5 cm, velocities scaled by 0.8-1.2, turned up to 15 deg); S >= 100 held out, below: tuning.")
@click.option("--engines", default="mujoco", show_default=True, help="Observing engines: mujoco (DejaView's contact mapped), bullet, "
                   "mujoco-default (MuJoCo's own default contact at the scene's step).")
@click.option("--mismatched", default=None, type=click.IntRange(min=0), metavar="S",
              help="Observe in worlds drawn by seed S: friction x0.7-1.4, restitution 0-0.3 (S >= 100 held out).")
@click.option("--inference-xml", default="", help="Also solve with this XML added to <inference>.")
@csv_option
def crossengine(seed_list, csv_path, **options):
    """Answers that survive another engine: MuJoCo or Bullet observes, DejaView solves, the observer re-simulates.

    First the fidelity table (the same start in DejaView, MuJoCo and Bullet, end distance after
    0.5/1.0/1.5 s), then every case solved from its end pose alone (the start area's centre at rest
    as the guess, the cases' <prior>) with `solve`'s defaults, without and with
    <model-uncertainty>, each answer re-simulated in the observing engine (and Warp where it is
    installed); success: within 3 cm of the observation. Needs mujoco (and pybullet for Bullet).
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    module = bench_module("crossengine")
    try:
        seeds = tuple(int(v) for v in seed_list.replace(" ", "").split(",") if v)
    except ValueError:
        raise click.BadParameter(f"{seed_list!r} is not a comma-separated list of whole numbers",
                                 param_hint="--seeds") from None
    try:
        rows = module.command(click.echo, seeds=seeds, **options)
    except ValueError as exc:
        hint = next((h for k, h in (("seeds", "--seeds"), ("area offset", "--area-offset"),
                                    ("engines", "--engines"), ("inference-xml", "--inference-xml"))
                     if k in str(exc)), "--cases")
        raise click.BadParameter(str(exc), param_hint=hint) from None
    except ImportError as exc:
        raise click.ClickException(f"the crossengine bench needs MuJoCo and PyBullet: {exc}") from None
    _finish(rows, csv_path, False, [])


@command.command("stories")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0),
              help="Seed of the stories: 0 is the development set, 100 and up are held out (run them to "
                   "check a change, never to make one).")
@click.option("--count", default=7, show_default=True, type=click.IntRange(min=1),
              help="Stories, one of each kind in turn.")
@click.option("--kinds", default=None,
              help="Comma-separated kinds [default: all of bench/story_scenes.py KINDS].")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("out/bench/stories"),
              show_default=True, help="The stories' scene files and truths go to OUT/seed<SEED>.")
@click.option("--no-solve", is_flag=True, help="Only write the stories.")
@csv_option
@check_option
def stories(seed, count, kinds, out, no_solve, csv_path, check):
    """Random stories solved from where the source was seen lying still.

    Writes COUNT scene files of everyday kinds (a ball thrown, bounced or rolled off a table, a mug
    knocked off a counter, tossed or slid off a desk, a box thrown), each with the source's resting
    pose as its target, a start area and no other setting, and solves each with `solve`'s
    defaults. Solved: the answer's end within 1 cm and 5 deg of the observed pose; --check: exit 1
    below the target, 6 of 7.
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    module = bench_module("stories")
    names = None
    if kinds is not None:
        names = [k for k in kinds.replace(" ", "").split(",") if k]
        known = module.story_scenes().KINDS
        bad = [k for k in names if k not in known]
        if not names or bad:
            raise click.BadParameter(f"expected a comma-separated list of {', '.join(known)}, got {kinds!r}",
                                     param_hint="--kinds")
    rows = module.run(print_fn=click.echo, seed=seed, count=count, out=out, kinds=names, solve=not no_solve)
    solved = sum(bool(r.get("solved")) for r in rows)
    _finish(rows, csv_path, check and not no_solve, [7 * solved >= 6 * len(rows)])


@command.command("tracked")
@click.option("--samples", default=300, show_default=True, type=click.IntRange(min=20),
              help="Posterior samples of each solve.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Seed of the solves.")
@csv_option
@check_option
def tracked(samples, seed, csv_path, check):
    """A tracked source against its last observation alone.

    Solves examples/scenes/box_tossed_tracked.xml (a box tossed, seen at four moments, two of them
    by position alone) with posterior samples, and the same scene with its last observation alone,
    and prints each free parameter's two 90 % intervals, their widths' ratio and whether each holds
    the truth. --check: exit 1 unless every start-velocity interval is narrower tracked and holds
    the truth.
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("tracked").run(print_fn=click.echo, samples=samples, seed=seed)
    velocity = [r for r in rows if r["parameter"].startswith("linear_velocity")]
    _finish(rows, csv_path, check, [all(r["width_ratio"] < 1 and r["truth_in_tracked"] for r in velocity)])


@command.command("peers")
@click.option("--quick", is_flag=True, help="N = 1, 2 over 50 steps, small batches (smoke test).")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(min=1),
              help="Timings are the best of at least this many runs (short calls repeat for 0.3 s).")
@click.option("--memory-batch", default=1024, show_default=True, type=click.IntRange(min=1),
              help="Candidates of the mug loss + gradient whose peak memory is reported.")
@csv_option
@check_option
def peers(quick, repeats, memory_batch, csv_path, check):
    """DejaView against MuJoCo with finite differences, in one process.

    A box thrown across a table onto the floor with N - 1 boxes in its way
    (N = 1, 2, 4, 8, 16; 750 steps of 2 ms, 12 free parameters): DejaView's
    rollout and exact loss + gradient beside MuJoCo's rollout and
    finite-difference gradient (13 rollouts); the mug reference scene at B = 1
    and 64; the peak memory of a 1024-candidate mug loss + gradient; and the
    targets. A few minutes without --quick.
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("peers").run(print_fn=click.echo, quick=quick, repeats=repeats,
                                     memory_batch=memory_batch)
    _finish(rows, csv_path, check, [r["met"] for r in rows if r["section"] == "target"])


@command.command("load")
@click.option("--clients", default=50, show_default=True, type=click.IntRange(min=1),
              help="Concurrent WebSocket clients, one short simulate job each.")
@click.option("--url", default=None, help="Benchmark this running server (ws://HOST:PORT/ws) instead of "
                                          "starting one.")
@click.option("--workers", default=None, type=click.IntRange(min=1),
              help="Workers of the server started [default: one per core, at most 4].")
@click.option("--executor", type=click.Choice(["process", "thread"]), default="process", show_default=True,
              help="Workers of the server started: processes or threads.")
@csv_option
@check_option
def load(clients, url, workers, executor, csv_path, check):
    """Service load: jobs per second and p50/p99 latency of many concurrent clients.

    Starts `dejaview serve` on a free loopback port (unless --url), opens
    --clients WebSocket connections at once, each submitting a 10-step
    simulate job, and checks that no job was lost (--check: exit 1 if one was).
    """
    row = bench_module("load").run(print_fn=click.echo, clients=clients, url=url, workers=workers,
                                   executor=executor)
    _finish([row], csv_path, check, [row["lost"] == 0])


@command.command("live")
@click.option("--answers", default=100, show_default=True, type=click.IntRange(min=1),
              help="Live messages answered one after another, idle and again with every worker busy.")
@click.option("--simulations", default=2000, show_default=True, type=click.IntRange(min=2),
              help="Training simulations of the train job that makes the model.")
@click.option("--epochs", default=30, show_default=True, type=click.IntRange(min=1), help="Its most epochs.")
@click.option("--workers", default=2, show_default=True, type=click.IntRange(min=1), help="Worker processes.")
@csv_option
def live(answers, simulations, epochs, workers, csv_path):
    """Live answers: round trips of `live` messages to a `dejaview serve` whose scene's model a train
    job made, idle and while solve jobs keep every worker busy (p50/p99/max, the server's own time)."""
    row = bench_module("live").run(print_fn=click.echo, answers=answers, simulations=simulations, epochs=epochs,
                                   workers=workers)
    _finish([row], csv_path, False, [])


@command.command("soak")
@click.option("--minutes", default=10.0, show_default=True, type=click.FloatRange(min=0.1, max=24 * 60),
              help="How long the clients submit jobs.")
@click.option("--clients", default=8, show_default=True, type=click.IntRange(min=1, max=256),
              help="Clients submitting solve and heatmap jobs one after another.")
@click.option("--kills", default=5, show_default=True, type=click.IntRange(min=0, max=100),
              help="Times the server and its workers are killed with -9 and restarted, at random moments.")
@click.option("--workers", default=2, show_default=True, type=click.IntRange(min=1),
              help="Worker processes of the server.")
@click.option("--seed", default=0, show_default=True, type=int, help="Seeds the kill moments and the clients.")
@click.option("--disk-mib", default=256, show_default=True, type=click.IntRange(min=0),
              help="The results dir is a tmpfs of this size (a mount namespace of the bench's own), filled "
                   "and freed once during the run; 0: no tmpfs, the disk is not filled.")
@csv_option
@check_option
def soak(minutes, clients, kills, workers, seed, disk_mib, csv_path, check):
    """Service soak: clients submit jobs for MINUTES while the server is killed -9 and restarted and
    its disk fills and is freed once; accepted, finished, failed by code, lost (must be 0),
    duplicated (must be 0), peak memory (--check: exit 1 if a job was lost or duplicated). Loopback
    only."""
    row = bench_module("soak").run(print_fn=click.echo, minutes=minutes, clients=clients, kills=kills,
                                   workers=workers, seed=seed, disk_mib=disk_mib)
    dicts = ("failed", "refused", "answers_while_full", "failed_while_full")
    _finish([{**row, **{key: json.dumps(row[key]) for key in dicts}}], csv_path, check,
            [row["lost"] == 0 and row["duplicated"] == 0])


def _register_inference_benchmarks() -> None:
    """The inference's benchmarks (physics, amortised, amortised-vs-sampler, calibration, identify), defined in
    ``bench_inference``."""
    from dejaview.cli import bench_inference

    for cmd in (bench_inference.physics, bench_inference.amortised, bench_inference.amortised_vs_sampler,
                bench_inference.calibration, bench_inference.identify_calibration):
        command.add_command(cmd)


_register_inference_benchmarks()
