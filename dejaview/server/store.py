"""Job records and the job queue in SQLite: what lets accepted jobs outlive a crash of the server.

One table, one row per job, in ``<results_dir>/jobs.sqlite3`` (WAL mode,
``synchronous=FULL``: a job is on disk before its submitter hears ``accepted``)::

    job_id  TEXT PRIMARY KEY  32 hex digits
    seq     INTEGER           submission order: the queue's order
    state   TEXT              queued | running | done | failed | cancelled
    record  TEXT              the JobStatus JSON that GET /jobs/{id} answers with
    spec    TEXT              what a worker needs to run the job (kind, scene text, overrides);
                              NULL once the job has finished
    starts  INTEGER           times a worker was given the job
    crashes INTEGER           times the worker process running it died

A job's queue is the rows in state ``queued`` or ``running`` ordered by ``seq``:
after a crash the next server runs them again (at-least-once: a job's
outputs are a pure function of its scene and overrides). The artefacts stay
files in ``<results_dir>/jobs/<id>/``.

A database that cannot be read (truncated, overwritten by hand) does not stop a server: the rows
still readable are kept, the file is moved aside to ``jobs.sqlite3.unreadable-<time>`` and the
server says so once in its log (``JobStore.moved_aside``).

Only one server may use a results dir at a time: the store holds an
exclusive ``flock`` on ``<results_dir>/jobs.lock`` while it is open (the
kernel drops it when the process dies, however it dies).
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from dejaview.server.errors import ServiceError

SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    job_id  TEXT PRIMARY KEY,
    seq     INTEGER NOT NULL,
    state   TEXT NOT NULL,
    record  TEXT NOT NULL,
    spec    TEXT,
    starts  INTEGER NOT NULL DEFAULT 0,
    crashes INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state, seq);
"""

log = logging.getLogger("dejaview.server")

# results dir -> [lock file, users]: the app of a test and a restarted app in one process share it
_LOCKS: dict[Path, list] = {}


@dataclass
class StoredJob:
    """One row of the store."""

    job_id: str
    state: str
    record: str
    spec: dict | None
    starts: int
    crashes: int


def _corrupt(exc: sqlite3.Error) -> bool:
    """Whether an error says the database file itself is damaged (not locked, not a full disk)."""
    text = str(exc).lower()
    return "malformed" in text or "not a database" in text or "quick_check" in text


def _readable_rows(path: Path) -> list[tuple]:
    """The rows of a damaged job store that can still be read, in order, until the first that cannot."""
    rows = []
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=1.0)
    except sqlite3.Error:
        return rows
    try:
        for row in db.execute("SELECT job_id, seq, state, record, spec, starts, crashes FROM jobs ORDER BY seq"):
            rows.append(row)
    except sqlite3.Error:
        pass
    finally:
        db.close()
    return rows


def _lock(results_dir: Path) -> None:
    key = results_dir.resolve()
    held = _LOCKS.get(key)
    if held is not None:
        held[1] += 1
        return
    path = key / "jobs.lock"
    fh = open(path, "a+")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise ServiceError("results_dir_busy", f"{key} is in use by another dejaview server "
                                               f"(it holds {path}); give each server its own --results-dir",
                           503) from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    _LOCKS[key] = [fh, 1]


def _unlock(results_dir: Path) -> None:
    key = results_dir.resolve()
    held = _LOCKS.get(key)
    if held is None:
        return
    held[1] -= 1
    if held[1] <= 0:
        del _LOCKS[key]
        held[0].close()  # closing the file drops the flock


