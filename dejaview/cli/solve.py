"""``dejaview solve SCENE -o DIR``: infer the source's initial state."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.options import (backend_options, common_options, configure_torch, package_path_option,
                                  show_progress)


@click.command("solve")
@click.argument("scene", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              required=True, help="output folder (created)")
@click.option("--budget", type=click.IntRange(min=1), default=None,
              help="most rollouts of the default search (default 40000; a Jacobian counts 3)")
@click.option("--multistart", type=click.IntRange(min=1), default=None,
              help="with --optimizer gd|adam|lbfgs|bfgs: initial guesses run as one batch")
@click.option("--screen", type=click.IntRange(min=0), default=None,
              help="with --optimizer gd|adam|lbfgs|bfgs: rank this many random guesses by loss first")
@click.option("--lr", type=float, default=None, help="with a local optimiser: learning rate")
@click.option("--samples", type=int, default=None,
              help="draw N samples of the posterior (posterior.csv; default: <posterior samples>, else 0)")
@click.option("--plot", is_flag=True, help="also write loss.png")
@click.option("--truth", "truth_file", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="a known true start (a .truth.json with initial_state): say where it lies in the posterior")
@click.option("--tolerance", type=float, default=None,
              help="stop once the best loss is at or below this (default: run all iterations)")
@click.option("--amortised", "amortised", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="answer from an amortised posterior trained for this scene (dejaview train): its draws "
                   "weighed by the exact likelihood, the sampler where they show it does not fit")
@click.option("--model-uncertainty", "model_uncertainty", nargs=2, default=None,
              type=click.FloatRange(min=0.0, max=1.0), metavar="FRICTION RESTITUTION",
              help="relative standard deviations the likelihood averages over (overrides the scene's "
                   "<model-uncertainty>; 0 0: none)")
@common_options
@package_path_option
@backend_options(with_compile=True)
def command(scene, out_dir, budget, multistart, screen, lr, samples, plot, truth_file, tolerance,
            amortised, model_uncertainty, backend, iterations, optimizer, gradient, seed, quiet):
    """Infer the most probable initial state of SCENE's source object (its <prior> and
    <observation>); write result.json, iterations.csv and trajectory.csv (the answer
    re-simulated) to DIR, and posterior.csv with --samples N."""
    from tqdm import tqdm

    from dejaview.inference import solve
    from dejaview.inference.solve import SolveParams
    from dejaview.scene import Scene

    configure_torch()
    truth = read_truth(truth_file) if truth_file is not None else None
    sc = Scene.from_xml(scene)
    if sc.inference is None:
        raise click.ClickException(f"{scene}: the scene has no <inference> section")
    if model_uncertainty is not None:
        from dataclasses import replace

        from dejaview.scene import ModelUncertainty

        sc = replace(sc, inference=replace(sc.inference, model_uncertainty=ModelUncertainty(*model_uncertainty)))
    total = iterations if iterations is not None else sc.inference.iterations
    bar = tqdm(total=total, desc="solve", unit="it", disable=not show_progress(quiet))

    def progress(p):
        if p.phase == "sample":
            bar.set_description("sample")
            bar.set_postfix(done=f"{100 * p.fraction:.0f}%", refresh=True)
            return
        bar.update(1)
        bar.set_postfix(loss=f"{p.loss:.4g}", best=f"{p.best_loss:.4g}", refresh=False)

    result = solve(sc, SolveParams(iterations=iterations, optimizer=optimizer, gradient=gradient, seed=seed,
                   lr=lr, multistart=multistart, screen=screen, budget=budget, samples=samples,
                   tolerance=tolerance, amortised=amortised), callback=progress, backend=backend, truth=truth)
    bar.close()
    paths = result.write(out_dir, plot=plot)
    if not quiet:
        s = result.initial_state
        fmt = lambda v: "(" + ", ".join(f"{x:.3f}" for x in v) + ")"  # noqa: E731
        click.echo(f"best loss {result.loss:.5g} m after {len(result.iterations)} iterations "
                   f"({result.settings['backend']} backend, {result.settings['optimizer']}, "
                   f"{result.settings['gradient']} mode)")
        search = result.settings.get("search")
        if search is not None:
            click.echo(f"  -log posterior {search['neg_log_posterior']:.4g} (end misfit chi2 "
                       f"{search['observation_chi2']:.3g}), {len(search['modes'])} mode(s) found, "
                       f"{search['rollouts']} rollouts")
            if "from_samples" in search:
                click.echo(f"  (a posterior sample, refined: more probable than the search's answer, -log posterior "
                           f"{search['from_samples']['search_neg_log_posterior']:.4g})")
            mu = result.settings.get("model_uncertainty")
            if mu is not None:
                click.echo(f"  model uncertainty: friction {mu['friction']:g}, restitution "
                           f"{mu['restitution']:g}, stiffness {mu['stiffness']:g} ({mu['variants']} variants)")
        click.echo(f"  start position   {fmt(s['position'])} m")
        click.echo(f"  start velocity   {fmt(s['linear_velocity'])} m/s, spin {fmt(s['angular_velocity'])} rad/s")
        if "physics" in result.settings:
            ph = result.settings["physics"]["most_probable"]
            click.echo(f"  physics          friction {ph['friction']:.3f}, restitution {ph['restitution']:.3f}, "
                       f"stiffness {ph['stiffness']:.4g} N/m per kg (inferred: "
                       f"{', '.join(result.settings['physics']['inferred'])})")
        for line in observation_lines(result):
            click.echo("  " + line)
        post = result.settings.get("posterior")
        if post is not None:
            sampler = post["sampler"]
            how = (f"{sampler['stages']} tempering steps" if sampler.get("method") != "amortised" else
                   f"{sampler['draws']} draws of the amortised model weighed, Pareto k-hat {sampler['k_hat']:.2f}, "
                   f"ESS {sampler['ess']:.0f}")
            click.echo(f"  posterior: {post['samples']} samples ({sampler['unique_samples']} distinct, "
                       f"{how}, {sampler['rollouts']} rollouts, "
                       f"{sampler['seconds']:.1f} s); modes by probability: "
                       + ", ".join(f"{m['probability']:.2f}" for m in post["modes"]))
            for name, iv in post["intervals"].items():
                lo, hi = iv["90%"]
                click.echo(f"    {name:20s} median {iv['median']:8.3f}   90% [{lo:8.3f}, {hi:8.3f}]"
                           + (f"   R-hat {iv['rhat']:.3f}" if "rhat" in iv else ""))
            from dejaview.inference.posterior_report import agreement_warning

            warning = agreement_warning(post.get("agreement"), "these intervals and mode probabilities")
            if warning:
                click.echo("  " + warning)
        t = result.settings.get("truth")
        if t is not None:
            level = ("" if "credible_level" not in t else
                     f"; credible level {100 * t['credible_level']:.0f} % (the posterior mass more probable "
                     f"than it)")
            click.echo(f"  the truth: -log posterior {t['neg_log_posterior']:.4g}, end misfit chi2 "
                       f"{t['observation_chi2']:.3g}{level}")
        for warning in result.settings.get("warnings", []):
            click.echo("  warning: " + warning)
        click.echo("  wrote " + ", ".join(str(p) for p in paths.values()))


def observation_lines(result) -> list[str]:
    """The answer against each observation as a user would check it (``SolveResult.observations``):
    the re-simulated end against a target without time (where the source lies, or flies on), each
    timed target against the answer at its moment; for a target seen moving at a moment not known,
    the best-matching moment beside the end."""
    fmt = lambda v: "(" + ", ".join(f"{x:.3f}" for x in v) + ")"  # noqa: E731
    rest = result.settings.get("rest", {})
    out = []
    for row, target in zip(result.observations(), result.scene.inference.targets):
        angle = "" if row["angle_error_deg"] is None else f", {row['angle_error_deg']:.2f} deg"
        off = f"{row['position_error'] * 1000:.2f} mm{angle} off"
        if target.time is not None:
            seen = "seen lying still" if row["at_rest"] else "seen"
            what = "" if target.orientation is not None else " (position only)"
            out.append(f"at t = {row['time']:.3f} s ({seen}{what}): {off}, at {fmt(row['position'])} m")
            continue
        came = rest.get("came_to_rest_s")
        when = (f"came to rest at {came:.2f} s" if came is not None else "still moving at the end")
        if row["at_rest"]:
            out.append(f"end (t = {row['time']:.2f} s) against where it was seen lying: {off} ({when})")
        else:
            out.append(f"end (t = {row['time']:.2f} s) at {fmt(row['position'])} m: {off} the observation")
        if "matched" in row:
            m = row["matched"]
            angle = "" if m["angle_error_deg"] is None else f", {m['angle_error_deg']:.2f} deg"
            out.append(f"passes the observed pose at t = {m['time']:.3f} s: {m['position_error'] * 1000:.2f} mm"
                       f"{angle} off (seen moving, moment not known)")
    return out


def read_truth(path: Path) -> dict:
    """The ``initial_state`` of a truth file (``examples/scenes/*.truth.json``), or a one-line error."""
    import json

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        state = data["initial_state"]
        return {k: [float(v) for v in state[k]] for k in ("position", "orientation", "linear_velocity",
                                                          "angular_velocity")}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise click.ClickException(f"{path}: not a truth file with an initial_state "
                                   f"(position, orientation, linear_velocity, angular_velocity): {exc}") from None

