"""Scene input: paths stay inside the scene root (``..``, absolute paths, symlinks), meshes too."""

from __future__ import annotations

import pytest

from dejaview.server.config import ServerConfig
from dejaview.server.errors import ServiceError
from dejaview.server.scenes import check_job, read_scene_input, resolve_scene_path

from .conftest import FIXTURES


def read(root, **kw):
    return read_scene_input(root, max_bytes=1 << 20, **kw)


@pytest.mark.parametrize("name", ["ball.xml", "sub/cube.xml", "./ball.xml", "sub/../ball.xml"])
def test_paths_inside_the_root_resolve(scene_root, name):
    assert resolve_scene_path(scene_root.resolve(), name).is_relative_to(scene_root.resolve())


@pytest.mark.parametrize("name, code", [
    ("../outside/secret.xml", "path_outside_root"),
    ("sub/../../outside/secret.xml", "path_outside_root"),
    ("/etc/passwd", "path_outside_root"),
    ("C:\\Windows\\win.ini", "path_outside_root"),
    ("escape.xml", "path_outside_root"),          # a symlink out of the root
    ("linked/secret.xml", "path_outside_root"),   # through a symlinked folder
    ("missing.xml", "scene_not_found"),
    ("sub", "scene_not_found"),                   # a folder
    ("", "scene_not_found"),
    ("a\x00b.xml", "scene_not_found"),
    ("x" * 5000, "scene_not_found"),              # name too long for the OS
])
def test_paths_that_leave_the_root_or_name_nothing_are_refused(scene_root, name, code):
    with pytest.raises(ServiceError) as info:
        resolve_scene_path(scene_root.resolve(), name)
    assert info.value.code == code


def test_outside_files_are_refused_before_anyone_looks_at_them(scene_root):
    # same answer whether or not the file outside exists: no oracle for the rest of the disk
    a = pytest.raises(ServiceError, resolve_scene_path, scene_root.resolve(), "../outside/secret.xml")
    b = pytest.raises(ServiceError, resolve_scene_path, scene_root.resolve(), "../outside/nothing.xml")
    assert a.value.code == b.value.code == "path_outside_root"


def mesh_scene(mesh: str) -> str:
    return f"""<scene version="1"><simulation dt="0.01" duration="0.05"/>
      <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
      <object id="cube" mesh="{mesh}" mass="0.5"><pose position="0 0 0.2"/></object></scene>"""


def test_uploaded_xml_resolves_meshes_against_the_root(scene_root):
    got = read(scene_root.resolve(), scene_xml=mesh_scene("meshes/cube.obj"))
    assert got.base_dir == scene_root.resolve() and got.source == {"scene_xml": got.source["scene_xml"]}
    # an absolute path is fine as long as it lands inside the root
    read(scene_root.resolve(), scene_xml=mesh_scene(str(scene_root.resolve() / "meshes" / "cube.obj")))


@pytest.mark.parametrize("mesh", ["../outside/secret.obj", "/etc/hostname.obj", "linked/secret.obj",
                                  "meshes/../../outside/secret.obj"])
def test_uploaded_xml_with_a_mesh_outside_the_root_is_refused(scene_root, mesh):
    with pytest.raises(ServiceError) as info:
        read(scene_root.resolve(), scene_xml=mesh_scene(mesh))
    assert info.value.code == "path_outside_root"


def test_a_scene_file_may_use_dotdot_inside_the_root(scene_root):
    got = read(scene_root.resolve(), scene_path="sub/cube.xml")
    assert got.source == {"scene_path": "sub/cube.xml"}


def test_missing_mesh_inside_the_root_is_a_scene_error_with_line(scene_root):
    with pytest.raises(ServiceError) as info:
        read(scene_root.resolve(), scene_xml=mesh_scene("meshes/nothing.obj"))
    assert info.value.code == "invalid_scene" and "<scene_xml>:3:" in info.value.message


def test_scene_size_limit(scene_root):
    text = (FIXTURES / "ball.xml").read_text()
    with pytest.raises(ServiceError) as info:
        read_scene_input(scene_root.resolve(), scene_xml=text, max_bytes=100)
    assert info.value.code == "scene_too_large" and info.value.status == 413


