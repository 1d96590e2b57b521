"""Load benchmark of the service: many WebSocket clients at once, each submitting a short simulate job.

    python bench/load.py                     # 50 clients against a fresh `dejaview serve`
    python bench/load.py --clients 200 --workers 2 --executor thread
    python bench/load.py --url ws://127.0.0.1:8765/ws   # an already running server

Starts ``dejaview serve`` (process workers, a queue as long as the number of
clients) on a free loopback port unless ``--url`` is given, waits until its
workers have imported torch, then opens all client connections at once; each
submits the same short simulate job (a ball thrown over a floor, 0.1 s in 10
steps of 10 ms) as XML text and follows it to ``done``. Reports jobs per
second (jobs / wall time from the first submit to the last ``done``), p50 /
p99 / max latency (submit to ``done`` as each client sees it), and checks
that no job was lost: every client got ``done``, every job id is distinct,
and the server's record of each says ``done``.
"""

from __future__ import annotations

import asyncio
import math
import os
import sys
import tempfile
import time
from pathlib import Path

SCENE = """<?xml version="1.0" encoding="UTF-8"?>
<scene version="1" name="load-ball">
  <simulation dt="0.01" duration="0.1"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.2">
    <pose position="0 0 0.3"/><velocity linear="0.5 0 0"/>
  </object>
</scene>
"""


def percentile(values, q: float) -> float:
    """Nearest-rank percentile (q in 0..100) of a non-empty list."""
    ordered = sorted(values)
    rank = max(1, math.ceil(q / 100 * len(ordered)))
    return ordered[rank - 1]


async def _clients(url: str, clients: int, timeout: float):
    from dejaview.server.client import submit_job

    async def one(i):
        try:
            return await submit_job(url, "simulate", scene_xml=SCENE, request_id=f"load-{i}", timeout=timeout,
                                    fetch=False)
        except Exception as exc:  # counted as lost below
            return exc

    start = time.perf_counter()
    outcomes = await asyncio.gather(*(one(i) for i in range(clients)))
    return outcomes, time.perf_counter() - start


def run(print_fn=print, clients: int = 50, url: str | None = None, workers: int | None = None,
        executor: str = "process", timeout: float = 600.0) -> dict:
    """Run the benchmark; returns its numbers as a dict (``lost`` must be 0)."""
    from dejaview.server.client import get_json, http_base
    from dejaview.server.local import LocalServer

    server = None
    if url is None:
        base = Path(tempfile.mkdtemp(prefix="dejaview-load-"))
        (base / "scenes").mkdir()
        options = {"queue_size": max(64, clients), "executor": executor, "log_level": "warning"}
        if workers is not None:
            options["workers"] = workers
        server = LocalServer(base / "scenes", base / "results", log_path=base / "serve.log", **options)
        server.start()
        server.wait_workers()
        url = server.ws_url
    try:
        health = get_json(f"{http_base(url)}/health")
        outcomes, wall = asyncio.run(_clients(url, clients, timeout))
        done = [o for o in outcomes if not isinstance(o, Exception) and o.state == "done"]
        failures = [o for o in outcomes if isinstance(o, Exception) or o.state != "done"]
        ids = {o.job_id for o in done}
        recorded = sum(get_json(f"{http_base(url)}/jobs/{job_id}")["state"] == "done" for job_id in ids)
        lost = clients - min(len(done), len(ids), recorded)
        latencies = [o.latency_s for o in done]
        row = {"clients": clients, "workers": health["workers"], "executor": health["executor"],
               "done": len(done), "lost": lost, "wall_s": wall,
               "jobs_per_s": len(done) / wall if wall > 0 else float("nan"),
               "p50_s": percentile(latencies, 50) if latencies else float("nan"),
               "p99_s": percentile(latencies, 99) if latencies else float("nan"),
               "max_s": max(latencies) if latencies else float("nan"),
               "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")}
        if print_fn is not None:
            print_fn(f"load: {clients} WebSocket clients, one short simulate job each, "
                     f"{row['workers']} {row['executor']} workers (load average {row['load_average']:.1f})")
            print_fn(f"  {row['jobs_per_s']:.1f} jobs/s ({len(done)} jobs in {wall:.2f} s); latency p50 "
                     f"{row['p50_s']:.2f} s, p99 {row['p99_s']:.2f} s, max {row['max_s']:.2f} s")
            print_fn(f"  lost: {lost} (every client got 'done', {len(ids)} distinct job ids, "
                     f"{recorded} recorded done by the server)")
            for failure in failures[:5]:
                print_fn(f"  failure: {failure if isinstance(failure, Exception) else failure.error}")
        return row
    finally:
        if server is not None:
            server.stop()


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--url", default=None, help="an already running server's ws://.../ws")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--executor", choices=("process", "thread"), default="process")
    args = parser.parse_args(argv)
    row = run(clients=args.clients, url=args.url, workers=args.workers, executor=args.executor)
    return 0 if row["lost"] == 0 else 1


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    sys.exit(main())
