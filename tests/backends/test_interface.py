"""The backend interface: ``make_problem``, the spheres wrapper, ``solve(backend=)`` and the
errors of unknown or missing backends (the warp backend itself: test_warp.py)."""

import json
import sys
from pathlib import Path

import pytest
import torch

from dejaview.backends import BACKENDS, WARP_MISSING, Backend, Problem, as_problem, get_backend, make_problem
from dejaview.cli import main
from dejaview.errors import InferenceError
from dejaview.backends.spheres import SpheresProblem
from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.sim.trajectory_csv import read_trajectory_csv
from dejaview.scene import Scene

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
BALL = FIXTURES / "cli" / "ball.xml"
BILLIARDS = FIXTURES / "inference" / "billiards.xml"


def test_spheres_problem_has_the_interface():
    problem = make_problem(Scene.from_xml(BALL))
    assert problem.backend == "spheres" and "reverse" in problem.gradient_modes
    assert problem.num_params == problem.layout.size == 3
    assert problem.body_names == ("ball",) and problem.dtype == torch.float64
    assert problem.duration_steps == 50 and problem.dt == pytest.approx(0.002)
    x = problem.layout.encode()
    values, grads = problem.objective_and_grad(x, "reverse")
    assert values.shape == (1,) and grads.shape == (1, 3)
    assert problem.evaluations == 1
    traj = problem.simulate(x, record_every=10)
    pos, q = problem.final_pose(traj)
    assert len(pos) == 3 and len(q) == 4
    csv = problem.trajectory_csv(traj)
    assert csv.splitlines()[0] == "step,time,object,x,y,z,qw,qx,qy,qz"
    # one class: the spheres backend's problem is dejaview.inference's SpheresProblem, no wrapper
    assert isinstance(problem, SpheresProblem) and as_problem(problem) is problem
    with pytest.raises(InferenceError, match="not a backend problem"):
        as_problem(object())


def _conforms(backend, problem):
    """Both halves of the protocol: the Backend, and a Problem with what the inference reads."""
    assert isinstance(backend, Backend) and isinstance(problem, Problem)
    assert problem.backend == backend.name and problem.gradient_modes == backend.gradient_modes
    # the shared parts are the base's, not copies: a backend supplies the rollout and its settings
    for name in ("loss", "value_and_grad", "objective_and_grad", "final_pose", "trajectory_csv",
                 "write_trajectory", "loss_of_trajectory"):
        assert getattr(type(problem), name) is getattr(Problem, name), name
    for name in ("simulate", "simulation_settings"):
        assert getattr(type(problem), name) is not getattr(Problem, name), name


@pytest.mark.parametrize("name", BACKENDS)
def test_every_registered_backend_conforms_to_the_protocol(name, tmp_path):
    """Each backend builds a Problem from the base (loss, gradients and I/O written once), runs a
    scene forward into a SimulationRun, and its problem's loss is ``dejaview.losses``' loss of its
    own trajectory."""
    if name == "warp":
        pytest.importorskip("warp", reason="the warp extra is not installed: pip install 'dejaview[warp]'")
    backend = get_backend(name)
    problem = backend.make_problem(Scene.from_xml(BALL))
    _conforms(backend, problem)
    x = problem.layout.encode()
    values, grads = problem.value_and_grad(x, "reverse")
    assert values.shape == (1,) and grads.shape == (1, 3) and torch.isfinite(grads).all()
    traj = problem.simulate(x)
    assert torch.allclose(values, problem.loss_of_trajectory(traj))
    run = backend.simulate(Scene.from_xml(BALL), steps=10, record_every=5)
    assert run.backend == name and run.steps == 10 and run.names == ("ball",)
    rows = read_trajectory_csv(run.write(tmp_path)["trajectory"])
    assert rows["ball"]["step"] == [0, 5, 10]


def test_trajectory_csv_holds_every_movable_object(tmp_path):
    problem = make_problem(BILLIARDS)
    traj = problem.simulate(problem.layout.encode(), steps=5)
    rows = read_trajectory_csv(problem.write_trajectory(tmp_path / "t.csv", traj))
    assert set(rows) == set(problem.body_names) and len(problem.body_names) == 2


def test_solve_reports_the_backend(tmp_path):
    result = solve(BALL, SolveParams(iterations=1), backend="spheres")
    result.write(tmp_path)
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "spheres" and data["simulation"]["steps"] == 50
    # a bare SpheresProblem is still accepted
    bare = SpheresProblem.from_scene(Scene.from_xml(BALL))
    assert solve(BALL, SolveParams(iterations=1), problem=bare).settings["backend"] == "spheres"
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
        solve(BALL, SolveParams(iterations=1), backend="warp")
    assert str(info.value) == WARP_MISSING


def test_cli_warp_without_the_extra_is_one_line_and_nonzero(no_warp, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["solve", str(BALL), "-o", str(tmp_path), "--backend", "warp", "--quiet"])
    assert info.value.code != 0
    err = capsys.readouterr().err.strip()
    assert err == f"error: {WARP_MISSING}"
    assert not (tmp_path / "result.json").exists()
