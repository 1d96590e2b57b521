"""Building the native extension never hangs: stale locks are taken over, waits time out with one
line naming the lock, and a build killed half-way (SIGKILL) does not block the next one.

The kill tests build a tiny pybind11 module through the same code path as ``rollout.cpp``
(``dejaview.sim.native.loader``), so they take seconds; the last one kills the real CLI while it
compiles the real simulator, as a user would (about a minute: it compiles rollout.cpp twice)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from dejaview.errors import SimulationError
from dejaview.sim.native import loader
from dejaview.sim.native.loader import BuildLock, build_key, roots

REPO = Path(__file__).resolve().parents[2]
TINY = """
#include <pybind11/pybind11.h>
int answer() { return 42; }
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def("answer", &answer); }
"""


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("DEJAVIEW_NATIVE_DIR", "TORCH_EXTENSIONS_DIR")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH")) if p)
    env.update(extra)
    return env


def _python(code: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, **kw)


def _hold_lock(path: Path) -> subprocess.Popen:
    """A live process holding the build lock ``path`` until killed."""
    proc = _python(f"""
        import time
        from dejaview.sim.native.loader import BuildLock
        with BuildLock({str(path)!r}, timeout=5):
            print("held", flush=True)
            time.sleep(300)
        """, env=_env())
    assert proc.stdout.readline().strip() == "held", proc.stderr.read()
    return proc


def _end(proc: subprocess.Popen) -> None:
    """SIGKILL the process group we started (the killed builder's orphaned ninja and g++ too)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(timeout=30)


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_lock_file_left_by_a_dead_process_is_taken_over(tmp_path):
    lock = tmp_path / "x.lock"
    dead = _dead_pid()
    lock.write_text(f"{dead}\n")
    start = time.monotonic()
    with BuildLock(lock, timeout=30) as held:
        assert time.monotonic() - start < 5
        assert held.took_over == dead
        assert lock.read_text() == f"{os.getpid()}\n"
    assert not lock.exists()


def test_waiting_on_a_live_holder_ends_in_one_line_naming_the_lock(tmp_path):
    lock = tmp_path / "x.lock"
    holder = _hold_lock(lock)
    try:
        with pytest.raises(SimulationError) as err:
            with BuildLock(lock, timeout=0.5):
                pass
        message = str(err.value)
        assert "\n" not in message and str(lock) in message and f"PID {holder.pid}" in message
        os.kill(holder.pid, signal.SIGKILL)  # dies holding it: the lock file stays behind
        holder.wait(timeout=30)
        assert lock.read_text().strip() == str(holder.pid)
        with BuildLock(lock, timeout=30) as held:
            assert held.took_over == holder.pid
    finally:
        _end(holder)


def test_the_build_timeout_setting(monkeypatch):
    monkeypatch.delenv("DEJAVIEW_NATIVE_BUILD_TIMEOUT", raising=False)
    assert loader.build_timeout() == loader.BUILD_TIMEOUT_S
    monkeypatch.setenv("DEJAVIEW_NATIVE_BUILD_TIMEOUT", "2.5")
    assert loader.build_timeout() == 2.5
    for bad in ("0", "-1", "soon", "nan"):
        monkeypatch.setenv("DEJAVIEW_NATIVE_BUILD_TIMEOUT", bad)
        with pytest.raises(SimulationError, match="DEJAVIEW_NATIVE_BUILD_TIMEOUT"):
            loader.build_timeout()


def test_different_sources_and_flags_never_share_a_build_folder(tmp_path):
    a, b = tmp_path / "a.cpp", tmp_path / "b.cpp"
    a.write_text(TINY)
    b.write_text(TINY + "// changed\n")
    assert build_key(a, ["-O3"]) == build_key(a, ["-O3"])
    assert len({build_key(a, ["-O3"]), build_key(b, ["-O3"]), build_key(a, ["-O2"])}) == 3
    root = tmp_path / "root"
    assert loader.build_folder("m", a, [], root) != loader.build_folder("m", b, [], root)
    assert loader.build_folder("m", a, [], root).parent == root


def test_where_builds_go(monkeypatch, tmp_path):
    monkeypatch.setenv("DEJAVIEW_NATIVE_DIR", str(tmp_path / "mine"))
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "torch"))
    assert roots() == [tmp_path / "mine"]
    monkeypatch.delenv("DEJAVIEW_NATIVE_DIR")
    assert roots() == [tmp_path / "torch"]  # the user's torch setting is honoured
    monkeypatch.delenv("TORCH_EXTENSIONS_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    found = roots()
    assert found[-1] == tmp_path / "cache" / "dejaview" / "native"
    if sys.prefix != sys.base_prefix:  # in a virtual environment: its own folder first
        assert found[0] == Path(sys.prefix) / "share" / "dejaview" / "native"


def _wait_for_build_started(root: Path, pid: int, timeout: float = 120) -> Path:
    """The builder's private folder, once ninja has been handed the build (g++ is running)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for tmp in root.glob(f".*.build-{pid}"):
            if (tmp / "build.ninja").exists():
                return tmp
        time.sleep(0.02)
    raise AssertionError(f"no build started under {root} in {timeout} s")


def test_a_build_killed_mid_way_does_not_block_the_next(tmp_path):
    source = tmp_path / "tiny.cpp"
    source.write_text(TINY)
    root = tmp_path / "builds"
    env = _env(DEJAVIEW_NATIVE_DIR=str(root))
    load = f"""
        from dejaview.sim.native.loader import load_extension
        m = load_extension("dv_tiny", {str(source)!r}, [], timeout=240)
        print(m.answer(), m.__file__, flush=True)
        """
    first = _python(load, env=env)
    try:
        _wait_for_build_started(root, first.pid)
        os.kill(first.pid, signal.SIGKILL)  # the builder only, as the OOM killer would
        first.wait(timeout=30)
        locks = list(root.glob("*.lock"))
        assert [p.read_text().strip() for p in locks] == [str(first.pid)]  # left behind
        second = subprocess.run([sys.executable, "-c", textwrap.dedent(load)], env=env, capture_output=True,
                                text=True, timeout=300)
        assert second.returncode == 0, second.stderr
        answer, path = second.stdout.split()
        assert answer == "42" and Path(path).parent == loader.build_folder("dv_tiny", source, [], root)
        assert not list(root.glob("*.lock"))
        # a finished build loads without the lock, even while a live process holds it
        holder = _hold_lock(locks[0])
        try:
            third = subprocess.run([sys.executable, "-c", textwrap.dedent(load)], env=env,
                                   capture_output=True, text=True, timeout=60)
            assert third.returncode == 0 and third.stdout.split() == [answer, path], third.stderr
        finally:
            _end(holder)
    finally:
        _end(first)


@pytest.mark.slow
def test_killing_the_first_cli_run_while_it_compiles_does_not_hang_the_next(tmp_path):
    """The issue's report: ``dejaview simulate`` killed (SIGKILL) while it compiles the native
    simulator on first use; the next run with the same extension folder must finish (two builds of
    the real engine, 110 s: slow; the default run kills a tiny module's build above)."""
    root = tmp_path / "ext"
    env = _env(TORCH_EXTENSIONS_DIR=str(root))
    scene = REPO / "examples" / "scenes" / "ball_off_table.xml"
    cmd = [sys.executable, "-m", "dejaview", "simulate", str(scene), "--engine", "native", "--quiet"]
    first = subprocess.Popen([*cmd, "-o", str(tmp_path / "o1")], env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        _wait_for_build_started(root, first.pid, timeout=300)
        time.sleep(2)
        os.kill(first.pid, signal.SIGKILL)
        first.wait(timeout=30)
        second = subprocess.run([*cmd, "-o", str(tmp_path / "o2")], env=env, capture_output=True, text=True,
                                timeout=600)
        assert second.returncode == 0, second.stderr
        assert (tmp_path / "o2" / "trajectory.csv").read_text().startswith("step,time,object")
    finally:
        _end(first)


@pytest.mark.slow  # four builds, 27 s; the build folder keyed by source and flags: test_different_sources_and_flags_never_share_a_build_folder
def test_two_installs_sharing_a_folder_keep_their_own_builds(tmp_path):
    """Two checkouts with different sources and one extension folder (TORCH_EXTENSIONS_DIR shared):
    each build gets its own folder, so neither rebuilds the other's."""
    root = tmp_path / "shared"
    env = _env(TORCH_EXTENSIONS_DIR=str(root))
    sources = []
    for i in range(2):
        src = tmp_path / f"install{i}" / "tiny.cpp"
        src.parent.mkdir()
        src.write_text(TINY.replace("42", str(42 + i)))
        sources.append(src)
    code = """
        import sys
        from dejaview.sim.native.loader import load_extension
        m = load_extension("dv_tiny", sys.argv[1], [], timeout=240)
        print(m.answer(), m.__file__)
        """
    paths = []
    for i, src in enumerate(sources + sources):  # A, B, then A and B again: loaded, not rebuilt
        out = subprocess.run([sys.executable, "-c", textwrap.dedent(code), str(src)], env=env, capture_output=True,
                             text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        answer, path = out.stdout.split()
        assert answer == str(42 + i % 2)
        paths.append((path, Path(path).stat().st_mtime_ns))
    assert paths[0] == paths[2] and paths[1] == paths[3] and paths[0][0] != paths[1][0]
    assert sorted(p.name for p in root.iterdir()) == sorted(Path(p).parent.name for p, _ in paths[:2])
