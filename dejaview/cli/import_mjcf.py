"""``dejaview import-mjcf MODEL -o SCENE [--key NAME]``: a MuJoCo model as a DejaView scene."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("import-mjcf")
@click.argument("model", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The scene file to write (meshes go to meshes/ beside it).")
@click.option("--key", metavar="NAME", help="Keyframe for the initial state [default: qpos0, at rest].")
def command(model: Path, output: Path, key: str | None) -> None:
    """Write a DejaView scene from the MJCF file MODEL (needs the mujoco package).

    World geoms become fixed objects, bodies with a free joint movable objects
    (one geom each) with their pose and velocity from qpos0 or --key, their
    masses and their geoms' friction and restitution (from solref's damping
    ratio). Bodies without a free joint are frozen at that pose as fixed
    objects. docs/robotics.md lists what does not carry over.
    """
    from dejaview.io.mjcf import MJCFError, import_mjcf

    try:
        import mujoco  # noqa: F401
    except ImportError as exc:
        raise MJCFError("import-mjcf needs the mujoco package: pip install mujoco") from exc
    scene = import_mjcf(model, output, key=key)
    movable = len(scene.movable)
    click.echo(f"wrote {output}: {len(scene.objects)} objects, {movable} movable")
