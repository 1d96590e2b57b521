"""``dejaview.parallel.map_chunks``: the same results in order here, in processes and on Ray; progress,
cancellation and errors come back; without Ray, ``--ray`` is a one-line error naming the extra."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dejaview.parallel import ParallelError, map_chunks

ROOT = Path(__file__).resolve().parents[1]


def _setup(offset):
    return {"offset": offset}


def _square(context, chunk, report, stopped):
    report(("started", chunk))
    if chunk == "boom":
        raise ValueError("chunk 'boom' is bad")
    return chunk * chunk + context["offset"]


def _until_stopped(context, chunk, report, stopped):
    import time

    for _ in range(200):
        if stopped():
            return "stopped"
        time.sleep(0.01)
    return "ran"


@pytest.mark.parametrize("workers", [1, 2])
def test_results_come_back_in_order_with_progress(workers):
    reports, done = [], []
    out = map_chunks(_square, [3, 1, 2], setup=_setup, setup_args=(10,), workers=workers,
                     on_report=lambda i, m: reports.append((i, m)), on_done=lambda i, r: done.append(i))
    assert out == [19, 11, 14]
    assert sorted(reports) == [(0, ("started", 3)), (1, ("started", 1)), (2, ("started", 2))]
    assert sorted(done) == [0, 1, 2]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_worker_error_is_raised_here(workers):
    with pytest.raises(ValueError, match="chunk 'boom' is bad"):
        map_chunks(_square, [1, "boom"], setup=_setup, setup_args=(0,), workers=workers)


def _killed(context, chunk, report, stopped):
    import os
    import signal
    import time

    if chunk == "kill":
        time.sleep(0.5)  # the other chunk is under way
        os.kill(os.getpid(), signal.SIGKILL)  # as the out-of-memory killer would
    return chunk


def test_a_killed_worker_process_is_a_one_line_error():
    with pytest.raises(ParallelError, match=r"a worker process died .* while chunk \d of 2 ran") as err:
        map_chunks(_killed, ["kill", 1], workers=2)
    assert "\n" not in str(err.value)


def _reporting_sleeper(context, chunk, report, stopped):
    import time

    report("started")
    for _ in range(1000):
        if stopped():
            return "stopped"
        time.sleep(0.01)
    return "ran"


def _spawned_children() -> list[tuple[int, int]]:
    """(start time, pid) of this process's ``multiprocessing`` spawned children, oldest first."""
    import os

    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == os.getpid() and b"spawn_main" in cmdline:
            out.append((int(fields[19]), int(entry.name)))
    return sorted(out)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the manager process through /proc")
def test_a_killed_manager_process_is_a_one_line_error():
    """The manager process (first spawned) carries progress and the stop flag; killed, the run
    ends with one line instead of click's 'aborted' (an EOFError from the queue). Skipped where
    there is no /proc (not Linux): the test finds the manager process through it."""
    import os
    import signal

    def kill_manager(index, message):
        if index == 0:
            os.kill(_spawned_children()[0][1], signal.SIGKILL)

    with pytest.raises(ParallelError, match="the helper process that carries the workers' progress died"):
        map_chunks(_reporting_sleeper, [0, 1], workers=2, on_report=kill_manager)


def test_cancellation_reaches_the_workers():
    out = map_chunks(_until_stopped, [0, 1], workers=2, should_stop=lambda: True)
    assert out == ["stopped", "stopped"]
    assert map_chunks(_until_stopped, [0, 1, 2], should_stop=lambda: True) == ["stopped"]  # the rest skipped


def test_bad_workers_are_refused():
    with pytest.raises(ParallelError, match="workers must be a positive integer"):
        map_chunks(_square, [1], workers=0)


def test_without_ray_the_cli_says_to_install_the_extra(tmp_path):
    """Ray hidden (a None entry in sys.modules makes ``import ray`` fail): one line naming the extra."""
    code = ("import sys; sys.modules['ray'] = None; from dejaview.cli import main; "
            f"main(['heatmap', {str(ROOT / 'examples/scenes/ball_down_ramp.xml')!r}, '-o', {str(tmp_path)!r}, "
            "'--ray', 'local', '--cells', '2x2', '--samples', '1', '--iterations', '1'])")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "error: --ray needs Ray, which is not installed: pip install 'dejaview[ray]'"


@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray", reason="Ray is the test extra's (pip install -e '.[test]')")
    import os

    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", log_to_driver=False,
             configure_logging=False)
    yield ray
    ray.shutdown()


def test_ray_runs_the_chunks_like_processes(local_ray):
    reports = []
    out = map_chunks(_square, [3, 1, 2], setup=_setup, setup_args=(10,), workers=2, ray="local",
                     on_report=lambda i, m: reports.append((i, m)))
    assert out == [19, 11, 14] and sorted(reports)[0] == (0, ("started", 3))
    with pytest.raises(ValueError, match="chunk 'boom' is bad"):
        map_chunks(_square, [1, "boom"], setup=_setup, setup_args=(0,), workers=2, ray="local")
    assert map_chunks(_until_stopped, [0, 1], workers=2, ray="local", should_stop=lambda: True) == \
        ["stopped", "stopped"]


def test_ray_heatmap_equals_the_local_heatmap(local_ray):
    from dejaview.heatmap import compute_heatmap
    from dejaview.scene import Scene

    scene = Scene.from_xml(ROOT / "examples" / "scenes" / "ball_down_ramp.xml")
    kw = dict(cells=(2, 2), samples=2, iterations=2, radii=(0.01, 0.05), directions=2)
    here = compute_heatmap(scene, workers=1, method="basins", **kw)  # ray distributes the basins method
    progress = []
    on_ray = compute_heatmap(scene, workers=2, ray="local", callback=progress.append, **kw)
    assert on_ray.settings.get("method", "basins") == "basins"
    np.testing.assert_allclose(on_ray.probability, here.probability, rtol=0, atol=1e-6)
    assert on_ray.best.loss == pytest.approx(here.best.loss, rel=1e-6)
    assert progress[-1].cells_done == 4 and {p.chunk for p in progress} == {0, 1}
