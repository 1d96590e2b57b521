"""Build and load a C++ extension into a folder of this install, without ever hanging.

torch's ``cpp_extension.load`` builds into one folder per extension name in a cache shared by
every install on the machine (``~/.cache/torch_extensions``), guarded by a ``lock`` file that a
process killed during the build leaves behind: every later process then waits on it forever,
and two installs with different sources rebuild each other's extension. Here instead:

- **where**: ``ROOT/<name>-<key>/``, ``key`` a hash of the source text, torch's version, the
  Python ABI, the compiler and its flags and the CPU (the flags include ``-march=native``).
  Different sources never share a folder; the same source on the same machine may (the
  build is the same). ``ROOT`` is ``DEJAVIEW_NATIVE_DIR`` or ``TORCH_EXTENSIONS_DIR`` when
  set, else the virtual environment (``sys.prefix/share/dejaview/native``; ``scripts/setup``
  builds there), else ``~/.cache/dejaview/native`` (a read-only install: the builds already
  in the environment are still used).
- **complete or absent**: a build runs in ``ROOT/.<name>-<key>.build-<pid>/`` and is renamed
  to its folder when done, so a folder that exists holds a whole build and is loaded without
  any lock; a build killed half-way leaves only its private temporary folder (removed by the
  next build).
- **one build at a time, never a hang**: builders take ``ROOT/<name>-<key>.lock`` with
  ``flock``, which the kernel releases when its holder dies (SIGKILL, OOM kill included): a
  lock whose owner is gone is taken over at once. The holder writes its PID into the file.
  A waiter gives up after ``build_timeout()`` seconds with a one-line error naming the lock
  file and the PID that holds it.
"""

from __future__ import annotations

import errno
import hashlib
import importlib.util
import os
import platform
import shutil
import sys
import sysconfig
import time
from pathlib import Path

from dejaview.errors import SimulationError

BUILD_TIMEOUT_S = 900.0
"""Longest wait for another process's build of the same extension (``DEJAVIEW_NATIVE_BUILD_TIMEOUT``
overrides it); a build alone takes about a minute with g++ on one core."""

WAIT_NOTICE_S = 3.0
"""A process that waits this long for another's build says so on stderr, once."""


def build_timeout() -> float:
    """Seconds to wait for another process's build: ``DEJAVIEW_NATIVE_BUILD_TIMEOUT`` or
    ``BUILD_TIMEOUT_S``."""
    value = os.environ.get("DEJAVIEW_NATIVE_BUILD_TIMEOUT")
    if not value:
        return BUILD_TIMEOUT_S
    try:
        seconds = float(value)
    except ValueError:
        seconds = float("nan")
    if not seconds > 0:  # nan included
        raise SimulationError(f"DEJAVIEW_NATIVE_BUILD_TIMEOUT must be a positive number of seconds, "
                              f"got {value!r}")
    return seconds


def _cpu_signature() -> str:
    """The CPU's model and feature flags (code built with ``-march=native`` runs only there)."""
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return platform.processor()
    keep = [ln for ln in text.splitlines() if ln.split(":")[0].strip() in ("model name", "flags", "Features")]
    return "\n".join(dict.fromkeys(keep))  # once per distinct line, not per core


def build_key(source: Path, cflags: list[str]) -> str:
    """16 hex digits naming a build of ``source`` (and the headers beside it) with ``cflags`` for this
    Python, torch and CPU."""
    import torch

    h = hashlib.sha256(Path(source).read_bytes())
    for header in sorted(Path(source).parent.glob("*.h")):  # the headers it includes (schema.h, ...)
        h.update(b"\0" + header.name.encode() + b"\0" + header.read_bytes())
    for part in (torch.__version__, str(getattr(torch.version, "git_version", "")),
                 sys.implementation.cache_tag, str(sysconfig.get_config_var("SOABI")), platform.machine(),
                 os.environ.get("CXX", "c++"), " ".join(cflags), _cpu_signature()):
        h.update(b"\0" + part.encode())
    return h.hexdigest()[:16]


def _default_root() -> Path:
    """The install's own folder: the virtual (or conda) environment when there is one."""
    prefix = Path(sys.prefix)
    if sys.prefix != sys.base_prefix or (prefix / "conda-meta").is_dir():
        return prefix / "share" / "dejaview" / "native"
    return _user_root()


def _user_root() -> Path:
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "dejaview" / "native"


def roots() -> list[Path]:
    """Folders searched for a build, in order; new builds go into the first writable one."""
    for var in ("DEJAVIEW_NATIVE_DIR", "TORCH_EXTENSIONS_DIR"):
        if os.environ.get(var):
            return [Path(os.environ[var]).expanduser()]
    first = _default_root()
    user = _user_root()
    return [first] if first == user else [first, user]


def _writable(root: Path) -> bool:
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(root, os.W_OK | os.X_OK)


def _module_file(folder: Path, name: str) -> Path | None:
    found = sorted(folder.glob(f"{name}*.so")) + sorted(folder.glob(f"{name}*.pyd"))
    return found[0] if found else None


def _import(path: Path):
    """Import the extension module in ``path`` (its init function is named after the file)."""
    name = path.name.split(".")[0]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"not a Python extension: {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def _read_pid(path: Path) -> int | None:
    try:
        text = path.read_text().split()
        return int(text[0]) if text else None
    except (OSError, ValueError):
        return None


