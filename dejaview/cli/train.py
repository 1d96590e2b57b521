"""``dejaview train SCENE -o MODEL``: an amortised posterior of a scene, for instant answers."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.options import configure_torch, package_path_option, show_progress


@click.command("train")
@click.argument("scene", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_file", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="the model file to write (safetensors)")
@click.option("--simulations", type=click.IntRange(min=2), default=None,
              help="training simulations (default 20000)")
@click.option("--seed", type=click.IntRange(min=0), default=0, help="random seed of the draws and the fit")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="processes simulating at once (default 1: this process, all its engine's threads; "
                   "with --ray: the cluster's CPUs)")
@click.option("--ray", "ray", envvar="DEJAVIEW_RAY_ADDRESS", default=None, metavar="ADDRESS",
              help="simulate on a Ray cluster: 'local' or its address (docs/scale.md; default "
                   "$DEJAVIEW_RAY_ADDRESS); needs pip install 'dejaview[ray]'")
@click.option("--quiet", "-q", is_flag=True, help="no progress bar")
@package_path_option
def command(scene, out_file, simulations, seed, workers, ray, quiet):
    """Train an amortised posterior for SCENE: simulate starts drawn from its prior (start area,
    <prior>, <physics-prior>), fit a conditional normalising flow to them, and write MODEL. Then
    'dejaview solve SCENE -o DIR --amortised MODEL' answers any observation of the same scene
    (its statics, source, prior and kinds of observation) from the model, and the service answers
    'live' requests from it."""
    from dataclasses import replace

    from tqdm import tqdm

    from dejaview.inference.amortised import train
    from dejaview.inference.params import TrainParams
    from dejaview.scene import Scene

    configure_torch()
    sc = Scene.from_xml(scene)
    params = TrainParams(seed=seed)
    if simulations is not None:
        params = replace(params, simulations=simulations)
    if ray:
        from dejaview.parallel import ray_cpus

        workers = workers or ray_cpus(ray)
    params = replace(params, workers=workers or 1, ray=ray or None)
    bars = {}

    def progress(d):
        if not show_progress(quiet):
            return
        if d["phase"] == "simulate":
            bar = bars.setdefault("simulate", tqdm(total=d["total"], desc="simulate", unit="sim"))
            bar.n = min(d["done"], d["total"])
            bar.refresh()
        else:
            if "simulate" in bars:
                bars.pop("simulate").close()
            bar = bars.setdefault("fit", tqdm(total=d["epochs"], desc="fit", unit="epoch"))
            bar.n = d["epoch"]
            bar.set_postfix(validation=f"{d['validation_loss']:.3f}", refresh=True)

    model = train(sc, params, callback=progress)
    for bar in bars.values():
        bar.close()
    path = model.save(out_file)
    info = model.info
    fit = info["fit"]
    click.echo(f"trained on {info['simulations']} simulations ({info['draws']} starts drawn, "
               f"{100 * info['feasible_share']:.0f} % free of the other objects) in {info['simulate_seconds']:.1f} s; "
               f"flow fitted in {fit['seconds']:.1f} s ({fit['epochs']} epochs, best {fit['best_epoch']}: "
               f"validation -log q {fit['validation_nll']:.3f})")
    click.echo(f"  wrote {path} (for {info['scene']}; {info['seconds']:.1f} s in all)")
