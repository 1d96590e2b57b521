"""Contact penalties: analytic gaps, zero in contact, gradients that pull the bodies together."""

import numpy as np
import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.losses import contact_penalty
from dejaview.sim import BodySpec, State, StaticShape, Trajectory, rollout
from dejaview.sim.rotation import rotvec_to_quat
from tests.losses.helpers import F64, assert_forward_equals_reverse, random_quat, rng
from tests.sim.conftest import ball_body, box_body, make_world

ZERO_G = dict(gravity=(0.0, 0.0, 0.0))


def two_balls(ra=0.05, rb=0.03):
    return make_world([ball_body("a", radius=ra), ball_body("b", radius=rb)], [], **ZERO_G)


def trajectory_of(world, pos, quat=None):
    """A hand-made Trajectory: pos (T, B, N, 3), quat (T, B, N, 4) (default identity)."""
    if quat is None:
        quat = torch.zeros(*pos.shape[:-1], 4, **F64) + torch.tensor([1.0, 0, 0, 0], **F64)
    zero = torch.zeros_like(pos)
    return Trajectory(State(pos, quat, zero, zero), torch.arange(pos.shape[0]), world.dt)


def test_two_separated_balls_give_the_analytic_gap():
    world = two_balls()
    state = world.state([[0.0, 0, 0], [0.2, 0.1, 0.0]], batch_size=1)
    traj = rollout(world, state, steps=3)
    expected = (0.2 ** 2 + 0.1 ** 2) ** 0.5 - 0.05 - 0.03
    gap = contact_penalty(world, traj, "a", "b")
    assert gap.shape == (1,)
    assert abs(gap.item() - expected) < 1e-12
    assert abs(contact_penalty(world, traj, "b", "a").item() - expected) < 1e-12  # symmetric


def test_minimum_over_time_of_approaching_balls():
    world = two_balls()
    x = torch.tensor([0.5, 0.3, 0.2, 0.25], **F64)  # closest at the third record
    pos = torch.zeros(4, 2, 2, 3, **F64)
    pos[:, :, 1, 0] = x[:, None]
    pos[:, 1, 1, 1] = 0.1  # candidate 1 is offset sideways
    gap = contact_penalty(world, trajectory_of(world, pos), "a", "b")
    assert torch.allclose(gap, torch.tensor([0.2 - 0.08, (0.2 ** 2 + 0.01) ** 0.5 - 0.08], **F64))


def test_penalty_is_zero_when_touching_or_overlapping():
    world = two_balls()
    for d in (0.08, 0.07, 0.0):
        traj = rollout(world, world.state([[0.0, 0, 0], [d, 0, 0]]), steps=1)
        assert contact_penalty(world, traj, "a", "b").item() == 0.0


def test_ball_above_a_plane_static():
    floor = StaticShape.make("floor", "plane")
    world = make_world([ball_body(radius=0.05)], [floor])
    traj = rollout(world, world.state([[0.0, 0.0, 0.5]]), steps=50)  # falling, not yet landed
    gap = contact_penalty(world, traj, "ball", "floor")
    assert abs(gap.item() - (traj.final.position[0, 0, 2].item() - 0.05)) < 1e-12
    assert gap.item() < 0.45  # it fell: the minimum is over time
    assert contact_penalty(world, traj, "floor", "ball").item() == gap.item()  # either order
    resting = rollout(world, world.state([[0.0, 0.0, 0.049]]), steps=1)
    assert contact_penalty(world, resting, "ball", "floor").item() == 0.0


def test_gradient_pulls_the_bodies_together():
    world = two_balls()
    direction = torch.tensor([0.6, 0.0, 0.8], **F64)

    def fn(x):  # x (B, 3): initial position of a; b sits 0.3 m away along ``direction``
        start = torch.stack([x, (0.3 * direction).expand_as(x)], -2)
        return contact_penalty(world, rollout(world, world.state(start), steps=2), "a", "b")

    g = assert_forward_equals_reverse(fn, torch.zeros(1, 3, **F64))
    assert torch.allclose(g[0], -direction, atol=1e-12)  # descent moves a straight towards b
    floor = StaticShape.make("floor", "plane")
    world_f = make_world([ball_body()], [floor], **ZERO_G)

    def fn_f(x):
        return contact_penalty(world_f, rollout(world_f, world_f.state(x[:, None]), steps=2), "ball", "floor")

    g = assert_forward_equals_reverse(fn_f, torch.tensor([[0.1, 0.2, 0.4]], **F64))
    assert torch.allclose(g[0], torch.tensor([0.0, 0.0, 1.0], **F64))


def dumbbell(name="bell"):
    """Two spheres 0.6 m apart: its COM (where padding would sit) is far from both."""
    centers = np.array([[-0.3, 0.0, 0.0], [0.3, 0.0, 0.0]])
    return BodySpec(name, 1.0, np.diag([0.01, 0.02, 0.02]), np.zeros(3), centers, np.array([0.02, 0.02]))


def brute_force_gap(world, traj, a, b):
    """min over records and real sphere pairs, all at once."""
    s = world.sphere_positions(State(*(t.flatten(0, 1) for t in traj.states.tensors())))
    s = s.reshape(*traj.states.position.shape[:2], *s.shape[1:])  # (T, B, N, S, 3)
    ma, mb = world.mask[a] > 0, world.mask[b] > 0
    ca, cb = s[:, :, a][:, :, ma], s[:, :, b][:, :, mb]
    d = (ca[:, :, :, None] - cb[:, :, None]).norm(dim=-1) - world.radii[a][ma][:, None] - world.radii[b][mb]
    return d.flatten(2).amin(-1).amin(0).clamp(min=0)


