"""Robots in scene files (``<object urdf= | mjcf= joints=>``): read, written back, and refused with one
line naming the scene file and the object's line where the robot file or its joints do not fit."""

from pathlib import Path

import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.errors import SceneError
from dejaview.scene import Scene

ROOT = Path(__file__).resolve().parents[2]
ARM = ROOT / "examples" / "robots" / "arm.urdf"
MJCF = ROOT / "tests" / "fixtures" / "robots" / "arm.mjcf.xml"


def scene_text(robot: str, extra: str = "") -> str:
    return f"""<scene version="1">
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="arm" {robot} {extra}>
    <pose position="0 0 0"/>
  </object>
  <object id="ball" shape="sphere" radius="0.03" mass="0.1"><pose position="0.5 0 0.8"/></object>
</scene>"""


def read(tmp_path, text: str) -> Scene:
    path = tmp_path / "scene.xml"
    path.write_text(text)
    return Scene.from_xml(path)


def test_a_robot_reads_and_writes_back(tmp_path):
    scene = read(tmp_path, scene_text(f'urdf="{ARM}" joints="0.1 -0.2 0.3" fixed="true"'))
    arm = scene.object("arm")
    assert arm.urdf == str(ARM) and arm.joints == (0.1, -0.2, 0.3) and arm.geometry_kind == "urdf"
    again = Scene.from_string(scene.to_xml())
    assert again == scene and again.object("arm").joints == (0.1, -0.2, 0.3)
    mjcf = read(tmp_path, scene_text(f'mjcf="{MJCF}" joints="0.4 -0.3" fixed="true"'))
    assert Scene.from_string(mjcf.to_xml()).object("arm").mjcf == str(MJCF)


@pytest.mark.parametrize("attrs, reason", [
    ('urdf="missing.urdf" joints="0" fixed="true"', "urdf file 'missing.urdf' not found"),
    (f'urdf="{ARM}" joints="0 0" fixed="true"',
     "'joints' needs 3 values, one per movable joint of arm.urdf (shoulder_yaw shoulder_pitch elbow), got 2"),
    (f'urdf="{ARM}" fixed="true"', "'joints' needs 3 values"),
    (f'urdf="{ARM}" joints="0 2.0 0" fixed="true"',
     "joint 'shoulder_pitch' = 2.0 rad is outside its limits [-1.6, 1.6] rad"),
    (f'urdf="{ARM}" joints="0 0 0"', "robot 'arm' must be fixed"),
    (f'urdf="{ARM}" joints="0 0 0" fixed="true" mass="2"', "'mass' does not apply to a robot"),
    (f'urdf="{ARM}" shape="box" size="1 1 1" joints="0 0 0" fixed="true"', "has both shape and urdf"),
    ('shape="box" size="1 1 1" joints="0" fixed="true"', "'joints' applies to a robot only"),
    (f'urdf="{ARM}" joints="0 nan 0" fixed="true"', "attribute 'joints' is not finite"),
    (f'mjcf="{MJCF}" joints="0.4 9" fixed="true"', "joint 'elbow' = 9.0 rad is outside its limits"),
])
def test_robot_problems_are_one_line_errors_with_file_and_line(tmp_path, attrs, reason):
    with pytest.raises(SceneError) as info:
        read(tmp_path, scene_text(attrs))
    err = info.value
    assert reason in str(err), str(err)
    assert err.file == str(tmp_path / "scene.xml") and err.line == 3 and "\n" not in str(err)


