"""Robots that move (``<joints time values>``, ``dejaview.sim.motion``): a link pushing a box, against a
closed form and against MuJoCo driving the same motion kinematically; a turntable carrying a box
(closed form); the sweep example; the export's motion."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from dejaview.scene import Scene
from dejaview.sim.simulate import simulate

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
G, MU = 9.81, 0.5

PUSHER = """<?xml version="1.0"?>
<robot name="pusher">
  <link name="base"/>
  <link name="paddle">
    <collision><geometry><box size="0.04 0.4 0.08"/></geometry></collision>
  </link>
  <joint name="slide" type="prismatic">
    <parent link="base"/><child link="paddle"/>
    <origin xyz="0 0 0.05"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="10" velocity="2"/>
  </joint>
</robot>
"""

# the paddle (its face 2 cm ahead of its joint) moves from -0.2 to 0.1 m at 0.6 m/s, then stops;
# the box (10 cm, at x = 0.1) is met at 0.38 s, pushed along and let go at 0.5 s
SPEED, START, STOP, T_STOP = 0.6, -0.2, 0.1, 0.5
BOX_X = 0.1


def pusher_scene(tmp_path: Path) -> Scene:
    (tmp_path / "pusher.urdf").write_text(PUSHER)
    return Scene.from_string(f"""<scene version="1">
  <simulation dt="0.002" duration="1.0" friction="{MU}" restitution="0.0"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="pusher" urdf="pusher.urdf" fixed="true">
    <pose position="0 0 0"/>
    <joints time="0" values="{START}"/>
    <joints time="{T_STOP}" values="{STOP}"/>
  </object>
  <object id="box" shape="box" size="0.1 0.1 0.1" mass="0.5"><pose position="{BOX_X} 0 0.05"/></object>
</scene>""", base_dir=tmp_path)


def mujoco_pusher_end() -> float:
    """The box's end x in MuJoCo: the paddle on a slide joint whose position and velocity are set to
    the same motion before every step (a kinematic drive, so the contact sees its velocity), the
    contacts as ``export-mjcf`` maps DejaView's (``contact_parameters``)."""
    mujoco = pytest.importorskip("mujoco")
    from dejaview.io.mjcf import MJ_TIMESTEP, OPTION, contact_parameters

    c = contact_parameters(MU, 0.0, 250.0 * 2, MJ_TIMESTEP)  # the scene's default at 4 substeps
    geom = " ".join(f'{k}="{v}"' for k, v in c.items())
    option = " ".join(f'{k}="{v}"' for k, v in OPTION.items())
    model = mujoco.MjModel.from_xml_string(f"""<mujoco>
  <option timestep="{MJ_TIMESTEP}" {option}/>
  <worldbody>
    <geom type="plane" size="0 0 1" {geom}/>
    <body name="paddle" pos="0 0 0.05"><joint name="slide" type="slide" axis="1 0 0"/>
      <geom type="box" size="0.02 0.2 0.04" mass="100" {geom}/></body>
    <body name="box" pos="{BOX_X} 0 0.05"><freejoint/><geom type="box" size="0.05 0.05 0.05" mass="0.5" {geom}/></body>
  </worldbody>
</mujoco>""")
    data = mujoco.MjData(model)
    while data.time < 1.0:
        t = data.time
        data.qpos[0] = START + SPEED * min(t, T_STOP)
        data.qvel[0] = SPEED if t < T_STOP else 0.0
        mujoco.mj_step(model, data)
    return float(data.qpos[1])


def test_a_moving_link_pushes_a_box_as_the_closed_form_and_mujoco_say(tmp_path):
    scene = pusher_scene(tmp_path)
    run = simulate(scene, engine="native")
    end = run.world.object_position(run.trajectory.final)[0, run.world.body_index("box")].numpy()
    # pushed at the paddle's speed until it stops (its face at STOP + 0.02, the box's back against
    # it), then sliding to rest under Coulomb friction: SPEED^2 / (2 mu g) further
    closed = STOP + 0.02 + 0.05 + SPEED ** 2 / (2 * MU * G)
    assert end[0] == pytest.approx(closed, abs=0.005)
    assert abs(end[1]) < 1e-6 and end[2] == pytest.approx(0.05, abs=0.002)
    assert end[0] == pytest.approx(mujoco_pusher_end(), abs=0.01)


