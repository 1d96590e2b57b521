"""Soak of the service: clients submit jobs for minutes while the server is killed and restarted.

    python bench/soak.py --minutes 10 --clients 8 --kills 5
    dejaview bench soak --minutes 1 --clients 4 --kills 2

Starts ``dejaview serve`` (process workers) on a free loopback port with a results dir of its own;
``--clients`` threads each submit, over REST, small solve and heatmap jobs (a ball dropped on a
floor, its start searched with a budget of a few hundred rollouts) one after another for
``--minutes``, retrying a submission the server did not answer (it was down). ``--kills`` times,
at random moments, the server and its workers are killed with SIGKILL and a new server started
on the same results dir. After the time is up the clients stop submitting, the server runs what
it holds, and every job a client heard ``202`` for is looked up:

- accepted: jobs a client heard ``202`` for; finished: those ``done``; failed, by code;
- lost: accepted jobs the server does not know or left unfinished (must be 0);
- duplicated: job ids accepted twice, or a finished job whose artefacts differ from those of
  another job of the same request (must be 0; every job of a kind is the same request, and its
  result a pure function of it);
- the peak memory of the server and its workers together (RSS sampled every 0.5 s from /proc).

The protocol's ``live`` message is not served yet (``dejaview.server.messages``: no ``live``
type), so there is no p50/p99 of live answers to report; the report says so. Nor does this
bench fill the disk (the full-disk tests: ``tests/server/test_full_disk.py``,
``tests/cli/test_sized.py``). Loopback only; bounded by ``--minutes`` and ``--kills``.
"""

from __future__ import annotations

import json
import random
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from pathlib import Path

SCENE = """<?xml version="1.0" encoding="UTF-8"?>
<scene version="1" name="soak-ball">
  <simulation dt="0.01" duration="0.3"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.2"><pose position="0 0 0.3"/></object>
  <inference source="ball" iterations="20" seed="0">
    <target position="0.1 0 0.05" orientation="1 0 0 0"/>
    <start-area min="-0.2 -0.2 0.3" max="0.2 0.2 0.3"/>
    <optimize position="true" orientation="false" linear-velocity="true" angular-velocity="false"/>
    <heatmap cells="2 2" samples="2"/>
  </inference>
</scene>
"""
REQUESTS = {"solve": {"budget": 300}, "heatmap": {"iterations": 10}}
"""Each kind's one request (its overrides): a job's artefacts are a pure function of it."""


