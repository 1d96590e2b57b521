"""``dejaview validate``: check scene files without simulating them."""

from __future__ import annotations

import sys

import click

from dejaview.errors import SceneError


@click.command("validate")
@click.argument("scenes", nargs=-1, required=True, metavar="SCENE...")
@click.option("--no-file-check", "no_file_check", is_flag=True,
              help="Do not check that mesh and sphere files exist.")
@click.option("--max-steps", type=click.IntRange(min=1), default=None,
              help="step budget of a simulation, steps x substeps (default 2000000 or DEJAVIEW_MAX_STEPS)")
def command(scenes: tuple[str, ...], no_file_check: bool, max_steps: int | None) -> None:
    """Check each SCENE file against the scene format.

    Prints ``OK <path>: N objects, source=<id>`` for a valid scene and the
    one-line error (file:line: <element> reason) on stderr for the others:
    everything ``dejaview simulate`` would refuse, the sphere simulator's
    <simulation> attributes, physical ranges and the step budget included.
    Exit status 0 when every scene is valid, 2 otherwise.
    """
    from dejaview.scene.xml import read_scene_file

    failed = 0
    for path in scenes:
        try:
            scene = read_scene_file(path, check_files=not no_file_check, max_steps=max_steps)
        except SceneError as exc:
            failed += 1
            click.echo(f"error: {exc}", err=True)
            continue
        n = len(scene.objects)
        source = scene.inference.source if scene.inference is not None else "none"
        click.echo(f"OK {path}: {n} object{'' if n == 1 else 's'}, source={source}")
    if failed:
        # sys.exit, not ctx.exit: the entry point runs click with standalone_mode=False,
        # where click would return ctx.exit's status instead of exiting with it.
        sys.exit(2)
