"""Smoke tests of the backend comparison (``bench/backends.py``, ``dejaview bench backends``):
tiny iteration counts, no timing assertions."""

from __future__ import annotations

import csv
import math

import pytest
from click.testing import CliRunner

from dejaview.backends import warp_available
from dejaview.cli import cli
from dejaview.cli.bench import bench_module, command

needs_warp = pytest.mark.skipif(not warp_available(),
                                reason="the warp extra is not installed: pip install 'dejaview[warp]'")


@needs_warp
def test_rows_of_both_backends_and_their_ratio(tmp_path):
    path = tmp_path / "backends.csv"
    rows = bench_module("backends").run(print_fn=None, iterations=(1, 2), optimizers=("lbfgs",),
                                        csv_path=path)
    runs = [r for r in rows if r["backend"] != "warp/spheres"]
    assert [(r["optimizer"], r["backend"]) for r in runs] == [("lbfgs", "spheres"), ("lbfgs", "warp")]
    for row in runs:
        assert row["iterations"] == 2 and row["params"] == 11
        assert row["best_loss_2"] <= row["best_loss_1"] and math.isfinite(row["best_loss_2"])
        assert row["s_per_iteration"] > 0 and row["evaluations_per_iteration"] >= 1
    ratios = [r for r in rows if r["backend"] == "warp/spheres"]
    assert [r["optimizer"] for r in ratios] == ["lbfgs", "all"]
    assert all(r["s_per_iteration"] > 0 and r["s_per_evaluation"] > 0 for r in ratios)
    with open(path, newline="", encoding="utf-8") as fh:
        read = list(csv.DictReader(fh))
    assert len(read) == len(rows) and read[-1]["optimizer"] == "all"


def test_cli_spheres_only(tmp_path):
    path = tmp_path / "out.csv"
    result = CliRunner().invoke(command, ["backends", "--iterations", "1", "--optimizers", "adam",
                                          "--backends", "spheres", "--csv", str(path)])
    assert result.exit_code == 0, result.output
    assert "adam" in result.output and "best@1" in result.output and "warp / spheres" not in result.output
    with open(path, newline="", encoding="utf-8") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["backend"] == "spheres" and math.isfinite(float(row["best_loss_1"]))


def test_cli_help_and_bad_lists():
    result = CliRunner().invoke(cli, ["bench", "backends", "--help"])
    assert result.exit_code == 0
    for option in ("--iterations", "--scene", "--backends", "--optimizers", "--integrator", "--quick", "--csv"):
        assert option in result.output
    result = CliRunner().invoke(command, ["backends", "--backends", "bullet"])
    assert result.exit_code == 2 and "spheres, warp" in result.output
