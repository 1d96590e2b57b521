"""Soak of the service: clients submit jobs for minutes while the server is killed and restarted
and its disk fills and is freed once.

    python bench/soak.py --minutes 10 --clients 8 --kills 5
    dejaview bench soak --minutes 1 --clients 4 --kills 2

Starts ``dejaview serve`` (process workers) on a free loopback port with a results dir of its own;
``--clients`` threads each submit, over REST, small solve and heatmap jobs (a ball dropped on a
floor, its start searched with a budget of a few hundred rollouts) one after another for
``--minutes``, retrying a submission the server did not answer (it was down). ``--kills`` times,
at random moments, the server and its workers are killed with SIGKILL and a new server started
on the same results dir. Once, in the longest stretch between kills (its middle half, at most
``FULL_S``), the results dir's disk is full: the results dir is a tmpfs of ``--disk-mib`` in a
mount namespace of the bench's own (``unshare -rm``; the whole bench runs in it), and the bench
writes a filler file there until ``ENOSPC`` (topped up every second: a job's removed folder
frees pages), then deletes it. After the time is up the clients stop submitting, the server runs what
it holds, and every job a client heard ``202`` for is looked up:

- accepted: jobs a client heard ``202`` for; finished: those ``done``; failed, by code;
- lost: accepted jobs the server does not know or left unfinished (must be 0); accepted jobs may
  fail with ``disk_full`` while the disk is full (counted under failed);
- duplicated: job ids accepted twice, or a finished job whose artefacts differ from those of
  another job of the same request (must be 0; every job of a kind is the same request, and its
  result a pure function of it);
- the peak memory of the server and its workers together (RSS sampled every 0.5 s from /proc);
- while the disk was full: the submissions the server answered (by status or code) and those it
  did not (must be 0: no kill falls there), the accepted jobs failed by then (by code; a job whose
  failure the full store could not keep runs again after the next restart) and, after it was
  freed, jobs accepted and finished.

The protocol's ``live`` message is not served yet (``dejaview.server.messages``: no ``live``
type), so there is no p50/p99 of live answers to report; the report says so. Where no mount namespace
can be had (``unshare -rm`` fails) the disk is not filled and the report says so (the full-disk
tests patch the writer instead: ``tests/server/test_full_disk.py``, ``tests/cli/test_sized.py``).
Loopback only; bounded by ``--minutes`` and ``--kills``.
"""

from __future__ import annotations

import errno
import json
import random
import shutil
import subprocess
import sys
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
FULL_S = 60.0
"""Longest the disk stays full (seconds)."""
FILLER = ".soak-filler"
"""The file that fills the results dir's disk (beside ``jobs/``, which the server reads)."""


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


def fill_disk(folder: Path) -> int:
    """Write ``folder/FILLER`` (appending) until its disk is full; returns the bytes it holds."""
    with open(folder / FILLER, "ab", buffering=0) as fh:
        for size in (2 ** 20, 4096, 1):
            block = b"\1" * size
            while True:
                try:
                    fh.write(block)
                except OSError as exc:
                    if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                        raise
                    break
        return fh.tell()


def _failed(get_json, url: str, ids: list[str]) -> dict[str, str]:
    """{job id: error code} of the jobs of ``ids`` the server says failed now."""
    codes = {}
    for job_id in ids:
        try:
            status = get_json(f"{url}/jobs/{job_id}")
        except Exception:  # noqa: BLE001  looked up again at the end
            continue
        if status["state"] == "failed":
            codes[job_id] = status["error"]["code"]
    return codes


def full_window(kill_at: list[float], duration: float) -> tuple[float, float]:
    """When the disk is full: the middle half of the longest stretch between kills (or the run's
    ends), at most ``FULL_S`` long, so that no restart falls in it."""
    points = [0.0, *kill_at, duration]
    a, b = max(zip(points, points[1:]), key=lambda gap: gap[1] - gap[0])
    length = min(FULL_S, (b - a) / 2)
    return (a + b - length) / 2, (a + b + length) / 2


def can_mount() -> bool:
    """Whether this process may make a mount namespace of its own (``unshare -rm``)."""
    return shutil.which("unshare") is not None and subprocess.run(
        ["unshare", "-rm", "true"], capture_output=True).returncode == 0