def test_a_link_standing_still_pushes_nothing(tmp_path):
    """The same paddle with one keyframe (it stands at -0.2): the box stays where it is."""
    scene = pusher_scene(tmp_path)
    from dataclasses import replace

    arm = scene.object("pusher")
    still = replace(scene, objects=tuple(replace(o, keyframes=o.keyframes[:1]) if o.id == "pusher" else o
                                         for o in scene.objects))
    assert arm.moving and still.object("pusher").moving
    run = simulate(still, engine="native")
    end = run.world.object_position(run.trajectory.final)[0, run.world.body_index("box")].numpy()
    assert end[0] == pytest.approx(BOX_X, abs=1e-4)


TURNTABLE = """<?xml version="1.0"?>
<robot name="turntable">
  <link name="base"/>
  <link name="plate"><collision><origin xyz="0 0 -0.025"/><geometry><box size="1.0 1.0 0.05"/></geometry></collision></link>
  <joint name="turn" type="continuous">
    <parent link="base"/><child link="plate"/><origin xyz="0 0 0.05"/><axis xyz="0 0 1"/>
  </joint>
</robot>
"""


def test_a_turntable_carries_a_box_round_as_the_closed_form_says(tmp_path):
    """A box resting on a plate that turns (speeding up in steps of 0.25 and 0.5 rad/s, to 1 rad/s,
    then stopping at 1.5 rad): friction turns it with the plate, so it ends about 1.5 rad round and
    turned by 1.5 rad itself. At each jump dv of the plate's speed under it the box slips
    dv^2 / (2 mu g) (behind while the plate speeds up, ahead when it stops). Without the link's
    velocity in the contact the box would see no slip and stay where it was."""
    (tmp_path / "turntable.urdf").write_text(TURNTABLE)
    keys = [(0.0, 0.0), (0.5, 0.125), (1.0, 0.5), (1.5, 1.0), (2.0, 1.5)]
    frames = "\n".join(f'<joints time="{t}" values="{q}"/>' for t, q in keys)
    scene = Scene.from_string(f"""<scene version="1">
  <simulation dt="0.002" duration="2.5" friction="0.8" restitution="0.0"/>
  <object id="table" urdf="turntable.urdf" fixed="true"><pose position="0 0 0"/>{frames}</object>
  <object id="box" shape="box" size="0.1 0.1 0.1" mass="0.5"><pose position="0.3 0 0.1"/></object>
</scene>""", base_dir=tmp_path)
    run = simulate(scene, engine="native")
    final = run.trajectory.final
    end = run.world.object_position(final)[0, 0].numpy()
    r, mu = 0.3, 0.8
    jumps = [r * dw for dw in (0.25, 0.5, 0.25)]  # speeding up: slips behind
    arc = r * 1.5 - sum(dv ** 2 for dv in jumps) / (2 * mu * G) + (r * 1.0) ** 2 / (2 * mu * G)
    assert math.hypot(*end[:2]) == pytest.approx(r, abs=0.002)  # the stop: 5.7 mm along the tangent
    assert r * math.atan2(end[1], end[0]) == pytest.approx(arc, abs=0.001)
    q = final.orientation[0, 0].numpy()
    yaw = 2 * math.atan2(q[3], q[0])
    # the stop leaves it sliding for r w / (mu g) = 38 ms, its spin of 1 rad/s running down meanwhile
    assert yaw == pytest.approx(1.5 + 0.5 * 1.0 * r * 1.0 / (mu * G), abs=0.005)
    assert float(np.linalg.norm(final.linear_velocity[0, 0].numpy())) < 0.01  # at rest with the plate


def test_the_sweep_example_reproduces_its_target_and_the_mug_starts_on_the_table():
    """examples/scenes/arm_sweeps_mug.xml: the truth's start, simulated, ends at the target (the
    mug on the floor); the guess in the file does not."""
    scene = Scene.from_xml(EXAMPLES / "scenes" / "arm_sweeps_mug.xml")
    truth = json.loads((EXAMPLES / "scenes" / "arm_sweeps_mug.truth.json").read_text())
    assert scene.object("arm").moving
    from dejaview.sim import World
    from dejaview.sim.integrate import rollout

    world = World.from_scene(scene)
    mug = world.body_index("mug")
    init = truth["initial_state"]
    state = world.state([init["position"]], [init["orientation"]])
    end = world.object_position(rollout(world, state, engine="native").final)[0, mug].numpy()
    target = np.asarray(scene.inference.target.position)
    assert np.allclose(end, target, atol=1e-5)
    assert target[2] < 0.1 and init["position"][2] > 0.3  # from the table top to the floor
    guess = world.object_position(rollout(world, world.state([scene.object("mug").pose.position]),
                                          engine="native").final)[0, mug].numpy()
    assert np.linalg.norm(guess - target) > 0.1