class JobStore:
    """The job table of one results dir (see the module docstring).

    Raises:
        ServiceError: ``results_dir_busy`` when another process serves the same results dir,
            ``store_error`` when the database cannot be opened.
    """

    def __init__(self, results_dir: Path):
        self.results_dir = Path(results_dir)
        self.path = self.results_dir / "jobs.sqlite3"
        self.results_dir.mkdir(parents=True, exist_ok=True)
        self.moved_aside: Path | None = None
        _lock(self.results_dir)
        try:
            try:
                self._open()
            except sqlite3.DatabaseError as exc:
                if isinstance(exc, sqlite3.OperationalError) and not _corrupt(exc):
                    raise  # locked, or the disk: not the file's fault
                self._set_aside(exc)
        except sqlite3.Error as exc:
            _unlock(self.results_dir)
            raise ServiceError("store_error", f"cannot open the job store {self.path}: {exc}", 503) from None

    def _open(self) -> None:
        # the event loop thread uses it; check_same_thread=False lets close() come from elsewhere
        self.db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=10.0)
        try:
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.executescript(SCHEMA)
            check = self.db.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise sqlite3.DatabaseError(f"quick_check: {check}")
            self._seq = self.db.execute("SELECT COALESCE(MAX(seq), 0) FROM jobs").fetchone()[0]
        except sqlite3.Error:
            self.db.close()
            raise

    def _set_aside(self, exc: sqlite3.Error) -> None:
        """A database that cannot be read (truncated, overwritten): the rows still readable are kept,
        the file (and its WAL) moved aside to ``jobs.sqlite3.unreadable-<time>``, a new one made."""
        rows = _readable_rows(self.path)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        self.moved_aside = self.path.with_name(f"{self.path.name}.unreadable-{stamp}")
        for suffix in ("", "-wal", "-shm"):
            part = Path(f"{self.path}{suffix}")
            if part.exists():
                os.replace(part, Path(f"{self.moved_aside}{suffix}"))
        self._open()
        with self.db:
            self.db.executemany("INSERT OR IGNORE INTO jobs (job_id, seq, state, record, spec, starts, crashes) "
                                "VALUES (?, ?, ?, ?, ?, ?, ?)", rows)
        self._seq = self.db.execute("SELECT COALESCE(MAX(seq), 0) FROM jobs").fetchone()[0]
        log.warning("the job store %s could not be read (%s): moved aside to %s; %d job record(s) of it "
                    "kept", self.path, exc, self.moved_aside.name, len(rows))

    def load(self) -> list[StoredJob]:
        """Every job, oldest first."""
        rows = self.db.execute("SELECT job_id, state, record, spec, starts, crashes FROM jobs ORDER BY seq")
        out = []
        for job_id, state, record, spec, starts, crashes in rows:
            try:
                spec = json.loads(spec) if spec else None
            except ValueError:
                spec = None
            out.append(StoredJob(job_id, state, record, spec, starts, crashes))
        return out

    def __contains__(self, job_id: str) -> bool:
        return self.db.execute("SELECT 1 FROM jobs WHERE job_id = ?", (job_id,)).fetchone() is not None

    def save(self, job_id: str, state: str, record: str, spec: dict | None, starts: int = 0,
             crashes: int = 0) -> None:
        """Insert or update one job (one transaction, on disk when this returns).

        Raises:
            ServiceError: ``store_error`` (503) when the database cannot be written.
        """
        try:
            self.db.execute(
                "INSERT INTO jobs (job_id, seq, state, record, spec, starts, crashes) "
                "VALUES (?, ?, ?, ?, ?, ?, ?) "
                "ON CONFLICT (job_id) DO UPDATE SET state = excluded.state, record = excluded.record, "
                "spec = excluded.spec, starts = excluded.starts, crashes = excluded.crashes",
                (job_id, self._seq + 1, state, record, None if spec is None else json.dumps(spec),
                 starts, crashes))
            self._seq += 1
        except sqlite3.Error as exc:
            raise ServiceError("store_error", f"cannot write job {job_id} to {self.path}: {exc}", 503) from None

    def delete(self, job_ids: list[str]) -> None:
        try:
            self.db.executemany("DELETE FROM jobs WHERE job_id = ?", [(j,) for j in job_ids])
        except sqlite3.Error as exc:
            raise ServiceError("store_error", f"cannot delete jobs from {self.path}: {exc}", 503) from None

    def close(self) -> None:
        try:
            self.db.close()
        finally:
            _unlock(self.results_dir)
