"""Contact capacity: only the deepest spheres of each contact set are computed.

A capacity that holds every touching sphere changes nothing (states and
gradients equal the dense computation); one that does not keeps the deepest.
"""

import math

import numpy as np
import pytest
import torch

from dejaview.errors import SceneError, SimulationError
from dejaview.sim import BodySpec, StaticShape
from dejaview.sim.contacts import pair_contact_wrench
from dejaview.sim.integrate import rollout, wrench
from dejaview.sim.state import State
from dejaview.sim.world import DEFAULT_MAX_PAIR_CONTACTS, DEFAULT_MAX_STATIC_CONTACTS
from tests.sim.conftest import box_body, make_world

DENSE = 10 ** 9


def _boxes(max_static, max_pair):
    # 4 x 4 x 2 = 32 spheres per box: 32 static candidates per body, 1024 per pair
    bodies = [box_body(f"box{i}", size=(0.1, 0.1, 0.05), per_axis=(4, 4, 2), mass=0.5)
              for i in range(2)]
    return make_world(bodies, [StaticShape.make("floor", "plane")],
                      max_static_contacts=max_static, max_pair_contacts=max_pair)


def _throw(world, v0=None):
    v = torch.tensor([[[1.2, 0.0, 0.0], [0.0, 0.0, 0.0]]], dtype=torch.float64) if v0 is None else v0
    s = world.state([[0.0, 0.0, 0.08], [0.16, 0.01, 0.025]],
                    orientation=[[math.cos(0.2), math.sin(0.2), 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    return s.replace(linear_velocity=v)


def _max_touching(world, traj):
    """Most touching spheres of one body on the floor, and of the body pair, over a trajectory."""
    sph = world.sphere_positions(State(*(t[:, 0] for t in traj.states.tensors())))  # records as batch
    d, _ = world.statics[0].distance(sph)
    static = int((world.radii - d > 0).sum(-1).max())
    dist = torch.linalg.vector_norm(sph[:, 1].unsqueeze(-3) - sph[:, 0].unsqueeze(-2), dim=-1)
    pair = int((world.radii[0][:, None] + world.radii[1][None, :] - dist > 0).sum((-1, -2)).max())
    return static, pair


def test_a_capacity_that_holds_every_contact_changes_nothing():
    dense = _boxes(DENSE, DENSE)
    capped = _boxes(20, 40)  # below the candidates (32, 1024), above what touches
    ref = rollout(dense, _throw(dense), steps=150)
    static, pair = _max_touching(dense, ref)
    assert 4 <= static <= 20 and 1 <= pair <= 40  # the boxes land and collide; the caps hold them
    out = rollout(capped, _throw(capped), steps=150)
    moved = torch.linalg.vector_norm(ref.final.position[0, 1] - ref.states.position[0, 0, 1])
    assert moved > 0.01  # the thrown box knocked the other
    assert torch.allclose(out.states.position, ref.states.position, rtol=0, atol=1e-12)
    assert torch.allclose(out.states.orientation, ref.states.orientation, rtol=0, atol=1e-12)


@pytest.mark.parametrize("mode", ["reverse", "forward"])
def test_gradients_through_a_capped_collision_equal_the_dense_ones(mode):
    def end_x(world):
        def f(v):
            s = _throw(world, torch.cat([v.reshape(1, 1, 3), torch.zeros(1, 1, 3, dtype=v.dtype)], 1))
            return rollout(world, s, steps=60).final.position[0, :, 0].sum()
        return f

    v0 = torch.tensor([1.2, 0.0, 0.0], dtype=torch.float64)
    grads = []
    for world in (_boxes(DENSE, DENSE), _boxes(20, 40)):
        if mode == "reverse":
            g = torch.func.grad(end_x(world))(v0)
        else:
            g = torch.func.jacfwd(end_x(world))(v0)
        grads.append(g)
    assert torch.isfinite(grads[0]).all() and grads[0].abs().max() > 0.01
    assert torch.allclose(grads[1], grads[0], rtol=1e-9, atol=1e-12)


def test_a_capacity_of_one_keeps_the_deepest_sphere():
    """A box tilted into the floor, capacity 1: the contact wrench is the deepest sphere's alone."""
    box = box_body("box", size=(0.2, 0.15, 0.1), per_axis=(4, 3, 2))
    floor = StaticShape.make("floor", "plane")
    world = make_world([box], [floor], max_static_contacts=1)
    q = (np.array([0.98, 0.05, 0.15, 0.02]) / np.linalg.norm([0.98, 0.05, 0.15, 0.02])).tolist()
    state = world.state([[0.0, 0.0, 0.045]], orientation=[q], linear_velocity=[[0.3, 0.0, -0.2]])
    sph = world.sphere_positions(state)  # (1, 1, S, 3)
    depth = world.radii[0] - floor.distance(sph)[0][0, 0]
    deepest = int(depth.argmax())  # (a tilt about no symmetry axis: no tie)
    assert (depth > 0).sum() >= 3  # several spheres touch; the cap drops all but one
    one = BodySpec("box", box.mass, box.inertia, box.com, box.centers[deepest:deepest + 1],
                   box.radii[deepest:deepest + 1])
    world_one = make_world([one], [floor])
    f, t = wrench(world, state, world.dt / world.substeps)[:2]
    f1, t1 = wrench(world_one, state, world.dt / world.substeps)[:2]
    assert torch.allclose(f, f1, rtol=1e-12) and torch.allclose(t, t1, rtol=1e-12)
    f_dense = wrench(make_world([box], [floor]), state, world.dt / world.substeps)[0]
    assert (f_dense - f).abs().max() > 1e-3 * f.abs().max()  # the cap did change the force


def test_pair_capacity_keeps_the_deepest_sphere_pairs():
    """Capacity 1 on a body pair: the wrench of the deepest sphere pair alone."""
    a = box_body("a", size=(0.1, 0.1, 0.1), per_axis=(2, 2, 2))
    b = box_body("b", size=(0.1, 0.1, 0.1), per_axis=(2, 2, 2))
    world = make_world([a, b], [], gravity=(0.0, 0.0, 0.0), max_pair_contacts=1)
    q = [math.cos(0.2), 0.0, 0.0, math.sin(0.2)]
    state = world.state([[0.0, 0.0, 0.0], [0.095, 0.01, 0.0]], orientation=[[1, 0, 0, 0], q],
                        linear_velocity=[[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    sph = world.sphere_positions(state)[0]
    dist = torch.linalg.vector_norm(sph[1].unsqueeze(-3) - sph[0].unsqueeze(-2), dim=-1)
    depth = world.radii[0][:, None] + world.radii[1][None, :] - dist
    assert (depth > 0).sum() >= 2
    i, j = divmod(int(depth.argmax()), depth.shape[1])
    a1 = BodySpec("a", a.mass, a.inertia, a.com, a.centers[i:i + 1], a.radii[i:i + 1])
    b1 = BodySpec("b", b.mass, b.inertia, b.com, b.centers[j:j + 1], b.radii[j:j + 1])
    world1 = make_world([a1, b1], [], gravity=(0.0, 0.0, 0.0))
    inv_w = torch.eye(3, dtype=torch.float64).expand(1, 2, 3, 3) * 10.0
    f, t = pair_contact_wrench(world, state, world.sphere_positions(state), 1e-3, inv_w)
    f1, t1 = pair_contact_wrench(world1, state, world1.sphere_positions(state), 1e-3, inv_w)
    assert f.abs().max() > 0
    assert torch.allclose(f, f1, rtol=1e-12) and torch.allclose(t, t1, rtol=1e-12)


def test_capacities_come_from_the_scene_and_are_checked(tmp_path):
    from dejaview.scene import Scene
    from dejaview.sim import World

    def scene(extra):
        p = tmp_path / "s.xml"
        p.write_text(f"""<scene version="1" name="c">
  <simulation dt="0.002" duration="0.1" {extra}/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="1.0"><pose position="0 0 0.2"/></object>
</scene>""")
        return Scene.from_xml(p)

    world = World.from_scene(scene(""))
    assert world.contact.max_static_contacts == DEFAULT_MAX_STATIC_CONTACTS
    assert world.contact.max_pair_contacts == DEFAULT_MAX_PAIR_CONTACTS
    world = World.from_scene(scene('max-static-contacts="8" max-pair-contacts="16"'))
    assert (world.contact.max_static_contacts, world.contact.max_pair_contacts) == (8, 16)
    with pytest.raises(SceneError, match="max-pair-contacts"):
        World.from_scene(scene('max-pair-contacts="0"'))
    with pytest.raises(SimulationError, match="capacities"):
        make_world([box_body()], [], max_static_contacts=0)
