"""Backend options travel as one object (``dejaview.backends.BackendOptions``): checked once,
read only by the backend; solve, the heatmap, the CLI commands and the service never name a
backend's own settings."""

import ast
import pickle
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from dejaview.backends import BackendOptions, make_problem
from dejaview.cli import cli
from dejaview.errors import InferenceError, SimulationError
from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.scene import Scene

ROOT = Path(__file__).resolve().parents[2]
BALL = ROOT / "tests" / "fixtures" / "cli" / "ball.xml"


@pytest.mark.parametrize("backend, settings, message", [
    ("spheres", {"engine": "fast"}, "unknown engine 'fast'; choose one of auto, native, torch"),
    ("spheres", {"engine": "native", "compile": True}, "compile applies to the torch engine"),
    ("spheres", {"engine": "native", "dtype": torch.float32}, "the native engine runs in float64"),
    ("spheres", {"integrator": "xpbd"}, "integrator is an option of the warp backend, not of spheres"),
    ("spheres", {"colour": "red"}, "colour is no backend's option, not of spheres"),
    ("nope", {}, "unknown backend 'nope'"),
])
def test_bad_options_are_refused_when_built_with_one_line(backend, settings, message):
    with pytest.raises(InferenceError) as info:
        BackendOptions.of(backend, **settings)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_the_error_type_is_the_callers():
    with pytest.raises(SimulationError, match="unknown engine"):
        BackendOptions.of("spheres", SimulationError, engine="fast")


def test_settings_merge_drop_unset_values_and_pickle():
    base = BackendOptions.of(None, engine="torch")
    assert base.name == "spheres" and base.get("engine") == "torch" and base.get("compile") is None
    more = BackendOptions.of(base, compile=True, engine=None)  # None: not given, the base's stays
    assert dict(more.settings) == {"engine": "torch", "compile": True}
    assert pickle.loads(pickle.dumps(more)) == more  # heatmap workers and Ray actors rebuild from it


def test_the_backend_reads_its_settings_into_the_problem():
    scene = Scene.from_xml(BALL)
    problem = BackendOptions.of("spheres", engine="torch", compile=True).make_problem(scene)
    assert problem.engine == "torch" and problem.compile
    assert make_problem(scene, BackendOptions.of(engine="native")).engine == "native"
    # a reused problem hands its engine to the workers that rebuild it
    assert problem.backend_options() == BackendOptions.of("spheres", engine="torch")


def test_solve_takes_backend_options_and_refuses_them_beside_a_built_problem():
    result = solve(BALL, SolveParams(iterations=2, optimizer="adam"), backend=BackendOptions.of(engine="torch"))
    assert result.problem.engine == "torch" and result.settings["backend"] == "spheres"
    with pytest.raises(InferenceError, match="pass one of backend and problem"):
        solve(BALL, SolveParams(iterations=1), problem=make_problem(BALL), backend="spheres")


def test_simulate_runs_on_the_options_backend(tmp_path):
    run = BackendOptions.of(engine="torch").simulate(Scene.from_xml(BALL), steps=4, record_every=2)
    assert run.backend == "spheres" and run.steps == 4


def test_cli_refuses_a_bad_combination_as_a_usage_error(tmp_path):
    result = CliRunner().invoke(cli, ["solve", str(BALL), "-o", str(tmp_path), "--engine", "native",
                                      "--compile", "-q"])
    assert result.exit_code == 2 and "compile applies to the torch engine" in result.output
    result = CliRunner().invoke(cli, ["simulate", str(BALL), "-o", str(tmp_path), "--engine", "native",
                                      "--float32", "-q"])
    assert result.exit_code == 2 and "the native engine runs in float64" in result.output


# the layers that pass backend options on without reading them
OPAQUE = ["dejaview/inference/solve.py", "dejaview/heatmap/search.py", "dejaview/heatmap/posterior.py",
          "dejaview/cli/solve.py", "dejaview/cli/heatmap.py", "dejaview/cli/simulate.py",
          *(str(p.relative_to(ROOT)) for p in sorted((ROOT / "dejaview" / "server").glob("*.py")))]


@pytest.mark.parametrize("path", OPAQUE)
def test_solve_heatmap_cli_and_service_never_name_a_backends_settings(path):
    """No variable, argument, keyword or attribute called ``engine`` or ``compile`` (nor
    ``integrator``, Warp's) in code that carries ``BackendOptions``."""
    named = set()
    for node in ast.walk(ast.parse((ROOT / path).read_text())):
        if isinstance(node, ast.Name):
            named.add(node.id)
        elif isinstance(node, ast.arg):
            named.add(node.arg)
        elif isinstance(node, ast.keyword) and node.arg:
            named.add(node.arg)
        elif isinstance(node, ast.Attribute) and not (isinstance(node.value, ast.Name) and node.value.id == "re"):
            named.add(node.attr)  # re.compile is a regular expression's
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in (
                "engine", "compile", "integrator"):
            named.add(node.value)
    assert not named & {"engine", "compile", "integrator", "use_compile"}, path