def run(print_fn=print, minutes: float = 10.0, clients: int = 8, kills: int = 5, workers: int = 2,
        seed: int = 0, drain_timeout: float = 900.0, disk_mib: int = 256) -> dict:
    """Run the soak; returns its numbers (``lost`` and ``duplicated`` must be 0).

    ``disk_mib``: the size of the tmpfs the results dir lives on, filled and freed once (0: no
    tmpfs, the disk is not filled). The bench runs in a mount namespace of its own for that (a
    child ``python bench/soak.py``: its lines go to ``print_fn``)."""
    base = Path(tempfile.mkdtemp(prefix="dejaview-soak-"))
    if not disk_mib or not can_mount():
        why = "--disk-mib 0" if not disk_mib else "no mount namespace here (unshare -rm failed)"
        return soak(base, print_fn, minutes, clients, kills, workers, seed, drain_timeout, disk=None,
                    not_filled=why)
    (base / "results").mkdir()
    row_path = base / "row.json"
    script = 'mount -t tmpfs -o size="$1"m tmpfs "$2" && shift 2 && exec "$@"'
    child = [sys.executable, "-u", str(Path(__file__).resolve()), "--in", str(base), "--row", str(row_path),
             "--minutes", str(minutes), "--clients", str(clients), "--kills", str(kills), "--workers",
             str(workers), "--seed", str(seed), "--drain-timeout", str(drain_timeout), "--disk-mib", str(disk_mib)]
    with subprocess.Popen(["unshare", "-rm", "sh", "-c", script, "sh", str(disk_mib), str(base / "results"),
                           *child], stdout=subprocess.PIPE, text=True) as process:
        for line in process.stdout:
            print_fn(line.rstrip("\n"))
    if process.returncode not in (0, 1) or not row_path.is_file():
        raise RuntimeError(f"the soak in its mount namespace exited with status {process.returncode}")
    return json.loads(row_path.read_text())


