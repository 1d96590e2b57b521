"""One physics per candidate (``World.physics``, ``dejaview.sim.physics``): friction, restitution and
stiffness as parameters of the rollout, with exact reverse-mode gradients in both engines."""

import math

import pytest
import torch

from dejaview.errors import SceneError
from dejaview.scene import Scene
from dejaview.sim import StaticShape
from dejaview.sim.integrate import rollout
from dejaview.sim.physics import PhysicsModel
from dejaview.sim.world import World
from tests.sim.test_native_gradients import _batch, _loss, _pile

PHYSICS = torch.tensor([[0.1, -0.2, 0.15], [-0.3, 0.4, -0.1], [0.0, 0.0, 0.0]], dtype=torch.float64)


def _pile_batch(restitution=0.2):
    world, state = _pile(boxes=3, restitution=restitution)
    return world, _batch(state, 3)


def _loss_and_grad(world, state, engine, physics, steps=60):
    p = physics.clone().requires_grad_(True)
    loss = _loss(rollout(world, state, steps=steps, engine=engine, physics=p))
    (g,) = torch.autograd.grad(loss, p)
    return float(loss), g


@pytest.mark.parametrize("restitution", [0.2, 0.06])
def test_native_physics_gradient_matches_torch_and_finite_differences(restitution):
    """Also at a restitution whose unloading factor is below zero (0.06: phi about -0.04), where the
    contact force is cut off at zero late in each unloading and the physics' factor acts on
    phi - UNLOAD_MIN."""
    world, state = _pile_batch(restitution)
    if restitution < 0.1:
        assert float(world.unload_static.max()) < 0.0 and float(world.unload_pair.max()) < 0.0
    ln, gn = _loss_and_grad(world, state, "native", PHYSICS)
    lt, gt = _loss_and_grad(world, state, "torch", PHYSICS)
    assert ln == pytest.approx(lt, rel=1e-10)
    assert float((gn - gt).abs().max()) <= 1e-8 * float(gt.abs().max())
    eps = 1e-6
    fd = torch.zeros_like(PHYSICS)
    with torch.no_grad():
        for i in range(PHYSICS.shape[0]):
            for j in range(3):
                up, down = PHYSICS.clone(), PHYSICS.clone()
                up[i, j] += eps
                down[i, j] -= eps
                fd[i, j] = (_loss(rollout(world, state, steps=60, engine="native", physics=up))
                            - _loss(rollout(world, state, steps=60, engine="native", physics=down))) / (2 * eps)
    assert float((gn - fd).abs().max()) <= 1e-3 * float(fd.abs().max())
    assert bool((gn.abs() > 0).all())  # every parameter moves this pile's loss


def test_zero_physics_is_the_scene_physics_bit_for_bit():
    world, state = _pile_batch()
    plain = rollout(world, state, steps=40, engine="native").states.position
    zero = rollout(world, state, steps=40, engine="native", physics=torch.zeros(3, 3, dtype=torch.float64))
    assert torch.equal(plain, zero.states.position)


def test_forward_mode_through_physics_is_refused():
    world, state = _pile_batch()
    p = PHYSICS.clone()
    with pytest.raises(Exception, match="reverse mode only"):
        torch.func.jacfwd(lambda ph: rollout(world, state, steps=5, engine="native",
                                             physics=ph).states.position.sum())(p)


def _slide(friction_log: float, engine: str) -> float:
    """How far a box slid at 2 m/s on a floor of friction 0.5 goes with its friction scaled."""
    from tests.sim.conftest import box_body, make_world

    world = make_world([box_body("box", size=(0.1, 0.1, 0.1), per_axis=(3, 3, 3), mass=1.0)],
                       [StaticShape.make("floor", "plane", friction=0.5)])
    state = world.state([[0.0, 0.0, 0.05]], linear_velocity=[[2.0, 0.0, 0.0]])
    physics = torch.tensor([[friction_log, 0.0, 0.0]], dtype=torch.float64)
    traj = rollout(world, state, steps=600, engine=engine, physics=physics)
    return float(traj.states.position[-1, 0, 0, 0])


@pytest.mark.parametrize("engine", ["native", "torch"])
def test_friction_factor_scales_the_sliding_distance(engine):
    mu = 0.5
    for factor in (0.6, 0.8):  # mu 0.3 and 0.4: sliding (at higher friction the packed box tips)
        d = _slide(math.log(factor), engine)
        expected = 2.0 ** 2 / (2 * mu * factor * 9.81)
        assert d == pytest.approx(expected, rel=0.1), (factor, d, expected)


SCENE = """<scene version="1">
  <simulation dt="0.002" duration="1.0" friction="0.5" restitution="{e}"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.2"><pose position="0 0 0.5"/></object>
  <inference source="ball">
    <target position="0.3 0 0.05"/>
    <physics-prior {prior}/>
  </inference>
</scene>"""


def _model(e=0.5, prior='friction="0.3" restitution="0.3"'):
    scene = Scene.from_string(SCENE.format(e=e, prior=prior))
    return PhysicsModel.from_scene(scene, World.from_scene(scene))


def _bounce(world, physics) -> float:
    """Restitution of a ball dropped from 0.3 m onto the floor: its fastest rise after the impact
    over its fastest fall before it (a rebound height would drown a low restitution's in the
    contact's depth)."""
    state = world.state([[0.0, 0.0, 0.35]])
    traj = rollout(world, state, steps=300, engine="native", physics=physics)
    z = traj.states.position[:, 0, 0, 2]
    vz = traj.states.linear_velocity[:, 0, 0, 2]
    first = int(torch.argmin(z[:250]))
    return float(vz[first:].max() / -vz[:first].min())


def test_restitution_is_what_a_scene_written_with_it_rebounds_with():
    model = _model(e=0.5)
    scene = Scene.from_string(SCENE.format(e=0.5, prior='restitution="0.3"'))
    world = World.from_scene(scene)
    for target in (0.07, 0.3, 0.7):  # 0.07: an unloading factor below zero (restitution.UNLOAD_MIN)
        z = torch.tensor([[0.0, math.log(target / 0.5) / 0.3]], dtype=torch.float64)
        values = model.values(z)
        assert float(values[0, 1]) == pytest.approx(target, rel=1e-9)
        inferred = _bounce(world, model.engine_logs(z))
        written = Scene.from_string(SCENE.format(e=target, prior='restitution="0.3"'))
        assert inferred == pytest.approx(_bounce(World.from_scene(written), None), abs=0.01)


def test_values_are_centred_on_the_scene_and_restitution_stays_below_one():
    model = _model(e=0.5)
    zero = model.values(torch.zeros(1, 2, dtype=torch.float64))[0]
    assert zero[0] == pytest.approx(0.5) and zero[1] == pytest.approx(0.5)
    high = model.values(torch.tensor([[0.0, 10.0]], dtype=torch.float64))[0]
    assert float(high[1]) == 1.0
    assert model.names == ("friction", "restitution")


def test_restitution_prior_on_a_scene_without_restitution_is_one_line_error():
    with pytest.raises(SceneError, match="restitution"):
        _model(e=0.0)


@pytest.mark.parametrize("value", ["-0.1", "nan", "11", "abc"])
def test_absurd_physics_priors_are_one_line_errors(value):
    from dejaview.scene.validate import validate_scene

    with pytest.raises(SceneError) as err:
        validate_scene(Scene.from_string(SCENE.format(e=0.5, prior=f'friction="{value}"')))
    assert "physics-prior" in str(err.value) and "\n" not in str(err.value)
