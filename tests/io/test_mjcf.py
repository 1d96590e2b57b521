"""MuJoCo round trips (dejaview.io.mjcf, dejaview export-mjcf / import-mjcf), checked in MuJoCo itself.

Skipped only where the ``mujoco`` package is missing: it is a test extra (``.[test]``), installed by
``scripts/setup`` and so in CI, like ``tests/sim/test_mujoco_crosscheck.py``'s cross-checks."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.io.mjcf import damping_ratio, export_mjcf, import_mjcf, restitution_of
from dejaview.scene import Scene

mujoco = pytest.importorskip("mujoco", reason="the mujoco test extra is not installed: pip install '.[test]'")

ROOT = Path(__file__).resolve().parents[2]
SCENES = sorted((ROOT / "examples" / "scenes").glob("*.xml"))

SLIDING = """<scene version="1" name="box-across-table">
  <simulation dt="0.002" duration="1.0" friction="0.5" restitution="0.0"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="table" shape="box" size="1.6 0.8 0.7" fixed="true"><pose position="0 0 0.35"/></object>
  <object id="box" shape="box" size="0.2 0.15 0.1" mass="1.0">
    <pose position="-0.5 0 0.75"/><velocity linear="2.0 0 0"/>
  </object>
</scene>"""

MODEL = """<mujoco model="table-world">
  <worldbody>
    <geom name="ground" type="plane" size="0 0 1" friction="0.6 0 0"/>
    <geom name="table" type="box" pos="0 0 0.35" size="0.8 0.4 0.35" friction="0.6 0 0"/>
    <body name="block" pos="0 0 0.76">
      <freejoint/>
      <geom type="box" size="0.05 0.05 0.05" mass="0.5" friction="0.6 0 0" solref="0.004 1"/>
    </body>
  </worldbody>
  <keyframe>
    <key name="pushed" qpos="-0.3 0 0.75 1 0 0 0" qvel="1.5 0 0 0 0 0"/>
  </keyframe>
</mujoco>"""


BALL_DROP = """<scene version="1"><simulation dt="0.002" duration="1.0" restitution="0.6"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.4"><pose position="0 0 0.5"/></object></scene>"""
"""A ball (radius 5 cm) dropped from 0.45 m above the floor onto it, restitution 0.6."""


