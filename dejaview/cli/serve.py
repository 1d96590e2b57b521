"""``dejaview serve``: the FastAPI service under uvicorn (REST, WebSocket ``/ws``, docs at ``/docs``)."""

from __future__ import annotations

from pathlib import Path

import click

from dejaview.server.config import KIB, MIB, default_workers


@click.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True, help="address to listen on")
@click.option("--port", default=8765, show_default=True, type=click.IntRange(0, 65535), help="TCP port")
@click.option("--scene-root", type=click.Path(file_okay=False, exists=True, path_type=Path), default=".",
              show_default=True, help="folder that scene paths and mesh files must lie in")
@click.option("--results-dir", type=click.Path(file_okay=False, path_type=Path), default="results",
              show_default=True, help="job records and artefacts (kept across restarts)")
@click.option("--workers", type=click.IntRange(min=1), default=default_workers(), show_default=True,
              help="jobs run at the same time")
@click.option("--executor", type=click.Choice(["process", "thread"]), default="process", show_default=True,
              help="run jobs in worker processes or in threads of the server")
@click.option("--queue-size", type=click.IntRange(min=1), default=64, show_default=True,
              help="jobs that may wait for a worker")
@click.option("--max-body-kb", type=click.IntRange(min=1), default=2 * MIB // KIB, show_default=True,
              help="largest REST request body")
@click.option("--max-message-kb", type=click.IntRange(min=1), default=2 * MIB // KIB, show_default=True,
              help="largest WebSocket message (4x this closes the connection)")
@click.option("--max-scene-kb", type=click.IntRange(min=1), default=MIB // KIB, show_default=True,
              help="largest scene XML")
@click.option("--rate", "messages_per_second", type=click.FloatRange(min=0, min_open=True), default=20.0,
              show_default=True, help="WebSocket messages per second per connection (bursts of 2x)")
@click.option("--inline-limit-kb", type=click.IntRange(min=1), default=100, show_default=True,
              help="larger payloads are sent as URLs only (1 kB = 1000 bytes)")
@click.option("--max-jobs-per-connection", type=click.IntRange(min=1), default=16, show_default=True,
              help="unfinished jobs one WebSocket connection may have")
@click.option("--max-steps", type=click.IntRange(min=1), default=200_000, show_default=True,
              help="largest rollout in integration substeps (steps x substeps)")
@click.option("--max-iterations", type=click.IntRange(min=1), default=10_000, show_default=True,
              help="largest number of optimiser iterations")
@click.option("--max-job-memory", "max_job_memory", default=None, metavar="SIZE",
              help="memory one job may hold, e.g. 2G (default: the machine's limit, DEJAVIEW_MEMORY_LIMIT or "
                   "80 % of its memory, shared by the workers); larger jobs fail with limit_exceeded")
@click.option("--job-timeout", type=click.FloatRange(min=0, min_open=True), default=3600.0,
              show_default=True, help="seconds a job may run")
@click.option("--max-connections", type=click.IntRange(min=1), default=None,
              help="concurrent connections (HTTP and WebSocket); more get 503")
@click.option("--token", envvar="DEJAVIEW_TOKEN", default=None, show_envvar=True,
              help="every request but GET /health must carry it (Authorization: Bearer TOKEN, or "
                   "?token=TOKEN on the WebSocket URL); required off loopback: one is generated and "
                   "printed when none is given")
@click.option("--allow-origin", "allow_origins", multiple=True, metavar="ORIGIN",
              help="a browser origin (scheme://host[:port]) that may use the server besides its own "
                   "pages; repeat for more")
@click.option("--log-level", type=click.Choice(["critical", "error", "warning", "info", "debug"]),
              default="info", show_default=True)
def command(host, port, scene_root, results_dir, workers, executor, queue_size, max_body_kb,
            max_message_kb, max_scene_kb, messages_per_second, inline_limit_kb, max_jobs_per_connection,
            max_steps, max_iterations, max_job_memory, job_timeout, max_connections, token, allow_origins,
            log_level):
    """Serve simulate, solve and heatmap jobs over REST and WebSocket.

    Clients submit scenes as XML text or as paths inside --scene-root; results
    go to --results-dir/jobs/ID/ (jobs accepted but unfinished when the server
    stops or crashes run when it starts again). The API and message schemas are
    at http://HOST:PORT/docs, the WebSocket at ws://HOST:PORT/ws.

    Off loopback (e.g. --host 0.0.0.0 for a VR headset on the LAN) every client
    needs the token (--token or DEJAVIEW_TOKEN; generated and printed once when
    not given); browsers open http://HOST:PORT/?token=TOKEN. Pages of other
    origins than the server's own (and --allow-origin) are refused.
    """
    import secrets

    import uvicorn

    from dejaview.memory import parse_size
    from dejaview.server.access import LOOPBACK_NAMES, host_name, is_loopback
    from dejaview.server.app import create_app
    from dejaview.server.config import ServerConfig
    from dejaview.server.store import JobStore

    token = token or None  # DEJAVIEW_TOKEN="" means none
    loopback = is_loopback(host)
    generated = not loopback and token is None
    if generated:
        token = secrets.token_urlsafe(24)
    try:
        config = ServerConfig(scene_root=scene_root, results_dir=results_dir, workers=workers,
                              executor=executor, queue_size=queue_size, max_body_bytes=max_body_kb * KIB,
                              max_message_bytes=max_message_kb * KIB, max_scene_bytes=max_scene_kb * KIB,
                              messages_per_second=messages_per_second,
                              inline_limit_bytes=inline_limit_kb * 1000,
                              max_jobs_per_connection=max_jobs_per_connection, max_steps=max_steps,
                              max_iterations=max_iterations, job_timeout_s=job_timeout, token=token,
                              max_job_memory_bytes=None if max_job_memory is None else parse_size(max_job_memory),
                              allow_origins=allow_origins, allowed_hosts=None)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    if loopback:  # a page whose name resolves to 127.0.0.1 (DNS rebinding) is not one of ours
        names = {*LOOPBACK_NAMES, host.strip("[]").lower()}
        names |= {host_name(o.split("://", 1)[1]) for o in config.allow_origins if "://" in o}
        config = config.replace(allowed_hosts=tuple(sorted(names)))
    # the results dir is this server's alone: say so now, not in a traceback from the app's start-up
    JobStore(config.results_dir).close()
    click.echo(f"dejaview serve: scene root {config.scene_root}, results in {config.results_dir}, "
               f"{workers} {executor} worker(s); API docs http://{host}:{port}/docs, "
               f"WebSocket ws://{host}:{port}/ws", err=True)
    if generated:
        click.echo(f"dejaview serve: listening on {host}, so clients need a token; generated one (given "
                   f"once, here): {token}\n  viewer: http://{host}:{port}/?token={token}\n"
                   f"  clients: DEJAVIEW_TOKEN={token} dejaview client ... (or --token)", err=True)
    elif token:
        click.echo("dejaview serve: clients need the token (Authorization: Bearer, or ?token= on the "
                   "WebSocket and viewer URLs)", err=True)
    uvicorn.run(create_app(config), host=host, port=port, log_level=log_level, ws="auto",
                ws_max_size=config.ws_max_size, limit_concurrency=max_connections,
                timeout_graceful_shutdown=10)
