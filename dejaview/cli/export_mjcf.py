"""``dejaview export-mjcf SCENE -o MODEL.xml [--state result.json] [--timestep S] [--contact mapped|mujoco]``:
the scene as a MuJoCo model."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.options import package_path_option


@click.command("export-mjcf")
@click.argument("scene", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="The MJCF file to write.")
@click.option("--state", type=click.Path(dir_okay=False, path_type=Path), metavar="RESULT.json",
              help="A solve's result.json: its initial_state replaces the source's in the keyframe.")
@click.option("--timestep", type=click.FloatRange(min=0.0, min_open=True, max=0.01), default=None,
              metavar="SECONDS",
              help="MuJoCo's time step (default 0.0005; the contacts' damping is mapped for it). "
                   "5e-05 is converged where 0.0005 is not: a box tipping over an edge "
                   "(docs/physics-fidelity.md, \"MuJoCo's time step\").")
@click.option("--contact", type=click.Choice(["mapped", "mujoco"]), default="mapped", show_default=True,
              help="mapped: DejaView's contact (stiffness, restitution, friction) carried over; mujoco: "
                   "MuJoCo's own default contact (soft, critically damped), only the friction carried.")
@package_path_option
def command(scene: Path, output: Path, state: Path | None, timestep: float | None, contact: str) -> None:
    """Write SCENE as an MJCF model that MuJoCo loads as it is.

    Fixed objects become world geoms, movable ones bodies with a free joint;
    the keyframe ``initial`` holds their initial state (from --state for the
    source, else from the scene), so an answer replays in MuJoCo with
    ``mj_resetDataKeyframe(model, data, 0)``. Meshes are inline mesh assets
    (non-convex ones as convex pieces: MuJoCo collides convex hulls).
    """
    from dejaview.io.mjcf import MJ_TIMESTEP, MJCFError, export_mjcf, read_state
    from dejaview.scene import Scene

    sc = Scene.from_xml(scene)
    text = export_mjcf(sc, read_state(state) if state is not None else None, timestep=timestep or MJ_TIMESTEP,
                       contact=contact)
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise MJCFError(f"{output}: cannot write: {exc.strerror or exc}") from exc
    click.echo(f"wrote {output}: {len(sc.objects)} objects, keyframe 'initial'")