def _rebound_apex(model, rising: float = 0.0) -> float:
    """Highest the ball's bottom gets above the floor in 0.8 s from keyframe 0, once it rises faster
    than ``rising`` (m/s) after its impact."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    bounced, apex = False, 0.0
    while data.time < 0.8:
        mujoco.mj_step(model, data)
        bounced = bounced or data.qvel[2] > rising
        if bounced:
            apex = max(apex, float(data.qpos[2]) - 0.05)
    return apex


def _run_mujoco(xml: str, seconds: float) -> tuple:
    """Load MJCF text, reset to keyframe 0 and step; returns (model, data)."""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    for _ in range(round(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
    return model, data


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_export_of_every_bundled_scene_loads_and_runs_in_mujoco(path):
    scene = Scene.from_xml(path)
    model, data = _run_mujoco(export_mjcf(scene), 0.2)
    assert model.key("initial").id == 0
    assert np.all(np.isfinite(data.qpos))
    for i, obj in enumerate(scene.movable):
        body = model.body(obj.id)
        adr = model.jnt_qposadr[body.jntadr[0]]
        np.testing.assert_allclose(model.key_qpos[0][adr:adr + 3], obj.pose.position)
        # nobody was launched out of the scene (MuJoCo's convex hulls of non-convex meshes would)
        assert data.xpos[body.id][2] < max(2.0, obj.pose.position[2] + 0.5)


def test_box_sliding_across_a_table_ends_within_3cm_in_both_engines():
    """2 m/s with mu = 0.5: it slides v^2 / (2 mu g) = 0.41 m and stops on the table."""
    from dejaview.sim.simulate import simulate

    scene = Scene.from_string(SLIDING)
    run = simulate(scene)
    dejaview_end = run.trajectory.states.position[-1, 0, 0].numpy()
    model, data = _run_mujoco(export_mjcf(scene), 1.0)
    mujoco_end = data.xipos[model.body("box").id]
    expected = np.array([-0.5 + 2.0 ** 2 / (2 * 0.5 * 9.81), 0.0, 0.75])
    assert np.linalg.norm(mujoco_end - expected) < 0.03
    assert np.linalg.norm(dejaview_end - expected) < 0.03
    assert np.linalg.norm(dejaview_end - mujoco_end) < 0.03


def test_export_at_another_timestep_keeps_the_restitution(tmp_path):
    """--timestep writes MuJoCo's step and maps the damping for it: a ball dropped with e = 0.6
    rebounds as high at 50 us as at the default 0.5 ms (the damping differs)."""
    from dejaview.io.mjcf import MJ_TIMESTEP

    scene = Scene.from_string(BALL_DROP)
    apexes, dampings = [], []
    for dt in (MJ_TIMESTEP, 5e-5):
        xml = export_mjcf(scene, timestep=dt)
        model = mujoco.MjModel.from_xml_string(xml)
        assert model.opt.timestep == pytest.approx(dt)
        dampings.append(float(model.geom_solref[0][1]))
        apexes.append(_rebound_apex(model))
    assert dampings[0] != pytest.approx(dampings[1])
    assert apexes[1] == pytest.approx(apexes[0], rel=0.03) and apexes[0] == pytest.approx(0.45 * 0.36, rel=0.1)
    out = tmp_path / "ball.xml"
    scene_path = tmp_path / "ball_scene.xml"
    scene.write(scene_path)
    result = CliRunner().invoke(cli, ["export-mjcf", str(scene_path), "-o", str(out), "--timestep", "5e-5"])
    assert result.exit_code == 0, result.output
    assert mujoco.MjModel.from_xml_path(str(out)).opt.timestep == pytest.approx(5e-5)
    bad = CliRunner().invoke(cli, ["export-mjcf", str(scene_path), "-o", str(out), "--timestep", "-1"])
    assert bad.exit_code != 0 and "--timestep" in bad.output


def test_state_from_a_result_json_goes_into_the_keyframe(tmp_path):
    """The mug (centre of mass off its frame origin) launched spinning: MuJoCo sees the same
    centre-of-mass velocity and world angular velocity as DejaView's initial_state."""
    scene = Scene.from_xml(ROOT / "examples" / "scenes" / "mug_thrown.xml")
    q = (math.cos(0.3), 0.0, math.sin(0.3), 0.0)
    state = {"source": "mug", "initial_state": {"position": [0.1, 0.2, 1.3], "orientation": list(q),
                                                "linear_velocity": [0.4, -0.2, 1.0],
                                                "angular_velocity": [1.0, 2.0, -3.0]}}
    result = tmp_path / "result.json"
    result.write_text(json.dumps(state))
    out = tmp_path / "mug.xml"
    cli_result = CliRunner().invoke(cli, ["export-mjcf", str(ROOT / "examples/scenes/mug_thrown.xml"),
                                          "-o", str(out), "--state", str(result)])
    assert cli_result.exit_code == 0, cli_result.output
    model = mujoco.MjModel.from_xml_path(str(out))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("initial").id)
    mujoco.mj_forward(model, data)
    body = model.body("mug").id
    np.testing.assert_allclose(data.xpos[body], [0.1, 0.2, 1.3], atol=1e-12)
    np.testing.assert_allclose(data.xquat[body], q, atol=1e-12)
    vel = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, vel, 0)
    np.testing.assert_allclose(vel[:3], [1.0, 2.0, -3.0], atol=1e-9)
    np.testing.assert_allclose(vel[3:], [0.4, -0.2, 1.0], atol=1e-9)
    assert model.body_mass[body] == pytest.approx(scene.object("mug").mass)


