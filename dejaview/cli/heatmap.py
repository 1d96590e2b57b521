"""``dejaview heatmap SCENE -o DIR``: probability of start positions over the start area."""

from __future__ import annotations

import os
from pathlib import Path

import click

from dejaview.cli.options import (backend_options, common_options, configure_torch, package_path_option,
                                  show_progress)


def _cells(ctx, param, value):
    if value is None:
        return None
    try:
        nx, ny = (int(v) for v in value.lower().replace(",", "x").split("x"))
    except ValueError:
        raise click.BadParameter(f"expected NXxNY, e.g. 16x16, got {value!r}") from None
    if nx < 1 or ny < 1:
        raise click.BadParameter(f"cells must be positive, got {value!r}")
    return nx, ny


@click.command("heatmap")
@click.argument("scene", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              required=True, help="output folder (created)")
@click.option("--cells", callback=_cells, default=None, help="grid NXxNY (overrides <heatmap cells>)")
@click.option("--samples", type=click.IntRange(min=1), default=None,
              help="posterior samples (basins: optimisations) per cell (overrides <heatmap samples>)")
@click.option("--sigma", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="the observation's position sigma in metres (overrides <observation sigma> and "
                   "<heatmap sigma>)")
@click.option("--method", type=click.Choice(["posterior", "basins"]), default=None,
              help="posterior: the posterior's marginal (default); basins: per-cell optimisations "
                   "(default with a local --optimizer or --backend warp)")
@click.option("--lr", type=float, default=None, help="learning rate (default per optimiser)")
@click.option("--batch-size", type=click.IntRange(min=1), default=1024, show_default=True,
              help="candidates per batched optimisation")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="processes optimising chunks at once (default: the CPU count, at most 2)")
@click.option("--ray", "ray", envvar="DEJAVIEW_RAY_ADDRESS", default=None, metavar="ADDRESS",
              help="optimise the chunks on Ray: 'local' (an instance in this process) or a cluster address "
                   "(docs/scale.md; default $DEJAVIEW_RAY_ADDRESS); needs pip install 'dejaview[ray]'")
@click.option("--amortised", "amortised", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="draw the posterior heatmap's samples from an amortised posterior trained for this scene "
                   "(dejaview train), weighed by the exact likelihood")
@click.option("--no-plot", is_flag=True, help="skip heatmap.png")
@common_options
@package_path_option
@backend_options()
def command(scene, out_dir, cells, samples, sigma, method, lr, batch_size, workers, ray, amortised, no_plot, backend,
            iterations, optimizer, gradient, seed, quiet):
    """Which cells of SCENE's start area could its source have started from? Writes
    heatmap.ppm, heatmap.png, heatmap.json, result.json and trajectory.csv (best solution) to DIR."""
    from tqdm import tqdm

    from dejaview.heatmap import compute_heatmap
    from dejaview.scene import Scene

    configure_torch()
    sc = Scene.from_xml(scene)
    if sc.inference is None:
        raise click.ClickException(f"{scene}: the scene has no <inference> section")
    hs = sc.inference.heatmap
    nx, ny = cells or (hs.cells if hs is not None else (16, 16))
    if ray:  # one worker per CPU of the cluster (local: of this machine) unless told
        from dejaview.parallel import ray_cpus

        workers = workers or ray_cpus(ray)
    workers = workers or max(1, min(os.cpu_count() or 1, 2))
    bar = tqdm(total=nx * ny, desc="heatmap", unit="cell", disable=not show_progress(quiet))

    def progress(p):
        bar.n = p.cells_done
        bar.set_postfix(best=f"{p.best_loss:.4g}", it=p.iteration, phase=p.phase, refresh=False)
        bar.refresh()

    result = compute_heatmap(sc, cells=(nx, ny), samples=samples, sigma=sigma, iterations=iterations,
                             optimizer=optimizer, gradient=gradient, seed=seed, lr=lr,
                             batch_size=batch_size, workers=workers, callback=progress, backend=backend,
                             method=method, ray=ray or None, amortised=amortised)
    bar.n = nx * ny
    bar.close()
    paths = result.write(out_dir, plot=not no_plot)
    if not quiet:
        i, j = divmod(int(result.probability.argmax()), nx)[::-1]
        cx = result.lo[0] + (i + 0.5) * (result.hi[0] - result.lo[0]) / nx
        cy = result.lo[1] + (j + 0.5) * (result.hi[1] - result.lo[1]) / ny
        start = result.best.initial_state["position"]
        if result.settings.get("method") == "posterior":
            from dejaview.heatmap.posterior import credible_area

            click.echo(f"{result.candidates} posterior samples over {nx} x {ny} cells in {result.seconds:.1f} s; "
                       f"{len(result.solutions)} mode(s); the 90 % credible region covers "
                       f"{100 * credible_area(result.probability):.1f} % of the start area")
            from dejaview.inference.posterior_report import agreement_warning

            warning = agreement_warning(result.settings.get("agreement"), "this heatmap")
            if warning:
                click.echo("  " + warning)
            for warning in result.settings.get("warnings", []):
                click.echo("  warning: " + warning)
        else:
            click.echo(f"{result.candidates} optimisations over {nx} x {ny} cells in {result.seconds:.1f} s; "
                       f"{len(result.solutions)} distinct solutions")
        click.echo(f"  most probable cell ({i}, {j}) around ({cx:.3f}, {cy:.3f}) m: "
                   f"p = {result.probability[j, i]:.3f}; entropy {result.entropy_bits():.2f} bits "
                   f"(uniform {__import__('math').log2(nx * ny):.2f})")
        click.echo(f"  best solution: loss {result.best.loss:.4g} from ({start[0]:.3f}, {start[1]:.3f}, "
                   f"{start[2]:.3f}) m")
        click.echo("  wrote " + ", ".join(str(p) for p in paths.values()))
