"""Bad inference settings fail early with one clear line naming the problem.

Every bad scene here is a small edit of ``tests/fixtures/inference/ball_throw.xml``
(a ball and a floor, 0.1 s), so nothing expensive runs: each error must come
before (or instead of) any optimisation. The Python API raises ``SceneError``
for what the scene file gets wrong (from the reader, with file and line) and
``InferenceError`` for settings that only the solver can judge; the command
line turns either into a non-zero exit and a single line on stderr.
"""

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from dejaview.cli import main
from dejaview.errors import InferenceError, SceneError
from dejaview.backends.spheres import SpheresProblem
from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.scene import Scene, SceneObject

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "inference"
BALL = FIXTURES / "ball_throw.xml"
BALL_TEXT = BALL.read_text(encoding="utf-8")

PINNED = ('<optimize position="true" orientation="false" linear-velocity="false" '
          'angular-velocity="false"/>\n    <start-area min="0 0 0.1" max="0 0 0.1"/>')
NOTHING = ('<optimize position="false" orientation="false" linear-velocity="false" '
           'angular-velocity="false"/>')


def edit(old: str, new: str, text: str = BALL_TEXT) -> str:
    """The fixture's XML with one piece of text replaced (which must be there)."""
    assert old in text, old
    return text.replace(old, new, 1)


def without_inference(text: str = BALL_TEXT) -> str:
    start, end = text.index("  <inference"), text.index("</inference>") + len("</inference>\n")
    return text[:start] + text[end:]


BAD_SCENES = {
    # name: (XML text, what the reader's one-line error must mention)
    "optimizer": (edit('optimizer="adam"', 'optimizer="newton"'), ["optimizer", "newton"]),
    "fixed-source": (edit('<object id="ball" shape="sphere"', '<object id="ball" fixed="true" shape="sphere"'),
                     ["ball", "fixed"]),
    "zero-iterations": (edit('iterations="20"', 'iterations="0"'), ["iterations"]),
    "nothing-free": (edit('<optimize position="true" orientation="false" linear-velocity="true" '
                          'angular-velocity="false"/>', NOTHING), ["nothing to optimize"]),
}

FREE_LINE = ('<optimize position="true" orientation="false" linear-velocity="true" angular-velocity="false"/>\n'
             '    <start-area min="-0.1 -0.1 0.1" max="0.1 0.1 0.1"/>')


def pinned_scene() -> Scene:
    """Only the position is free, and the start area is a single point: no parameter."""
    return Scene.from_string(edit(FREE_LINE, PINNED), filename="pinned.xml")


def assert_one_line(err: Exception, *needles: str) -> None:
    msg = str(err)
    assert msg and "\n" not in msg, msg
    for needle in needles:
        assert needle in msg, (needle, msg)


# ------------------------------------------------------------------- reader
@pytest.mark.parametrize("name", sorted(BAD_SCENES))
def test_the_reader_refuses_bad_inference_settings_with_file_and_line(name):
    """What the scene file gets wrong is a SceneError from the reader: one line with the
    file, the <inference> line and the reason."""
    text, needles = BAD_SCENES[name]
    with pytest.raises(SceneError) as err:
        Scene.from_string(text, filename=f"{name}.xml")
    assert_one_line(err.value, f"{name}.xml:", *needles)
    assert err.value.line is not None


# ----------------------------------------------------------------- solve API
@pytest.fixture(scope="module")
def ball():
    return Scene.from_xml(BALL)


def test_unknown_optimizer_is_refused_before_any_work(ball):
    """``solve(scene, optimizer="newton")``: InferenceError naming it and the choices."""
    with pytest.raises(InferenceError) as err:
        solve(ball, SolveParams(optimizer="newton"))
    assert_one_line(err.value, "newton", "gd", "adam", "lbfgs", "bfgs")


def test_unknown_gradient_mode_is_refused(ball):
    with pytest.raises(InferenceError) as err:
        solve(ball, SolveParams(gradient="sideways", iterations=1))
    assert_one_line(err.value, "sideways", "forward", "reverse")


@pytest.mark.parametrize("iterations", [0, -1, True, 2.5, "3"])
def test_iterations_must_be_a_positive_integer(ball, iterations):
    """0 and -1 are not a number of iterations, nor are True (a bool is an int in Python),
    2.5 or a string."""
    with pytest.raises(InferenceError) as err:
        solve(ball, SolveParams(iterations=iterations))
    assert_one_line(err.value, "iterations", repr(iterations))


def test_multistart_must_be_positive(ball):
    with pytest.raises(InferenceError) as err:
        solve(ball, SolveParams(iterations=1, multistart=0))
    assert_one_line(err.value, "multistart")


def test_no_free_parameter():
    """A scene may free only the position (valid XML) with a start area that pins every
    axis: nothing is left to optimise, which the problem (and so solve) refuses."""
    scene = pinned_scene()
    with pytest.raises(InferenceError) as err:
        SpheresProblem.from_scene(scene)
    assert_one_line(err.value, "no free parameter")
    with pytest.raises(InferenceError) as err:
        solve(scene, SolveParams(iterations=1))
    assert_one_line(err.value, "no free parameter")