def soak(base: Path, print_fn, minutes: float, clients: int, kills: int, workers: int, seed: int,
         drain_timeout: float, disk: int | None, not_filled: str = "") -> dict:
    """The soak itself, its results dir ``base/results`` (a tmpfs of ``disk`` MiB where ``disk``)."""
    from dejaview.server.client import get_json
    from dejaview.server.local import LocalServer

    (base / "scenes").mkdir()
    results_dir = base / "results"
    server = LocalServer(base / "scenes", results_dir, log_path=base / "serve.log", workers=workers,
                         queue_size=4 * clients, log_level="warning")
    server.start()
    server.wait_workers()
    rng = random.Random(seed)
    duration = 60.0 * minutes
    kill_at = sorted(rng.uniform(0.1, 0.9) * duration for _ in range(kills))
    full_from, full_to = full_window(kill_at, duration) if disk else (duration, duration)
    accepted: list[tuple[str, str, float]] = []  # job id, kind, when (s from the start)
    refused: Counter = Counter()
    answers: list[tuple[float, str]] = []  # when, the status or code ("no answer": the server was down)
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
                with lock:
                    answers.append((time.monotonic() - t0, "no answer"))
                time.sleep(0.5)
                continue
            with lock:
                now = time.monotonic() - t0
                if status == 202:
                    accepted.append((body["job_id"], kind, now))
                    answers.append((now, "202"))
                else:
                    refused[body.get("code", str(status))] += 1
                    answers.append((now, body.get("code", str(status))))
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
    restarts, filled, health_full, failed_full = [], 0, None, {}
    events = sorted([(at, "kill") for at in kill_at] + ([(full_from, "fill"), (full_to, "free")] if disk else []))
    for at, event in events:
        time.sleep(max(0.0, t0 + at - time.monotonic()))
        if event == "kill":
            server.kill_all()
            started = time.monotonic()
            server.start()
            restarts.append(time.monotonic() - started)
            print_fn(f"  {time.monotonic() - t0:6.1f} s: killed -9 and restarted ({restarts[-1]:.1f} s to healthy)")
        elif event == "fill":
            filled = fill_disk(results_dir)
            print_fn(f"  {time.monotonic() - t0:6.1f} s: the results dir's disk is full "
                     f"({filled / 2 ** 20:.0f} MiB of filler)")
            while time.monotonic() < t0 + full_to - 1.0:  # keep it full: a removed folder frees pages
                time.sleep(1.0)
                filled = fill_disk(results_dir)
            try:
                health_full = get_json(f"{server.http_url}/health")["status"]
            except Exception as exc:  # noqa: BLE001  reported: the server did not answer
                health_full = f"no answer ({exc})"
        else:
            failed_full = _failed(get_json, server.http_url, [job_id for job_id, _, _ in accepted])
            (results_dir / FILLER).unlink()
            print_fn(f"  {time.monotonic() - t0:6.1f} s: the disk is freed (/health while full: {health_full})")
    time.sleep(max(0.0, t0 + duration - time.monotonic()))
    submitting = time.monotonic() - t0
    stop.set()
    for t in threads[:-1]:
        t.join(30)
    deadline = time.monotonic() + drain_timeout
    states: dict[str, dict] = {}
    while time.monotonic() < deadline:
        states = {}
        for job_id, _, _ in accepted:
            try:
                states[job_id] = get_json(f"{server.http_url}/jobs/{job_id}")
            except Exception:  # noqa: BLE001  unknown to the server: counted as lost below
                pass
        if all(s["state"] in ("done", "failed", "cancelled") for s in states.values()):
            break
        time.sleep(2.0)
    measured.set()
    threads[-1].join(5)
    ids = [job_id for job_id, _, _ in accepted]
    finished = [j for j in ids if states.get(j, {}).get("state") == "done"]
    failed = Counter(states[j]["error"]["code"] for j in ids if states.get(j, {}).get("state") == "failed")
    lost = [j for j in ids if states.get(j, {}).get("state") not in ("done", "failed", "cancelled")]
    results: dict[str, set] = {kind: set() for kind in REQUESTS}
    for job_id, kind, _ in accepted:
        if job_id in finished:
            text = (results_dir / "jobs" / job_id / "trajectory.csv").read_text()
            results[kind].add(text)
    duplicated = (len(ids) - len(set(ids))) + sum(max(0, len(v) - 1) for v in results.values())
    while_full = Counter(code for at, code in answers if full_from <= at < full_to)
    after = [job_id for job_id, _, at in accepted if at >= full_to]
    rerun = sum(j in finished for j in failed_full)  # failed while full, the failure not on disk: run again
    server.stop()
    row = {"minutes": minutes, "clients": clients, "workers": workers, "kills": len(kill_at),
           "submitting_s": round(submitting, 1), "accepted": len(ids), "finished": len(finished),
           "failed": dict(failed), "refused": dict(refused), "lost": len(lost), "duplicated": duplicated,
           "peak_memory_mib": round(peak[0] / 2 ** 20), "restart_s_max": round(max(restarts, default=0.0), 1),
           "disk": f"tmpfs of {disk} MiB (unshare -rm)" if disk else f"not filled: {not_filled}",
           "full_from_s": round(full_from, 1) if disk else None, "full_to_s": round(full_to, 1) if disk else None,
           "filler_mib": round(filled / 2 ** 20, 1), "answers_while_full": dict(while_full),
           "health_while_full": health_full, "failed_while_full": dict(Counter(failed_full.values())),
           "failed_while_full_then_finished": rerun, "accepted_after_free": len(after),
           "finished_after_free": sum(j in finished for j in after),
           "live": "absent (the service has no live message yet)", "log": str(base / "serve.log")}
    print_fn(f"soak: {minutes:g} min, {clients} clients, {workers} workers, {len(kill_at)} kill -9 restarts "
             f"(at most {row['restart_s_max']} s to healthy)")
    print_fn(f"  accepted {len(ids)}, finished {len(finished)}, failed {dict(failed) or 0}, refused "
             f"{dict(refused) or 0}, lost {len(lost)}, duplicated {duplicated}")
    if disk:
        print_fn(f"  disk: {row['disk']} full from {row['full_from_s']} s to {row['full_to_s']} s; submissions "
                 f"answered while full {dict(while_full) or 0}; /health while full: {health_full}")
        print_fn(f"  failed while full {row['failed_while_full'] or 0} ({rerun} of them finished later: run "
                 f"again after a restart, the full store had not kept their failure); after the disk was "
                 f"freed {row['finished_after_free']} of {len(after)} accepted jobs finished")
    else:
        print_fn(f"  disk: {row['disk']}")
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
    parser.add_argument("--drain-timeout", type=float, default=900.0)
    parser.add_argument("--disk-mib", type=int, default=256, help="the results dir's tmpfs (0: no disk filled)")
    parser.add_argument("--in", dest="inside", type=Path, help=argparse.SUPPRESS)  # run() in its namespace
    parser.add_argument("--row", type=Path, help=argparse.SUPPRESS)
    a = parser.parse_args()
    if a.inside is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's dejaview
        result = soak(a.inside, print, a.minutes, a.clients, a.kills, a.workers, a.seed, a.drain_timeout,
                      disk=a.disk_mib)
        a.row.write_text(json.dumps(result))
    else:
        result = run(minutes=a.minutes, clients=a.clients, kills=a.kills, workers=a.workers, seed=a.seed,
                     drain_timeout=a.drain_timeout, disk_mib=a.disk_mib)
    raise SystemExit(0 if result["lost"] == 0 and result["duplicated"] == 0 else 1)
