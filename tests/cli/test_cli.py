"""The dejaview command line: every subcommand's help, simulate and solve end to end, errors."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from dejaview.cli import SUBCOMMANDS, cli
from dejaview.sim.trajectory_csv import HEADER, read_trajectory_csv

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
BALL = FIXTURES / "cli" / "ball.xml"


def run_cli(*args):
    """Run ``python -m dejaview ARGS`` (the real entry point, exit codes included)."""
    return subprocess.run([sys.executable, "-m", "dejaview", *map(str, args)], capture_output=True,
                          text=True, timeout=300)


def test_every_subcommand_has_help():
    runner = CliRunner()
    names = CliRunner().invoke(cli, ["--help"]).output
    for name in cli.list_commands(None):
        assert name in names
        result = runner.invoke(cli, [name, "--help"])
        assert result.exit_code == 0, (name, result.output)
        assert "Usage:" in result.output
    assert set(cli.list_commands(None)) <= set(SUBCOMMANDS)


def test_simulate_writes_trajectory_csv(tmp_path):
    result = run_cli("simulate", BALL, "-o", tmp_path, "--quiet")
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "trajectory.csv").read_text()
    assert text.splitlines()[0] == ",".join(HEADER)
    traj = read_trajectory_csv(tmp_path / "trajectory.csv")
    assert set(traj) == {"ball"}  # the fixed floor is left out
    ball = traj["ball"]
    assert ball["step"][0] == 0 and ball["step"][-1] == 50
    # free flight: x = 0.5 m/s * t, and the ball falls
    assert ball["position"][-1][0] == pytest.approx(0.05, abs=1e-6)
    assert ball["position"][-1][2] < 0.5


def test_solve_writes_results(tmp_path):
    result = run_cli("solve", BALL, "-o", tmp_path, "--quiet", "--iterations", "3", "--plot")
    assert result.returncode == 0, result.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    for key in ("source", "backend", "optimizer", "gradient", "loss", "initial_state", "iterations"):
        assert key in data
    assert data["source"] == "ball" and data["optimizer"] == "lbfgs"
    assert len(data["iterations"]) == 3
    assert set(data["initial_state"]) == {"position", "orientation", "linear_velocity", "angular_velocity"}
    rows = (tmp_path / "iterations.csv").read_text().splitlines()
    assert rows[0] == "iteration,loss,best_loss,duration_s,restarted" and len(rows) == 4
    assert (tmp_path / "trajectory.csv").exists() and (tmp_path / "loss.png").stat().st_size > 0
    # three L-BFGS iterations on this smooth flight get close to the target
    assert data["loss"] < 0.01


def test_solve_screens_random_guesses(tmp_path):
    """``--screen 5``: the scene's guess and 5 random ones are ranked before optimising."""
    result = run_cli("solve", BALL, "-o", tmp_path, "--quiet", "--iterations", "1", "--screen", "5")
    assert result.returncode == 0, result.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["screened"] == 6 and data["multistart"] == 1


@pytest.mark.parametrize("args, needle", [
    (["solve", BALL, "--screen", "-1"], "screen"),
    (["solve", BALL, "--optimizer", "auto", "--screen", "5"], "screen applies to the local optimisers"),
    (["solve", BALL, "--budget", "0"], "budget"),
    (["solve", BALL, "--optimizer", "newton"], "newton"),
    (["solve", BALL, "--iterations", "0"], "iterations"),
    (["simulate", FIXTURES / "scenes" / "broken" / "nan-position.xml"], "nan-position.xml:"),
    (["simulate", FIXTURES / "cli" / "missing.xml"], "missing.xml"),
])
def test_bad_input_exits_nonzero_with_one_line(tmp_path, args, needle):
    result = run_cli(*args, "-o", tmp_path, "--quiet")
    assert result.returncode != 0
    lines = [ln for ln in result.stderr.strip().splitlines() if ln.strip()]
    assert lines, result.stderr
    assert needle in result.stderr
    assert "Traceback" not in result.stderr


def test_simulate_rejects_an_engine_for_another_backend(tmp_path):
    """As solve and heatmap do: --engine belongs to the spheres backend."""
    result = CliRunner().invoke(cli, ["simulate", "examples/scenes/ball_rolled.xml", "-o", str(tmp_path),
                                      "--backend", "warp", "--engine", "native", "-q"])
    assert result.exit_code == 2
    assert "engine is an option of the spheres backend, not of warp" in result.output
