"""Worker pools that run jobs away from the event loop: processes (default) or threads.

Why processes by default: a rollout is thousands of tiny torch ops, each
paying Python and dispatcher overhead under the GIL (docs/benchmarks.md, "Service"),
so worker *threads* mostly take turns on one core, and every one of them
competes with the event loop for the GIL (processes against threads,
``dejaview bench load --executor process|thread``: docs/benchmarks.md, "Service").
Worker processes (``spawn``, one torch thread each) run on separate cores,
keep the event loop's latency flat
while they compute, can be restarted when one dies (a crash sends its job
back to the runner, not the server down), and stop by themselves when the
server goes away. The cost is a start-up of a few seconds per worker (torch
imports) and progress travelling through a ``multiprocessing`` queue. Threads
(``executor="thread"``) start instantly and suit tests and tiny deployments.

Both pools speak the same events, delivered to ``on_event`` from a
background thread:

- ``("ready", slot)`` a worker has imported torch, run one tiny rollout and waits for jobs,
- ``("progress", job_id, data)`` throttled progress of a running job,
- ``("finished", job_id, slot, {"summary": ..., "artefacts": [...]})``,
- ``("failed", job_id, slot, code, message)``,
- ``("cancelled", job_id, slot)``,
- ``("crashed", job_id, slot, exit_code)`` the worker process died while running the job.

Cancellation sets the slot's flag; the job's ``StopCheck`` sees it at its
next iteration (solve, heatmap) or step (simulate). The pool's owner only
hands a slot a new job after that slot's previous job has reported its end,
and clears the flag when it does, so a cancel never hits the wrong job.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
import traceback
from pathlib import Path

log = logging.getLogger("dejaview.server")


def serve_jobs(slot: int, get_task, put_event, cancelled, options: dict, parent_pid: int | None = None):
    """A worker's loop: take ``(job_id, spec, out_dir)`` tasks until ``None``, run, report.

    Args:
        slot: this worker's index.
        get_task: blocking; returns a task or None (stop).
        put_event: sends an event tuple to the server.
        cancelled: callable -> bool, the slot's cancel flag.
        options: ``job_timeout_s``, ``progress_interval_s``.
        parent_pid: stop when the parent process is gone (process workers).
    """
    from dejaview.server.jobs import JobStopped, StopCheck, run_job, worker_error

    _warm_up()
    put_event(("ready", slot))
    while True:
        task = get_task()
        if task is None:
            return
        job_id, spec, out_dir = task
        stop = StopCheck(cancelled, options.get("job_timeout_s"), parent_pid)
        try:
            result = run_job(spec, Path(out_dir), lambda data, j=job_id: put_event(("progress", j, data)),
                             stop, options.get("progress_interval_s", 0.25))
            put_event(("finished", job_id, slot, result))
        except Exception as exc:  # every failure becomes the job's error, never the worker's end
            if stop.reason == "orphaned":
                return
            if stop.reason == "cancelled":
                put_event(("cancelled", job_id, slot))
                continue
            # stopped for its time limit: whatever the library raised on the way out, say so
            err = worker_error(JobStopped(stop.reason) if stop.reason else exc)
            if err.code == "internal_error" and not isinstance(exc, JobStopped):
                log.error("job %s failed:\n%s", job_id, traceback.format_exc())
            put_event(("failed", job_id, slot, err.code, err.message))


class ThreadPool:
    """Jobs run in ``size`` threads of the server process."""

    kind = "thread"

    def __init__(self, size: int, options: dict):
        self.size = size
        self.options = options
        self._inboxes = [queue.Queue() for _ in range(size)]
        self._cancel = [threading.Event() for _ in range(size)]
        self._threads: list[threading.Thread] = []
        self.ready = 0

    def start(self, on_event) -> None:
        def put(event):
            if event[0] == "ready":
                self.ready += 1
            on_event(event)

        for i in range(self.size):
            t = threading.Thread(target=serve_jobs, name=f"dejaview-worker-{i}", daemon=True,
                                 args=(i, self._inboxes[i].get, put, self._cancel[i].is_set, self.options))
            t.start()
            self._threads.append(t)

    def run(self, slot: int, job_id: str, spec: dict, out_dir: str) -> None:
        self._cancel[slot].clear()
        self._inboxes[slot].put((job_id, spec, out_dir))

    def cancel(self, slot: int) -> None:
        self._cancel[slot].set()

    def close(self, timeout: float = 10.0) -> None:
        for flag, inbox in zip(self._cancel, self._inboxes):
            flag.set()
            inbox.put(None)
        for t in self._threads:
            t.join(timeout)


WARM_UP_SCENE = """<scene version="1"><simulation dt="0.01" duration="0.01"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05"><pose position="0 0 0.1"/></object></scene>"""


