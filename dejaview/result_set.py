"""A result set (``result.json``, ``iterations.csv``, ``trajectory.csv``...) written whole or not at all.

``write_result_set(out_dir, write, names)`` has ``write`` fill a new folder beside ``out_dir``
(``.<name>.partial-<pid>-<random>``), flushes every file to disk, and only then puts the set in
place: where ``out_dir`` does not exist the folder is renamed to it (one atomic step); where it
does, each file is renamed over its namesake (the folder's other files stay: a job's
``scene.xml``, a user's notes) and the files an earlier set left that this one does not write
(of ``names``: a ``posterior.csv`` of an earlier run with samples) are removed. A failure while
writing (a full disk, no permission) or a kill leaves ``out_dir`` as it was, and the failure
is one ``OutputError`` naming the path and the cause. Readers (a server answering
``GET /jobs/{id}/result.json``) never see a half-written file.

The folders a killed writer left beside ``out_dir`` are found by ``partial_folders``.
"""

from __future__ import annotations

import errno as errno_codes
import os
import shutil
import uuid
from pathlib import Path
from typing import Callable, Iterable

from dejaview.errors import OutputError

PARTIAL = ".partial-"
"""What the name of a folder being written holds (``.<name>.partial-<pid>-<random>``)."""


def partial_folders(out_dir: Path) -> list[Path]:
    """The folders writers of ``out_dir``'s result sets left beside it (killed while writing)."""
    out_dir = Path(out_dir)
    return sorted(out_dir.parent.glob(f".{out_dir.name}{PARTIAL}*"))


def write_result_set(out_dir, write: Callable[[Path], dict[str, Path]],
                     names: Iterable[str] = ()) -> dict[str, Path]:
    """Write a result set into ``out_dir`` whole or not at all (module docstring).

    Args:
        out_dir: the folder the set goes to (created with its parents).
        write: ``write(folder) -> {key: path}`` writes the set's files directly into ``folder``.
        names: every file name a set of this kind may hold: those an earlier set left in
            ``out_dir`` that this one does not write are removed.
    Returns:
        ``{key: path}`` as ``write`` returned them, the paths in ``out_dir``.
    Raises:
        OutputError: the set could not be written (``out_dir`` keeps what it held).
    """
    out_dir = Path(out_dir)
    stage = out_dir.parent / f".{out_dir.name}{PARTIAL}{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        stage.mkdir()
        written = write(stage)
        for path in written.values():
            _sync(path)
        _sync(stage)
    except OSError as exc:
        shutil.rmtree(stage, ignore_errors=True)
        raise _output_error(exc, out_dir, stage) from None
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    try:
        if not out_dir.exists():
            os.rename(stage, out_dir)
        else:
            for path in written.values():
                os.replace(path, out_dir / path.name)
            produced = {path.name for path in written.values()}
            for name in set(names) - produced:
                (out_dir / name).unlink(missing_ok=True)
            shutil.rmtree(stage, ignore_errors=True)
        _sync(out_dir)
        _sync(out_dir.parent)
    except OSError as exc:
        shutil.rmtree(stage, ignore_errors=True)
        raise _output_error(exc, out_dir, stage) from None
    return {key: out_dir / path.name for key, path in written.items()}


def _sync(path: Path) -> None:
    """fsync a file or folder (a rename is durable once its folder is synced)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _output_error(exc: OSError, out_dir: Path, stage: Path) -> OutputError:
    """One line: the path in ``out_dir`` (not the stage's) and the cause."""
    path = Path(exc.filename) if exc.filename else out_dir
    if stage in path.parents or path == stage:
        path = out_dir / path.relative_to(stage)
    cause = exc.strerror or str(exc)
    if exc.errno in (errno_codes.ENOSPC, errno_codes.EDQUOT):
        cause += " (the disk is full)"
    kept = "keeps what it held" if out_dir.exists() else "was not created"
    return OutputError(f"cannot write {path}: {cause}; the result set was not written ({out_dir} {kept})",
                       path=path, errno=exc.errno)
