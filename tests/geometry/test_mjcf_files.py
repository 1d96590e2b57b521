"""MJCF models with mesh geoms (``dejaview.geometry.mjcf_files``): mesh names resolve by the robot files'
one rule (meshdir/assetdir, strippath, file://, package://, includes), the meshes lie where MuJoCo puts
them, and ``<object mjcf>``, ``import-mjcf`` and ``export-mjcf`` take them."""

from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from dejaview.errors import SceneError
from dejaview.geometry.mjcf_files import MeshOutsideRoot, read_mjcf
from dejaview.geometry.robot import link_transforms, read_robot

mujoco = pytest.importorskip("mujoco", reason="the mujoco package (test extra) compiles MJCF models")

ROBOT = """<mujoco><compiler angle="radian" {compiler}/>
<asset><mesh {name} file="{file}" scale="{scale}"/></asset>
<worldbody><body name="b" pos="0 0 1"><joint name="j" type="hinge" range="-1 1"/>
<geom type="mesh" mesh="part" pos="0.1 0.2 0.3" euler="0.3 0.2 0.1"/></body></worldbody></mujoco>"""


def part_mesh(folder: Path, name: str = "part.stl") -> Path:
    """A box off its file's origin and turned: MuJoCo moves it into its inertial frame."""
    folder.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.4, (1, 1, 0)))
    mesh.apply_translation((0.3, -0.1, 0.05))
    mesh.export(folder / name)
    return folder / name


def robot(tmp_path, compiler='meshdir="meshes"', file="part.stl", scale="2 2 2", name='name="part"') -> Path:
    path = tmp_path / "robot.xml"
    path.write_text(ROBOT.format(compiler=compiler, file=file, scale=scale, name=name))
    return path


def test_a_mesh_geom_lies_where_mujoco_puts_it(tmp_path):
    mesh_file = part_mesh(tmp_path / "meshes")
    model = read_robot(robot(tmp_path), "mjcf")
    (g,) = model.geometry
    assert g.kind == "mesh" and g.mesh == mesh_file and g.scale == 2.0 and g.convex_hull  # as MuJoCo collides
    assert model.files == (mesh_file,)
    pose = link_transforms(model, (0.5,))["b"] @ g.origin
    ours = trimesh.load(mesh_file).vertices * g.scale @ pose[:3, :3].T + pose[:3, 3]
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "robot.xml"))
    d = mujoco.MjData(m)
    d.qpos[:] = 0.5
    mujoco.mj_kinematics(m, d)
    theirs = m.mesh_vert[:m.mesh_vertnum[0]] @ d.geom_xmat[0].reshape(3, 3).T + d.geom_xpos[0]
    gap = np.linalg.norm(ours[:, None] - theirs[None], axis=-1).min(axis=0)
    assert gap.max() < 1e-6


@pytest.mark.parametrize("compiler, file, name", [
    ('meshdir="meshes"', "part.stl", 'name="part"'),
    ('assetdir="meshes"', "part.stl", ""),  # no name: MuJoCo names it after the file
    ('meshdir="meshes" strippath="true"', "elsewhere/part.stl", 'name="part"'),
    ("", "meshes/part.stl", 'name="part"'),
    ("", "{abs}", 'name="part"'),
    ("", "file://{abs}", 'name="part"'),
    ("", "package://pkg/meshes/part.stl", 'name="part"'),  # the model's folder is called pkg
])
def test_mesh_names_resolve_by_the_robot_files_rule(tmp_path, compiler, file, name):
    mesh_file = part_mesh(tmp_path / "pkg" / "meshes")
    path = robot(tmp_path / "pkg", compiler, file.format(abs=mesh_file), name=name)
    source = read_mjcf(path)
    assert source.meshes == (("part", mesh_file),)
    assert read_robot(path, "mjcf").geometry[0].mesh == mesh_file


def test_an_include_is_spliced_in_and_its_meshes_found(tmp_path):
    mesh_file = part_mesh(tmp_path / "meshes")
    (tmp_path / "assets.xml").write_text('<mujoco><asset><mesh name="part" file="part.stl"/></asset></mujoco>')
    path = tmp_path / "robot.xml"
    path.write_text(ROBOT.format(compiler='meshdir="meshes"', file="part.stl", scale="1 1 1", name='name="x"')
                    .replace("<asset>", '<include file="assets.xml"/><asset>'))
    source = read_mjcf(path)
    assert source.files == (tmp_path / "assets.xml", mesh_file, mesh_file)
    assert len(read_robot(path, "mjcf").geometry) == 1


