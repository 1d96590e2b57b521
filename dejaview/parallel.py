"""Map a function over chunks of work: in this process, in a local process pool, or on Ray.

The one scale-out seam of DejaView (heatmaps today; posteriors, calibration and recovery fan-outs
can use it the same way). It knows nothing of what a chunk is::

    results = map_chunks(optimise, chunks, setup=build_problem, setup_args=(scene,),
                         workers=4, ray="local", on_report=show, should_stop=cancelled)

- ``setup(*setup_args)`` runs once per worker (per process of the pool, per Ray actor) and gives
  the ``context`` every chunk of that worker gets (e.g. a problem built from the scene).
- ``fn(context, chunk, report, stopped)`` does one chunk and returns its result. ``report(message)``
  hands a picklable message to ``on_report(index, message)`` in this process (progress);
  ``stopped()`` turns True once ``should_stop()`` has (cancellation: ``fn`` should return early).
- Results come back in chunk order; a worker's exception is raised here as it was raised there.
  After cancellation chunks not yet started are skipped, so the list may be shorter.

Where: ``ray`` None and ``workers`` 1 (or one chunk): in this process, in order. ``workers`` > 1: a
pool of spawned processes on this machine. ``ray="local"``: a Ray instance started in this process
(``workers`` CPUs, no dashboard, localhost only); ``ray="ADDRESS"`` (``ray://host:10001`` or
``host:6379``, see docs/scale.md): a running cluster, ``workers`` actors (default: its CPU count).
``fn``, ``setup`` and their arguments must be picklable (module-level functions); on a cluster
every node needs DejaView installed. Ray is imported only here, and only when asked for.
"""

from __future__ import annotations

import os
import time
from typing import Any, Callable, Sequence

from dejaview.errors import DejaViewError

__all__ = ["ParallelError", "connect_ray", "map_chunks", "ray_cpus"]

RAY_EXTRA_HINT = "pip install 'dejaview[ray]'"
_REPORT_EVERY_S = 0.2
"""Ray workers send progress in batches at most this often (one actor call per batch)."""


class ParallelError(DejaViewError):
    """The scale-out could not start (Ray missing or unreachable, bad settings) or lost a worker."""


