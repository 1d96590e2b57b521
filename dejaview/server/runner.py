"""The job runner: a bounded queue in front of a worker pool, job records on disk, subscribers.

Everything here runs on the event loop (worker events arrive through
``call_soon_threadsafe``), so job state needs no locks. A job is

    queued -> running -> done | failed | cancelled      (queued -> cancelled too)

and every change is written to the job store (``dejaview.server.store``:
SQLite in ``<results_dir>/jobs.sqlite3``) before anyone hears of it; the
job's scene (``scene.xml``) and artefacts are files in
``<results_dir>/jobs/<id>/``; train jobs' models are ``<results_dir>/models/<fingerprint>.safetensors``
(``dejaview.server.live``), kept when their jobs are pruned. A client that went away can fetch the results
later, and a restarted server serves finished jobs and runs again the jobs a
previous server left queued or running (after a crash or a plain stop), in
their order: at-least-once, as a job's outputs are a pure function of its
scene and overrides, and a worker writes them atomically (``jobs.run_job``).

A finished job whose artefacts cannot be read when the server starts (a file
gone, a JSON file edited by hand) is moved to ``<results_dir>/unreadable/`` and
fails with ``result_unreadable``; the log says so once, the rest is served.

A job whose worker process dies is queued again at the front; the second
time (``MAX_CRASHES``) it fails with ``worker_crashed``, and the server goes
on with the next job. A job the server itself was stopped under
``MAX_STARTS`` times (a job that takes a thread-executor server down with it)
fails with ``interrupted``.

Subscribers are objects with a ``deliver(job_id, message)`` method; each job
keeps them (with the request id each one's messages carry) and every
progress and final message goes to all of them.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import re
import shutil
import time
import uuid
from pathlib import Path

from dejaview.server.config import ServerConfig
from dejaview.result_set import partial_folders
from dejaview.server.errors import ServiceError, write_error
from dejaview.server.messages import (
    FINISHED_STATES,
    AcceptedMessage,
    DoneMessage,
    ErrorInfo,
    ErrorMessage,
    HeatmapMessage,
    JobStatus,
    ProgressData,
    ProgressMessage,
    ResultMessage,
    TrajectoryMessage,
)
from dejaview.server.live import MODELS
from dejaview.server.scenes import SceneInput, check_job, read_scene_input
from dejaview.server.store import JobStore
from dejaview.server.workers import make_pool

log = logging.getLogger("dejaview.server")

JOB_ID_RE = re.compile(r"^[0-9a-f]{32}$")
FINGERPRINT_RE = re.compile(r"^[0-9a-f]{64}$")  # a train job's model: models/<fingerprint>.safetensors
MAX_CRASHES = 2  # a job whose worker process dies this many times fails (worker_crashed)
UNREADABLE = "unreadable"  # where finished jobs whose artefacts cannot be read are moved, in the results dir
MAX_STARTS = 5  # a job started this many times, the server stopping under it each time, fails

# artefact file name -> media type; what GET /jobs/{id}/{name} may serve
ARTEFACTS = {
    "trajectory.csv": "text/csv; charset=utf-8",
    "result.json": "application/json",
    "heatmap.ppm": "image/x-portable-pixmap",
    "heatmap.png": "image/png",
    "heatmap.json": "application/json",
    "iterations.csv": "text/csv; charset=utf-8",
    "posterior.csv": "text/csv; charset=utf-8",
    "posterior_paths.csv": "text/csv; charset=utf-8",
    "posterior.nc": "application/x-netcdf",  # where the server has the analysis extra (arviz)
}


def artefact_url(job_id: str, name: str) -> str:
    return f"/jobs/{job_id}/{name}"


class Job:
    """A job in memory: its record plus what only a live server knows."""

    def __init__(self, status: JobStatus, spec: dict | None = None):
        self.status = status
        self.spec = spec
        self.slot: int | None = None
        self.subscribers: dict[object, str | None] = {}  # subscriber -> its request id
        self.cancel_requested = False
        self.starts = 0  # times a worker was given the job (kept in the store)
        self.crashes = 0  # times its worker process died under it

    @property
    def id(self) -> str:
        return self.status.job_id

    @property
    def finished(self) -> bool:
        return self.status.state in FINISHED_STATES


class JobRunner:
    """Queue, dispatch, cancel and record jobs; fan their messages out to subscribers."""

    def __init__(self, config: ServerConfig):
        self.config = config
        self.jobs: dict[str, Job] = {}
        self.pending: collections.deque[str] = collections.deque()
        self.free_slots: list[int] = list(range(config.workers))[::-1]
        self.pool = None
        self.store: JobStore | None = None
        self.closing = False
        self.loop: asyncio.AbstractEventLoop | None = None
        self.jobs_dir = config.results_dir / "jobs"

    # ------------------------------------------------------------ life cycle
    async def start(self) -> None:
        """Open the store, queue again what a previous server left unfinished, start the workers.

        Raises:
            ServiceError: ``results_dir_busy`` / ``store_error`` (see ``JobStore``).
        """
        self.loop = asyncio.get_running_loop()
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self.store = JobStore(self.config.results_dir)
        self._import_json_records()
        self._load_records()
        self._prune()
        self.pool = make_pool(self.config.executor, self.config.workers,
                              {"job_timeout_s": self.config.job_timeout_s,
                               "progress_interval_s": self.config.progress_interval_s,
                               "memory_limit": self.config.job_memory_bytes,
                               "models_dir": str(self.config.results_dir / MODELS),
                               "niceness": self.config.worker_niceness})
        self.pool.start(self._from_worker)
        self._dispatch()

    async def close(self) -> None:
        """Stop the workers. Unfinished jobs keep their records: the next server runs them."""
        self.closing = True
        self.pending.clear()
        if self.pool is not None:
            await asyncio.to_thread(self.pool.close)
        if self.store is not None:
            self.store.close()
            self.store = None

    def _load_records(self) -> None:
        requeued, aside = 0, []
        for row in self.store.load():
            try:
                status = JobStatus.model_validate_json(row.record)
            except ValueError as exc:
                log.warning("skipping unreadable record of job %s: %s", row.job_id, first_line(exc))
                continue
            job = Job(status, row.spec)
            job.starts, job.crashes = row.starts, row.crashes
            self.jobs[job.id] = job
            if job.finished:
                job.spec = None
                unreadable = self._unreadable_artefact(job)
                if unreadable is not None:
                    aside.append(self._set_aside(job, unreadable))
            elif job.spec is None:
                self._finish(job, "failed", ErrorInfo(
                    code="interrupted", message="the server stopped before this job finished (its record "
                                                "has no job spec to run it again)"))
            elif job.starts >= MAX_STARTS:
                self._finish(job, "failed", ErrorInfo(
                    code="interrupted", message=f"the server stopped {job.starts} times while this job ran; "
                                                f"it is not run again"))
            else:
                self._requeue(job)
                requeued += 1
        if requeued:
            log.warning("%d unfinished job(s) of a previous server queued again", requeued)
        if aside:
            log.warning("%d finished job(s) whose artefacts could not be read moved aside to %s: %s",
                        len(aside), self.config.results_dir / UNREADABLE, ", ".join(aside))

    def _unreadable_artefact(self, job: Job) -> str | None:
        """What of a finished job's artefacts cannot be read (a file missing, JSON edited by hand into
        something else), or None."""
        for name in job.status.artefacts:
            path = self.jobs_dir / job.id / name
            try:
                if name.endswith(".json"):
                    json.loads(path.read_text(encoding="utf-8"))
                elif not path.is_file():
                    return f"{name}: missing"
            except (OSError, ValueError) as exc:
                return f"{name}: {first_line(exc)}"
        return None

    def _set_aside(self, job: Job, why: str) -> str:
        """Move a job with an unreadable artefact to ``<results_dir>/unreadable/<id>``; the job is failed
        with ``result_unreadable``, the rest of the results dir served as before."""
        target = self.config.results_dir / UNREADABLE / job.id
        try:
            target.parent.mkdir(exist_ok=True)
            os.replace(self.jobs_dir / job.id, target)
        except OSError as exc:
            why += f" (not moved: {exc.strerror})"
        job.status.artefacts = {}
        job.status.state = "failed"
        job.status.error = ErrorInfo(code="result_unreadable", message=f"the job's artefacts could not be read "
                                     f"when the server started ({why}); they were moved to {target}")
        self._save(job)
        return job.id

    def _import_json_records(self) -> None:
        """Records of older versions (``jobs/<id>/job.json``) that the store does not hold yet."""
        for path in sorted(self.jobs_dir.glob("*/job.json")):
            job_id = path.parent.name
            if not JOB_ID_RE.match(job_id) or job_id in self.store:
                continue
            try:
                status = JobStatus.model_validate_json(path.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                log.warning("skipping unreadable job record %s: %s", path, first_line(exc))
                continue
            if status.job_id == job_id:
                self._save(Job(status))

    def _requeue(self, job: Job, front: bool = False) -> None:
        """Back into the queue (after a crash of the server or of the job's worker)."""
        job.status.state = "queued"
        job.status.started_at = None
        job.status.progress = None
        job.slot = None
        (self.pending.appendleft if front else self.pending.append)(job.id)
        for stale in partial_folders(self.jobs_dir / job.id):
            shutil.rmtree(stale, ignore_errors=True)  # what a killed worker left half written
        self._save(job)

    # ------------------------------------------------------------ queries
    @property
    def running(self) -> int:
        return sum(1 for j in self.jobs.values() if j.status.state == "running")

    def get(self, job_id: str) -> Job:
        job = self.jobs.get(job_id) if isinstance(job_id, str) and JOB_ID_RE.match(job_id) else None
        if job is None:
            raise ServiceError("not_found", f"no job {job_id!r}", 404)
        return job

    def status(self, job_id: str) -> JobStatus:
        job = self.get(job_id)
        status = job.status.model_copy()
        if status.state == "queued":
            status.queue_position = self.pending.index(job.id) + 1
        return status

    def artefact(self, job_id: str, name: str) -> Path:
        """The path of a finished job's artefact.

        Raises:
            ServiceError: ``not_found``, ``not_ready`` (409) or ``no_artefact`` (404).
        """
        job = self.get(job_id)
        if not job.finished:
            raise ServiceError("not_ready", f"job {job_id} is {job.status.state}: no artefacts yet", 409)
        path = self.jobs_dir / job.id / name
        if name not in ARTEFACTS or name not in job.status.artefacts or not path.is_file():
            why = {"failed": "the job failed", "cancelled": "the job was cancelled"}.get(
                job.status.state, f"a {job.status.kind} job writes none")
            raise ServiceError("no_artefact", f"job {job_id} has no {name}: {why}", 404)
        return path

    def model(self, job_id: str) -> Path:
        """The model file a finished train job wrote (``<results_dir>/models/<fingerprint>.safetensors``,
        kept when the job is pruned), checked to be the one it wrote: a later train job of the same
        scene replaces the file.

        Raises:
            ServiceError: ``not_found``, ``not_ready`` (409) or ``no_artefact`` (404: not a train job,
                failed or cancelled, the file gone or replaced).
        """
        from dejaview.server.live import model_digest, model_path

        job = self.get(job_id)
        if job.status.kind != "train":
            raise ServiceError("no_artefact", f"job {job_id} is a {job.status.kind} job: only train jobs "
                                              f"have a model", 404)
        if not job.finished:
            raise ServiceError("not_ready", f"job {job_id} is {job.status.state}: no model yet", 409)
        summary = job.status.summary or {}
        fingerprint = summary.get("fingerprint")
        if job.status.state != "done" or not isinstance(fingerprint, str) or not FINGERPRINT_RE.match(fingerprint):
            why = {"failed": "the job failed", "cancelled": "the job was cancelled"}.get(
                job.status.state, "its record names none")
            raise ServiceError("no_artefact", f"job {job_id} has no model: {why}", 404)
        path = model_path(self.config.results_dir / MODELS, fingerprint)
        try:
            digest = model_digest(path)
        except OSError:
            raise ServiceError("no_artefact", f"job {job_id} has no model: its file "
                                              f"{MODELS}/{path.name} is gone", 404) from None
        if summary.get("model_sha256") not in (None, digest):  # records from before the digest: unchecked
            raise ServiceError("no_artefact", f"job {job_id} has no model: a later train job of the same scene "
                                              f"replaced {MODELS}/{path.name}", 404)
        return path

    # ------------------------------------------------------------ submitting
    async def submit_request(self, kind: str, *, scene_xml: str | None = None,
                             scene_path: str | None = None, overrides: dict | None = None,
                             subscriber=None, request_id: str | None = None) -> Job:
        """Read and check the scene (in a thread), then ``submit``."""
        self._check_room()
        scene_input = await asyncio.to_thread(read_scene_input, self.config.scene_root, scene_xml=scene_xml,
                                              scene_path=scene_path, max_bytes=self.config.max_scene_bytes)
        return self.submit(kind, scene_input, overrides or {}, subscriber, request_id)

    def _check_room(self) -> None:
        if len(self.pending) >= self.config.queue_size and not self.free_slots:
            raise ServiceError("queue_full", f"the job queue is full ({self.config.queue_size} jobs "
                                             f"waiting): try again later", 503)

    def submit(self, kind: str, scene_input: SceneInput, overrides: dict, subscriber=None,
               request_id: str | None = None) -> Job:
        """Queue a checked job; ``subscriber`` gets ``accepted`` first, then everything else.

        Raises:
            ServiceError: ``queue_full`` (503), ``invalid_scene`` / ``limit_exceeded`` (422),
                ``disk_full`` (507) / ``write_failed`` / ``store_error`` where nothing can be written.
        """
        check_job(kind, scene_input.scene, overrides, self.config)
        self._check_room()
        job_id = uuid.uuid4().hex
        folder = self.jobs_dir / job_id
        try:
            folder.mkdir(parents=True)
            write_atomically(folder / "scene.xml", scene_input.text.encode("utf-8"))
        except OSError as exc:  # a full disk refuses the job; the server goes on
            shutil.rmtree(folder, ignore_errors=True)
            raise write_error(exc) from None
        status = JobStatus(job_id=job_id, kind=kind, state="queued", created_at=time.time(),
                           scene=scene_input.source, overrides=overrides)
        spec = {"kind": kind, "text": scene_input.text, "base_dir": str(scene_input.base_dir),
                "root": str(self.config.scene_root), "filename": scene_input.filename, "overrides": overrides}
        job = Job(status, spec)
        try:
            self._save(job, strict=True)  # on disk before anyone hears "accepted"
        except ServiceError:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        self.jobs[job_id] = job
        self.pending.append(job_id)
        if subscriber is not None:
            job.subscribers[subscriber] = request_id
            subscriber.deliver(job_id, AcceptedMessage(job_id=job_id, request_id=request_id, kind=kind,
                                                       state="queued", queue_position=len(self.pending)))
        self._dispatch()
        return job

    def _dispatch(self) -> None:
        while self.free_slots and self.pending:
            job = self.jobs[self.pending.popleft()]
            slot = self.free_slots.pop()
            job.slot = slot
            job.starts += 1
            job.status.state = "running"
            job.status.started_at = time.time()
            self._save(job)
            self.pool.run(slot, job.id, job.spec, str(self.jobs_dir / job.id))

    # ------------------------------------------------------------ cancelling, subscribing
    def cancel(self, job_id: str) -> JobStatus:
        """Cancel a queued job at once, a running one at its next iteration.

        Raises:
            ServiceError: ``not_found`` (404), ``not_cancellable`` (409, already finished).
        """
        job = self.get(job_id)
        if job.finished:
            raise ServiceError("not_cancellable", f"job {job_id} has already finished "
                                                  f"({job.status.state})", 409)
        if job.status.state == "queued":
            self.pending.remove(job.id)
            self._finish(job, "cancelled")
        elif not job.cancel_requested:
            job.cancel_requested = True
            self.pool.cancel(job.slot)
        return self.status(job_id)

    def subscribe(self, job_id: str, subscriber, request_id: str | None = None) -> Job:
        """Send ``subscriber`` the job's messages: all final ones now if it has finished."""
        job = self.get(job_id)
        if job.finished:
            for message in self.final_messages(job):
                subscriber.deliver(job.id, message.model_copy(update={"request_id": request_id}))
        else:
            job.subscribers[subscriber] = request_id
            if job.status.progress is not None:
                subscriber.deliver(job.id, ProgressMessage(job_id=job.id, request_id=request_id,
                                                           **job.status.progress.model_dump()))
        return job

    def unsubscribe(self, job_id: str, subscriber) -> None:
        job = self.jobs.get(job_id)
        if job is not None:
            job.subscribers.pop(subscriber, None)

    # ------------------------------------------------------------ worker events
    def _from_worker(self, event) -> None:
        """Called from a pool thread: hand the event to the loop."""
        try:
            self.loop.call_soon_threadsafe(self._handle, event)
        except RuntimeError:  # the loop is closed: the server is gone
            pass

    def _handle(self, event) -> None:
        try:
            self._apply(event)
        except Exception:  # a bug here must not leave a job hanging silently
            log.exception("cannot handle worker event %r", event[:2])

    def _apply(self, event) -> None:
        kind = event[0]
        if kind == "ready":
            return
        job = self.jobs.get(event[1])
        if job is None or job.finished:
            return
        if self.closing and (kind == "crashed" or (kind == "cancelled" and not job.cancel_requested)):
            return  # stopped by the server's own shutdown: the record stays, the next server runs it
        if kind == "progress":
            progress = ProgressData(**event[2])
            job.status.progress = progress
            self._notify(job, ProgressMessage(job_id=job.id, **progress.model_dump()))
            return
        slot = event[2]
        if kind == "finished":
            job.status.summary = event[3].get("summary")
            job.status.artefacts = {name: artefact_url(job.id, name) for name in event[3].get("artefacts", [])
                                    if name in ARTEFACTS}
            self._finish(job, "done")
        elif kind == "failed":
            self._finish(job, "failed", ErrorInfo(code=event[3], message=event[4]))
        elif kind == "cancelled":
            self._finish(job, "cancelled")
        elif kind == "crashed":
            self._crashed(job, event[3])
        if job.slot == slot:
            job.slot = None
            self.free_slots.append(slot)
        self._dispatch()

    def _crashed(self, job: Job, exit_code) -> None:
        job.crashes += 1
        if job.cancel_requested:
            self._finish(job, "cancelled")
        elif job.crashes >= MAX_CRASHES:
            self._finish(job, "failed", ErrorInfo(
                code="worker_crashed", message=f"the job crashed its worker process {job.crashes} times "
                                               f"(last exit code {exit_code}); it is not run again"))
        else:
            log.warning("job %s: its worker died (exit code %s); running it again", job.id, exit_code)
            slot = job.slot
            self._requeue(job, front=True)
            job.slot = slot  # freed by the caller

    def _finish(self, job: Job, state: str, error: ErrorInfo | None = None) -> None:
        job.status.state = state
        job.status.finished_at = time.time()
        job.status.error = error
        job.status.queue_position = None
        job.spec = None
        self._save(job)
        messages = self.final_messages(job)
        subscribers = list(job.subscribers.items())
        job.subscribers.clear()
        for subscriber, request_id in subscribers:
            for message in messages:
                subscriber.deliver(job.id, message.model_copy(update={"request_id": request_id}))
        self._prune()

    def _notify(self, job: Job, message) -> None:
        for subscriber, request_id in list(job.subscribers.items()):
            subscriber.deliver(job.id, message.model_copy(update={"request_id": request_id}))

    # ------------------------------------------------------------ final messages
    def final_messages(self, job: Job) -> list:
        """What a subscriber gets when the job ends: trajectory, heatmap, result (each inline up to
        the inline limit, always with a URL), or the error; then ``done``."""
        jid, state, folder = job.id, job.status.state, self.jobs_dir / job.id
        out = []
        if state == "done":
            names = job.status.artefacts
            if "trajectory.csv" in names:
                csv_text, size = self._inline(folder / "trajectory.csv")
                out.append(TrajectoryMessage(job_id=jid, csv=csv_text, url=names["trajectory.csv"],
                                             bytes=size))
            if "heatmap.ppm" in names:
                ppm, _ = self._inline(folder / "heatmap.ppm")
                grid_text, _ = self._inline(folder / "heatmap.json") if "heatmap.json" in names else (None, 0)
                out.append(HeatmapMessage(job_id=jid, ppm=ppm, ppm_url=names["heatmap.ppm"],
                                          png_url=names.get("heatmap.png"),
                                          grid=_json_or_none(grid_text),
                                          grid_url=names.get("heatmap.json")))
            if "result.json" in names:
                text, _ = self._inline(folder / "result.json")
                out.append(ResultMessage(job_id=jid, result=_json_or_none(text), url=names["result.json"]))
        elif state == "failed" and job.status.error is not None:
            out.append(ErrorMessage(job_id=jid, code=job.status.error.code, message=job.status.error.message))
        out.append(DoneMessage(job_id=jid, state=state))
        return out

    def _inline(self, path: Path) -> tuple[str | None, int]:
        """(text, size) of a file, text None when larger than the inline limit or unreadable."""
        try:
            size = path.stat().st_size
            if size > self.config.inline_limit_bytes:
                return None, size
            return path.read_text(encoding="utf-8"), size
        except (OSError, UnicodeDecodeError):
            return None, 0

    # ------------------------------------------------------------ records on disk
    def _save(self, job: Job, strict: bool = False) -> None:
        """Write the job's record to the store; ``strict``: raise ``store_error`` instead of
        logging it (a submission is refused rather than accepted without a record)."""
        record = job.status.model_copy(update={"queue_position": None}).model_dump_json()
        try:
            self.store.save(job.id, job.status.state, record, None if job.finished else job.spec,
                            job.starts, job.crashes)
        except ServiceError as exc:
            if strict:
                raise
            log.error("%s", exc.message)

    def _prune(self) -> None:
        finished = [j for j in self.jobs.values() if j.finished]
        excess = len(finished) - self.config.keep_jobs
        if excess <= 0:
            return
        finished.sort(key=lambda j: j.status.finished_at or 0.0)
        try:
            self.store.delete([job.id for job in finished[:excess]])
        except ServiceError as exc:
            log.error("%s", exc.message)
            return
        for job in finished[:excess]:
            del self.jobs[job.id]
            shutil.rmtree(self.jobs_dir / job.id, ignore_errors=True)


def write_atomically(path: Path, data: bytes) -> None:
    """Write a file so that a reader (or a crash) sees the old content or the new, never a part:
    a temporary file beside it, flushed to disk, renamed over it."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _json_or_none(text: str | None):
    """The JSON of an artefact's text, None where absent or not JSON (a file edited since the start:
    its URL still says where it is)."""
    try:
        return json.loads(text) if text else None
    except ValueError:
        return None


def first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