def test_import_mjcf_with_a_plane_a_table_and_a_free_body_validates_and_simulates(tmp_path):
    from dejaview.sim.simulate import simulate

    model = tmp_path / "model.xml"
    model.write_text(MODEL)
    out = tmp_path / "scene" / "scene.xml"
    result = CliRunner().invoke(cli, ["import-mjcf", str(model), "-o", str(out), "--key", "pushed"])
    assert result.exit_code == 0, result.output
    assert CliRunner().invoke(cli, ["validate", str(out)]).exit_code == 0
    scene = Scene.from_xml(out)
    assert [o.id for o in scene.objects] == ["ground", "table", "block"]
    block = scene.object("block")
    assert not block.fixed and block.shape == "box" and block.size == pytest.approx((0.1, 0.1, 0.1))
    assert block.mass == pytest.approx(0.5) and block.friction == pytest.approx(0.6)
    # solref "0.004 1" at the model's 2 ms step: as damped as a stable explicit contact gets
    assert block.restitution == 0.0
    assert block.pose.position == pytest.approx((-0.3, 0.0, 0.75))
    assert block.velocity.linear == pytest.approx((1.5, 0.0, 0.0))
    assert scene.object("table").fixed and scene.object("ground").shape == "plane"
    # it simulates: the block slides 1.5^2 / (2 * 0.6 * 9.81) = 0.19 m along the table
    run = simulate(scene.replace(simulation=scene.simulation.__class__(duration=0.8, friction=0.6,
                                                                       restitution=0.0)))
    end = run.trajectory.states.position[-1, 0, 0].numpy()
    assert end == pytest.approx([-0.3 + 1.5 ** 2 / (2 * 0.6 * 9.81), 0.0, 0.75], abs=0.03)
    # without --key: qpos0 (the body's own pose), at rest
    rest = import_mjcf(model, tmp_path / "rest.xml")
    assert rest.object("block").pose.position == pytest.approx((0.0, 0.0, 0.76))
    assert rest.object("block").velocity.linear == pytest.approx((0.0, 0.0, 0.0))


def test_round_trip_of_a_primitive_scene(tmp_path):
    scene = Scene.from_xml(ROOT / "examples" / "scenes" / "ball_down_ramp.xml")
    model = tmp_path / "m.xml"
    model.write_text(export_mjcf(scene))
    back = import_mjcf(model, tmp_path / "back.xml", key="initial")
    assert [o.id for o in back.objects] == [o.id for o in scene.objects]
    ramp, ramp_back = scene.object("ramp"), back.object("ramp")
    assert ramp_back.size == pytest.approx(ramp.size)
    assert ramp_back.pose.position == pytest.approx(ramp.pose.position, abs=1e-9)
    assert np.abs(np.dot(ramp_back.pose.orientation, ramp.pose.orientation)) == pytest.approx(1.0)
    assert back.object("ball").restitution == pytest.approx(scene.simulation.restitution, abs=1e-6)


def test_restitution_maps_to_a_damping_ratio_and_back():
    assert restitution_of(damping_ratio(0.0)) == 0.0
    for e in (0.05, 0.2, 0.5, 0.9):
        assert restitution_of(damping_ratio(e)) == pytest.approx(e, abs=1e-6)


@pytest.mark.parametrize("restitution", [0.3, 0.7, 0.9])
def test_exported_ball_rebounds_in_mujoco_with_the_scene_restitution(restitution):
    """A ball dropped 0.45 m onto the floor rises to e^2 x 0.45 m in MuJoCo, as in DejaView.

    The classic damping ratio of a spring-damper that may pull (the mapping before) made MuJoCo's
    ball rebound with 0.40 at e = 0.3 and diverge at e = 0.9."""
    mujoco = pytest.importorskip("mujoco", reason="the mujoco test extra is not installed: pip install '.[test]'")
    text = f"""<scene version="1"><simulation dt="0.002" duration="1" restitution="{restitution}"/>
      <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
      <object id="ball" shape="sphere" radius="0.05" mass="0.4">
        <pose position="0 0 0.5" orientation="1 0 0 0"/></object></scene>"""
    model = mujoco.MjModel.from_xml_string(export_mjcf(Scene.from_string(text)))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    z, landed = [], False
    for _ in range(1600):
        mujoco.mj_step(model, data)
        z.append(float(data.xipos[1, 2]))
        landed = landed or z[-1] < 0.05
    i = int(np.argmin(z))
    apex = max(z[i:]) - 0.05
    assert apex == pytest.approx(restitution ** 2 * 0.45, rel=0.25)