@pytest.mark.parametrize("name, text, reason", [
    ("bomb.urdf", '<!DOCTYPE r [<!ENTITY a "x">]><robot name="&a;"/>', "DOCTYPE declarations are not allowed"),
    ("notrobot.urdf", "<mujoco/>", "the root element is <mujoco>, a URDF's is <robot>"),
    ("broken.urdf", "<robot><link name='a'>", "not well-formed XML"),
    ("package.urdf", '<robot name="r"><link name="a"><collision><geometry><mesh filename="package://x/a.stl"/>'
                     "</geometry></collision></link></robot>", "package 'x' not found: looked for x/a.stl in"),
    ("file.urdf", '<robot name="r"><link name="a"><collision><geometry><mesh filename="file:///nowhere/a.stl"/>'
                  "</geometry></collision></link></robot>", "mesh file '/nowhere/a.stl' named by 'file.urdf' not found"),
    ("host.urdf", '<robot name="r"><link name="a"><collision><geometry><mesh filename="file://host/a.stl"/>'
                  "</geometry></collision></link></robot>", "a file:// URI names an absolute path on this machine"),
    ("http.urdf", '<robot name="r"><link name="a"><collision><geometry><mesh filename="http://x/a.stl"/>'
                  "</geometry></collision></link></robot>", "http:// URIs are not resolved"),
    ("floating.urdf", '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="floating">'
                      '<parent link="a"/><child link="b"/></joint></robot>', "joint 'j' is floating"),
    ("nomesh.urdf", '<robot name="r"><link name="a"><collision><geometry><mesh filename="gone.obj"/>'
                    "</geometry></collision></link></robot>", "mesh file"),
])
def test_bad_urdf_files_are_named_with_their_line(tmp_path, name, text, reason):
    (tmp_path / name).write_text(text)
    with pytest.raises(SceneError) as info:
        read(tmp_path, scene_text(f'urdf="{name}" fixed="true"'))
    assert reason in str(info.value) and "\n" not in str(info.value), str(info.value)
    assert str(info.value).startswith(f"{tmp_path / 'scene.xml'}:3:")


def test_an_mjcf_robots_files_are_named_with_their_line(tmp_path):
    """An MJCF robot's include and mesh files are read like a URDF's meshes; what is wrong with them is
    one line naming the MJCF file, its line and what was looked for where."""
    (tmp_path / "inc.xml").write_text('<mujoco>\n<include file="/etc/passwd"/></mujoco>')
    with pytest.raises(SceneError) as info:
        read(tmp_path, scene_text('mjcf="inc.xml" fixed="true"'))
    assert "passwd" in str(info.value) and "not well-formed XML" in str(info.value), str(info.value)
    (tmp_path / "gone.xml").write_text('<mujoco><compiler meshdir="meshes"/>\n<asset><mesh file="a.stl"/></asset>'
                                       '<worldbody><geom type="mesh" mesh="a"/></worldbody></mujoco>')
    with pytest.raises(SceneError) as info:
        read(tmp_path, scene_text('mjcf="gone.xml" fixed="true"'))
    assert f"gone.xml:2: <mesh> mesh 'a.stl': file not found: looked for {tmp_path / 'meshes' / 'a.stl'} " \
           "(meshdir 'meshes')" in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_validate_command_reports_a_robot_problem_in_one_line(tmp_path):
    path = tmp_path / "scene.xml"
    path.write_text(scene_text(f'urdf="{ARM}" joints="0 0 3" fixed="true"'))
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}:3:") and "elbow" in lines[0], result.output


def test_validate_names_an_object_inside_a_link(tmp_path):
    path = tmp_path / "scene.xml"
    # the forearm (level at z 0.4, x 0.4..0.7) and a ball buried in it
    path.write_text(scene_text(f'urdf="{ARM}" joints="0 0 0" fixed="true"').replace("0.5 0 0.8", "0.55 0 0.4"))
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2 and "'arm/forearm' and 'ball' interpenetrate" in result.output, result.output


def test_a_penalty_names_a_link_of_a_robot_not_the_robot(tmp_path):
    base = scene_text(f'urdf="{ARM}" joints="0 0 0" fixed="true"')
    inference = ('<inference source="ball"><target position="0.5 0 0.45"/>'
                 '<penalty between="ball {}"/></inference></scene>')
    scene = read(tmp_path, base.replace("</scene>", inference.format("arm/forearm")))
    assert scene.inference.penalties[0].between == ("ball", "arm/forearm")
    with pytest.raises(SceneError, match="'between' names robot 'arm': name one of its links"):
        read(tmp_path, base.replace("</scene>", inference.format("arm")))


# -- package:// URIs (spec: "Robots as users have them") ----------------------------------------------
BOX_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
PACKAGE_URDF = ('<robot name="r"><link name="a"><collision><geometry><mesh filename="package://{name}/meshes/a.obj" '
                'scale="0.1 0.1 0.1"/></geometry></collision></link></robot>')


