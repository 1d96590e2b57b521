"""The default heatmap: the posterior's start-position marginal (``dejaview.heatmap.posterior``)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dejaview.errors import InferenceError
from dejaview.heatmap import compute_heatmap
from dejaview.heatmap.posterior import choose_method, credible_area
from dejaview.scene import Scene

SCENES = Path(__file__).resolve().parents[2] / "examples" / "scenes"


def truth_xy(name):
    start = json.loads((SCENES / f"{name}.truth.json").read_text())["initial_state"]["position"]
    return start[0], start[1]


@pytest.fixture(scope="module")
def ramp_16():
    progress = []
    result = compute_heatmap(Scene.from_xml(SCENES / "ball_down_ramp.xml"), cells=(16, 16),
                             callback=progress.append)
    return result, progress


def test_the_ramp_pins_its_start_on_a_16_by_16_grid(ramp_16):
    """Issue 20: the true start's cell among the 3 most probable, the 90 % credible region within
    10 % of the start area."""
    result, _ = ramp_16
    assert result.settings["method"] == "posterior" and result.candidates == 16 * 16 * 2
    assert result.probability.shape == (16, 16) and result.probability.sum() == pytest.approx(1.0)
    assert result.rank_of(*truth_xy("ball_down_ramp")) < 3, result.cell_of(*truth_xy("ball_down_ramp"))
    assert credible_area(result.probability, 0.9) <= 0.10


def test_progress_runs_from_search_to_sample(ramp_16):
    _, progress = ramp_16
    phases = [p.phase for p in progress]
    assert phases[0] == "search" and phases[-1] == "sample"
    done = [p.cells_done for p in progress]
    assert done == sorted(done) and done[-1] == 256 and progress[-1].cells_total == 256


def test_files_carry_the_posterior(ramp_16, tmp_path):
    result, _ = ramp_16
    paths = result.write(tmp_path, plot=False)
    grid = json.loads(paths["heatmap_json"].read_text())
    assert grid["cells"] == [16, 16] and np.isclose(sum(map(sum, grid["probability"])), 1.0)
    assert (tmp_path / "posterior.csv").is_file()
    res = json.loads(paths["result"].read_text())
    assert res["posterior"]["samples"] == 512 and res["heatmap"]["cells"] == [16, 16]


def test_credible_area_counts_the_most_probable_cells():
    p = np.array([[0.5, 0.3], [0.15, 0.05]])
    assert credible_area(p, 0.5) == 0.25 and credible_area(p, 0.8) == 0.5 and credible_area(p, 0.9) == 0.75


@pytest.mark.parametrize("method, optimizer, backend, expected", [
    (None, None, "spheres", "posterior"), (None, "auto", None, "posterior"),
    (None, "adam", "spheres", "basins"), (None, None, "warp", "basins"), ("basins", None, None, "basins")])
def test_the_method_follows_the_optimizer_and_backend(method, optimizer, backend, expected):
    assert choose_method(method, optimizer, backend) == expected


@pytest.mark.parametrize("kw, match", [
    ({"method": "votes"}, "unknown heatmap method"), ({"optimizer": "newton"}, "unknown optimizer"),
    ({"method": "posterior", "optimizer": "adam"}, "applies to the basins"),
    ({"lr": 0.1}, "applies to the basins"), ({"samples": 0}, "samples"), ({"sigma": -1.0}, "sigma"),
    ({"cells": (0, 2)}, "cells")])
def test_bad_settings_are_one_line_errors(kw, match):
    with pytest.raises(InferenceError, match=match) as err:
        compute_heatmap(Scene.from_xml(SCENES / "ball_down_ramp.xml"), **kw)
    assert "\n" not in str(err.value)


def test_cli_heatmap_defaults_to_the_posterior(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "dejaview", "heatmap", SCENES / "ball_down_ramp.xml", "-o",
                           tmp_path, "--cells", "4x4", "--samples", "8"], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "128 posterior samples over 4 x 4 cells" in proc.stdout and "credible region" in proc.stdout
    for name in ("heatmap.ppm", "heatmap.png", "heatmap.json", "result.json", "posterior.csv"):
        assert (tmp_path / name).is_file(), name
