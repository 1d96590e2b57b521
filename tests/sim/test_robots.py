"""Robots in scenes (URDF/MJCF, ``dejaview.geometry.robot``): their links are static geometry posed by
pytorch-kinematics' forward kinematics, in both simulation engines."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from dejaview.geometry.robot import link_transforms, read_robot, robot_pieces
from dejaview.scene import Scene
from dejaview.sim.simulate import simulate

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
ARM = EXAMPLES / "robots" / "arm.urdf"
FOREARM_HALF_THICKNESS = 0.025  # arm.urdf: the forearm box is 0.05 m thick
BALL_RADIUS = 0.03


def drop_scene(yaw: float, pitch: float, engine_note: str = "") -> str:
    """A ball dropped onto the forearm of the example arm, posed so the forearm is level
    (elbow = -pitch), the robot itself turned and moved by its <pose>."""
    return f"""<scene version="1">
  <simulation dt="0.002" duration="1.0" friction="0.6" restitution="0.0"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="arm" urdf="{ARM}" joints="{yaw} {pitch} {-pitch}" fixed="true">
    <pose position="0.1 -0.05 0" orientation="0.9950041652780258 0 0 0.09983341664682815"/>
  </object>
  <object id="ball" shape="sphere" radius="{BALL_RADIUS}" mass="0.1">
    <pose position="{{x}} {{y}} 0.8"/>
  </object>
</scene>"""


def forearm_top(yaw: float, pitch: float) -> tuple[np.ndarray, float]:
    """Centre (x, y) of the forearm box and the height of its top face, from pytorch-kinematics'
    forward kinematics of the URDF and the robot's <pose> (a turn of 0.2 rad about z, moved
    by (0.1, -0.05, 0))."""
    model = read_robot(ARM, "urdf")
    links = link_transforms(model, (yaw, pitch, -pitch))
    c, s = math.cos(0.2), math.sin(0.2)
    base = np.array([[c, -s, 0, 0.1], [s, c, 0, -0.05], [0, 0, 1, 0], [0, 0, 0, 1]])
    centre = base @ links["forearm"] @ np.array([0.15, 0.0, 0.0, 1.0])
    return centre[:2], float(centre[2]) + FOREARM_HALF_THICKNESS


@pytest.mark.parametrize("engine", ["torch", "native"])
@pytest.mark.parametrize("yaw,pitch", [(0.0, 0.0), (0.7, 0.4)])
def test_ball_dropped_on_a_link_rests_where_forward_kinematics_puts_it(engine, yaw, pitch):
    xy, top = forearm_top(yaw, pitch)
    # the closed form, independently: shoulder 0.4 m up, the upper arm 0.4 m long pitched down
    assert top == pytest.approx(0.4 - 0.4 * math.sin(pitch) + FOREARM_HALF_THICKNESS, abs=1e-6)
    text = drop_scene(yaw, pitch).replace("{x}", repr(float(xy[0]))).replace("{y}", repr(float(xy[1])))
    scene = Scene.from_string(text)
    run = simulate(scene, engine=engine)
    ball = run.world.body_index("ball")
    end = run.world.object_position(run.trajectory.final)[0, ball]
    assert float(end[2]) == pytest.approx(top + BALL_RADIUS, abs=0.003)
    assert np.allclose(end[:2].numpy(), xy, atol=0.01)  # it stayed on the link
    speed = float(torch.linalg.vector_norm(run.trajectory.final.linear_velocity[0, ball]))
    assert speed < 0.05


def test_pieces_are_named_after_the_links_and_posed_by_the_object_pose():
    scene = Scene.from_string(drop_scene(0.0, 0.0).replace("{x}", "0.6").replace("{y}", "0"))
    pieces = robot_pieces(scene, scene.object("arm"))
    assert [p.name for p in pieces] == ["arm/base", "arm/turret", "arm/upper_arm", "arm/forearm"]
    base = pieces[0]
    assert base.kind == "cylinder" and base.radius == 0.12 and base.height == 0.1
    assert base.position == pytest.approx((0.1, -0.05, 0.05))
    assert base.orientation == pytest.approx((0.9950041652780258, 0, 0, 0.09983341664682815))


def test_mjcf_robot_matches_mujoco_forward_kinematics():
    """pytorch-kinematics' pose of an MJCF body tree against MuJoCo's own (mj_kinematics)."""
    mujoco = pytest.importorskip("mujoco", reason="the mujoco package (test extra) checks MJCF poses")
    path = Path(__file__).resolve().parents[1] / "fixtures" / "robots" / "arm.mjcf.xml"
    model = read_robot(path, "mjcf")
    q = (0.4, -0.3)
    links = link_transforms(model, q)
    m = mujoco.MjModel.from_xml_path(str(path))
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    for b in range(1, m.nbody):
        name = m.body(b).name
        assert links[name][:3, 3] == pytest.approx(d.xpos[b], abs=1e-6), name
        assert links[name][:3, :3] == pytest.approx(d.xmat[b].reshape(3, 3), abs=1e-6), name
    kinds = [g.kind for g in model.geometry]
    assert kinds == ["cylinder", "box", "cylinder", "sphere", "sphere"]  # the capsule: cylinder + 2 spheres
