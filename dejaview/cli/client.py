"""``dejaview client SCENE --kind solve --url ws://127.0.0.1:8765/ws -o DIR``: run a job on a server."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.cli.options import OPTIMIZERS, show_progress


@click.command("client")
@click.argument("scene")
@click.option("--kind", type=click.Choice(["simulate", "solve", "heatmap"]), default="solve",
              show_default=True, help="what to run")
@click.option("--url", default="ws://127.0.0.1:8765/ws", show_default=True, help="the server's WebSocket")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="output folder (created): trajectory.csv, result.json, heatmap.ppm/.png/.json")
@click.option("--scene-path", "as_path", is_flag=True,
              help="SCENE is a path inside the server's scene root (default: a local file sent as text)")
@click.option("--iterations", type=int, default=None, help="optimiser iterations (overrides the scene)")
@click.option("--optimizer", type=click.Choice(OPTIMIZERS), default=None)
@click.option("--gradient", type=click.Choice(["forward", "reverse"]), default=None)
@click.option("--seed", type=int, default=None)
@click.option("--steps", type=int, default=None, help="simulation steps (simulate jobs)")
@click.option("--timeout", type=float, default=None, help="give up after this many seconds")
@click.option("--token", envvar="DEJAVIEW_TOKEN", default=None, show_envvar=True,
              help="the server's token (needed when it listens off loopback or was given one)")
@click.option("--quiet", "-q", is_flag=True, help="no progress bar or summary")
def command(scene, kind, url, out_dir, as_path, iterations, optimizer, gradient, seed, steps, timeout, token,
            quiet):
    """Submit SCENE to a DejaView server, show its progress and save the artefacts in DIR.

    SCENE is a local scene file, sent as XML text (its relative mesh paths
    must then name files inside the server's scene root), or with
    --scene-path a path the server resolves inside its scene root. Exit
    status 0 when the job is done, otherwise non-zero with one line saying why.
    """
    from tqdm import tqdm

    from dejaview.server.client import ClientError, run_job

    overrides = {k: v for k, v in (("iterations", iterations), ("optimizer", optimizer),
                                   ("gradient", gradient), ("seed", seed), ("steps", steps)) if v is not None}
    if as_path:
        source = {"scene_path": scene}
    else:
        try:
            source = {"scene_xml": Path(scene).read_text(encoding="utf-8")}
        except (OSError, UnicodeDecodeError) as exc:
            raise click.UsageError(f"cannot read {scene}: {getattr(exc, 'strerror', None) or exc}")
    bar = tqdm(desc=kind, unit="it", disable=not show_progress(quiet))

    def progress(msg):
        if msg.get("type") == "accepted":
            bar.set_description(f"{kind} {msg['job_id'][:8]}")
        elif msg.get("type") == "progress":
            if msg.get("total"):
                bar.total = msg["total"]
            bar.n = msg.get("iteration", bar.n)
            if msg.get("best_loss") is not None:
                bar.set_postfix(loss=f"{msg['loss']:.4g}" if msg.get("loss") is not None else "-",
                                best=f"{msg['best_loss']:.4g}", refresh=False)
            bar.refresh()

    try:
        outcome = run_job(url, kind, overrides=overrides, out_dir=out_dir, on_message=progress,
                          timeout=timeout, token=token or None, **source)
    finally:
        bar.close()
    if outcome.state != "done":
        err = outcome.error or {}
        reason = f"{err.get('code')}: {err.get('message')}" if err else f"the job was {outcome.state}"
        raise ClientError(f"job {outcome.job_id} {outcome.state}: {reason}" if outcome.job_id else reason)
    if not quiet:
        loss = (outcome.result or {}).get("loss")
        click.echo(f"job {outcome.job_id} done in {outcome.latency_s:.2f} s"
                   + (f", best loss {loss:.5g}" if isinstance(loss, (int, float)) else "")
                   + "; wrote " + ", ".join(str(p) for p in outcome.files.values()))