@pytest.mark.parametrize("restitution", [0.5, 0.7, 0.9])
def test_exported_ball_dropped_with_sideways_speed_leaves_the_floor_rolling(restitution):
    """A ball dropped 0.45 m at 0.3 m/s sideways (friction 0.5): Coulomb friction can stop its
    slip within the impact (it needs 2/7 of 0.3 m/s, the normal impulse gives up to 2.5 m/s), so
    it leaves rolling, at 5/7 of its speed, in DejaView as in a rigid impact. Each exported
    contact pair's friction decays a slip at twice the contact frequency (``solreffriction``); with
    MuJoCo's default, the normal contact's damping (2 zeta omega_0: 61 /s at e = 0.7), it left
    slipping at 0.06, 0.14 and 0.24 m/s (e = 0.5, 0.7, 0.9). MuJoCo's soft friction leaves it
    spinning a little fast: slip -0.010 and 0.2081-0.2087 m/s at every e (-0.007 to -0.009 and
    0.2100 at 4 omega_0)."""
    text = f"""<scene version="1"><simulation dt="0.002" duration="1" friction="0.5" restitution="{restitution}"/>
      <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
      <object id="ball" shape="sphere" radius="0.05" mass="0.4">
        <pose position="0 0 0.5" orientation="1 0 0 0"/><velocity linear="0.3 0 0"/></object></scene>"""
    xml = export_mjcf(Scene.from_string(text), timestep=5e-5)
    assert xml.count("<pair ") == 1
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    for _ in range(round(0.45 / model.opt.timestep)):  # the impact is over by 0.35 s
        mujoco.mj_step(model, data)
    slip = data.qvel[0] - 0.05 * data.qvel[4]  # the contact point's speed along x (spin about y)
    assert abs(slip) < 0.015, slip
    assert data.qvel[0] == pytest.approx(0.3 * 5 / 7, abs=0.008)


@pytest.mark.parametrize("spin", [20.0, 50.0])
def test_exported_ball_landing_with_backspin_rebounds_as_without_it_and_leaves_rolling(spin):
    """A ball (friction 0.5, e 0.3) landing at 2 m/s with backspin (slip 1 and 2.5 m/s): the
    normal passes through its centre, so in a rigid impact with Coulomb friction the slip changes
    neither the normal impulse nor the rebound, and friction (it needs 2/7 of the slip, the normal
    impulse allows 1.3 m/s) leaves it rolling at 2/7 of the slip. MuJoCo's convex soft contact
    couples its friction's reference into the normal force: at the export's friction damping,
    twice the contact frequency (``mjcf.FRICTION_DAMPING``), the rebound stays within 0.010 m/s
    of the spinless one; at 4 omega_0 it lost 0.027 and 0.088 m/s, at 8 0.19 (spin 50); at 1
    omega_0 the slip was not stopped (7 % short of rolling). MuJoCo at 5 us, its converged step."""
    def land(w):
        text = f"""<scene version="1"><simulation dt="0.002" duration="1" friction="0.5" restitution="0.3"/>
          <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
          <object id="ball" shape="sphere" radius="0.05" mass="0.4">
            <pose position="0 0 0.06" orientation="1 0 0 0"/><velocity linear="0 0 -2" angular="0 {w} 0"/>
          </object></scene>"""
        model = mujoco.MjModel.from_xml_string(export_mjcf(Scene.from_string(text), timestep=5e-6))
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, 0)
        for _ in range(round(0.03 / model.opt.timestep)):  # the impact is over by 0.02 s
            mujoco.mj_step(model, data)
        return data.qvel.copy()

    plain, spun = land(0.0), land(spin)
    assert plain[2] > 0.3  # in flight after the bounce
    assert spun[2] == pytest.approx(plain[2], abs=0.02)
    assert spun[0] == pytest.approx(2 / 7 * spin * 0.05, rel=0.01)


