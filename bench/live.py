"""Live answers: latency of ``live`` messages against a real ``dejaview serve``, idle and while jobs run.

Starts ``dejaview serve`` (process workers) on a free loopback port with one scene (default: the
server tests' ``throw.xml``), trains its amortised model with a ``train`` job (``--simulations``,
``--epochs``: small by default, the latency does not depend on how well the model fits), then sends
``--answers`` live messages one after another, each with the target moved a little, and times each
from send to its ``live-result`` (the client's round trip, which bounds the server's "within 100
ms of arrival"), and the server's own ``seconds``. Then the same while solve jobs keep every
worker busy: live answers do not queue behind jobs. The first answer of a scene builds its
posterior and loads the model and is reported apart.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "tests" / "fixtures" / "server" / "throw.xml"


def percentile(values, q: float) -> float:
    """Nearest-rank percentile (q in 0..100) of a non-empty list."""
    ordered = sorted(values)
    return ordered[max(0, min(len(ordered) - 1, int(round(q / 100 * len(ordered) + 0.5)) - 1))]


def _until(ws, kinds, request_id=None):
    while True:
        msg = json.loads(ws.recv(timeout=600))
        if msg["type"] in kinds and (request_id is None or msg.get("request_id") == request_id):
            return msg


def _answers(ws, scene_path: str, target, n: int, tag: str):
    """n live answers one after another: (round trips s, server seconds, fitted count)."""
    trips, seconds, fitted = [], [], 0
    for i in range(n):
        moved = [target[0] + 0.002 * (i % 20), target[1] - 0.001 * (i % 10), target[2]]
        rid = f"{tag}{i}"
        t0 = time.perf_counter()
        ws.send(json.dumps({"type": "live", "scene_path": scene_path, "target": {"position": moved},
                            "request_id": rid}))
        msg = _until(ws, ("live-result", "error"), rid)
        trips.append(time.perf_counter() - t0)
        if msg["type"] == "error":
            raise RuntimeError(f"live answer failed: {msg['code']}: {msg['message']}")
        seconds.append(msg["seconds"])
        fitted += msg["fitted"]
        time.sleep(0.02)  # a dragging hand, not a flood (the rate limit is not measured here)
    return trips, seconds, fitted


def run(print_fn=print, answers: int = 100, simulations: int = 2000, epochs: int = 30, workers: int = 2,
        scene: Path = SCENE) -> dict:
    """Run the benchmark; returns its numbers (milliseconds)."""
    from websockets.sync.client import connect

    from dejaview.scene import Scene
    from dejaview.server.local import LocalServer

    base = Path(tempfile.mkdtemp(prefix="dejaview-live-"))
    (base / "scenes").mkdir()
    shutil.copy(scene, base / "scenes" / scene.name)
    target = list(Scene.from_xml(scene).inference.target.position)
    server = LocalServer(base / "scenes", base / "results", log_path=base / "serve.log", workers=workers,
                         log_level="warning")
    server.start()
    try:
        server.wait_workers()
        with connect(server.ws_url, max_size=2 ** 24) as ws:
            t0 = time.perf_counter()
            ws.send(json.dumps({"type": "submit", "kind": "train", "scene_path": scene.name, "request_id": "t",
                                "overrides": {"simulations": simulations, "epochs": epochs}}))
            done = _until(ws, ("done",), "t")
            if done["state"] != "done":
                raise RuntimeError(f"the train job ended {done['state']}: see {base / 'serve.log'}")
            train_s = time.perf_counter() - t0
            first, _, _ = _answers(ws, scene.name, target, 1, "first")
            idle, idle_server, idle_fitted = _answers(ws, scene.name, target, answers, "idle")
            for i in range(2 * workers):  # keep every worker busy
                ws.send(json.dumps({"type": "submit", "kind": "solve", "scene_path": scene.name,
                                    "overrides": {"optimizer": "auto", "samples": 2000}, "request_id": f"job{i}"}))
            started = _until(ws, ("progress", "error"))
            if started["type"] == "error":
                raise RuntimeError(f"the busy workers' solve job failed: {started['code']}: {started['message']}")
            busy, busy_server, _ = _answers(ws, scene.name, target, answers, "busy")
            jobs_running = json.loads(_health(server.http_url))["running"]
        ms = 1000.0
        row = {"answers": answers, "workers": workers, "train_s": train_s, "first_ms": first[0] * ms,
               "idle_p50_ms": percentile(idle, 50) * ms, "idle_p99_ms": percentile(idle, 99) * ms,
               "idle_max_ms": max(idle) * ms, "idle_server_p50_ms": percentile(idle_server, 50) * ms,
               "busy_p50_ms": percentile(busy, 50) * ms, "busy_p99_ms": percentile(busy, 99) * ms,
               "busy_max_ms": max(busy) * ms, "busy_server_p50_ms": percentile(busy_server, 50) * ms,
               "jobs_running": jobs_running, "fitted": idle_fitted,
               "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")}
        if print_fn is not None:
            print_fn(f"live: {scene.name}, model from a train job of {simulations} simulations, {epochs} epochs "
                     f"({train_s:.1f} s); load average {row['load_average']:.1f}")
            print_fn(f"  first answer (posterior built, model loaded): {row['first_ms']:.0f} ms")
            print_fn(f"  idle: round trip p50 {row['idle_p50_ms']:.1f} ms, p99 {row['idle_p99_ms']:.1f} ms, max "
                     f"{row['idle_max_ms']:.1f} ms (server {row['idle_server_p50_ms']:.1f} ms); "
                     f"{idle_fitted}/{answers} fitted")
            print_fn(f"  {jobs_running} jobs running: round trip p50 {row['busy_p50_ms']:.1f} ms, p99 "
                     f"{row['busy_p99_ms']:.1f} ms, max {row['busy_max_ms']:.1f} ms (server "
                     f"{row['busy_server_p50_ms']:.1f} ms)")
        return row
    finally:
        server.stop()
        shutil.rmtree(base, ignore_errors=True)


def _health(http_url: str) -> str:
    import urllib.request

    with urllib.request.urlopen(f"{http_url}/health", timeout=10) as response:
        return response.read().decode()


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--answers", type=int, default=100)
    parser.add_argument("--simulations", type=int, default=2000)
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scene", type=Path, default=SCENE)
    args = parser.parse_args(argv)
    run(answers=args.answers, simulations=args.simulations, epochs=args.epochs, workers=args.workers,
        scene=args.scene)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