def map_chunks(fn: Callable, chunks: Sequence, *, setup: Callable | None = None, setup_args: tuple = (),
               workers: int = 1, ray: str | None = None, on_report: Callable | None = None,
               on_done: Callable | None = None, should_stop: Callable | None = None) -> list:
    """``[fn(context, chunk, report, stopped) for chunk in chunks]``, here, in processes or on Ray.

    Args:
        fn: module-level function ``fn(context, chunk, report, stopped) -> result``.
        chunks: the work, one picklable item per chunk.
        setup: ``setup(*setup_args) -> context``, once per worker (None: the context is None).
        workers: processes (or Ray actors) at once; 1 without ``ray``: in this process.
        ray: None, ``"local"`` or a Ray cluster address.
        on_report: ``on_report(index, message)``, called in this process for every ``report``.
        on_done: ``on_done(index, result)``, called in this process as each chunk finishes.
        should_stop: polled here; True stops the run (``stopped()`` turns True in the workers).
    Returns:
        The results, in chunk order (shorter after cancellation).
    Raises:
        ParallelError: Ray not installed or not reachable, ``workers`` < 1, a worker process
            killed (the OOM killer, a signal) or crashed while it ran a chunk.
        Whatever ``fn`` or ``setup`` raised.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ParallelError(f"workers must be a positive integer, got {workers!r}")
    report = on_report or (lambda _i, _m: None)
    done = on_done or (lambda _i, _r: None)
    if ray is not None:
        return _on_ray(fn, chunks, setup, setup_args, workers, ray, report, done, should_stop)
    if workers > 1 and len(chunks) > 1:
        return _in_processes(fn, chunks, setup, setup_args, workers, report, done, should_stop)
    return _here(fn, chunks, setup, setup_args, report, done, should_stop)


# ------------------------------------------------------------------ in this process
def _here(fn, chunks, setup, setup_args, report, done, should_stop) -> list:
    context = setup(*setup_args) if setup is not None else None
    stopped = should_stop or (lambda: False)
    results = []
    for i, chunk in enumerate(chunks):
        if results and stopped():
            break
        results.append(fn(context, chunk, lambda m, _i=i: report(_i, m), stopped))
        done(i, results[-1])
    return results


# ------------------------------------------------------------------ local process pool
_CONTEXT: dict = {}


def _pool_init(setup, setup_args) -> None:
    _CONTEXT["context"] = setup(*setup_args) if setup is not None else None


def _pool_run(fn, index: int, chunk, queue, stop):
    return fn(_CONTEXT["context"], chunk, lambda m: queue.put((index, m)), stop.is_set)


def _in_processes(fn, chunks, setup, setup_args, workers, report, done, should_stop) -> list:
    """A pool of ``workers`` spawned processes; messages come back through a queue and are reported
    from this thread."""
    import multiprocessing
    import queue as queue_mod
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    ctx = multiprocessing.get_context("spawn")
    with ctx.Manager() as manager:
        q, stop = manager.Queue(), manager.Event()
        with ProcessPoolExecutor(max_workers=min(workers, len(chunks)), mp_context=ctx,
                                 initializer=_pool_init, initargs=(setup, setup_args)) as pool:
            futures = [pool.submit(_pool_run, fn, i, chunk, q, stop) for i, chunk in enumerate(chunks)]
            pending = set(range(len(futures)))
            def manager(call, *args):
                """A call on q or stop; the manager process behind them may have been killed."""
                try:
                    return call(*args)
                except (EOFError, OSError):
                    raise ParallelError(f"the helper process that carries the workers' progress died "
                                        f"(killed by a signal or the out-of-memory killer); "
                                        f"{len(pending)} chunk(s) left unfinished: try again") from None

            while pending:
                try:
                    report(*manager(q.get, True, 0.1))
                except queue_mod.Empty:
                    pass
                if should_stop is not None and should_stop():
                    manager(stop.set)
                for i in sorted(c for c in pending if futures[c].done()):
                    pending.discard(i)
                    try:
                        result = futures[i].result()  # raises a worker's error here
                    except BrokenProcessPool:
                        raise ParallelError(
                            f"a worker process died (killed by a signal or the out-of-memory killer, or "
                            f"crashed) while chunk {i} of {len(chunks)} ran; {len(pending) + 1} chunk(s) "
                            f"left unfinished: try again, with fewer workers if memory is short") from None
                    except (EOFError, OSError):  # the chunk's own error, or it lost the manager: which?
                        manager(q.qsize)
                        raise
                    done(i, result)
            while True:  # the last messages
                try:
                    report(*manager(q.get_nowait))
                except queue_mod.Empty:
                    break
            return [f.result() for f in futures]


# ------------------------------------------------------------------ Ray
def _import_ray():
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # Ray reports usage over the internet otherwise
    try:
        import ray
    except ImportError:
        raise ParallelError(f"--ray needs Ray, which is not installed: {RAY_EXTRA_HINT}") from None
    return ray


def connect_ray(address: str, num_cpus: int | None = None) -> tuple[Any, bool]:
    """Ray, initialised: ``address`` ``"local"`` starts an instance in this process (``num_cpus``
    CPUs, no dashboard, on 127.0.0.1), another address joins that cluster. An already
    initialised Ray is used as it is.

    Returns:
        (the ray module, whether this call started it).
    Raises:
        ParallelError: Ray not installed, or the cluster not reachable (one line).
    """
    ray = _import_ray()
    if ray.is_initialized():
        return ray, False
    if not isinstance(address, str) or not address.strip():
        raise ParallelError("--ray needs 'local' or a Ray cluster address (e.g. ray://head:10001)")
    try:
        if address == "local":
            ray.init(num_cpus=num_cpus, include_dashboard=False, _node_ip_address="127.0.0.1",
                     log_to_driver=False, configure_logging=False)
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
    except Exception as exc:  # Ray raises ConnectionError, RuntimeError, ValueError... on a bad address
        raise ParallelError(f"cannot connect to Ray at {address!r}: {' '.join(str(exc).split())[:300]}") from None
    return ray, True


def ray_cpus(address: str, num_cpus: int | None = None) -> int:
    """The CPU count of the Ray cluster at ``address`` (connecting as :func:`connect_ray`)."""
    ray, _ = connect_ray(address, num_cpus)
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


class _Inbox:
    """A Ray actor between the driver and the workers: progress messages in, the stop flag out."""

    def __init__(self):
        self.messages, self.stop = [], False

    def put(self, batch):
        self.messages.extend(batch)

    def take(self):
        out, self.messages = self.messages, []
        return out

    def set_stop(self):
        self.stop = True

    def stopped(self):
        return self.stop


class _Failed:
    """A worker's exception, carried back as a result so it is raised here unchanged."""

    def __init__(self, exc: BaseException):
        self.exc = exc


