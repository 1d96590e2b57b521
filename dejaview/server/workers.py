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
imports) and progress travelling through a pipe. Threads
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
        options: ``job_timeout_s``, ``progress_interval_s``, ``memory_limit`` (bytes a job may hold),
            ``models_dir`` (where train jobs put their models), ``niceness`` (added to a worker
            process's nice value: 0 none).
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
                             stop, options.get("progress_interval_s", 0.25), options.get("memory_limit"),
                             options.get("models_dir"))
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
    import dejaview.inference.solve  # noqa: F401  imported now so the first solve starts at once
    from dejaview.scene.xml import read_scene_string
    from dejaview.sim.simulate import simulate

    try:
        simulate(read_scene_string(WARM_UP_SCENE), steps=1)
    except Exception:  # never keep a worker from starting
        log.exception("worker warm-up failed")


def _process_main(slot, serve, inbox, events, cancel, options, parent_pid):
    """Entry point of a worker process (spawned: a fresh interpreter).

    ``inbox``/``events`` are this worker's own pipe ends and ``cancel`` its flag
    in shared memory (see ``ProcessPool``): nothing here takes a lock that
    another process could wait on, so a worker killed at any moment leaves
    nothing held.
    """
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which stops us
    if options.get("niceness"):
        # batch work yields the cores to the server process, whose live answers are interactive
        # (docs/benchmarks.md, "Live answers": busy workers at the server's priority starved them)
        os.nice(int(options["niceness"]))
    import torch

    torch.set_num_threads(1)
    send_lock = threading.Lock()

    def get_task():
        while True:
            try:
                if inbox.poll(1.0):
                    return inbox.recv()
            except (EOFError, OSError):  # the server closed our inbox: it is gone
                return None
            if os.getppid() != parent_pid:
                return None

    def put_event(event):
        with send_lock:
            try:
                events.send(event)
            except OSError:  # the server is gone; nobody is left to hear of the job
                os._exit(0)

    serve(slot, get_task, put_event, lambda: cancel.value != 0, options, parent_pid)


class _Sender:
    """Sends tasks down a worker's inbox pipe from a thread of its own.

    A task carries its scene text, which can be larger than a pipe's buffer;
    ``put`` never blocks the caller (the server's event loop) on a worker that
    is still starting or has just died. The thread ends at ``close`` or when
    the worker's end of the pipe is gone.
    """

    _CLOSE = object()

    def __init__(self, conn, name: str):
        self._conn = conn
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._run, name=name, daemon=True).start()

    def put(self, item) -> None:
        self._queue.put(item)

    def close(self) -> None:
        self._queue.put(self._CLOSE)

    def _run(self) -> None:
        try:
            while (item := self._queue.get()) is not self._CLOSE:
                self._conn.send(item)
        except OSError:  # the worker died: what it was sent is the runner's to run again
            pass
        finally:
            self._conn.close()


