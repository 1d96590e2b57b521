"""``dejaview solve SCENE`` with no solver flags finds a past that explains the observed end.

Issue 19's criterion: on every bundled story scene and for seeds 0, 1 and 2, the answer
re-simulated meets the target within 1 cm and 5 degrees (position alone for the balls, whose
loss is ``position``), at the record the scene compares (``result.json``'s ``matched_pose``).
The real command line runs, as a user would run it. Two scenes with seed 0 run in the default
suite, their other seeds and every other scene in the ``slow`` one.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCENES = Path(__file__).resolve().parents[2] / "examples" / "scenes"
FAST = ("mug_off_counter", "box_along_shelf")
SLOW = ("box_among_boxes", "ball_off_table", "ball_down_ramp", "box_down_ramp")


def solve_with_defaults(scene: str, seed: int, out: Path) -> dict:
    result = subprocess.run([sys.executable, "-m", "dejaview", "solve", str(SCENES / f"{scene}.xml"),
                             "-o", str(out), "--seed", str(seed), "--quiet"],
                            capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    return json.loads((out / "result.json").read_text())


def check_explains_the_end(data: dict) -> None:
    m = data["matched_pose"]
    assert data["optimizer"] == "auto"
    assert m["position_error"] <= 0.01, m
    if data["loss_kind"] != "position":
        assert m["angle_error_deg"] <= 5.0, m
    # a start, not inside the furniture: its own end, and a record of what the search assumed
    assert data["prior"]["position"] == "uniform in the start area"
    assert data["search"]["rollouts"] > 0 and data["search"]["modes"]


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
@pytest.mark.parametrize("scene", FAST)
def test_default_solve_explains_the_end(scene, seed, tmp_path):
    check_explains_the_end(solve_with_defaults(scene, seed, tmp_path))


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("scene", SLOW)
def test_default_solve_explains_the_end_on_every_story_scene(scene, seed, tmp_path):
    check_explains_the_end(solve_with_defaults(scene, seed, tmp_path))


@pytest.mark.slow
def test_a_prior_on_speed_and_spin_keeps_the_answer_gentle(tmp_path):
    """``<prior speed="1.0" spin="3.0">`` on the mug: the most probable past slides the mug off
    rather than flinging it: every velocity component within 3 standard deviations (a mug solve,
    35 s: slow; the default run solves mug_off_counter_prior.xml in the notebook's test)."""
    text = (SCENES / "mug_off_counter.xml").read_text()
    text = text.replace("</inference>", '  <prior speed="1.0" spin="3.0"/>\n  </inference>')
    scene = tmp_path / "mug_prior.xml"
    scene.write_text(text)
    (tmp_path / "meshes").symlink_to(SCENES.parent / "meshes")
    (tmp_path / "packings").symlink_to(SCENES.parent / "packings")
    text = text.replace('mesh="../meshes/', 'mesh="meshes/').replace('spheres="../packings/', 'spheres="packings/')
    scene.write_text(text)
    result = subprocess.run([sys.executable, "-m", "dejaview", "solve", str(scene), "-o", str(tmp_path / "out"),
                             "--quiet"], capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    data = json.loads((tmp_path / "out" / "result.json").read_text())
    assert data["prior"]["speed"] == 1.0 and data["prior"]["spin"] == 3.0
    v, w = data["initial_state"]["linear_velocity"], data["initial_state"]["angular_velocity"]
    assert max(abs(c) for c in v) <= 3 * 1.0, v
    assert max(abs(c) for c in w) <= 3 * 3.0, w
    # and it still explains the end within the observation's noise (sigma = the heatmap's 2 cm)
    assert data["matched_pose"]["position_error"] <= 3 * data["observation"]["sigma"]