def test_errors_are_one_line(tmp_path):
    model = tmp_path / "model.xml"
    model.write_text(MODEL)
    result = CliRunner().invoke(cli, ["import-mjcf", str(model), "-o", str(tmp_path / "s.xml"),
                                      "--key", "nope"])
    assert result.exit_code != 0 and "no keyframe 'nope' (keyframes: pushed)" in str(result.exception)
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><geom type='box'/></worldbody>")
    result = CliRunner().invoke(cli, ["import-mjcf", str(broken), "-o", str(tmp_path / "s.xml")])
    assert "broken.xml:1: not well-formed XML" in str(result.exception)
    broken.write_text("<mujoco><worldbody><geom type='nope'/></worldbody></mujoco>")
    result = CliRunner().invoke(cli, ["import-mjcf", str(broken), "-o", str(tmp_path / "s.xml")])
    assert "MuJoCo cannot compile the model" in str(result.exception) and "\n" not in str(result.exception)
    static = tmp_path / "static.xml"
    static.write_text("<mujoco><worldbody><geom type='plane' size='1 1 1'/></worldbody></mujoco>")
    result = CliRunner().invoke(cli, ["import-mjcf", str(static), "-o", str(tmp_path / "s.xml")])
    assert "no body with a free joint" in str(result.exception)
    bad_state = tmp_path / "r.json"
    bad_state.write_text('{"source": "nobody", "initial_state": {}}')
    result = CliRunner().invoke(cli, ["export-mjcf", str(SCENES[0]), "-o", str(tmp_path / "m.xml"),
                                      "--state", str(bad_state)])
    assert "state: expected a result.json" in str(result.exception)


def test_export_with_mujoco_s_default_contact_carries_the_friction_and_not_the_rebound(tmp_path):
    """``contact="mujoco"``: MuJoCo's own soft, critically damped contact (no solref, solimp or
    cone written), the scene's friction kept: a ball dropped with e = 0.6 rebounds in the mapped
    export and hardly at all in this one, and a box slides as far in both (the friction carried)."""
    ball = Scene.from_string(BALL_DROP)
    apexes = {}
    for contact, dt in (("mapped", 5e-4), ("mujoco", 0.002)):
        xml = export_mjcf(ball, timestep=dt, contact=contact)
        assert ("solref" in xml) == (contact == "mapped") and ("impratio" in xml) == (contact == "mapped")
        apexes[contact] = _rebound_apex(mujoco.MjModel.from_xml_string(xml), rising=0.05)
    assert apexes["mapped"] == pytest.approx(0.45 * 0.36, rel=0.1)
    assert apexes["mujoco"] < 0.1 * apexes["mapped"]
    scene = Scene.from_string(SLIDING)
    model, data = _run_mujoco(export_mjcf(scene, timestep=0.002, contact="mujoco"), 1.0)
    assert model.pair_friction[0][0] == pytest.approx(0.5) and model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    end = data.xipos[model.body("box").id]
    assert abs(end[0] - (-0.5 + 2.0 ** 2 / (2 * 0.5 * 9.81))) < 0.03
    with pytest.raises(Exception, match="contact"):
        export_mjcf(scene, contact="soft")
    out = tmp_path / "box.xml"
    path = tmp_path / "box_scene.xml"
    scene.write(path)
    result = CliRunner().invoke(cli, ["export-mjcf", str(path), "-o", str(out), "--contact", "mujoco"])
    assert result.exit_code == 0, result.output
    assert "solref" not in out.read_text()
