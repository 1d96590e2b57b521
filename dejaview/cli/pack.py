"""``dejaview pack``: build the sphere packing of a mesh."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click


@click.command(name="pack")
@click.argument("mesh", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-n", "--max-spheres", default=256, show_default=True, type=click.IntRange(min=1),
              help="Sphere budget.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path),
              help="The .spheres file to write [default: MESH with the suffix .spheres].")
@click.option("--min-radius", type=click.FloatRange(min=0), metavar="METRES",
              help="Use no sphere smaller than this.")
@click.option("--coverage", type=click.FloatRange(min=0, max=1, min_open=True),
              metavar="FRACTION", help="Stop once this fraction of the volume is covered.")
@click.option("--tolerance", default=0.001, show_default=True,
              type=click.FloatRange(min=0, max=0.002), metavar="METRES",
              help="How far a sphere may reach outside the surface (at most 0.002).")
@click.option("--resolution", type=click.FloatRange(min=0, min_open=True), metavar="METRES",
              help="Lattice spacing of the interior samples [default: chosen per mesh].")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
def command(mesh, max_spheres, output, min_radius, coverage, tolerance, resolution, quiet):
    """Approximate MESH (.obj .stl .ply .glb) by a union of spheres.

    Spheres are added greedily, each covering as much of the still uncovered
    volume as it can, until the budget (-n), the minimum radius or the coverage
    target is reached. No sphere reaches more than --tolerance outside the
    surface. Prints the sphere count, the covered share of the volume, how far
    the spheres reach outside the surface and how far the surface lies from
    the spheres (the largest gap: together the largest distance between the
    packing's surface and the mesh's), and the time taken.

    \b
    Example:
      dejaview pack examples/meshes/mug.obj -n 150 -o mug.spheres
    """
    from dejaview.geometry.mesh import load_mesh
    from dejaview.geometry.packing import SpherePacking

    output = output or mesh.with_suffix(".spheres")
    started = time.perf_counter()
    solid = load_mesh(mesh)
    show_bar = not quiet and sys.stderr.isatty()
    bar = None
    if show_bar:
        from tqdm import tqdm

        bar = tqdm(total=max_spheres, desc=f"packing {mesh.name}", unit="sphere", leave=False,
                   file=sys.stderr)

    def progress(done: int, total: int) -> None:
        if bar is not None:
            bar.update(done - bar.n)

    try:
        packing = SpherePacking.from_mesh(solid, max_spheres=max_spheres, min_radius=min_radius,
                                          coverage=coverage, resolution=resolution,
                                          tolerance=tolerance, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    built = time.perf_counter() - started
    packing.write(output, source=mesh)
    quality = packing.quality(solid)
    click.echo(f"{output}: {quality.count} spheres, coverage {100 * quality.coverage:.1f} %, "
               f"max outside {1000 * quality.max_outside:.2f} mm, "
               f"max gap {1000 * quality.max_gap:.2f} mm, {built:.1f} s")
