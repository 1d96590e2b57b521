"""The calibration bench (``bench/calibration.py``, ``dejaview bench calibration``): the truth's rank
among the posterior samples, and a short run whose coverage must be in a plausible band."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.cli.bench import bench_module


def test_one_case_ranks_the_truth_in_every_parameter():
    row = bench_module("calibration").run_case("ramp", 0, 64)
    assert row["parameters"] == ["position.x", "position.y"]
    assert len(row["ranks"]) == 2 and all(0.0 <= r <= 1.0 for r in row["ranks"])
    assert len(row["cover50"]) == len(row["cover90"]) == 2
    assert all(0 < s < 1 for s in row["sharpness"])  # the end taught something about the start
    assert 0.0 <= row["density_rank"] <= 1.0


def test_summary_counts_coverage_and_ranks():
    module = bench_module("calibration")
    rows = [{"cover50": [True, False], "cover90": [True, True], "ranks": [0.05, 0.95], "sharpness": [0.2, 0.4],
             "seconds": 1.0, "density_rank": 0.99},
            {"cover50": [False, False], "cover90": [True, False], "ranks": [0.5, 0.999], "sharpness": [0.1, 0.1],
             "seconds": 3.0, "density_rank": 0.3}]
    s = module.summarize(rows)
    assert s["cover50"] == 0.25 and s["cover90"] == 0.75 and s["n"] == 4
    assert s["histogram"] == [1, 0, 0, 0, 0, 1, 0, 0, 0, 2] and s["seconds"] == 2.0
    assert s["density_histogram"] == [0, 1, 0, 0, 1]
    assert module.verdict(s) == "missed"


def test_cli_rejects_an_unknown_scene():
    result = CliRunner().invoke(cli, ["bench", "calibration", "--scenes", "moon"])
    assert result.exit_code != 0 and "moon" in result.output


@pytest.mark.slow
def test_the_ramp_posterior_is_calibrated():
    """20 truths of the ramp (the end pins the start): pooled coverage of the central intervals in
    a band around the nominal 50 % and 90 % (40 binary outcomes: +-15 points is ~2 standard
    errors)."""
    rows = bench_module("calibration").run(print_fn=None, scenes=("ramp",), truths=20, samples=200)
    c50 = sum(c == "True" for r in rows for c in r["cover50"].split(",")) / 40
    c90 = sum(c == "True" for r in rows for c in r["cover90"].split(",")) / 40
    assert 0.35 <= c50 <= 0.65 and 0.75 <= c90 <= 1.0, (c50, c90)
