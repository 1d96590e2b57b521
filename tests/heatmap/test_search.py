"""compute_heatmap on bundled scenes with a known start, the written files, settings errors, the CLI.

The per-cell optimisation heatmap (``method="basins"``) is tested here; the posterior's marginal
(the default) in ``test_posterior.py``.

The ramp scenes are built for this: the source is let go at rest (velocities known,
only the start position free), so the observed end pins the start and the heatmap
must find it. Scenes whose velocities are free (ball_off_table) are explained from
many cells: their heatmaps are ridges, not peaks.
"""

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dejaview.errors import InferenceError
from dejaview.heatmap import compute_heatmap, read_ppm
from dejaview.scene import Scene

SCENES = Path(__file__).resolve().parents[2] / "examples" / "scenes"


def truth_xy(name):
    start = json.loads((SCENES / f"{name}.truth.json").read_text())["initial_state"]["position"]
    return start[0], start[1]


def check_peak(result, name):
    """The true start's cell is among the 10% most probable, and the mass is concentrated."""
    nx, ny = result.cells
    x, y = truth_xy(name)
    top = max(1, math.floor(0.1 * nx * ny))
    assert result.rank_of(x, y) < top, (result.probability[::-1], result.cell_of(x, y))
    assert result.entropy_bits() < 0.6 * math.log2(nx * ny)
    assert result.probability.sum() == pytest.approx(1.0)


@pytest.fixture(scope="module")
def ball_heatmap():
    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    progress = []
    result = compute_heatmap(scene, cells=(4, 5), samples=1, iterations=30, callback=progress.append,
                             method="basins")
    return result, progress


def test_ball_down_ramp_peaks_at_the_true_start(ball_heatmap):
    result, _ = ball_heatmap
    check_peak(result, "ball_down_ramp")
    assert result.best.loss < 0.02


def test_progress_reports_cells_and_both_phases(ball_heatmap):
    _, progress = ball_heatmap
    assert progress[0].cells_total == 20 and progress[0].iteration == 0
    assert [p.iteration for p in progress] == list(range(len(progress)))
    assert {p.phase for p in progress} == {"optimize", "robustness"}
    assert progress[-1].cells_done == 20
    best = [p.best_loss for p in progress]
    assert all(a >= b for a, b in zip(best, best[1:]))


def test_written_files_follow_the_spec(ball_heatmap, tmp_path):
    result, _ = ball_heatmap
    paths = result.write(tmp_path, truth=truth_xy("ball_down_ramp"))
    hm = json.loads((tmp_path / "heatmap.json").read_text())
    assert hm["cells"] == [4, 5] and hm["min"] == pytest.approx([-0.4, -0.25])
    assert hm["max"] == pytest.approx([0.0, 0.25])
    assert len(hm["probability"]) == 5 and all(len(r) == 4 for r in hm["probability"])
    assert sum(map(sum, hm["probability"])) == pytest.approx(1.0, abs=1e-9)
    rgb = read_ppm(tmp_path / "heatmap.ppm")
    assert rgb.shape == (5, 4, 3)
    # the most probable cell is the brightest pixel, with rows flipped (+y first)
    j, i = np.unravel_index(np.argmax(hm["probability"]), (5, 4))
    assert (rgb[4 - j, i] == rgb.reshape(-1, 3)[np.argmax(rgb.sum(-1))]).all()
    import matplotlib.image as mpimg

    assert mpimg.imread(paths["heatmap_png"]).ndim == 3
    res = json.loads((tmp_path / "result.json").read_text())
    assert res["source"] == "ball" and res["loss"] == pytest.approx(result.best.loss)
    assert res["heatmap"]["cells"] == [4, 5]
    assert (tmp_path / "trajectory.csv").read_text().startswith("step,time,object,")


