"""``dejaview simulate SCENE -o DIR``: run a scene forward and write trajectory.csv."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.options import (backend_options, common_options, configure_torch, package_path_option,
                                  show_progress)


@click.command("simulate")
@click.argument("scene", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              required=True, help="output folder (created)")
@click.option("--steps", type=int, default=None, help="number of steps (default: duration / dt)")
@click.option("--record-every", type=int, default=1, show_default=True, help="record every k-th step")
@click.option("--float32", is_flag=True, help="simulate in float32 instead of float64")
@click.option("--max-steps", type=int, default=None,
              help="step budget, steps x substeps (default 2000000 or DEJAVIEW_MAX_STEPS)")
@common_options
@package_path_option
@backend_options()
def command(scene, out_dir, steps, record_every, float32, max_steps, backend, iterations, optimizer,
            gradient, seed, quiet):
    """Simulate SCENE from the objects' given poses and velocities; write DIR/trajectory.csv."""
    import torch
    from tqdm import tqdm

    from dejaview.backends import BackendOptions
    from dejaview.errors import DejaViewError, SimulationError
    from dejaview.scene import Scene, bounds

    configure_torch()
    if record_every < 1:
        raise click.BadParameter("must be >= 1", param_hint="--record-every")
    if steps is not None and steps < 1:
        raise click.BadParameter("must be >= 1", param_hint="--steps")
    if max_steps is not None and max_steps < 1:
        raise click.BadParameter("must be >= 1", param_hint="--max-steps")
    max_steps = bounds.max_steps(max_steps)
    if steps is not None and steps > max_steps:
        raise click.BadParameter(f"{steps} steps is over the step budget of {max_steps} (--max-steps)",
                                 param_hint="--steps")
    sc = Scene.from_xml(scene, max_steps=max_steps)
    try:  # --float32 is the spheres backend's dtype: another backend, or its native engine, refuses it
        backend = BackendOptions.of(backend, SimulationError, dtype=torch.float32 if float32 else None)
    except DejaViewError as exc:
        raise click.BadParameter(str(exc)) from None
    bar = tqdm(desc="simulate", unit="step", disable=not show_progress(quiet))

    def progress(done, total):
        bar.total = total
        bar.update(done - bar.n)

    run = backend.simulate(sc, steps=steps, record_every=record_every, max_steps=max_steps,
                           callback=None if bar.disable else progress)
    bar.close()
    path = run.write(out_dir)["trajectory"]
    if not quiet:
        click.echo(f"simulated {run.steps} steps ({run.steps * run.dt:.3f} s) of {len(run.names)} bodies "
                   f"({run.backend}) in {run.elapsed_s:.2f} s -> {path}")