def test_the_export_drives_the_links_in_mujoco():
    """export-mjcf of the sweep: the links are mocap bodies, the motion keyframes follow the
    sweep, and a MuJoCo replay with ``drive_mocap`` knocks the mug off the table too."""
    mujoco = pytest.importorskip("mujoco")
    from dejaview.io.mjcf import export_mjcf
    from dejaview.io.mjcf_motion import MOTION_INTERVAL, drive_mocap

    scene = Scene.from_xml(EXAMPLES / "scenes" / "arm_sweeps_mug.xml")
    truth = json.loads((EXAMPLES / "scenes" / "arm_sweeps_mug.truth.json").read_text())
    model = mujoco.MjModel.from_xml_string(export_mjcf(scene, state={"source": "mug", **truth}))
    assert model.nmocap == 4  # base, turret, upper arm, forearm
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("initial").id)
    last = model.key(model.nkey - 1)
    assert float(last.time[0]) == pytest.approx(0.9) and model.nkey == 2 + round(0.9 / MOTION_INTERVAL)
    forearm = model.body("arm/forearm").mocapid[0]
    start = data.mocap_pos[forearm].copy()
    while data.time < 2.0:
        drive_mocap(model, data)
        mujoco.mj_step(model, data)
    # the forearm turned from -1.0 to 0.9 rad about the base, 0.55 m out
    assert math.atan2(*data.mocap_pos[forearm][1::-1]) == pytest.approx(0.9, abs=1e-3)
    assert math.atan2(*start[1::-1]) == pytest.approx(-1.0, abs=1e-3)
    mug = data.qpos[:3]
    assert mug[2] < 0.1 and mug[1] > 0.5  # on the floor beyond the table's +y edge, as in DejaView


def test_a_moving_urdf_robot_built_from_its_scene_is_the_same_in_both_engines():
    """The World of a scene with a moving URDF robot (paths by forward kinematics): its forearm bats a
    ball about, the torch and native engines alike (states within 1e-9)."""
    import torch

    from dejaview.sim import World
    from dejaview.sim.integrate import rollout

    scene = Scene.from_string(f"""<scene version="1">
  <simulation dt="0.002" duration="0.2" friction="0.5" restitution="0.3"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="arm" urdf="{EXAMPLES / 'robots' / 'arm.urdf'}" fixed="true"><pose position="0 0 0"/>
    <joints time="0" values="-0.4 0.1253 -0.1253"/><joints time="0.3" values="0.8 0.1253 -0.1253"/>
  </object>
  <object id="ball" shape="sphere" radius="0.04" mass="0.2"><pose position="0.5 0.05 0.35"/></object>
</scene>""")
    world = World.from_scene(scene)
    assert world.moving and len(world.statics[-1].path) == 301  # to 0.3 s at h = 1 ms
    state = world.state([[0.5, 0.05, 0.35]], batch_size=1)
    ref = rollout(world, state, steps=80)
    out = rollout(world, state, steps=80, engine="native")
    assert float(ref.final.linear_velocity[0, 0, 1]) > 0.3  # batted along +y by the turning forearm
    for x, y in zip(ref.states.tensors(), out.states.tensors()):
        assert torch.allclose(x, y, rtol=0, atol=1e-9), float((x - y).abs().max())


def test_a_moving_robot_changes_its_substeps_with_its_paths_sampled_again(tmp_path):
    """``World.with_substeps`` samples a moving robot's links again at the new substep (by forward
    kinematics, as a World built at that substep has them), and the pusher still ends where the
    closed form says; back at the old substep the paths are the old ones."""
    import torch

    from dejaview.sim import World
    from dejaview.sim.integrate import rollout

    scene = pusher_scene(tmp_path)
    world = World.from_scene(scene)
    assert world.moving and world.substeps == 4
    fine = world.with_substeps(8)
    text = scene.to_xml().replace('restitution="0.0"', 'restitution="0.0" substeps="8"', 1)
    built = World.from_scene(Scene.from_string(text, base_dir=tmp_path))
    paddle, again, ref = (w.statics[-1] for w in (fine, fine.with_substeps(4), built))
    assert len(paddle.path) == len(ref.path) == 2 * len(world.statics[-1].path) - 1  # to 0.5 s at h = 0.25 ms
    for a, b in zip(paddle.path.rows(), ref.path.rows()):
        assert torch.allclose(a, b, rtol=0, atol=1e-12)
    assert torch.equal(again.path.rows(), world.statics[-1].path.rows())
    run = rollout(fine, fine.state([[BOX_X, 0.0, 0.05]]), steps=500, engine="native")
    end = fine.object_position(run.final)[0, 0].numpy()
    assert end[0] == pytest.approx(STOP + 0.02 + 0.05 + SPEED ** 2 / (2 * MU * G), abs=0.005)