def _warm_up() -> None:
    """One tiny rollout before the first job: torch's first ops and the simulator's lazy imports
    cost a second or two, which would otherwise land on the first client's latency."""
    from dejaview.scene.xml import read_scene_string
    from dejaview.sim.simulate import simulate

    try:
        simulate(read_scene_string(WARM_UP_SCENE), steps=1)
    except Exception:  # never keep a worker from starting
        log.exception("worker warm-up failed")


def _process_main(slot, inbox, events, cancel, options, parent_pid):
    """Entry point of a worker process (spawned: a fresh interpreter)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which stops us
    import torch

    import dejaview.inference.solve  # noqa: F401  imported now so the first job starts at once
    import dejaview.sim.simulate  # noqa: F401

    torch.set_num_threads(1)

    def get_task():
        while True:
            try:
                return inbox.get(timeout=1.0)
            except queue.Empty:
                if os.getppid() != parent_pid:
                    return None

    serve_jobs(slot, get_task, events.put, cancel.is_set, options, parent_pid)


class ProcessPool:
    """Jobs run in ``size`` worker processes; a dead worker is replaced and its job failed."""

    kind = "process"

    def __init__(self, size: int, options: dict):
        import multiprocessing

        self.size = size
        self.options = options
        self._ctx = multiprocessing.get_context("spawn")
        self._events = self._ctx.Queue()
        self._procs: list = [None] * size
        self._inboxes: list = [None] * size
        self._cancel = [self._ctx.Event() for _ in range(size)]
        self._current: list[str | None] = [None] * size
        self._spawned_at = [0.0] * size
        self._lock = threading.Lock()
        self._closing = False
        self._reader: threading.Thread | None = None
        self._on_event = None
        self.ready = 0

    def _spawn(self, slot: int) -> None:
        self._spawned_at[slot] = time.monotonic()
        inbox = self._ctx.Queue()
        proc = self._ctx.Process(target=_process_main, name=f"dejaview-worker-{slot}", daemon=True,
                                 args=(slot, inbox, self._events, self._cancel[slot], self.options,
                                       os.getpid()))
        proc.start()
        self._inboxes[slot], self._procs[slot] = inbox, proc

    def start(self, on_event) -> None:
        self._on_event = on_event
        for i in range(self.size):
            self._spawn(i)
        self._reader = threading.Thread(target=self._read, name="dejaview-worker-events", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while not self._closing:
            try:
                event = self._events.get(timeout=0.5)
            except queue.Empty:
                event = None
            except (EOFError, OSError):
                return
            if event is not None:
                if event[0] == "ready":
                    self.ready += 1
                elif event[0] in ("finished", "failed", "cancelled"):
                    with self._lock:
                        if self._current[event[2]] == event[1]:
                            self._current[event[2]] = None
                self._on_event(event)
            self._replace_dead()

    def _replace_dead(self) -> None:
        for slot, proc in enumerate(self._procs):
            if self._closing or proc is None or proc.is_alive():
                continue
            if time.monotonic() - self._spawned_at[slot] < 5.0:
                continue  # a worker that dies at start-up is retried every 5 s, not in a tight loop
            with self._lock:
                job_id, self._current[slot] = self._current[slot], None
            log.error("worker %d died (exit code %s); starting a new one", slot, proc.exitcode)
            self.ready = max(0, self.ready - 1)
            self._spawn(slot)
            if job_id is not None:  # the runner queues the job again, or fails it the second time
                self._on_event(("crashed", job_id, slot, proc.exitcode))

    def run(self, slot: int, job_id: str, spec: dict, out_dir: str) -> None:
        self._cancel[slot].clear()
        with self._lock:
            self._current[slot] = job_id
        self._inboxes[slot].put((job_id, spec, out_dir))

    def cancel(self, slot: int) -> None:
        self._cancel[slot].set()

    def close(self, timeout: float = 10.0) -> None:
        self._closing = True
        for flag, inbox in zip(self._cancel, self._inboxes):
            flag.set()
            if inbox is not None:
                inbox.put(None)
        for proc in self._procs:
            if proc is not None:
                proc.join(timeout)
                if proc.is_alive():
                    proc.terminate()
                    proc.join(2.0)
        if self._reader is not None:
            self._reader.join(2.0)


def make_pool(kind: str, size: int, options: dict):
    """A ``ProcessPool`` or ``ThreadPool`` of ``size`` workers."""
    return (ProcessPool if kind == "process" else ThreadPool)(size, options)
