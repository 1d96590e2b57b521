"""``dejaview simulate SCENE -o DIR``: run a scene forward and write trajectory.csv."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.options import common_options, configure_torch, show_progress


@click.command("simulate")
@click.argument("scene", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              required=True, help="output folder (created)")
@click.option("--steps", type=int, default=None, help="number of steps (default: duration / dt)")
@click.option("--record-every", type=int, default=1, show_default=True, help="record every k-th step")
@click.option("--float32", is_flag=True, help="simulate in float32 instead of float64")
@common_options
def command(scene, out_dir, steps, record_every, float32, backend, iterations, optimizer, gradient,
            seed, quiet):
    """Simulate SCENE from the objects' given poses and velocities; write DIR/trajectory.csv."""
    import time

    import torch
    from tqdm import tqdm

    from dejaview.io.trajectory import write_trajectory_csv
    from dejaview.scene import Scene
    from dejaview.sim import World
    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import rollout

    configure_torch()
    if record_every < 1:
        raise click.BadParameter("must be >= 1", param_hint="--record-every")
    sc = Scene.from_xml(scene)
    world = World.from_scene(sc, dtype=torch.float32 if float32 else torch.float64)
    state = initial_state(world, sc)
    n = world.steps if steps is None else steps
    if n < 1:
        raise click.BadParameter("must be >= 1", param_hint="--steps")
    bar = tqdm(total=n, desc="simulate", unit="step", disable=not show_progress(quiet))
    start = time.perf_counter()

    def step_with_progress(world_, state_, broadphase=None):
        from dejaview.sim.integrate import step

        bar.update(1)
        return step(world_, state_, broadphase)

    with torch.no_grad():
        traj = rollout(world, state, steps=n, record_every=record_every, step_fn=None if bar.disable
                       else step_with_progress)
    bar.close()
    path = write_trajectory_csv(out_dir / "trajectory.csv", world, traj)
    if not quiet:
        click.echo(f"simulated {n} steps ({n * world.dt:.3f} s) of {len(world.names)} bodies in "
                   f"{time.perf_counter() - start:.2f} s -> {path}")
