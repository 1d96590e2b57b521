"""The process pool survives workers killed at any moment (SIGKILL: an OOM kill, a segfault)."""

from __future__ import annotations

import os
import queue
import signal
import threading
import time

from dejaview.server.workers import ProcessPool


def hammer(slot, get_task, put_event, cancelled, options, parent_pid):
    """A worker loop that does nothing but what a job does most: read its cancel flag and report
    progress, as fast as it can, so that a kill lands inside those calls."""
    put_event(("ready", slot))
    while (task := get_task()) is not None:
        job_id = task[0]
        n = 0
        while not cancelled():
            n += 1
            if n % 50 == 0:
                put_event(("progress", job_id, {"iteration": n}))
        put_event(("cancelled", job_id, slot))


class Events:
    """The pool's events: progress counted per job, the others queued."""

    def __init__(self):
        self.others: queue.Queue = queue.Queue()
        self.progress: dict[str, int] = {}

    def __call__(self, event):
        if event[0] == "progress":
            self.progress[event[1]] = self.progress.get(event[1], 0) + 1
        else:
            self.others.put(event)

    def expect(self, *head, timeout: float = 60.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                event = self.others.get(timeout=0.1)
            except queue.Empty:
                continue
            if event[:len(head)] == head:
                return event
        raise AssertionError(f"no {head} event within {timeout:g} s")

    def wait_progress(self, job_id: str, timeout: float = 30.0):
        deadline = time.monotonic() + timeout
        while self.progress.get(job_id, 0) < 3:
            assert time.monotonic() < deadline, f"no progress of {job_id} within {timeout:g} s"
            time.sleep(0.02)


def returns_soon(fn, *args, timeout: float = 5.0):
    """Call ``fn`` in a thread; fail if it has not returned within ``timeout``
    (the event loop calls ``run`` and ``cancel``: they must never wait on a worker)."""
    t = threading.Thread(target=fn, args=args, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), f"{fn.__name__} did not return within {timeout:g} s"


def test_workers_killed_inside_their_cancel_check_and_progress_leave_the_pool_working():
    """Killed while reading its cancel flag or writing an event, a worker must leave no lock held:
    with ``multiprocessing.Event`` flags and one shared event ``Queue`` (before), about half of
    such kills left ``run``/``cancel`` (on the event loop) or every later event waiting forever."""
    events = Events()
    pool = ProcessPool(1, {"respawn_delay_s": 0.2}, serve=hammer)
    pool.start(events)
    try:
        events.expect("ready", 0)
        for round_ in range(5):
            job_id = f"job-{round_}"
            returns_soon(pool.run, 0, job_id, {}, "")
            events.wait_progress(job_id)
            time.sleep(0.1 * round_)  # kills at different points of the loop
            os.kill(pool.pid(0), signal.SIGKILL)
            assert events.expect("crashed", job_id)[2:] == (0, -signal.SIGKILL)
            events.expect("ready", 0)  # the new worker's events get through
            returns_soon(pool.cancel, 0)  # a cancel of a job that is gone: a no-op, never a wait
        returns_soon(pool.run, 0, "last", {}, "")
        events.wait_progress("last")
        returns_soon(pool.cancel, 0)
        events.expect("cancelled", "last", 0)
    finally:
        pool.close()
