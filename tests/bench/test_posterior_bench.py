"""The posterior bench (``bench/posterior.py``, ``dejaview bench posterior``): its wiring, parsing and
verdicts, with a stand-in for the solve (a real one takes minutes: ``dejaview bench posterior``)."""

from __future__ import annotations

import csv

import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.cli.bench import bench_module


def _result(rhat: float) -> dict:
    """A ``result.json`` as a solve with --samples writes it, cut to what the bench reads."""
    return {"search": {"rollouts": 5000, "jacobians": 120},
            "posterior": {"sampler": {"rollouts": 20000, "stages": 12, "particles": 600, "seconds": 9.0},
                          "agreement": {"max_rhat": rhat, "limit": 1.1, "runs_agree": rhat <= 1.1},
                          "intervals": {"position.x": {"rhat": 1.01}, "angular_velocity.y": {"rhat": rhat}},
                          "modes": [{"probability": 0.75}, {"probability": 0.25}]}}


def test_a_result_becomes_a_row_with_the_worst_parameter():
    row = bench_module("posterior").row_from_result(_result(1.3))
    assert row["search_rollouts"] == 5000 and row["sampler_rollouts"] == 20000 and row["stages"] == 12
    assert row["max_rhat"] == 1.3 and row["worst_parameter"] == "angular_velocity.y"
    assert row["modes"] == "0.750;0.250"


@pytest.mark.parametrize("rhat, seconds, met", [(1.05, 20.0, True), (1.3, 20.0, False), (1.05, 45.0, False)])
def test_both_targets_decide_the_verdict(rhat, seconds, met):
    module = bench_module("posterior")
    row = {"seconds": seconds, **module.row_from_result(_result(rhat))}
    assert module.verdict(row) is met


def test_scenes_parse_with_their_sample_counts():
    module = bench_module("posterior")
    assert module.parse_scenes("mug_off_counter, box_tossed_tracked:300") == (
        ("mug_off_counter", 500), ("box_tossed_tracked", 300))
    for bad in ("", "moon", "mug_off_counter:0", "mug_off_counter:x"):
        with pytest.raises(ValueError):
            module.parse_scenes(bad)


def test_cli_runs_every_scene_and_seed_and_writes_csv(tmp_path, monkeypatch):
    module = bench_module("posterior")
    calls = []

    def fake(name, samples, seed):
        calls.append((name, samples, seed))
        row = {"scene": name, "samples": samples, "seed": seed, "seconds": 12.0, "cpu_seconds": 20.0,
               **module.row_from_result(_result(1.02 if seed == 0 else 1.4))}
        row["met"] = module.verdict(row)
        return row

    monkeypatch.setattr(module, "solve_once", fake)
    out = tmp_path / "posterior.csv"
    result = CliRunner().invoke(cli, ["bench", "posterior", "--scenes", "mug_off_counter:50", "--seeds", "0,1",
                                      "--csv", str(out), "--check"])
    assert calls == [("mug_off_counter", 50, 0), ("mug_off_counter", 50, 1)]
    assert result.exit_code == 1, result.output  # --check: seed 1's runs disagree
    assert "1 of 2 solves met both targets" in result.output
    assert "1.400 (angular_velocity.y)" in result.output
    rows = list(csv.DictReader(open(out, encoding="utf-8")))
    assert [r["seed"] for r in rows] == ["0", "1"] and rows[0]["met"] == "True"


def test_cli_rejects_bad_seeds_and_scenes():
    for args in (["--seeds", "x"], ["--seeds", "-1"], ["--scenes", "moon"]):
        result = CliRunner().invoke(cli, ["bench", "posterior", *args])
        assert result.exit_code == 2, (args, result.output)
