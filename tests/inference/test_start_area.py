"""Issue 56: a start area that cannot hold the source is refused before any work, in one line
naming the objects and the depth (``dejaview.inference.start_area``).

``box_in_desk.xml``: a 10 cm box whose whole start area sinks it 0.0267 m into a desk top.
"""

from dataclasses import replace
from pathlib import Path

import pytest

from dejaview import solve
from dejaview.errors import InferenceError, SceneError, StartAreaError
from dejaview.inference.params import StartAreaParams
from dejaview.inference.start_area import check_start_area
from dejaview.scene import Scene
from dejaview.inference.solve import SolveParams

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "inference"
BOX_IN_DESK = FIXTURES / "box_in_desk.xml"
EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "scenes"
AREA = '<start-area min="-0.2 -0.1 0.7233" max="0.2 0.1 0.7233"/>'


def scene_text(area: str = AREA, orientation: bool = False) -> str:
    text = BOX_IN_DESK.read_text().replace(AREA, area)
    assert area in text
    return text.replace('orientation="false"', f'orientation="{str(orientation).lower()}"')


def write_scene(tmp_path, **kwargs) -> Path:
    path = tmp_path / "scene.xml"
    path.write_text(scene_text(**kwargs))
    return path


def area_line() -> int:
    return next(i for i, line in enumerate(BOX_IN_DESK.read_text().splitlines(), 1) if "<start-area" in line)


def test_an_area_inside_the_desk_is_refused_in_one_line_naming_both_objects_and_the_depth():
    with pytest.raises(StartAreaError) as caught:
        check_start_area(Scene.from_xml(BOX_IN_DESK))
    message = str(caught.value)
    assert message == (f"{BOX_IN_DESK}:{area_line()}: <start-area> (-0.2, -0.1, 0.7233) to (0.2, 0.1, 0.7233) "
                       f"cannot hold 'src': everywhere in it 'src' and 'desk' interpenetrate, by 0.0267 m at the "
                       f"shallowest start found (more than the 0.003 m accepted as resting contact)")
    # both what solve promises to raise and validate's kind of error (file:line: <element> reason)
    assert isinstance(caught.value, InferenceError) and isinstance(caught.value, SceneError)
    assert caught.value.element == "start-area" and caught.value.line == area_line()


def test_with_the_orientation_free_no_orientation_fits_either(tmp_path):
    """The box contains a 5 cm ball about its centre at every orientation, and that ball alone
    overlaps the desk by more than the margin everywhere in the area: proven, not sampled."""
    with pytest.raises(StartAreaError, match=r"everywhere in it, at any orientation, 'src' and 'desk' "
                                             r"interpenetrate, by 0\.0267 m"):
        check_start_area(Scene.from_xml(write_scene(tmp_path, orientation=True)))


def test_solve_raises_it_before_building_anything(monkeypatch):
    scene = Scene.from_xml(BOX_IN_DESK)

    def no_problem(*args, **kwargs):
        raise AssertionError("a problem was built for a start area that cannot hold the source")

    monkeypatch.setattr("dejaview.backends.BackendOptions.make_problem", no_problem)
    with pytest.raises(StartAreaError, match="'src' and 'desk' interpenetrate, by 0.0267 m"):
        solve(scene)
    with pytest.raises(StartAreaError, match="'src' and 'desk' interpenetrate, by 0.0267 m"):
        solve(scene, SolveParams(optimizer="adam"))  # the local optimisers know nothing of feasibility: checked too
    with pytest.raises(StartAreaError):
        solve(BOX_IN_DESK)  # a path


def test_an_area_that_reaches_above_the_desk_passes_and_solves(tmp_path):
    """Most of the area is inside the desk; its top 2.7 cm is not: the check passes (its own
    start is infeasible, the first random starts find the free ones) and the search only ever
    returns a free start."""
    scene = Scene.from_xml(write_scene(tmp_path, area='<start-area min="-0.2 -0.1 0.6" max="0.2 0.1 0.78"/>'))
    assert check_start_area(scene) is not None
    result = solve(scene, SolveParams(iterations=3, budget=300))
    assert result.initial_state["position"][2] >= 0.75 - 0.003


def test_an_overlap_everywhere_just_past_the_margin_is_refused_after_the_budget(tmp_path):
    """0.5 mm past the margin everywhere: cells would have to shrink below half a millimetre to
    prove it, so the search stops at its budget, with no free start found, and says so."""
    area = '<start-area min="-0.2 -0.1 0.7465" max="0.2 0.1 0.7465"/>'  # 3.5 mm into the desk
    with pytest.raises(StartAreaError) as caught:
        check_start_area(Scene.from_xml(write_scene(tmp_path, area=area)))
    message = str(caught.value)
    assert "cannot hold 'src' at any of the " in message and "starts tried in it" in message
    tried = int(message.split("at any of the ")[1].split()[0])
    assert StartAreaParams.budget <= tried < StartAreaParams.budget + 64
    assert "at each 'src' and 'desk' interpenetrate, by 0.0035 m at the shallowest" in message


def test_an_area_beyond_the_bounds_of_positions_is_refused():
    """The reader refuses such an area in a file; a scene built in Python meets the same bound."""
    scene = Scene.from_xml(BOX_IN_DESK)
    inf = scene.inference
    far = replace(scene, inference=replace(inf, start_area=replace(inf.start_area, max=(0.2, 0.1, 2e4))))
    with pytest.raises(StartAreaError, match=r"cannot hold 'src': it reaches z = 20000 m, beyond the bounds "
                                             r"of every backend \(\|x\|, \|y\|, \|z\| up to 10000 m\)"):
        solve(far)


def test_a_fixed_start_inside_the_desk_is_refused_at_the_pose():
    """Position and orientation fixed: the one start is the pose."""
    scene = Scene.from_xml(BOX_IN_DESK)
    inf = scene.inference
    fixed = replace(scene, inference=replace(inf, start_area=None,
                                             optimize=replace(inf.optimize, position=False)))
    with pytest.raises(StartAreaError, match=r"<pose> the start \(0, 0, 0\.7233\) cannot hold 'src': there "
                                             r"'src' and 'desk' interpenetrate, by 0\.0267 m"):
        check_start_area(fixed)


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.xml")))
def test_every_bundled_scene_passes_at_its_own_start(name, monkeypatch):
    """The scene's own start is free in every bundled scene: one query decides."""
    import dejaview.geometry.collision as collision

    calls = []
    penetration = collision.SceneCollision.penetration

    def counted(self, *args, **kwargs):
        calls.append(1)
        return penetration(self, *args, **kwargs)

    monkeypatch.setattr(collision.SceneCollision, "penetration", counted)
    check_start_area(Scene.from_xml(EXAMPLES / name))
    assert len(calls) == 1