def test_job_limits(scene_root, tmp_path):
    config = ServerConfig(scene_root=scene_root, results_dir=tmp_path, max_steps=40, max_iterations=10,
                          max_heatmap_runs=4, max_objects=2)
    ball = read(scene_root.resolve(), scene_path="ball.xml").scene  # 20 steps x 2 substeps, 3 iterations
    check_job("solve", ball, {}, config)
    check_job("heatmap", ball, {}, config)  # 2 x 2 cells x 1 sample
    for kind, overrides, fragment in [("simulate", {"steps": 21}, "42 integration substeps"),
                                      ("solve", {"iterations": 11}, "11 iterations"),
                                      ("heatmap", {"cells": [3, 2]}, "6 runs")]:
        with pytest.raises(ServiceError) as info:
            check_job(kind, ball, overrides, config)
        assert info.value.code == "limit_exceeded" and fragment in info.value.message
    with pytest.raises(ServiceError, match="objects"):
        check_job("simulate", ball, {}, config.replace(max_objects=1))
    drop = read(scene_root.resolve(), scene_path="drop.xml").scene
    for kind in ("solve", "heatmap"):
        with pytest.raises(ServiceError) as info:
            check_job(kind, drop, {}, config)
        assert info.value.code == "invalid_scene" and "no <inference>" in info.value.message


def robot_scene(urdf: str, joints: str = "0 0.3 -0.3") -> str:
    return f"""<scene version="1"><simulation dt="0.01" duration="0.05"/>
      <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
      <object id="arm" urdf="{urdf}" joints="{joints}" fixed="true"><pose position="0 0 0"/></object>
      <object id="ball" shape="sphere" radius="0.03" mass="0.1"><pose position="0.5 0 0.6"/></object></scene>"""


def urdf_with_mesh(mesh: str) -> str:
    return f"""<robot name="r"><link name="base"><collision><geometry>
      <mesh filename="{mesh}"/></geometry></collision></link>
      <link name="arm"><collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision></link>
      <joint name="j" type="revolute"><parent link="base"/><child link="arm"/>
      <limit lower="-1" upper="1"/></joint></robot>"""


def test_robot_files_and_the_meshes_they_name_stay_inside_the_root(scene_root, tmp_path):
    root = scene_root.resolve()
    (root / "robots").mkdir(exist_ok=True)
    (root / "robots" / "ok.urdf").write_text(urdf_with_mesh("../meshes/cube.obj"))
    got = read(root, scene_xml=robot_scene("robots/ok.urdf", joints="0.5"))
    assert got.scene.object("arm").joints == (0.5,)
    # a URDF outside the root, and a URDF inside that names a mesh outside (relative, absolute, symlink)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret.obj").write_text("v 0 0 0\n")
    (outside / "arm.urdf").write_text(urdf_with_mesh("secret.obj"))
    (root / "robots" / "up.urdf").write_text(urdf_with_mesh("../../elsewhere/secret.obj"))
    (root / "robots" / "abs.urdf").write_text(urdf_with_mesh(str(outside / "secret.obj")))
    (root / "robots" / "link.obj").symlink_to(outside / "secret.obj")
    (root / "robots" / "sym.urdf").write_text(urdf_with_mesh("link.obj"))
    for urdf in (str(outside / "arm.urdf"), "../elsewhere/arm.urdf", "robots/up.urdf", "robots/abs.urdf",
                 "robots/sym.urdf"):
        with pytest.raises(ServiceError) as info:
            read(root, scene_xml=robot_scene(urdf, joints="0"))
        assert info.value.code == "path_outside_root", urdf
        if urdf.startswith("robots/"):  # what the URDF names outside is not shown: nothing about the disk
            assert str(outside) not in info.value.message and "elsewhere" not in info.value.message


def test_hostile_or_wrong_robot_files_are_one_line_scene_errors(scene_root):
    root = scene_root.resolve()
    (root / "robots").mkdir(exist_ok=True)
    (root / "robots" / "bomb.urdf").write_text(
        '<?xml version="1.0"?>\n<!DOCTYPE r [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;">]>\n'
        '<robot name="&b;"><link name="x"/></robot>')
    (root / "robots" / "ext.urdf").write_text(
        '<!DOCTYPE r SYSTEM "file:///etc/passwd"><robot name="r"><link name="x"/></robot>')
    (root / "robots" / "ok.urdf").write_text(urdf_with_mesh("../meshes/cube.obj"))
    cases = {"robots/bomb.urdf": "robots/bomb.urdf:2: <!DOCTYPE> DOCTYPE declarations are not allowed in URDF",
             "robots/ext.urdf": "robots/ext.urdf:1: <!DOCTYPE> DOCTYPE declarations are not allowed in URDF",
             "robots/ok.urdf": "'joints' needs 1 values, one per movable joint of ok.urdf (j), got 2"}
    for urdf, reason in cases.items():
        with pytest.raises(ServiceError) as info:
            read(root, scene_xml=robot_scene(urdf, joints="0 0"))
        assert info.value.code == "invalid_scene" and reason in info.value.message, info.value.message
        assert "\n" not in info.value.message
    with pytest.raises(ServiceError) as info:
        read(root, scene_xml=robot_scene("robots/ok.urdf", joints="1.5"))
    assert "joint 'j' = 1.5 rad is outside its limits [-1.0, 1.0] rad" in info.value.message