class ProcessPool:
    """Jobs run in ``size`` worker processes; a dead worker is replaced and its job reported crashed.

    Each worker has its own two pipes (tasks in, events out) and its own cancel
    flag, a byte in shared memory. No ``multiprocessing`` lock, queue or event
    is shared with a worker: one killed while holding such a lock (inside
    ``Event.is_set``, or writing to a shared ``Queue``) would leave it held
    for good, and the next ``Event.clear`` on the event loop, or every other
    worker's next event, would wait forever. A worker killed halfway through
    writing an event leaves a truncated message on its own pipe, which the
    reader sees as the end of that pipe.

    Options besides the job ones: ``respawn_delay_s`` (default 5), the least
    time between starting a worker and starting its replacement, so a worker
    that dies at start-up is not restarted in a tight loop.
    """

    kind = "process"

    def __init__(self, size: int, options: dict, serve=None):
        """``serve``: the worker's loop, ``serve_jobs`` unless a test gives another
        (a module-level function with its signature)."""
        import multiprocessing

        self.size = size
        self.options = options
        self._serve = serve or serve_jobs
        self._ctx = multiprocessing.get_context("spawn")
        self._procs: list = [None] * size
        self._senders: list[_Sender | None] = [None] * size
        self._events: list = [None] * size  # the reading ends of the workers' event pipes
        self._cancel = [self._ctx.RawValue("b", 0) for _ in range(size)]
        self._current: list[str | None] = [None] * size
        self._spawned_at = [0.0] * size
        self._respawn_delay_s = float(options.get("respawn_delay_s", 5.0))
        self._lock = threading.Lock()
        self._closing = False
        self._reader: threading.Thread | None = None
        self._on_event = None
        self.ready = 0

    def _spawn(self, slot: int) -> None:
        self._spawned_at[slot] = time.monotonic()
        task_out, task_in = self._ctx.Pipe(duplex=False)
        event_out, event_in = self._ctx.Pipe(duplex=False)
        proc = self._ctx.Process(target=_process_main, name=f"dejaview-worker-{slot}", daemon=True,
                                 args=(slot, self._serve, task_out, event_in, self._cancel[slot],
                                       self.options, os.getpid()))
        proc.start()
        task_out.close()  # the worker holds these ends now: its death closes them for good
        event_in.close()
        old = self._senders[slot]
        if old is not None:
            old.close()
        self._senders[slot] = _Sender(task_in, f"dejaview-worker-{slot}-inbox")
        self._events[slot], self._procs[slot] = event_out, proc

    def pid(self, slot: int) -> int | None:
        """The process id of the worker in ``slot`` (None before ``start``)."""
        proc = self._procs[slot]
        return None if proc is None else proc.pid

    def start(self, on_event) -> None:
        self._on_event = on_event
        for i in range(self.size):
            self._spawn(i)
        self._reader = threading.Thread(target=self._read, name="dejaview-worker-events", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        """The events thread: every worker's events in, dead workers replaced."""
        from multiprocessing.connection import wait

        while not self._closing:
            conns = {conn: slot for slot, conn in enumerate(self._events) if conn is not None}
            for conn in wait(list(conns), timeout=0.5):
                self._receive(conns[conn], conn)
            self._replace_dead()

    def _receive(self, slot: int, conn) -> bool:
        """Read one event of ``slot``'s worker and pass it on; False at the end of its pipe."""
        try:
            event = conn.recv()
        except (EOFError, OSError):  # the worker is gone, perhaps halfway through an event
            if self._events[slot] is conn:
                self._events[slot] = None
            conn.close()
            return False
        except Exception:  # noqa: BLE001  an event that does not unpickle is dropped, not the reader
            log.exception("unreadable event from worker %d", slot)
            return True
        if event[0] == "ready":
            self.ready += 1
        elif event[0] in ("finished", "failed", "cancelled"):
            with self._lock:
                if self._current[event[2]] == event[1]:
                    self._current[event[2]] = None
        self._on_event(event)
        return True

    def _replace_dead(self) -> None:
        for slot, proc in enumerate(self._procs):
            if self._closing or proc is None or proc.is_alive():
                continue
            if time.monotonic() - self._spawned_at[slot] < self._respawn_delay_s:
                continue  # a worker that dies at start-up is retried after a pause, not in a tight loop
            conn = self._events[slot]
            while conn is not None and self._receive(slot, conn):  # what it said before it died
                pass
            with self._lock:
                job_id, self._current[slot] = self._current[slot], None
            log.error("worker %d died (exit code %s); starting a new one", slot, proc.exitcode)
            self.ready = max(0, self.ready - 1)
            self._spawn(slot)
            if job_id is not None:  # the runner queues the job again, or fails it the second time
                self._on_event(("crashed", job_id, slot, proc.exitcode))

    def run(self, slot: int, job_id: str, spec: dict, out_dir: str) -> None:
        self._cancel[slot].value = 0
        with self._lock:
            self._current[slot] = job_id
        self._senders[slot].put((job_id, spec, out_dir))

    def cancel(self, slot: int) -> None:
        self._cancel[slot].value = 1

    def close(self, timeout: float = 10.0) -> None:
        self._closing = True
        for flag, sender in zip(self._cancel, self._senders):
            flag.value = 1
            if sender is not None:
                sender.put(None)
                sender.close()
        for proc in self._procs:
            if proc is not None:
                proc.join(timeout)
                if proc.is_alive():
                    proc.terminate()
                    proc.join(2.0)
        if self._reader is not None:
            self._reader.join(2.0)
        for conn in self._events:
            if conn is not None:
                conn.close()


def make_pool(kind: str, size: int, options: dict):
    """A ``ProcessPool`` or ``ThreadPool`` of ``size`` workers."""
    return (ProcessPool if kind == "process" else ThreadPool)(size, options)
