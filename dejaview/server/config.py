"""Settings of a DejaView server: where scenes and results live, workers, and every limit.

``dejaview serve`` fills a ``ServerConfig`` from its options; tests build one
directly and hand it to ``create_app``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

KIB = 1024
MIB = 1024 * KIB


def default_workers() -> int:
    """One worker per core (each runs torch on one thread), at most 4."""
    return max(1, min(4, os.cpu_count() or 1))


@dataclass(frozen=True)
class ServerConfig:
    """Everything a server needs to know.

    Attributes:
        scene_root: folder that ``scene_path`` and every mesh path must resolve inside.
        results_dir: job records and artefacts (``jobs/<id>/``); kept across restarts.
        workers: jobs run at the same time.
        executor: ``"process"`` (a pool of worker processes, the default) or ``"thread"``.
        queue_size: jobs that may wait for a worker; one more is refused with ``queue_full``.
        max_body_bytes: largest REST request body (413 above).
        max_message_bytes: largest WebSocket message answered with an error rather than a
            closed connection; messages above ``4 x`` this are cut off by the WebSocket layer
            (close code 1009).
        max_scene_bytes: largest scene XML (text or file).
        messages_per_second: sustained WebSocket messages per connection; bursts of twice
            that are allowed, more are answered with one ``rate_limited`` error per second.
        live_messages_per_second: sustained ``live`` messages per connection (their own budget,
            bursts of twice that): a client dragging the source sends many, and the server
            answers one at a time, the newest (``dejaview.server.live``).
        live_draws: draws from the flow behind a live answer's heatmap.
        live_samples: start positions a live answer carries (of its draws).
        max_train_simulations: most training simulations a ``train`` job may ask for.
        worker_niceness: added to the nice value of each worker process (process executor), so
            that busy workers leave the cores to the server process's live answers first; 0: none.
        inline_limit_bytes: larger CSV / PPM / result JSON is sent as a URL only.
        max_bare_bytes: largest payload of the bare-text compatibility mode (which cannot
            send URLs).
        max_jobs_per_connection: unfinished jobs one WebSocket connection may have.
        max_objects: largest number of objects in a scene.
        max_steps: largest number of integration substeps (steps x substeps) of one rollout.
        max_iterations: largest number of optimiser iterations.
        max_heatmap_runs: largest cells_x * cells_y * samples of a heatmap.
        max_job_memory_bytes: memory one job's worker may hold (``dejaview.memory``); a job sized
            over it fails with ``limit_exceeded`` before any work. None: the machine's limit
            (``DEJAVIEW_MEMORY_LIMIT`` or 80 % of its memory) shared equally by the workers.
        job_timeout_s: a running job is stopped (failed, ``timeout``) after this long.
        progress_interval_s: at most one progress message per job per this many seconds.
        keep_jobs: finished jobs kept on disk; the oldest are deleted beyond it.
        token: every request but ``GET /health`` must carry it (``dejaview.server.access``);
            None: none needed.
        allow_origins: browser origins (``scheme://host[:port]``) that may use the server besides
            its own pages.
        allowed_hosts: names a request's ``Host`` may give (None: any); ``dejaview serve`` on a
            loopback address sets the loopback names, against DNS rebinding.
    """

    scene_root: Path
    results_dir: Path
    workers: int = field(default_factory=default_workers)
    executor: str = "process"
    queue_size: int = 64
    max_body_bytes: int = 2 * MIB
    max_message_bytes: int = 2 * MIB
    max_scene_bytes: int = 1 * MIB
    messages_per_second: float = 20.0
    live_messages_per_second: float = 60.0
    live_draws: int = 512
    live_samples: int = 256
    max_train_simulations: int = 200_000
    worker_niceness: int = 5
    inline_limit_bytes: int = 100_000
    max_bare_bytes: int = 16 * MIB
    max_jobs_per_connection: int = 16
    max_objects: int = 64
    max_steps: int = 200_000
    max_iterations: int = 10_000
    max_heatmap_runs: int = 4096
    max_job_memory_bytes: int | None = None
    job_timeout_s: float | None = 3600.0
    progress_interval_s: float = 0.25
    keep_jobs: int = 1000
    token: str | None = None
    allow_origins: tuple[str, ...] = ()
    allowed_hosts: tuple[str, ...] | None = None

    def __post_init__(self):
        object.__setattr__(self, "scene_root", Path(self.scene_root).resolve())
        object.__setattr__(self, "results_dir", Path(self.results_dir).resolve())
        if self.executor not in ("process", "thread"):
            raise ValueError(f"executor must be 'process' or 'thread', got {self.executor!r}")
        for name in ("workers", "queue_size", "max_body_bytes", "max_message_bytes", "max_scene_bytes",
                     "inline_limit_bytes", "max_bare_bytes", "max_jobs_per_connection", "max_objects",
                     "max_steps", "max_iterations", "max_heatmap_runs", "keep_jobs", "live_draws", "live_samples",
                     "max_train_simulations"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.worker_niceness <= 19:
            raise ValueError(f"worker_niceness must lie in 0..19, got {self.worker_niceness}")
        if self.max_job_memory_bytes is not None and self.max_job_memory_bytes < 1:
            raise ValueError(f"max_job_memory_bytes must be >= 1, got {self.max_job_memory_bytes}")
        if not self.messages_per_second > 0 or not self.live_messages_per_second > 0:
            raise ValueError("messages_per_second and live_messages_per_second must be > 0")
        if self.token is not None and (not self.token or any(c.isspace() or not c.isprintable()
                                                             for c in self.token)):
            raise ValueError("the token must be non-empty, without spaces or control characters")
        object.__setattr__(self, "allow_origins", tuple(_origin(o) for o in self.allow_origins))
        if self.allowed_hosts is not None:
            object.__setattr__(self, "allowed_hosts", tuple(h.lower() for h in self.allowed_hosts))

    @property
    def job_memory_bytes(self) -> int:
        """Memory one job may hold: ``max_job_memory_bytes`` (at most the machine's limit), or the
        machine's limit over the workers."""
        from dejaview import memory

        machine = memory.limit()[0]
        if self.max_job_memory_bytes is not None:
            return min(self.max_job_memory_bytes, machine)
        return machine // self.workers

    @property
    def ws_max_size(self) -> int:
        """The WebSocket layer's hard message limit (bytes)."""
        return 4 * self.max_message_bytes

    def replace(self, **changes) -> "ServerConfig":
        return replace(self, **changes)


def _origin(text: str) -> str:
    from dejaview.server.access import normalize_origin

    if text.strip() == "null":
        return "null"
    origin = normalize_origin(text)
    if origin is None:
        raise ValueError(f"allowed origin {text!r} is not an origin: give scheme://host[:port], "
                         f"e.g. http://192.168.1.20:8765")
    return origin
