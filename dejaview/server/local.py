"""A ``dejaview serve`` child process on a free loopback port (for tests and benchmarks).

::

    with LocalServer(scene_root="scenes", results_dir="results", workers=2) as server:
        run_job(server.ws_url, "simulate", scene_path="ball.xml")
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dejaview.server.client import ClientError, wait_healthy


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def descendants(pid: int) -> list[int]:
    """The pids of the processes below ``pid`` (children, their children...), from ``/proc``."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])  # field 4, after "(comm)"
    found, frontier = [], [pid]
    while frontier:
        children = [child for child, parent in parents.items() if parent in frontier]
        found += children
        frontier = children
    return found


class LocalServer:
    """Run ``python -m dejaview serve`` with the given options until ``stop()`` (or the end of a
    ``with`` block); its log goes to ``log_path``.

    Args:
        scene_root, results_dir: as ``dejaview serve``.
        options: more ``dejaview serve`` options, e.g. ``workers=2`` -> ``--workers 2``.
    """

    def __init__(self, scene_root, results_dir, host: str = "127.0.0.1", port: int | None = None,
                 startup_timeout: float = 120.0, log_path=None, **options):
        self.scene_root = Path(scene_root)
        self.results_dir = Path(results_dir)
        self.host = host
        self.port = port
        self.options = options
        self.startup_timeout = startup_timeout
        self.log_path = Path(log_path) if log_path else Path(tempfile.mkstemp(prefix="dejaview-serve-",
                                                                             suffix=".log")[1])
        self.process: subprocess.Popen | None = None

    @property
    def http_url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{self.host}:{self.port}/ws"

    def command(self) -> list[str]:
        cmd = [sys.executable, "-m", "dejaview", "serve", "--host", self.host, "--port", str(self.port),
               "--scene-root", str(self.scene_root), "--results-dir", str(self.results_dir)]
        for key, value in self.options.items():
            for one in value if isinstance(value, (list, tuple)) else [value]:  # repeated options
                cmd += [f"--{key.replace('_', '-')}", str(one)]
        return cmd

    def start(self) -> "LocalServer":
        for _attempt in range(3):  # a port taken between free_port() and bind: try another
            if self.port is None or _attempt:
                self.port = free_port(self.host)
            with open(self.log_path, "ab") as log:
                self.process = subprocess.Popen(self.command(), stdout=log, stderr=subprocess.STDOUT,
                                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
            deadline = time.monotonic() + self.startup_timeout
            while time.monotonic() < deadline:
                if self.process.poll() is not None:
                    break
                try:
                    wait_healthy(self.http_url, timeout=1.0)
                    return self
                except ClientError:
                    continue
            if self.process.poll() is None:
                self.stop()
                raise ClientError(f"dejaview serve did not become healthy in {self.startup_timeout:g} s; "
                                  f"log: {self.log_path}")
        raise ClientError(f"dejaview serve exited with status {self.process.returncode}: "
                          f"{self.log_tail()}")

    def wait_workers(self, timeout: float = 120.0) -> dict:
        """Wait until every worker has started (imported torch); returns /health."""
        deadline = time.monotonic() + timeout
        while True:
            health = wait_healthy(self.http_url, timeout=10.0)
            if health["workers_ready"] >= health["workers"] or time.monotonic() > deadline:
                return health
            time.sleep(0.2)

    def log_tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def stop(self, kill: bool = False, timeout: float = 30.0) -> int | None:
        """SIGTERM (or SIGKILL with ``kill``) and wait; returns the exit status."""
        if self.process is None or self.process.poll() is not None:
            return None if self.process is None else self.process.returncode
        self.process.send_signal(signal.SIGKILL if kill else signal.SIGTERM)
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            return self.process.wait(5)

    def kill_all(self) -> list[int]:
        """SIGKILL the server and every process it started (its workers), as a crash or an OOM kill
        of the whole group would; returns their pids. Linux (reads ``/proc``)."""
        if self.process is None or self.process.poll() is not None:
            return []
        pids = [self.process.pid, *descendants(self.process.pid)]
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.process.wait(30)
        return pids

    def __enter__(self) -> "LocalServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
