"""A robot's collision meshes as users have them (spec: "Robots as users have them"): a mesh with holes
that cannot be closed takes part as its convex hull, with one ``note:`` line in ``dejaview validate``
and nothing failing; a URDF mesh ``scale`` holds in the simulator, the fcl checks and ``export-mjcf``."""

from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.geometry.mesh import collision_solid
from dejaview.scene import Scene
from dejaview.sim.simulate import simulate

SCALE = 0.5
HALF = 0.2  # the open box's half edge in the file (m): 0.1 at the scale


def open_box(path: Path) -> None:
    """A 0.4 m cube, each face split in four, with its top face's eight triangles gone: a hole of eight
    edges, which trimesh's repair (triangles and quads) cannot close."""
    box = trimesh.creation.box(extents=(2 * HALF,) * 3).subdivide()
    keep = ~np.isclose(box.triangles_center[:, 2], HALF)
    trimesh.Trimesh(box.vertices, box.faces[keep]).export(path)


def scene_with(tmp_path, ball_z: float) -> Path:
    open_box(tmp_path / "open.stl")
    (tmp_path / "r.urdf").write_text(
        '<robot name="r"><link name="base"/><link name="top"><collision><origin xyz="0 0 0.1"/><geometry>'
        f'<mesh filename="open.stl" scale="{SCALE} {SCALE} {SCALE}"/></geometry></collision></link>'
        '<joint name="lift" type="prismatic"><parent link="base"/><child link="top"/><axis xyz="0 0 1"/>'
        '<limit lower="0" upper="1" effort="1" velocity="1"/></joint></robot>')
    path = tmp_path / "scene.xml"
    path.write_text(f"""<scene version="1">
  <simulation dt="0.002" duration="1.0" friction="0.6" restitution="0.0"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="arm" urdf="r.urdf" joints="0.3" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.03" mass="0.1"><pose position="0.02 0.01 {ball_z}"/></object>
</scene>""")
    return path


def test_a_mesh_with_holes_collides_as_its_hull_and_validate_says_so_in_one_line(tmp_path):
    path = scene_with(tmp_path, 0.8)
    solid, hull = collision_solid(tmp_path / "open.stl", SCALE)
    assert hull and solid.is_watertight and np.allclose(solid.extents, 2 * HALF * SCALE)
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 2 and lines[1].startswith(f"OK {path}"), result.output
    assert lines[0] == (f"note: {path}:4: <object> robot 'arm': link 'top': mesh open.stl is not watertight; "
                        "it collides as its convex hull (as in MuJoCo and Bullet)")
    # the ball lands on the hull's top, where the file has a hole: lift 0.3 + 0.1 + half an edge 0.1
    run = simulate(Scene.from_xml(path), engine="native")
    end = run.world.object_position(run.trajectory.final)[0, run.world.body_index("ball")]
    assert float(end[2]) == pytest.approx(0.5 + 0.03, abs=0.003)


def test_the_scale_holds_in_the_fcl_checks_and_the_mjcf_export(tmp_path):
    # the ball's centre 5 cm inside the scaled box's top (z 0.5): 8 cm deep; outside the box unscaled it
    # would be 20 cm inside
    path = scene_with(tmp_path, 0.45)
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2 and "'arm/top' and 'ball' interpenetrate by 0.08" in result.output, result.output
    mujoco = pytest.importorskip("mujoco")
    from dejaview.io.mjcf import export_mjcf

    model = mujoco.MjModel.from_xml_string(export_mjcf(Scene.from_xml(path)))
    geom = model.geom("arm/top")
    vertices = model.mesh_vert[model.mesh_vertadr[geom.dataid[0]]:][:model.mesh_vertnum[geom.dataid[0]]]
    assert np.allclose(np.ptp(vertices, axis=0), 2 * HALF * SCALE)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert data.geom_xpos[geom.id] == pytest.approx([0, 0, 0.4])