def package_tree(tmp_path, name: str = "my_robot") -> Path:
    """A ROS package as checked out: NAME/urdf/r.urdf naming package://NAME/meshes/a.obj; the
    robot's folder is NAME/urdf, so the package is found above it, as a folder called NAME."""
    pkg = tmp_path / "ws" / "src" / name
    (pkg / "meshes").mkdir(parents=True)
    (pkg / "urdf").mkdir()
    (pkg / "meshes" / "a.obj").write_text(BOX_OBJ)
    (pkg / "urdf" / "r.urdf").write_text(PACKAGE_URDF.format(name=name))
    return pkg


def test_package_uris_resolve_in_the_folders_above_the_robot_file(tmp_path):
    from dejaview.geometry.robot import read_robot

    pkg = package_tree(tmp_path)
    model = read_robot(pkg / "urdf" / "r.urdf", "urdf")
    assert model.files == (pkg / "meshes" / "a.obj",) and model.geometry[0].scale == 0.1
    # "the path as it stands": package://meshes/... beside the robot file (pybullet_data's Panda)
    (pkg / "urdf" / "flat.urdf").write_text(PACKAGE_URDF.format(name="meshes").replace("meshes/a.obj", "a.obj"))
    (pkg / "urdf" / "meshes").mkdir()
    (pkg / "urdf" / "meshes" / "a.obj").write_text(BOX_OBJ)
    assert read_robot(pkg / "urdf" / "flat.urdf", "urdf").files == (pkg / "urdf" / "meshes" / "a.obj",)


def test_package_uris_resolve_on_the_package_path_variables_and_the_cli_option(tmp_path, monkeypatch):
    from dejaview.geometry.robot import read_robot

    pkg = package_tree(tmp_path / "elsewhere")
    robot = tmp_path / "robots" / "r.urdf"  # the robot file moved away from its package
    robot.parent.mkdir()
    robot.write_text(PACKAGE_URDF.format(name="my_robot"))
    monkeypatch.delenv("DEJAVIEW_PACKAGE_PATH", raising=False)
    monkeypatch.setenv("ROS_PACKAGE_PATH", str(pkg.parent))
    assert read_robot(robot, "urdf").files == (pkg / "meshes" / "a.obj",)
    # DEJAVIEW_PACKAGE_PATH comes before ROS_PACKAGE_PATH
    other = package_tree(tmp_path / "other")
    monkeypatch.setenv("DEJAVIEW_PACKAGE_PATH", str(other.parent))
    assert read_robot(robot, "urdf").files == (other / "meshes" / "a.obj",)
    monkeypatch.delenv("DEJAVIEW_PACKAGE_PATH")
    monkeypatch.delenv("ROS_PACKAGE_PATH")
    path = tmp_path / "scene.xml"
    path.write_text(scene_text(f'urdf="{robot}" fixed="true"'))
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2 and "package 'my_robot' not found" in result.output
    assert len(result.output.strip().splitlines()) == 1 and f"in {robot.parent} and the" in result.output
    assert "DEJAVIEW_PACKAGE_PATH: (none); ROS_PACKAGE_PATH: (none)" in result.output
    result = CliRunner().invoke(cli, ["validate", str(path), "--package-path", str(pkg.parent)])
    assert result.exit_code == 0, result.output


def test_the_service_resolves_package_uris_only_inside_its_scene_root(tmp_path, monkeypatch):
    from dejaview.geometry.robot import read_robot

    pkg = package_tree(tmp_path / "outside")
    root = tmp_path / "root"
    (root / "robots").mkdir(parents=True)
    robot = root / "robots" / "r.urdf"
    robot.write_text(PACKAGE_URDF.format(name="my_robot"))
    monkeypatch.setenv("DEJAVIEW_PACKAGE_PATH", str(pkg.parent))
    assert read_robot(robot, "urdf").files == (pkg / "meshes" / "a.obj",)
    with pytest.raises(SceneError, match="package 'my_robot' not found: looked for my_robot/meshes/a.obj inside "
                                         "the scene root in .*DEJAVIEW_PACKAGE_PATH: \\(none\\)"):
        read_robot(robot, "urdf", root=root)
    (root / "robots" / "my_robot").symlink_to(pkg)  # a link out of the root is outside it too
    with pytest.raises(SceneError, match="package 'my_robot' not found"):
        read_robot(robot, "urdf", root=root)
    scene = Scene.from_string(scene_text(f'urdf="robots/r.urdf" fixed="true"'), base_dir=root, check_files=False,
                              root=root)
    assert scene.root == root
