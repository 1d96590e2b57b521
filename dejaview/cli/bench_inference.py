"""``dejaview bench`` commands of the inference's targets: what a physics prior costs, what an
amortised posterior costs and gives and how its answers compare with the sampler's, and the
posterior's calibration. ``dejaview.cli.bench``
adds them to its group."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.bench_table import _comma_list, _finish, bench_module, check_option, csv_option


@click.command("physics")
@click.option("--scenes", default="box_along_shelf,ball_off_table,box_tossed_tracked", show_default=True,
              help="Comma-separated bundled scenes.")
@click.option("--prior", default="0.3 0.3 0", show_default=True,
              help="The <physics-prior> added: friction, restitution and stiffness relative standard deviations.")
@csv_option
@check_option
def physics(scenes, prior, csv_path, check):
    """What a <physics-prior> costs: each scene solved without and with it (target: at most 3x)."""
    try:
        values = tuple(float(v) for v in prior.split())
    except ValueError:
        values = ()
    if len(values) != 3 or min(values) < 0:
        raise click.BadParameter(f"expected three numbers >= 0, got {prior!r}")
    rows = bench_module("physics_cost").run(print_fn=click.echo, scenes=tuple(s for s in scenes.split(",") if s),
                                            prior=values)
    _finish(rows, csv_path, check, [r["met"] for r in rows])


@click.command("amortised")
@click.option("--scenes", default="mug_off_counter", show_default=True, help="Comma-separated bundled scenes.")
@click.option("--simulations", default=None, type=click.IntRange(min=2), help="Training simulations (default 20000).")
@click.option("--samples", default=500, show_default=True, type=click.IntRange(min=1),
              help="Samples of the weighed answer (solve --amortised).")
@click.option("--repeats", default=20, show_default=True, type=click.IntRange(min=1), help="Live answers timed.")
@click.option("--model-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Keep the trained models here and reuse them when they fit the scene.")
@csv_option
@check_option
def amortised(scenes, simulations, samples, repeats, model_dir, csv_path, check):
    """Amortised posteriors: training time (target <= 5 min for the mug), live answers (1000 draws and
    a 16x16 heatmap, target <= 100 ms) and the answer weighed by the exact likelihood (k-hat)."""
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("amortised").run(print_fn=click.echo, scenes=tuple(s for s in scenes.split(",") if s),
                                         simulations=simulations, samples=samples, repeats=repeats,
                                         model_dir=model_dir)
    _finish(rows, csv_path, check, [r["met"] for r in rows])


@click.command("amortised-vs-sampler")
@click.option("--scenes", default="ball_down_ramp,box_down_ramp", show_default=True,
              help="Comma-separated bundled scenes, each answered at its own observation.")
@click.option("--simulations", default=None, type=click.IntRange(min=2), help="Training simulations (default 20000).")
@click.option("--samples", default=500, show_default=True, type=click.IntRange(min=2),
              help="Posterior samples of each answer.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0), help="Both answers' seed.")
@click.option("--model-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Keep the trained models here and reuse them when they fit the scene.")
@csv_option
def amortised_vs_sampler(scenes, simulations, samples, seed, model_dir, csv_path):
    """The amortised answer (solve --amortised) beside the sampler's (solve --samples N) on each
    scene's own observation: per parameter both medians and 90 % intervals and the KS statistic
    between them, the energy distance, k-hat, rollouts and seconds (bench/amortised.py, compare)."""
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("amortised").compare(print_fn=click.echo, scenes=tuple(s for s in scenes.split(",") if s),
                                             simulations=simulations, samples=samples, model_dir=model_dir, seed=seed)
    _finish(rows, csv_path, False, [])


@click.command("calibration")
@click.option("--scenes", default="ball_off_table,box_thrown,ramp", show_default=True,
              callback=_comma_list(("ball_off_table", "box_thrown", "ramp")), help="Calibration scenes.")
@click.option("--truths", default=50, show_default=True, type=click.IntRange(min=1),
              help="Truths drawn from each scene's prior.")
@click.option("--samples", default=300, show_default=True, type=click.IntRange(min=1),
              help="Posterior samples per truth.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the rank histograms as a PNG here.")
@click.option("--amortised", is_flag=True,
              help="Answer each truth with solve --amortised from a model trained for the scene first.")
@click.option("--first", default=0, show_default=True, type=click.IntRange(min=0),
              help="Index of the first truth (truth i draws from seed 1000 + i): another set is held out.")
@click.option("--simulations", default=None, type=click.IntRange(min=2),
              help="With --amortised: training simulations (default TrainParams').")
@csv_option
def calibration(scenes, truths, samples, plot_path, amortised, first, simulations, csv_path):
    """Simulation-based calibration of the posterior samples (Talts et al. 2018).

    Draws truths from each scene's prior, observes their ends with the stated noise, samples the
    posterior with `solve(samples=N)` and prints the coverage of the central 50 % and 90 %
    intervals, their sharpness and the rank histograms (targets 40-60 % and 85-97 %).
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("calibration").run(print_fn=click.echo, scenes=scenes, truths=truths,
                                           samples=samples, plot=plot_path, amortised=amortised, first=first,
                                           simulations=simulations)
    _finish(rows, csv_path, False, [])


@click.command("identify")
@click.option("--kinds", default="ball,box", show_default=True, callback=_comma_list(("ball", "box")),
              help="Kinds of throws (bench/identify_calibration.py).")
@click.option("--truths", default=20, show_default=True, type=click.IntRange(min=1),
              help="Truths (one physics, three throws each) per kind.")
@click.option("--first", default=0, show_default=True, type=click.IntRange(min=0),
              help="Index of the first truth (truth i draws from seed 2000 + i): another set is held out.")
@click.option("--samples", default=0, show_default=True, type=click.IntRange(min=0),
              help="identify's importance samples (0: none).")
@csv_option
def identify_calibration(kinds, truths, first, samples, csv_path):
    """Simulation-based calibration of `dejaview identify` over start and physics.

    Draws a physics and three throws from the scenes' priors per truth, tracks them with the
    stated noise, identifies the shared physics and prints the coverage of its central 50 % and
    90 % intervals (targets 35-65 % and 80-98 %) and the errors (friction 15 %, restitution 0.05).
    """
    from dejaview.cli.options import configure_torch

    configure_torch()
    rows = bench_module("identify_calibration").run(print_fn=click.echo, kinds=kinds, truths=truths, first=first,
                                                    samples=samples)
    _finish([{k: (v if not isinstance(v, list) else "; ".join(map(str, v))) for k, v in r.items()} for r in rows],
            csv_path, False, [])