def test_scene_without_inference_cannot_be_solved():
    scene = Scene.from_string(without_inference())
    assert scene.inference is None
    for attempt in (lambda: solve(scene), lambda: SpheresProblem.from_scene(scene)):
        with pytest.raises(InferenceError) as err:
            attempt()
        assert_one_line(err.value, "<inference>")


def fixed_source_scene(with_other_movable: bool) -> Scene:
    """The fixture's scene built in code (no reader, so no validation) with the source
    made fixed; optionally a second, movable ball so that the world itself can be built."""
    scene = Scene.from_xml(BALL)
    ball = scene.object("ball")
    objects = tuple(replace(o, fixed=True) if o.id == "ball" else o for o in scene.objects)
    if with_other_movable:
        objects += (SceneObject(id="other", shape="sphere", radius=0.05,
                                pose=replace(ball.pose, position=(1.0, 0.0, 0.05))),)
    return replace(scene, objects=objects)


@pytest.mark.parametrize("with_other_movable", [True, False])
def test_fixed_source_built_in_code_is_an_inference_error(with_other_movable):
    """A fixed object's past cannot be inferred. A scene built in code skips the reader's
    check, so the problem must say it, naming the source, whether or not the scene
    has any other movable object (without one, the error must still be about the source,
    not that the world has nothing to simulate)."""
    scene = fixed_source_scene(with_other_movable)
    with pytest.raises(InferenceError) as err:
        SpheresProblem.from_scene(scene)
    assert_one_line(err.value, "'ball'")
    with pytest.raises(InferenceError):
        solve(scene, SolveParams(iterations=1))


def test_unknown_source_built_in_code_is_an_inference_error():
    scene = Scene.from_xml(BALL)
    scene = replace(scene, inference=replace(scene.inference, source="ghost"))
    with pytest.raises(InferenceError) as err:
        SpheresProblem.from_scene(scene)
    assert_one_line(err.value, "'ghost'")


# ---------------------------------------------------------------- command line
def run_main(argv, capsys):
    """``dejaview ARGV`` in this process (the console entry point): (exit code, stdout, stderr)."""
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


def write(tmp_path, name, text) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


CLI_CASES = {
    # name: (scene text or None for the fixture, extra arguments, what stderr must mention)
    "optimizer-in-scene": (BAD_SCENES["optimizer"][0], [], ["newton", ".xml:"]),
    "optimizer-option": (None, ["--optimizer", "newton"], ["newton", "--optimizer"]),
    "fixed-source": (BAD_SCENES["fixed-source"][0], [], ["'ball'", "fixed"]),
    "zero-iterations-option": (None, ["--iterations", "0"], ["iterations"]),
    "negative-iterations-option": (None, ["--iterations", "-1"], ["iterations"]),
    "zero-iterations-in-scene": (BAD_SCENES["zero-iterations"][0], [], ["iterations"]),
    "no-inference": (without_inference(), [], ["<inference>"]),
    "no-free-parameter": (edit(FREE_LINE, PINNED), [], ["no free parameter"]),
    "missing-file": ("", [], ["no-such.xml"]),
}


@pytest.mark.parametrize("name", sorted(CLI_CASES))
def test_cli_solve_fails_with_one_line(tmp_path, capsys, name):
    """``dejaview solve`` with bad settings exits non-zero, prints exactly one line on
    stderr naming the problem, and writes no results."""
    text, extra, needles = CLI_CASES[name]
    if name == "missing-file":
        scene = tmp_path / "no-such.xml"
    else:
        scene = BALL if text is None else write(tmp_path, f"{name}.xml", text)
    out_dir = tmp_path / "out"
    code, out, err = run_main(["solve", scene, "-o", out_dir, "--quiet", *extra], capsys)
    assert code not in (0, None)
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert "Traceback" not in err
    assert not (out_dir / "result.json").exists()


def test_cli_error_through_the_real_entry_point(tmp_path):
    """The same through ``python -m dejaview`` (the console script's code path, exit code
    included): a scene whose optimizer is unknown."""
    scene = write(tmp_path, "bad.xml", BAD_SCENES["optimizer"][0])
    result = subprocess.run([sys.executable, "-m", "dejaview", "solve", str(scene), "-o",
                             str(tmp_path / "out"), "--quiet"], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "bad.xml:" in lines[0] and "newton" in lines[0]


def test_cancelled_before_the_first_iteration_says_so(ball):
    """A stop request before any evaluation (a server job cancelled at once) has no solution
    to report; the error must say that, not blame the scene's numbers."""
    with pytest.raises(InferenceError) as err:
        solve(ball, SolveParams(iterations=3), should_stop=lambda: True)
    assert_one_line(err.value, "stopped before the first iteration")