@pytest.mark.parametrize("kwargs, reason", [
    (dict(scale="1 1 2"), "geom '#0': mesh 'part' has scale 1.0 1.0 2.0; it must be uniform and positive"),
    (dict(file="part.ply"), "robot.xml:2: <mesh> mesh 'part.ply': unsupported suffix '.ply' (use one of .obj, .stl)"),
    (dict(file="http://host/part.stl"), "mesh 'http://host/part.stl': http:// URIs are not resolved"),
    (dict(file="file://host/part.stl"), "a file:// URI names an absolute path on this machine"),
    (dict(file="package://nothere/part.stl"), "package 'nothere' not found: looked for nothere/part.stl in"),
])
def test_mesh_problems_are_one_line_naming_file_and_line(tmp_path, kwargs, reason):
    part_mesh(tmp_path / "meshes")
    with pytest.raises(SceneError) as info:
        read_robot(robot(tmp_path, **kwargs), "mjcf")
    assert reason in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_files_outside_the_root_are_refused_unread(tmp_path):
    mesh_file = part_mesh(tmp_path / "outside")
    root = tmp_path / "root"
    root.mkdir()
    for file in (str(mesh_file), f"file://{mesh_file}", "../outside/part.stl"):
        with pytest.raises(MeshOutsideRoot, match="leads outside the scene root"):
            read_robot(robot(root, compiler="", file=file), "mjcf", root=root)


def test_validate_simulate_and_export_take_an_mjcf_robots_meshes(tmp_path):
    """A mesh box link (0.2 m cube, top at z 0.5) in a scene: valid, a ball dropped on it rests on its
    top, and the export holds it as a mesh geom MuJoCo loads."""
    from dejaview.cli import cli
    from dejaview.io.mjcf import export_mjcf
    from dejaview.scene import Scene
    from dejaview.sim.simulate import simulate

    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=(0.2, 0.2, 0.2)).export(tmp_path / "meshes" / "cube.stl")
    (tmp_path / "robot.xml").write_text(
        '<mujoco><compiler angle="radian" meshdir="meshes"/><asset><mesh file="cube.stl"/></asset>'
        '<worldbody><body name="post" pos="0 0 0.4"><joint name="turn" type="hinge" axis="0 0 1" range="-1 1"/>'
        '<geom type="mesh" mesh="cube"/></body></worldbody></mujoco>')
    scene_path = tmp_path / "scene.xml"
    scene_path.write_text("""<scene version="1">
  <simulation dt="0.002" duration="0.8" friction="0.5" restitution="0.0"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="arm" mjcf="robot.xml" joints="0.3" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.03" mass="0.1"><pose position="0.02 0.01 0.7"/></object>
</scene>""")
    result = CliRunner().invoke(cli, ["validate", str(scene_path)])
    assert result.exit_code == 0, result.output
    scene = Scene.from_xml(scene_path)
    run = simulate(scene, engine="native")
    end = run.world.object_position(run.trajectory.final)[0, run.world.body_index("ball")].numpy()
    assert end == pytest.approx((0.02, 0.01, 0.53), abs=0.003)
    model = mujoco.MjModel.from_xml_string(export_mjcf(scene))
    kinds = {model.geom(g).name: int(model.geom_type[g]) for g in range(model.ngeom)}
    assert kinds["arm/post"] == mujoco.mjtGeom.mjGEOM_MESH


def test_import_mjcf_finds_package_meshes_and_takes_a_hull_for_a_mesh_with_holes(tmp_path):
    """import-mjcf reads mesh files by the same rule; a mesh with holes (an open box) is written as its
    convex hull, which is what MuJoCo collides."""
    from dejaview.io.mjcf import import_mjcf

    folder = tmp_path / "pkg" / "meshes"
    folder.mkdir(parents=True)
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2])
    assert not open_box.is_watertight
    open_box.export(folder / "open.stl")
    model = tmp_path / "pkg" / "model.xml"
    model.write_text('<mujoco><asset><mesh file="package://pkg/meshes/open.stl"/></asset><worldbody>'
                     '<geom name="floor" type="plane" size="1 1 0.1"/><geom name="crate" type="mesh" mesh="open" pos="0 0 0.1"/>'
                     '<body name="ball" pos="0 0 1"><freejoint/><geom type="sphere" size="0.05" mass="0.1"/></body>'
                     "</worldbody></mujoco>")
    scene = import_mjcf(model, tmp_path / "out" / "scene.xml")
    crate = trimesh.load(tmp_path / "out" / scene.object("crate").mesh)
    assert crate.is_watertight and crate.volume == pytest.approx(0.008, rel=1e-6)
