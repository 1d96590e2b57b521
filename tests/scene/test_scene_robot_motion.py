"""A moving robot's ``<joints time values>`` keyframes in scene files: read, written back, and refused
with one line naming the scene file and the keyframe's line where they do not fit."""

from pathlib import Path

import pytest

from dejaview.errors import SceneError
from dejaview.scene import JointKeyframe, Scene

ROOT = Path(__file__).resolve().parents[2]
ARM = ROOT / "examples" / "robots" / "arm.urdf"


def scene_text(frames: str, robot: str = f'urdf="{ARM}" fixed="true"') -> str:
    return f"""<scene version="1">
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="arm" {robot}>
    <pose position="0 0 0"/>
    {frames}
  </object>
  <object id="ball" shape="sphere" radius="0.03" mass="0.1"><pose position="0.5 0 0.8"/></object>
</scene>"""


def read(tmp_path, text: str) -> Scene:
    path = tmp_path / "scene.xml"
    path.write_text(text)
    return Scene.from_xml(path)


def test_keyframes_read_interpolate_and_write_back(tmp_path):
    scene = read(tmp_path, scene_text('<joints time="0" values="0 0.1 0"/>\n'
                                      '    <joints time="0.5" values="1 0.1 -0.4"/>'))
    arm = scene.object("arm")
    assert arm.moving and arm.joints is None
    assert arm.keyframes == (JointKeyframe(0.0, (0.0, 0.1, 0.0)), JointKeyframe(0.5, (1.0, 0.1, -0.4)))
    assert arm.joints_at(-1.0) == (0.0, 0.1, 0.0) and arm.joints_at(9.0) == (1.0, 0.1, -0.4)
    assert arm.joints_at(0.25) == pytest.approx((0.5, 0.1, -0.2))
    again = Scene.from_string(scene.to_xml())
    assert again == scene and again.object("arm").keyframes == arm.keyframes
    still = read(tmp_path, scene_text("", f'urdf="{ARM}" joints="0 0 0" fixed="true"'))
    assert not still.object("arm").moving and still.object("arm").joints_at(3.0) == (0.0, 0.0, 0.0)


def test_a_moving_robot_stands_at_its_first_keyframe_for_the_checks(tmp_path):
    """validate's interpenetration checks and the viewer pose a moving robot at time 0."""
    from dejaview.geometry.robot import robot_pieces

    scene = read(tmp_path, scene_text('<joints time="0.2" values="0.5 0 0"/><joints time="1" values="1 0 0"/>'))
    still = read(tmp_path, scene_text("", f'urdf="{ARM}" joints="0.5 0 0" fixed="true"'))
    a = {p.name: p.position for p in robot_pieces(scene, scene.object("arm"))}
    b = {p.name: p.position for p in robot_pieces(still, still.object("arm"))}
    assert a == b


@pytest.mark.parametrize("frames, robot, reason, line", [
    ('<joints time="0" values="0 0"/>', None,
     '<joints time="0"> needs 3 values, one per movable joint of arm.urdf (shoulder_yaw shoulder_pitch elbow), '
     "got 2", 5),
    ('<joints time="0" values="0 0 0"/>\n    <joints time="0.5" values="0 0 0"/>\n'
     '    <joints time="0.5" values="1 0 0"/>', None, "<joints> times must increase: 0.5 s follows 0.5 s", 7),
    ('<joints time="0.4" values="0 0 0"/>\n    <joints time="0.1" values="1 0 0"/>', None,
     "<joints> times must increase: 0.1 s follows 0.4 s", 6),
    ('<joints time="-1" values="0 0 0"/>', None, "'time' must be >= 0", 5),
    ('<joints time="0" values="0 nan 0"/>', None, "attribute 'values' is not finite", 5),
    ('<joints time="inf" values="0 0 0"/>', None, "attribute 'time' is not finite", 5),
    ('<joints time="0" values="0 0 0"/>\n    <joints time="1" values="0 2.0 0"/>', None,
     "joint 'shoulder_pitch' = 2.0 rad is outside its limits [-1.6, 1.6] rad", 6),
    ('<joints time="0" values="0 0 0"/>', 'urdf="ARM" joints="0 0 5" fixed="true"',
     "joint 'elbow' = 5.0 rad is outside its limits", 3),
    ('<joints time="0" values="0 0 0"/>', 'shape="box" size="0.1 0.1 0.1" fixed="true"',
     "<joints> keyframes apply to a robot only", 5),
    ('<joints values="0 0 0"/>', None, "time", 5),
])
def test_keyframe_problems_are_one_line_errors_with_file_and_line(tmp_path, frames, robot, reason, line):
    robot = None if robot is None else robot.replace("ARM", str(ARM))
    with pytest.raises(SceneError) as info:
        read(tmp_path, scene_text(frames, robot) if robot else scene_text(frames))
    err = info.value
    assert reason in str(err), str(err)
    assert err.file == str(tmp_path / "scene.xml") and err.line == line and "\n" not in str(err)

