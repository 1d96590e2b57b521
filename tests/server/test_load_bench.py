"""Smoke test of bench/load.py (a few clients against the shared live server; no timing asserts)."""

from __future__ import annotations

import math

from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.cli.bench import bench_module


def test_load_bench_loses_no_job(live_server):
    lines = []
    row = bench_module("load").run(print_fn=lines.append, clients=6, url=live_server.ws_url)
    assert row["lost"] == 0 and row["done"] == 6
    assert row["jobs_per_s"] > 0 and 0 < row["p50_s"] <= row["p99_s"] <= row["max_s"]
    assert all(math.isfinite(row[k]) for k in ("wall_s", "p50_s", "p99_s"))
    assert any("jobs/s" in line for line in lines) and any("lost: 0" in line for line in lines)


def test_bench_load_subcommand(live_server, tmp_path):
    result = CliRunner().invoke(cli, ["bench", "load", "--clients", "3", "--url", live_server.ws_url,
                                      "--check", "--csv", str(tmp_path / "load.csv")])
    assert result.exit_code == 0, result.output
    assert "p50" in result.output and "lost: 0" in result.output
    assert (tmp_path / "load.csv").read_text().startswith("clients,")


def test_percentile():
    p = bench_module("load").percentile
    assert p([3, 1, 2], 50) == 2 and p(list(range(1, 101)), 99) == 99 and p([5], 99) == 5