@pytest.mark.parametrize("chunk", [1, 7, 1 << 21])
def test_chunked_search_equals_brute_force_and_ignores_padding(chunk):
    """The dumbbell is padded to the box's 24 spheres; padding at its COM must never count."""
    world = make_world([box_body(), dumbbell()], [], **ZERO_G)
    t, b = 5, 3
    pos = torch.zeros(t, b, 2, 3, **F64)
    pos[:, :, 1] = torch.tensor([0.0, 0.3, 0.0], **F64)  # dumbbell beside the box, its COM nearest
    pos = pos + torch.randn(t, b, 2, 3, generator=rng(), **F64) * 0.02
    quat = random_quat(t, b, 2, seed=1) * 0.05 + torch.tensor([1.0, 0, 0, 0], **F64)
    quat = quat / quat.norm(dim=-1, keepdim=True)
    traj = trajectory_of(world, pos, quat)
    expected = brute_force_gap(world, traj, 0, 1)
    assert (expected > 0).all()
    got = contact_penalty(world, traj, "box", "bell", chunk_elements=chunk)
    assert torch.allclose(got, expected, rtol=0, atol=1e-12)


def test_box_static_and_batched_gradients():
    """Against a box static, forward equals reverse and gradcheck passes (float64)."""
    table = StaticShape.make("table", "box", position=(0.0, 0.0, -0.1), half=(0.5, 0.5, 0.1))
    world = make_world([box_body()], [table], **ZERO_G)
    g = rng(2)
    base = torch.tensor([0.1, -0.05, 0.3], **F64) + torch.randn(4, 2, 1, 3, generator=g, **F64) * 0.03
    rot = torch.randn(4, 2, 1, 3, generator=g, **F64) * 0.5

    def fn(x):  # x (B, 6): shift and turn every record of a candidate
        traj = trajectory_of(world, base + x[None, :, None, :3], rotvec_to_quat(rot + x[None, :, None, 3:]))
        return contact_penalty(world, traj, "box", "table", chunk_elements=50)

    x = torch.randn(2, 6, generator=rng(3), **F64) * 0.01
    assert (fn(x) > 0).all()
    assert_forward_equals_reverse(fn, x)
    assert torch.autograd.gradcheck(fn, (x.clone().requires_grad_(True),))
    world2 = make_world([box_body(), ball_body()], [], **ZERO_G)

    def fn2(x):
        ball = torch.tensor([0.3, 0.2, 0.3], **F64).expand(4, 2, 3)
        p = torch.stack([base[:, :, 0] + x[None, :, :3], ball], 2)
        q = rotvec_to_quat(torch.cat([rot + x[None, :, None, 3:], torch.zeros_like(rot)], 2))
        return contact_penalty(world2, trajectory_of(world2, p, q), "box", "ball", chunk_elements=50)

    assert (fn2(x) > 0).all()
    assert_forward_equals_reverse(fn2, x)
    assert torch.autograd.gradcheck(fn2, (x.clone().requires_grad_(True),))


def test_bad_pairs_are_errors():
    floor = StaticShape.make("floor", "plane")
    wall = StaticShape.make("wall", "plane", orientation=(0.7071, 0.7071, 0, 0))
    world = make_world([ball_body()], [floor, wall])
    traj = rollout(world, world.state([[0.0, 0.0, 0.5]]), steps=1)
    with pytest.raises(InferenceError, match="two fixed"):
        contact_penalty(world, traj, "floor", "wall")
    with pytest.raises(InferenceError, match="itself"):
        contact_penalty(world, traj, "ball", "ball")
    with pytest.raises(InferenceError, match="neither"):
        contact_penalty(world, traj, "ball", "ceiling")


def test_a_box_body_meets_a_plane_with_its_corners():
    """A box body (``box_half``) tilted above the floor: its gap is that of its corner spheres
    (radius ``BOX_CORNER_RADIUS``, their surfaces through the corners), as its contacts see it
    (``dejaview.sim.box_edges``), within 0.73 mm of its lowest corner's height; its packing's lowest
    sphere sits more than 1 cm higher (spheres round a box's corners off). A packed box without
    ``box_half`` keeps its spheres' gap."""
    from dejaview.sim.box_edges import BOX_CORNER_RADIUS
    from dejaview.sim.rotation import quat_to_matrix

    half = np.array([0.1, 0.075, 0.05])
    q = rotvec_to_quat(torch.tensor([0.3, -0.2, 0.1], **F64))
    pos = torch.tensor([0.2, -0.1, 0.15], **F64)
    rot = quat_to_matrix(q).numpy()
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    r = BOX_CORNER_RADIUS
    corner_gap = float(pos[2]) + float(((signs * (half - r)) @ rot.T)[:, 2].min()) - r
    lowest = float(pos[2]) + float(((signs * half) @ rot.T)[:, 2].min())
    gaps = {}
    for box in (True, False):
        body = box_body("box", box_half=tuple(half) if box else None)
        world = make_world([body], [StaticShape.make("floor", "plane")], **ZERO_G)
        traj = trajectory_of(world, pos.reshape(1, 1, 1, 3), q.reshape(1, 1, 1, 4))
        gaps[box] = contact_penalty(world, traj, "box", "floor").item()
    assert abs(gaps[True] - corner_gap) < 1e-12
    assert 0 <= gaps[True] - lowest < (3 ** 0.5 - 1) * r + 1e-12
    assert gaps[False] > lowest + 0.01