@pytest.mark.slow
def test_box_down_ramp_peaks_at_the_true_start():
    scene = Scene.from_xml(SCENES / "box_down_ramp.xml")
    result = compute_heatmap(scene, cells=(4, 5), samples=1, iterations=30, workers=2)
    check_peak(result, "box_down_ramp")


def test_a_heatmap_needs_a_start_area_with_extent():
    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    with pytest.raises(InferenceError, match="start-area"):
        compute_heatmap(replace(scene, inference=replace(scene.inference, start_area=None)))
    flat = replace(scene.inference.start_area, max=(-0.4, 0.25, 0.55))
    with pytest.raises(InferenceError, match="x and y extent"):
        compute_heatmap(replace(scene, inference=replace(scene.inference, start_area=flat)))


@pytest.mark.parametrize("method", ["posterior", "basins"])
def test_a_start_area_that_cannot_hold_the_source_is_refused_before_any_work(method, monkeypatch):
    """Issue 56: a start area inside a desk; both methods refuse it before a problem is built (the
    posterior's through ``solve``), in one line naming the objects and the depth."""
    from dejaview.errors import StartAreaError

    def no_problem(*args, **kwargs):
        raise AssertionError("a problem was built for a start area that cannot hold the source")

    monkeypatch.setattr("dejaview.backends.BackendOptions.make_problem", no_problem)
    scene = Scene.from_xml(Path(__file__).resolve().parents[1] / "fixtures" / "inference" / "box_in_desk.xml")
    with pytest.raises(StartAreaError, match="cannot hold 'src': everywhere in it 'src' and 'desk' "
                                             "interpenetrate, by 0.0267 m") as err:
        compute_heatmap(scene, method=method, cells=(2, 2), samples=1)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("kw,match", [
    ({"cells": (0, 3)}, "cells"), ({"samples": 0}, "samples"), ({"sigma": -1.0}, "sigma"),
    ({"iterations": 0}, "iterations"), ({"optimizer": "newton"}, "unknown optimizer"),
    ({"radii": (0.2, 0.1)}, "ascending"), ({"gradient": "sideways"}, "gradient mode")])
def test_bad_settings_fail_with_one_line(kw, match):
    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    with pytest.raises(InferenceError, match=match) as err:
        compute_heatmap(scene, method="basins", **kw)
    assert "\n" not in str(err.value)


def test_stop_request_ends_the_run():
    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    with pytest.raises(InferenceError, match="stopped"):
        compute_heatmap(scene, cells=(2, 2), samples=1, iterations=50, should_stop=lambda: True)


def test_cli_heatmap_writes_the_files(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "hm"
    proc = subprocess.run([sys.executable, "-m", "dejaview", "heatmap", SCENES / "ball_down_ramp.xml",
                           "-o", out, "--cells", "2x2", "--samples", "1", "--iterations", "2",
                           "--workers", "1", "--method", "basins"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    for name in ("heatmap.ppm", "heatmap.png", "heatmap.json", "result.json", "trajectory.csv"):
        assert (out / name).is_file(), name
    assert "most probable cell" in proc.stdout
    bad = subprocess.run([sys.executable, "-m", "dejaview", "heatmap", SCENES / "ball_down_ramp.xml",
                          "-o", out, "--cells", "2by2"], capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and "NXxNY" in bad.stderr


def test_worker_processes_give_the_same_heatmap_as_one_process():
    scene = Scene.from_xml(SCENES / "ball_down_ramp.xml")
    kw = dict(cells=(2, 2), samples=2, iterations=2, radii=(0.01, 0.05), directions=2)
    one = compute_heatmap(scene, workers=1, method="basins", **kw)
    progress = []
    two = compute_heatmap(scene, workers=2, callback=progress.append, method="basins", **kw)
    np.testing.assert_allclose(two.probability, one.probability, rtol=1e-9, atol=1e-12)
    assert two.best.loss == pytest.approx(one.best.loss, rel=1e-9)
    assert progress[-1].cells_done == 4 and {p.chunk for p in progress} == {0, 1}
