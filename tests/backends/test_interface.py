"""The backend interface: ``make_problem``, the spheres wrapper, ``solve(backend=)`` and the
errors of unknown or missing backends (the warp backend itself: test_warp.py)."""

import json
import sys
from pathlib import Path

import pytest
import torch

from dejaview.backends import BACKENDS, WARP_MISSING, as_problem, make_problem
from dejaview.cli import main
from dejaview.errors import InferenceError
from dejaview.inference import InferenceProblem, solve
from dejaview.io.trajectory import read_trajectory_csv
from dejaview.scene import Scene

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
BALL = FIXTURES / "cli" / "ball.xml"
BILLIARDS = FIXTURES / "inference" / "billiards.xml"


def test_spheres_problem_has_the_interface_and_shares_the_wrapped_problem():
    problem = make_problem(Scene.from_xml(BALL))
    assert problem.backend == "spheres" and "reverse" in problem.gradient_modes
    assert problem.num_params == problem.layout.size == 3
    assert problem.body_names == ("ball",) and problem.dtype == torch.float64
    assert problem.duration_steps == 50 and problem.dt == pytest.approx(0.002)
    x = problem.layout.encode()
    values, grads = problem.objective_and_grad(x, "reverse")
    assert values.shape == (1,) and grads.shape == (1, 3)
    # the wrapper holds no state: counters and settings live in the InferenceProblem
    assert problem.evaluations == problem.inner.evaluations == 1
    problem.compile = True
    assert problem.inner.compile is True
    problem.compile = False
    traj = problem.simulate(x, record_every=10)
    pos, q = problem.final_pose(traj)
    assert len(pos) == 3 and len(q) == 4
    csv = problem.trajectory_csv(traj)
    assert csv.splitlines()[0] == "step,time,object,x,y,z,qw,qx,qy,qz"
    assert as_problem(problem) is problem and as_problem(problem.inner).inner is problem.inner


def test_trajectory_csv_holds_every_movable_object(tmp_path):
    problem = make_problem(BILLIARDS)
    traj = problem.simulate(problem.layout.encode(), steps=5)
    rows = read_trajectory_csv(problem.write_trajectory(tmp_path / "t.csv", traj))
    assert set(rows) == set(problem.body_names) and len(problem.body_names) == 2


def test_solve_reports_the_backend(tmp_path):
    result = solve(BALL, iterations=1, backend="spheres")
    result.write(tmp_path)
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "spheres" and data["simulation"]["steps"] == 50
    # a bare InferenceProblem is still accepted
    bare = InferenceProblem.from_scene(Scene.from_xml(BALL))
    assert solve(BALL, iterations=1, problem=bare).settings["backend"] == "spheres"
    assert bare.evaluations >= 1


def test_unknown_backend_is_one_line_naming_the_choices():
    with pytest.raises(InferenceError) as info:
        make_problem(BALL, backend="bullet")
    message = str(info.value)
    assert "\n" not in message and "bullet" in message
    assert all(name in message for name in BACKENDS)


@pytest.fixture
def no_warp(monkeypatch):
    """Make ``import warp`` fail as it does without the extra."""
    monkeypatch.setitem(sys.modules, "warp", None)


def test_warp_without_the_extra_says_how_to_install_it(no_warp):
    with pytest.raises(InferenceError, match="pip install 'dejaview\\[warp\\]'"):
        make_problem(BALL, backend="warp")
    with pytest.raises(InferenceError) as info:
        solve(BALL, iterations=1, backend="warp")
    assert str(info.value) == WARP_MISSING


def test_cli_warp_without_the_extra_is_one_line_and_nonzero(no_warp, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["solve", str(BALL), "-o", str(tmp_path), "--backend", "warp", "--quiet"])
    assert info.value.code != 0
    err = capsys.readouterr().err.strip()
    assert err == f"error: {WARP_MISSING}"
    assert not (tmp_path / "result.json").exists()
