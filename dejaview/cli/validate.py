"""``dejaview validate``: check scene files without simulating them."""

from __future__ import annotations

import sys

import click

from dejaview.cli.options import package_path_option

from dejaview.errors import GeometryError, SceneError
from dejaview.geometry import DEFAULT_MARGIN


@click.command("validate")
@click.argument("scenes", nargs=-1, required=True, metavar="SCENE...")
@click.option("--no-file-check", "no_file_check", is_flag=True,
              help="Do not check that mesh and sphere files exist (nor whether objects overlap).")
@click.option("--margin", type=click.FloatRange(min=0), default=DEFAULT_MARGIN, show_default=True,
              metavar="METRES", help="Overlap accepted as resting contact between objects.")
@click.option("--max-steps", type=click.IntRange(min=1), default=None,
              help="step budget of a simulation, steps x substeps (default 2000000 or DEJAVIEW_MAX_STEPS)")
@package_path_option
def command(scenes: tuple[str, ...], no_file_check: bool, margin: float, max_steps: int | None) -> None:
    """Check each SCENE file against the scene format, and that no objects overlap.

    Prints ``OK <path>: N objects, source=<id>`` for a valid scene and the
    one-line error (file:line: <element> reason) on stderr for the others:
    everything ``dejaview simulate`` would refuse, the sphere simulator's
    <simulation> attributes, physical ranges and the step budget included.
    Objects that interpenetrate at their given poses (deeper than --margin;
    two fixed objects may) are errors too, one line per pair:
    ``file:line: <object> 'a' and 'b' interpenetrate by D m``.
    A robot's collision mesh that is not watertight takes part as its convex
    hull: a ``note:`` line per mesh says so, and the scene stays valid.
    A moving robot stands where its keyframes put it at time 0 for the
    checks above; where its links pass through a fixed object later on
    (they push movable objects, but pass through fixed ones), a
    ``warning:`` line per robot and object says so, and the scene stays valid.
    Exit status 0 when every scene is valid, 2 otherwise.
    """
    from dejaview.scene.xml import read_scene_file

    failed = 0
    for path in scenes:
        try:
            scene = read_scene_file(path, check_files=not no_file_check, max_steps=max_steps)
            notes = [] if no_file_check else _hull_notes(scene, path)
            collision = None if no_file_check else _collision(scene, path)
            overlaps = [] if no_file_check else _interpenetrations(scene, path, collision, margin)
            warnings = [] if no_file_check or overlaps else _sweeps(scene, path, collision, margin)
        except SceneError as exc:
            failed += 1
            click.echo(f"error: {exc}", err=True)
            continue
        if overlaps:
            failed += 1
            for line in overlaps:
                click.echo(f"error: {line}", err=True)
            continue
        for line in notes:
            click.echo(f"note: {line}")
        for line in warnings:
            click.echo(f"warning: {line}")
        n = len(scene.objects)
        source = scene.inference.source if scene.inference is not None else "none"
        click.echo(f"OK {path}: {n} object{'' if n == 1 else 's'}, source={source}")
    if failed:
        # sys.exit, not ctx.exit: the entry point runs click with standalone_mode=False,
        # where click would return ctx.exit's status instead of exiting with it.
        sys.exit(2)


def _hull_notes(scene, path: str) -> list[str]:
    """One line per robot collision mesh that takes part as its convex hull (it has holes)."""
    from dejaview.scene.robot_links import hull_notes

    out = []
    for obj in scene.objects:
        if obj.robot is None:
            continue
        where = f"{path}:{obj.line}" if obj.line is not None else path
        try:
            out.extend(f"{where}: <object> {note}" for note in hull_notes(scene, obj))
        except GeometryError as exc:
            raise SceneError(f"object {obj.id!r}: {exc}", file=path, line=obj.line, element="object") from exc
    return out


def _collision(scene, path: str):
    from dejaview.geometry.collision import SceneCollision

    try:
        return SceneCollision(scene)
    except GeometryError as exc:
        raise SceneError(str(exc), file=path, element="object") from exc


def _interpenetrations(scene, path: str, collision, margin: float) -> list[str]:
    """One message per pair of objects that overlap deeper than ``margin`` at their poses."""
    pairs = collision.interpenetrations(margin=margin)
    out = []
    for a, b, depth in pairs:
        # the line of the movable one: that is the pose to fix
        fixed_a = _object(scene, a).fixed
        obj = _object(scene, b) if fixed_a else _object(scene, a)
        where = f"{path}:{obj.line}" if obj.line is not None else path
        out.append(f"{where}: <object> {a!r} and {b!r} interpenetrate by {depth:.4f} m "
                   f"(more than the {margin:g} m accepted as resting contact)")
    return out


def _sweeps(scene, path: str, collision, margin: float) -> list[str]:
    """One message per moving robot and fixed object its links pass through (``geometry.sweep``)."""
    from dejaview.geometry.sweep import swept_overlaps

    out = []
    for s in swept_overlaps(scene, collision, margin):
        obj = scene.object(s.robot)
        where = f"{path}:{obj.line}" if obj.line is not None else path
        out.append(f"{where}: <object> robot {s.robot!r} passes through {s.other!r} as it moves: link "
                   f"{s.link.split('/', 1)[1]!r} by {s.depth:.4f} m at t = {s.time:.3f} s (its links push "
                   f"movable objects but pass through fixed ones; check the keyframes)")
    return out


def _object(scene, name: str):
    """The scene object ``name``, or the robot a link ``robot-id/link`` belongs to."""
    try:
        return scene.object(name)
    except KeyError:
        return scene.object(name.split("/", 1)[0])