def _post(base: str, body: dict, timeout: float = 10.0) -> tuple[int, dict]:
    request = urllib.request.Request(f"{base}/jobs", data=json.dumps(body).encode(), method="POST",
                                     headers={"content-type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")


def _tree_rss(pid: int) -> int:
    """Bytes the process ``pid`` and its descendants hold (VmRSS from /proc)."""
    from dejaview.server.local import descendants

    total = 0
    for p in [pid, *descendants(pid)]:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
        except OSError:
            pass
    return total


def run(print_fn=print, minutes: float = 10.0, clients: int = 8, kills: int = 5, workers: int = 2,
        seed: int = 0, drain_timeout: float = 900.0) -> dict:
    """Run the soak; returns its numbers (``lost`` and ``duplicated`` must be 0)."""
    from dejaview.server.client import get_json
    from dejaview.server.local import LocalServer

    base = Path(tempfile.mkdtemp(prefix="dejaview-soak-"))
    (base / "scenes").mkdir()
    server = LocalServer(base / "scenes", base / "results", log_path=base / "serve.log", workers=workers,
                         queue_size=4 * clients, log_level="warning")
    server.start()
    server.wait_workers()
    rng = random.Random(seed)
    duration = 60.0 * minutes
    kill_at = sorted(rng.uniform(0.1, 0.9) * duration for _ in range(kills))
    accepted: list[tuple[str, str]] = []
    refused: Counter = Counter()
    lock = threading.Lock()
    stop, measured = threading.Event(), threading.Event()  # clients stop; memory sampling stops
    peak = [0]
    t0 = time.monotonic()

    def client(i: int) -> None:
        r = random.Random(seed * 1000 + i)
        while not stop.is_set():
            kind = r.choice(sorted(REQUESTS))
            try:
                status, body = _post(server.http_url, {"kind": kind, "scene_xml": SCENE,
                                                       "overrides": REQUESTS[kind]})
            except OSError:  # the server is down: wait and retry
                time.sleep(0.5)
                continue
            with lock:
                if status == 202:
                    accepted.append((body["job_id"], kind))
                else:
                    refused[body.get("code", str(status))] += 1
            time.sleep(r.uniform(0.5, 2.0) if status == 202 else 1.0)

    def sample_memory() -> None:
        while not measured.is_set():
            if server.process is not None and server.process.poll() is None:
                peak[0] = max(peak[0], _tree_rss(server.process.pid))
            time.sleep(0.5)

    threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(clients)]
    threads.append(threading.Thread(target=sample_memory, daemon=True))
    for t in threads:
        t.start()
    restarts = []
    for at in kill_at:
        time.sleep(max(0.0, t0 + at - time.monotonic()))
        server.kill_all()
        started = time.monotonic()
        server.start()
        restarts.append(time.monotonic() - started)
        print_fn(f"  {time.monotonic() - t0:6.1f} s: killed -9 and restarted ({restarts[-1]:.1f} s to healthy)")
    time.sleep(max(0.0, t0 + duration - time.monotonic()))
    submitting = time.monotonic() - t0
    stop.set()
    for t in threads[:-1]:
        t.join(30)
    deadline = time.monotonic() + drain_timeout
    states: dict[str, dict] = {}
    while time.monotonic() < deadline:
        states = {}
        for job_id, _ in accepted:
            try:
                states[job_id] = get_json(f"{server.http_url}/jobs/{job_id}")
            except Exception:  # noqa: BLE001  unknown to the server: counted as lost below
                pass
        if all(s["state"] in ("done", "failed", "cancelled") for s in states.values()):
            break
        time.sleep(2.0)
    measured.set()
    threads[-1].join(5)
    ids = [job_id for job_id, _ in accepted]
    finished = [j for j in ids if states.get(j, {}).get("state") == "done"]
    failed = Counter(states[j]["error"]["code"] for j in ids if states.get(j, {}).get("state") == "failed")
    lost = [j for j in ids if states.get(j, {}).get("state") not in ("done", "failed", "cancelled")]
    results: dict[str, set] = {kind: set() for kind in REQUESTS}
    for job_id, kind in accepted:
        if job_id in finished:
            text = (base / "results" / "jobs" / job_id / "trajectory.csv").read_text()
            results[kind].add(text)
    duplicated = (len(ids) - len(set(ids))) + sum(max(0, len(v) - 1) for v in results.values())
    server.stop()
    row = {"minutes": minutes, "clients": clients, "workers": workers, "kills": len(kill_at),
           "submitting_s": round(submitting, 1), "accepted": len(ids), "finished": len(finished),
           "failed": dict(failed), "refused": dict(refused), "lost": len(lost), "duplicated": duplicated,
           "peak_memory_mib": round(peak[0] / 2 ** 20), "restart_s_max": round(max(restarts, default=0.0), 1),
           "live": "absent (the service has no live message yet)", "results_dir": str(base / "results")}
    print_fn(f"soak: {minutes:g} min, {clients} clients, {workers} workers, {len(kill_at)} kill -9 restarts "
             f"(at most {row['restart_s_max']} s to healthy)")
    print_fn(f"  accepted {len(ids)}, finished {len(finished)}, failed {dict(failed) or 0}, refused "
             f"{dict(refused) or 0}, lost {len(lost)}, duplicated {duplicated}")
    print_fn(f"  peak memory of the server and its workers {row['peak_memory_mib']} MiB; live: {row['live']}")
    return row


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--kills", type=int, default=5)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    a = parser.parse_args()
    result = run(minutes=a.minutes, clients=a.clients, kills=a.kills, workers=a.workers, seed=a.seed)
    raise SystemExit(0 if result["lost"] == 0 and result["duplicated"] == 0 else 1)
