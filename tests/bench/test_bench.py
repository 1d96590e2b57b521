"""Smoke tests of the benchmarks: quick modes and tiny iteration counts, no timing assertions."""

from __future__ import annotations

import csv
import math

import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.cli.bench import bench_module, command
from dejaview.cli.bench_table import write_rows_csv

ROW_KEYS = {"section", "name", "batch", "mode", "value", "unit"}


def assert_finite_numbers(row: dict) -> None:
    for key, value in row.items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            assert math.isfinite(value), (key, row)


@pytest.fixture(scope="module")
def sim_rows():
    return bench_module("sim").run(print_fn=None, quick=True)


def test_sim_quick_returns_every_section(sim_rows):
    assert {r["section"] for r in sim_rows} == {"rollout", "loss+grad", "check", "memory", "target"}
    for row in sim_rows:
        assert ROW_KEYS <= set(row), row
        assert_finite_numbers(row)
        if row["value"] is None:
            assert row["note"], row
    rollout = [r for r in sim_rows if r["section"] == "rollout"]
    assert [(r["engine"], r["batch"]) for r in rollout] == [("torch", 1), ("torch", 4), ("native", 1),
                                                            ("native", 4)]
    assert all(r["value"] > 0 and r["per_candidate_s"] > 0 for r in rollout)
    for engine in ("torch", "native"):
        timed = [r for r in sim_rows if r["section"] == "loss+grad" and r["value"] is not None
                 and r["engine"] == engine]
        assert {(r["mode"], r["batch"]) for r in timed} == {("forward", 1), ("forward", 4), ("reverse", 1),
                                                            ("reverse", 4)}
    compiled = [r for r in sim_rows if r["section"] == "loss+grad" and r["value"] is None]
    assert {r["mode"] for r in compiled} == {"forward", "reverse"}
    memory = [r for r in sim_rows if r["section"] == "memory"]
    assert {r["checkpoint_every"] > 0 for r in memory} == {True, False}
    assert {r["engine"] for r in memory} == {"torch", "native"}
    assert all(r["value"] >= 0 for r in memory)
    targets = [r for r in sim_rows if r["section"] == "target"]
    assert len(targets) == 2 and all(isinstance(r["met"], bool) for r in targets)


def test_sim_forward_and_reverse_gradients_agree(sim_rows):
    checks = {r["name"]: r["value"] for r in sim_rows if r["section"] == "check"}
    assert set(checks) == {"forward vs reverse gradient", "native forward vs eager reverse gradient",
                           "native reverse vs eager reverse gradient"}
    assert all(value < 1e-6 for value in checks.values()), checks


def test_sim_rows_write_a_parseable_csv(sim_rows, tmp_path):
    path = write_rows_csv(sim_rows, tmp_path / "sim.csv")
    with open(path, newline="", encoding="utf-8") as fh:
        read = list(csv.DictReader(fh))
    assert len(read) == len(sim_rows)
    assert ROW_KEYS <= set(read[0])
    assert all(math.isfinite(float(r["value"])) for r in read if r["value"])


def test_optimizers_rows_and_csv(tmp_path):
    path = tmp_path / "optimizers.csv"
    rows = bench_module("optimizers").run(print_fn=None, iterations=(1, 2), modes=("forward", "reverse"),
                                          optimizers=("gd", "lbfgs"), csv_path=path)
    assert [(r["optimizer"], r["mode"]) for r in rows] == [
        ("gd", "forward"), ("gd", "reverse"), ("lbfgs", "forward"), ("lbfgs", "reverse")]
    for row in rows:
        assert {"optimizer", "mode", "params", "iterations", "best_loss_1", "best_loss_2",
                "final_best_loss", "ms_per_iteration", "evaluations_per_iteration", "ms_per_evaluation",
                "idle_iterations"} <= set(row)
        assert_finite_numbers(row)
        assert row["iterations"] == 2 and row["params"] == 11
        assert row["best_loss_2"] <= row["best_loss_1"]
        assert row["evaluations_per_iteration"] >= 1
    with open(path, newline="", encoding="utf-8") as fh:
        read = list(csv.DictReader(fh))
    assert [(r["optimizer"], r["mode"]) for r in read] == [(r["optimizer"], r["mode"]) for r in rows]
    assert all(math.isfinite(float(r["best_loss_2"])) for r in read)


def test_cli_optimizers_writes_csv(tmp_path):
    path = tmp_path / "out.csv"
    result = CliRunner().invoke(command, ["optimizers", "--iterations", "1", "--optimizers", "adam",
                                          "--modes", "reverse", "--csv", str(path)])
    assert result.exit_code == 0, result.output
    assert "adam" in result.output and "best@1" in result.output
    with open(path, newline="", encoding="utf-8") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["optimizer"] == "adam" and math.isfinite(float(row["best_loss_1"]))


def test_cli_packing_writes_csv(tmp_path):
    path = tmp_path / "packing.csv"
    result = CliRunner().invoke(command, ["packing", "--max-spheres", "4", "--csv", str(path)])
    assert result.exit_code == 0, result.output
    with open(path, newline="", encoding="utf-8") as fh:
        read = list(csv.DictReader(fh))
    assert [r["name"] for r in read][-1] == "all"
    assert all(math.isfinite(float(r["seconds"])) for r in read[:-1])


