"""System identification (``dejaview.inference.identify``): scenes of the same objects share one
physics, each keeps its own start."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace

import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.inference.identify import JointPosterior, identify, shared_scenes
from dejaview.inference.params import IdentifyParams, SearchParams
from dejaview.inference.posterior import Posterior
from dejaview.scene import Scene
from dejaview.sim.build import initial_state
from tests.inference.tracking import position_targets

TRUE = {"friction": 0.3, "restitution": 0.6}
SCENE = """<scene version="1" name="{name}">
  <simulation dt="0.002" duration="{duration}" friction="{friction}" restitution="{restitution}"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.2">
    <pose position="{x} 0 {z}"/><velocity linear="{vx} 0 0" angular="0 0 0"/>
  </object>
  <inference source="ball" loss="position">
    {targets}
    <optimize position="true" orientation="false" linear-velocity="true" angular-velocity="false"/>
    <start-area min="-0.2 -0.1 0.2" max="0.2 0.1 0.6"/>
    <observation sigma="0.003"/>
    {prior}
  </inference>
</scene>"""
THROWS = ({"x": -0.1, "z": 0.4, "vx": 0.8}, {"x": 0.05, "z": 0.5, "vx": 1.2})
TIMES = (0.1, 0.25, 0.4, 0.55, 0.7)


def _scene(k: int, prior: str = '<physics-prior friction="0.5" restitution="0.5"/>', names=None) -> Scene:
    """Throw k of a ball bouncing on the floor, tracked at TIMES in DejaView's engine at TRUE physics;
    the scene says friction 0.5 and restitution 0.4."""
    throw = THROWS[k]
    true = Scene.from_string(SCENE.format(name=f"throw-{k}", duration=0.7, targets='<target position="0 0 0"/>',
                                          prior="", **TRUE, **throw))
    return Scene.from_string(SCENE.format(name=f"throw-{k}", duration=0.7, targets=position_targets(true, TIMES),
                                          prior=prior, friction=0.5, restitution=0.4, x=0.0, z=0.4, vx=0.0))


FAST = IdentifyParams(search=replace(SearchParams(), budget=1500), lm_iterations=25, rounds=1, grid=25, scan=0)


def test_identify_recovers_the_shared_physics_of_two_tracked_throws(tmp_path):
    scenes = [_scene(0), _scene(1)]
    result = identify(scenes, replace(FAST, samples=200))
    physics = result.physics()
    assert physics["inferred"] == ["friction", "restitution"]
    assert physics["most_probable"]["restitution"] == pytest.approx(TRUE["restitution"], abs=0.05)
    lo, hi = physics["intervals"]["restitution"]["90%"]
    assert lo <= TRUE["restitution"] <= hi
    for sc, throw in zip(result.to_json()["scenes"], THROWS):
        assert sc["initial_state"]["position"][0] == pytest.approx(throw["x"], abs=0.02)
        assert sc["initial_state"]["linear_velocity"][0] == pytest.approx(throw["vx"], abs=0.1)
    paths = result.write(tmp_path)
    data = json.loads(paths["result"].read_text())
    assert set(data["physics"]["most_probable"]) == {"friction", "restitution", "stiffness"}
    if "posterior" in paths:  # the importance samples held
        header = next(csv.reader(open(paths["posterior"])))
        assert header[:3] == ["sample", "weight", "throw-0.x"]
        assert header[-3:] == ["friction", "restitution", "stiffness"]
        assert "throw-1.wz" in header


def test_the_joint_posterior_counts_the_physics_prior_once():
    scenes = shared_scenes([_scene(0), _scene(1)], FAST)
    posts = [Posterior.from_scene(s) for s in scenes]
    joint = JointPosterior(posts)
    x = torch.cat([posts[0].layout.encode(), posts[1].layout.encode()], -1)
    x = torch.cat([x[:, :posts[0].layout.start_size], x[:, posts[0].layout.size:posts[0].layout.size
                                                        + posts[1].layout.start_size]], -1)
    z = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
    x = torch.cat([x, z], -1)
    each = sum(float(p.cost(xs)[0][0]) for p, xs in zip(posts, joint.split(x)))
    assert float(joint.cost(x)[0]) == pytest.approx(each - 0.5 * float((z * z).sum()), rel=1e-12)
    r, J = joint.jacobian(x)
    assert 0.5 * float((r * r).sum()) == pytest.approx(float(joint.cost(x)[0]), rel=1e-9)
    assert J.shape == (1, r.shape[1], joint.size)


def test_identify_names_the_scene_that_does_not_share_the_objects():
    other = Scene.from_string(SCENE.format(name="other", duration=0.7, targets='<target position="0 0 0.05"/>',
                                           prior="", friction=0.5, restitution=0.4, x=0, z=0.4, vx=0)
                              .replace('id="ball"', 'id="puck"').replace('source="ball"', 'source="puck"'))
    with pytest.raises(InferenceError, match="other.*source is 'puck'"):
        shared_scenes([_scene(0), other], FAST)
    with pytest.raises(InferenceError, match="at least two"):
        shared_scenes([_scene(0)], FAST)
    with pytest.raises(InferenceError, match="physics-prior"):
        shared_scenes([_scene(0), _scene(1, prior='<physics-prior friction="0.2"/>')], FAST)