class BuildLock:
    """An exclusive lock on ``path`` held with ``flock``: released by the kernel when the holder
    dies, so a lock file left by a killed process is taken over at once (its PID, read from the
    file, is gone). The holder writes its PID into the file and removes the file when done.

    ``timeout`` seconds of waiting for a live holder end in a one-line ``SimulationError``
    naming the lock file and the holder's PID. Where the file system has no ``flock``, the
    lock is a no-op (callers must be correct without it: builds here are atomic renames).
    """

    def __init__(self, path: Path, timeout: float, what: str = "the native simulator build"):
        self.path = Path(path)
        self.timeout = timeout
        self.what = what
        self.fd: int | None = None
        self.took_over: int | None = None  # PID of a dead holder whose lock file was taken over

    def __enter__(self) -> "BuildLock":
        try:
            import fcntl
        except ImportError:
            return self
        start = time.monotonic()
        told = False
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                waited = time.monotonic() - start
                holder = _read_pid(self.path)
                if waited >= self.timeout:
                    who = f"PID {holder}" if holder is not None else "another process"
                    raise SimulationError(
                        f"gave up waiting for {self.what} after {waited:.0f} s: {self.path} is held by "
                        f"{who}{'' if holder is None or _pid_alive(holder) else ' (gone)'}; if that "
                        f"process is stuck, end it (DEJAVIEW_NATIVE_BUILD_TIMEOUT sets the wait)") from None
                if not told and waited >= WAIT_NOTICE_S:
                    told = True
                    print(f"dejaview: waiting for {self.what} in PID {holder} (lock {self.path})",
                          file=sys.stderr, flush=True)
                time.sleep(0.2)
                continue
            except OSError as exc:  # a file system without locks
                os.close(fd)
                if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                    return self
                raise
            try:  # the previous holder may have removed the file between our open and flock
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            previous = _read_pid(self.path)
            if previous is not None and previous != os.getpid():
                self.took_over = previous  # its owner is gone: the kernel dropped its flock
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            self.fd = fd
            return self

    def __exit__(self, *exc) -> None:
        if self.fd is None:
            return
        try:
            os.unlink(self.path)  # while still holding it: waiters re-check the inode
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None


def _clean_stale(root: Path, stem: str) -> None:
    """Remove temporary build folders of ``stem`` left by processes that are gone."""
    for tmp in root.glob(f".{stem}.build-*"):
        try:
            pid = int(tmp.name.rsplit("-", 1)[1])
        except ValueError:
            continue
        if pid != os.getpid() and not _pid_alive(pid):
            shutil.rmtree(tmp, ignore_errors=True)


def _compile(name: str, source: Path, cflags: list[str], folder: Path):
    """torch's builder (ninja) in ``folder``; returns the imported module."""
    from torch.utils.cpp_extension import load

    _ninja_on_path()
    return load(name=name, sources=[str(source)], extra_cflags=list(cflags), build_directory=str(folder),
                verbose=False)


def _ninja_on_path() -> None:
    """torch's builder runs ``ninja`` from PATH: add the ``ninja`` package's binary folder (a
    virtual environment's ``bin`` is not on PATH unless activated)."""
    try:
        import ninja
    except ImportError:
        return
    folder = getattr(ninja, "BIN_DIR", None)
    path = os.environ.get("PATH", "")
    if folder and folder not in path.split(os.pathsep):
        os.environ["PATH"] = os.pathsep.join(p for p in (folder, path) if p)


def build_folder(name: str, source: Path, cflags: list[str], root: Path | None = None) -> Path:
    """Where the build of ``source`` lives (or will), under ``root`` (default: the first of
    ``roots()``)."""
    return (root or roots()[0]) / f"{name}-{build_key(source, cflags)}"


def load_extension(name: str, source: Path, cflags: list[str], *, timeout: float | None = None):
    """The extension module built from ``source``: loaded from the first root holding a finished
    build, else built (once across processes) into the first writable root.

    Raises:
        SimulationError: no writable root, a wait on another build over ``timeout`` seconds
            (default ``build_timeout()``), or a finished build that does not load.
        Exception: whatever the compiler step raised (the caller turns it into one line).
    """
    source = Path(source)
    stem = f"{name}-{build_key(source, cflags)}"
    candidates = roots()
    for root in candidates:
        found = _ready(root / stem, name)
        if found is not None:
            return found
    root = next((r for r in candidates if _writable(r)), None)
    if root is None:
        raise SimulationError("no writable folder to build the native simulator in (tried "
                              + ", ".join(str(r) for r in candidates) + "); set DEJAVIEW_NATIVE_DIR")
    final = root / stem
    with BuildLock(root / f"{stem}.lock", build_timeout() if timeout is None else timeout):
        found = _ready(final, name)  # built by the holder we waited for
        if found is not None:
            return found
        _clean_stale(root, stem)
        tmp = root / f".{stem}.build-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        if sys.stderr.isatty():
            print(f"dejaview: compiling the native simulator (first use, about a minute) in {final}",
                  file=sys.stderr, flush=True)
        try:
            module = _compile(name, source, cflags, tmp)
            for leftover in tmp.iterdir():  # the loaded module is all a later process needs
                if leftover.suffix not in (".so", ".pyd"):
                    shutil.rmtree(leftover) if leftover.is_dir() else leftover.unlink()
            try:
                tmp.rename(final)
                module.__file__ = str(final / Path(module.__file__).name)
            except OSError:  # a lockless builder finished first: same build, keep theirs
                pass
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return module


def _ready(folder: Path, name: str):
    """The module of a finished build in ``folder``, or None when there is none."""
    path = _module_file(folder, name) if folder.is_dir() else None
    if path is None:
        return None
    try:
        return _import(path)
    except (ImportError, OSError) as exc:
        raise SimulationError(f"the native simulator built in {folder} does not load ({exc}); "
                              f"delete that folder to rebuild it") from None
