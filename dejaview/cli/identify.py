"""``dejaview identify SCENE... -o DIR``: the friction, restitution and stiffness several scenes share."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.options import configure_torch, package_path_option


@click.command("identify")
@click.argument("scenes", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="output folder (created)")
@click.option("--samples", type=click.IntRange(min=0), default=0,
              help="importance samples of the joint posterior (posterior.csv; 0: Laplace intervals)")
@click.option("--seed", type=click.IntRange(min=0), default=0, help="random seed")
@click.option("--budget", type=click.IntRange(min=1), default=None,
              help="most rollouts of each scene's search (default 40000)")
@click.option("--quiet", "-q", is_flag=True, help="no progress lines")
@package_path_option
def command(scenes, out_dir, samples, seed, budget, quiet):
    """Several SCENES of the same objects (the same source thrown several times, each with its own
    observations, tracked ones best) share one friction, restitution and stiffness; each keeps its
    own start. Their <physics-prior> (the same in every scene; default friction and restitution
    50 %) says what is known before. Writes DIR/result.json (the shared physics with intervals and
    each scene's most probable start) and, with --samples N, DIR/posterior.csv."""
    import json
    from dataclasses import replace

    from dejaview.inference.identify import identify
    from dejaview.inference.params import IdentifyParams, SearchParams
    from dejaview.scene import Scene

    configure_torch()
    loaded = [Scene.from_xml(s) for s in scenes]
    search = SearchParams() if budget is None else replace(SearchParams(), budget=budget)
    result = identify(loaded, IdentifyParams(samples=samples, seed=seed, search=search),
                      callback=None if quiet else (lambda line: click.echo(f"  {line}", err=True)))
    paths = result.write(out_dir)
    written = json.loads(paths["result"].read_text(encoding="utf-8"))  # not computed again: it re-simulates
    physics = written["physics"]
    mp = physics["most_probable"]
    click.echo(f"shared physics of {len(loaded)} scenes: friction {mp['friction']:.3f}, restitution "
               f"{mp['restitution']:.3f}, stiffness {mp['stiffness']:.4g} N/m per kg ({result.seconds:.1f} s)")
    for name, iv in physics["intervals"].items():
        lo, hi = iv["90%"]
        click.echo(f"  {name:12s} median {iv['median']:.3f}   90% [{lo:.3f}, {hi:.3f}]  ({physics['intervals_from']})")
    for sc in written["scenes"]:
        p = sc["initial_state"]["position"]
        click.echo(f"  {sc['name']}: start ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m, observation "
                   f"chi2 {sc['observation_chi2']:.1f} over {sc['observed']} residuals")
    for note in result.notes:
        click.echo(f"  warning: {note}")
    click.echo(f"  wrote {', '.join(str(p) for p in paths.values())}")