class _RayWorker:
    """A Ray actor: ``setup`` once, then chunks one after another."""

    def __init__(self, setup, setup_args):
        self.context = setup(*setup_args) if setup is not None else None

    def run(self, fn, index, chunk, inbox):
        import ray

        buffer, last = [], [time.monotonic()]
        flag = [False, 0.0]

        def flush():
            if buffer:
                ray.get(inbox.put.remote(list(buffer)))
                buffer.clear()
            last[0] = time.monotonic()

        def report(message):
            buffer.append((index, message))
            if time.monotonic() - last[0] > _REPORT_EVERY_S:
                flush()

        def stopped():
            if not flag[0] and time.monotonic() - flag[1] > _REPORT_EVERY_S:
                flag[0], flag[1] = ray.get(inbox.stopped.remote()), time.monotonic()
            return flag[0]

        try:
            return fn(self.context, chunk, report, stopped)
        except Exception as exc:  # noqa: BLE001 - raised in the driver as it was
            return _Failed(exc)
        finally:
            flush()


def _on_ray(fn, chunks, setup, setup_args, workers, address, report, done, should_stop) -> list:
    ray, started = connect_ray(address, workers if address == "local" else None)
    inbox = ray.remote(num_cpus=0)(_Inbox).remote()
    actor_class = ray.remote(num_cpus=1)(_RayWorker)
    actors = [actor_class.remote(setup, setup_args) for _ in range(min(workers, len(chunks)))]
    results: dict[int, Any] = {}
    pending, inflight, free = list(range(len(chunks))), {}, list(actors)
    cancelled = False

    def pump():
        for i, message in ray.get(inbox.take.remote()):
            report(i, message)

    try:
        while pending or inflight:
            while free and pending and not cancelled:
                i = pending.pop(0)
                actor = free.pop()
                inflight[actor.run.remote(fn, i, chunks[i], inbox)] = (i, actor)
            if cancelled:
                pending.clear()
            ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.1) if inflight else ([], [])
            pump()
            if not cancelled and should_stop is not None and should_stop():
                cancelled = True
                ray.get(inbox.set_stop.remote())
            for ref in ready:
                i, actor = inflight.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayError as exc:  # an actor died, setup failed, ...
                    cause = getattr(exc, "cause", None)
                    if isinstance(cause, Exception):
                        raise cause from None
                    raise ParallelError(f"Ray worker failed on chunk {i}: {' '.join(str(exc).split())[:300]}") \
                        from None
                if isinstance(result, _Failed):
                    raise result.exc
                results[i] = result
                free.append(actor)
                done(i, result)
        pump()
    finally:
        for actor in actors:
            ray.kill(actor)
        ray.kill(inbox)
        if started and address == "local":
            ray.shutdown()
    return [results[i] for i in sorted(results)]