@pytest.mark.parametrize("args, options", [
    ([], ["sim", "packing", "optimizers"]),
    (["sim"], ["--quick", "--compile", "--csv", "--check"]),
    (["packing"], ["--max-spheres", "--csv", "--check"]),
    (["optimizers"], ["--iterations", "--scene", "--optimizers", "--modes", "--quick", "--csv"]),
    (["posterior"], ["--scenes", "--seeds", "--csv", "--check"]),
])
def test_cli_help(args, options):
    result = CliRunner().invoke(cli, ["bench", *args, "--help"])
    assert result.exit_code == 0, result.output
    for option in options:
        assert option in result.output


def test_cli_rejects_bad_iterations():
    result = CliRunner().invoke(command, ["optimizers", "--iterations", "0,x"])
    assert result.exit_code == 2
    assert "iterations" in result.output


def test_heatmap_quick(tmp_path):
    out = tmp_path / "heatmap.csv"
    result = CliRunner().invoke(cli, ["bench", "heatmap", "--quick", "--csv", str(out)])
    assert result.exit_code == 0, result.output
    assert "ratio one-at-a-time / batched" in result.output
    rows = list(csv.DictReader(out.open()))
    names = [r["name"] for r in rows]
    assert "batched total" in names and "one at a time per candidate" in names
    assert all(math.isfinite(float(r["value"])) and float(r["value"]) > 0 for r in rows)


def test_profile_reports_time_per_evaluation_and_the_top_ops():
    out = bench_module("op_profile").run(steps=3, rows=5, print_fn=None)
    assert out["seconds_per_evaluation"] > 0 and out["warmup_s"] > 0
    assert "Self CPU" in out["table"]


def test_search_bench_solves_with_both_pipelines_and_reports_the_ratio():
    """``dejaview bench search`` on a cheap scene: both pipelines' rows, success and the time ratio."""
    lines = []
    rows = bench_module("search").run(print_fn=lines.append, scenes=("box_down_ramp",), seeds=(0,))
    assert [r["pipeline"] for r in rows] == ["auto", "seed-pipeline"]
    assert rows[0]["success"] and rows[0]["seconds"] > 0
    assert any("time ratio" in line for line in lines)


def test_peers_quick_compares_both_engines_and_writes_csv(tmp_path):
    pytest.importorskip("mujoco", reason="the peers bench runs MuJoCo beside DejaView")
    out = tmp_path / "peers.csv"
    result = CliRunner().invoke(cli, ["bench", "peers", "--quick", "--csv", str(out)])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(out.open()))
    boxes = [r for r in rows if r["section"] == "boxes"]
    assert [int(r["n"]) for r in boxes] == [1, 2]
    for r in boxes:
        for key in ("dv_rollout_s", "dv_grad_s", "mj_rollout_s", "mj_fd_grad_s"):
            assert math.isfinite(float(r[key])) and float(r[key]) > 0, (key, r)
    assert {r["section"] for r in rows} == {"boxes", "mug", "memory", "target"}
    assert [r for r in rows if r["section"] == "memory"][0]["finite"] == "True"


@pytest.mark.slow  # 14-15 s of micro benchmarks; the bench CLI's other sections run in the default run
def test_cli_micro_writes_every_section(tmp_path):
    path = tmp_path / "micro.csv"
    result = CliRunner().invoke(command, ["micro", "--poses", "3", "--csv", str(path)])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(path.open()))
    from dejaview.sim import native

    sections = {"forward-ops", "collision", "threads"} | ({"divergence"} if native.available() else set())
    assert {r["section"] for r in rows} == sections
    threads = [r for r in rows if r["section"] == "threads"]
    assert {(r["threads"], r["busy"]) for r in threads} >= {("1", "False"), ("1", "True")}
    collision = [r for r in rows if r["section"] == "collision"]
    assert len(collision) == 4 and all(r["poses"] == "3" and 0 <= int(r["overlapping"]) <= 3 for r in collision)
    assert all(float(r["seconds"]) > 0 for r in rows)


def test_cli_warp_limits_checks_both_backends_gradients_and_rolling(tmp_path):
    pytest.importorskip("warp", reason="the Warp backend is an extra")
    path = tmp_path / "warp.csv"
    result = CliRunner().invoke(command, ["warp-limits", "--quick", "--scenes", "ball_rolled", "--csv", str(path)])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(path.open()))
    grads = {r["backend"]: r for r in rows if r["section"] == "gradients"}
    assert set(grads) == {"spheres", "warp"}
    spheres = grads["spheres"]
    # the control: DejaView's exact gradient is its central difference, component by component
    assert spheres["wrong_signs"] == "0" and float(spheres["worst_ratio"]) < 1.05
    assert len(spheres["exact"].split()) == len(spheres["params"].split()) == 11
    rolling = [r for r in rows if r["section"] == "rolling"]
    assert {r["backend"] for r in rolling} == {"spheres", "warp"}
    assert all(0.5 < float(r["speed_from"]) < 1.0 for r in rolling)  # slipped into rolling below 1 m/s


def test_cli_warp_limits_names_an_unknown_scene():
    result = CliRunner().invoke(command, ["warp-limits", "--scenes", "no_such_scene"])
    assert result.exit_code == 2 and "no_such_scene" in result.output
