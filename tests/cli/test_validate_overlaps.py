"""``dejaview validate`` names objects that interpenetrate at their given poses."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from dejaview.cli import cli

ROOT = Path(__file__).resolve().parents[2]
SCENES = sorted((ROOT / "examples" / "scenes").glob("*.xml"))


def _mug_scene(tmp_path: Path, mug_z: float, name: str = "scene.xml") -> Path:
    """mug_off_counter with the mug at height ``mug_z`` (0.95: standing on the counter)."""
    text = (ROOT / "examples" / "scenes" / "mug_off_counter.xml").read_text()
    text = text.replace('<pose position="0.0 0.0 0.95"', f'<pose position="0.0 0.0 {mug_z}"')
    text = text.replace("../meshes/", f"{ROOT}/examples/meshes/").replace(
        "../packings/", f"{ROOT}/examples/packings/")
    path = tmp_path / name
    path.write_text(text)
    return path


def test_every_bundled_scene_still_validates():
    result = CliRunner().invoke(cli, ["validate", *map(str, SCENES)])
    assert result.exit_code == 0, result.output
    assert len(result.stdout.splitlines()) == len(SCENES)


def test_a_mug_2cm_inside_the_counter_is_an_error_naming_both(tmp_path):
    path = _mug_scene(tmp_path, 0.93)
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2
    assert result.stdout == ""
    [line] = result.stderr.strip().splitlines()
    # the line of the movable object (the mug's <object> is on line 11)
    assert line.startswith(f"error: {path}:11: <object> 'counter' and 'mug' interpenetrate by 0.0200 m")


def test_resting_contact_and_the_margin(tmp_path):
    """Touching is fine; 1 mm deep is within the default 2 mm; --margin decides."""
    assert CliRunner().invoke(cli, ["validate", str(_mug_scene(tmp_path, 0.95))]).exit_code == 0
    sunk = _mug_scene(tmp_path, 0.949, "sunk.xml")
    assert CliRunner().invoke(cli, ["validate", str(sunk)]).exit_code == 0
    result = CliRunner().invoke(cli, ["validate", "--margin", "0.0005", str(sunk)])
    assert result.exit_code == 2 and "interpenetrate by 0.0010 m" in result.stderr
    deep = _mug_scene(tmp_path, 0.93, "deep.xml")
    assert CliRunner().invoke(cli, ["validate", "--margin", "0.03", str(deep)]).exit_code == 0


def test_one_line_per_pair_and_other_scenes_still_checked(tmp_path):
    boxes = tmp_path / "boxes.xml"
    boxes.write_text("""<scene version="1">
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="a" shape="box" size="0.2 0.2 0.2"><pose position="0 0 0.05"/></object>
  <object id="b" shape="box" size="0.1 0.1 0.1"><pose position="0 0 0.1"/></object>
</scene>""")
    ramp = ROOT / "examples" / "scenes" / "ball_down_ramp.xml"
    result = CliRunner().invoke(cli, ["validate", str(boxes), str(ramp)])
    assert result.exit_code == 2
    errors = result.stderr.strip().splitlines()
    assert len(errors) == 2
    assert f"{boxes}:3: <object> 'floor' and 'a' interpenetrate by 0.0500 m" in errors[0]
    assert f"{boxes}:3: <object> 'a' and 'b' interpenetrate by 0.1000 m" in errors[1]
    assert result.stdout.strip() == f"OK {ramp}: 3 objects, source=ball"


def test_no_file_check_skips_the_overlap_check(tmp_path):
    path = _mug_scene(tmp_path, 0.93)
    assert CliRunner().invoke(cli, ["validate", "--no-file-check", str(path)]).exit_code == 0


@pytest.mark.parametrize("margin", ["-1", "x"])
def test_bad_margin_is_a_usage_error(tmp_path, margin):
    result = CliRunner().invoke(cli, ["validate", "--margin", margin, str(SCENES[0])])
    assert result.exit_code == 2 and "--margin" in result.output


def _sweep_scene(tmp_path: Path, pitch: float, mug: str = "0.45 -0.15 0.35") -> Path:
    """arm_sweeps_mug with the arm's shoulder pitched down by ``pitch`` (the elbow keeping the
    forearm level) and the mug at ``mug``."""
    text = (ROOT / "examples" / "scenes" / "arm_sweeps_mug.xml").read_text()
    for old in ("-1.0 0.1253 -0.1253", "0.9 0.1253 -0.1253"):
        text = text.replace(old, f"{old.split()[0]} {pitch} {-pitch}")
    text = text.replace('<pose position="0.45 -0.15 0.35"', f'<pose position="{mug}"')
    for folder in ("robots", "meshes", "packings"):
        text = text.replace(f"../{folder}/", f"{ROOT}/examples/{folder}/")
    path = tmp_path / "sweep.xml"
    path.write_text(text)
    return path


def test_a_moving_arm_passing_through_the_table_is_a_one_line_warning(tmp_path):
    """Links push movable objects but pass through fixed ones: validate warns once per robot and
    object, naming the deepest link, its depth and when, and the scene stays valid. Pitched down
    0.35 rad the upper arm's far bottom edge reaches z = 0.4 - 0.4 sin 0.35 - 0.04 cos 0.35, 7.47 cm
    below the table's top (z = 0.3), as it swings over the table. (The bundled sweep, 2.5 cm above
    the table and through the mug, a movable object, gets no warning: see the first test.)"""
    import math

    path = _sweep_scene(tmp_path, 0.35)
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 0, result.output
    warning, ok = result.stdout.strip().splitlines()
    assert ok.startswith("OK ")
    assert warning.startswith(f"warning: {path}:12: <object> robot 'arm' passes through 'table' as it moves: "
                              "link 'upper_arm' by ")
    depth = float(warning.split(" by ")[1].split(" m")[0])
    assert depth == pytest.approx(0.3 - (0.4 - 0.4 * math.sin(0.35) - 0.04 * math.cos(0.35)), abs=2e-4)
    t = float(warning.split("at t = ")[1].split(" s")[0])
    assert 0.0 < t < 0.9


def test_a_source_in_the_moving_arm_at_time_0_is_an_error_as_for_a_robot_that_stands(tmp_path):
    """A moving robot stands where its first keyframe puts it for the interpenetration checks: a mug
    on the forearm's spot at yaw -1 overlaps it."""
    path = _sweep_scene(tmp_path, 0.1253, mug="0.2955 -0.4603 0.33")
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2
    assert "<object> 'arm/forearm' and 'mug' interpenetrate by" in result.stderr
