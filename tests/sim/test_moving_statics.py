"""Static shapes that move on a known path (a moving robot's links, ``dejaview.sim.motion``): the
native engine against the torch engine on them (states, both gradient modes), the gradients
against finite differences, and the relative velocity's link part."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from dejaview.errors import SimulationError
from dejaview.sim import StaticShape
from dejaview.sim.integrate import rollout
from dejaview.sim.motion import ShapePath, joint_path
from dejaview.sim.state import State
from tests.sim.conftest import ball_body, both_modes, box_body, make_world, state_gradient as _grad

ATOL = 1e-9


def sweeping_paddle(count: int, h: float, omega: float = 3.0, theta0: float = -0.6, radius: float = 0.3,
                    z: float = 0.06, tilt: float = 0.0) -> StaticShape:
    """A static box paddle (0.3 x 0.04 x 0.08) whose centre turns about the z axis at ``radius``,
    ``omega`` rad/s from ``theta0`` (tilted ``tilt`` about its long axis), on a path of ``count``
    substeps of ``h``: pose and velocity in closed form."""
    t = torch.arange(count, dtype=torch.float64) * h
    th = theta0 + omega * t
    c, s = torch.cos(th), torch.sin(th)
    ct, st = math.cos(tilt), math.sin(tilt)
    rz = torch.zeros(count, 3, 3, dtype=torch.float64)
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    rx = torch.tensor([[1.0, 0, 0], [0, ct, -st], [0, st, ct]], dtype=torch.float64)
    rot = rz @ rx
    trans = torch.stack([radius * c, radius * s, torch.full_like(c, z)], -1)
    vel = torch.stack([-omega * radius * s, omega * radius * c, torch.zeros_like(c)], -1)
    ang = torch.tensor([0.0, 0.0, omega], dtype=torch.float64).expand(count, 3).clone()
    path = ShapePath(rotation=rot, translation=trans, velocity=vel, angular_velocity=ang)
    shape = StaticShape.make("arm/paddle", "box", half=(0.15, 0.02, 0.04), friction=0.6, restitution=0.2)
    return replace(shape, path=path).at(0)


def _world(body: str, steps: int, substeps: int = 2, dt: float = 0.002, **paddle):
    bodies = {"ball": [ball_body(radius=0.05, mass=0.3, friction=0.5)],
              "packed box": [box_body(size=(0.1, 0.1, 0.1), per_axis=(3, 3, 3), mass=0.4)],
              "box": [box_body(size=(0.1, 0.1, 0.1), per_axis=(3, 3, 3), mass=0.4, box_half=(0.05, 0.05, 0.05))],
              "two": [ball_body(radius=0.05, mass=0.3), box_body(name="b2", size=(0.1, 0.1, 0.1), mass=0.4)]}[body]
    statics = [StaticShape.make("floor", "plane"), sweeping_paddle(steps * substeps + 1, dt / substeps, **paddle)]
    world = make_world(bodies, statics, dt=dt, substeps=substeps, steps=steps)
    pos = [[0.35, 0.0, 0.05]] if len(bodies) == 1 else [[0.35, 0.0, 0.05], [0.2, 0.25, 0.05]]
    return world, world.state(pos, batch_size=2).replace(
        position=world.state(pos, batch_size=2).position
        + torch.tensor([[[0.0, 0.0, 0.0]], [[0.02, -0.03, 0.0]]], dtype=torch.float64))


@pytest.mark.parametrize("body", ["ball", "packed box", "box", "two"])
def test_a_moving_static_pushes_bodies_the_same_in_both_engines(body):
    steps = 120
    world, state = _world(body, steps, tilt=0.3 if body == "box" else 0.0)
    ref = rollout(world, state, steps=steps)
    out = rollout(world, state, steps=steps, engine="native")
    # the paddle hit it: the first body moved (it stood still on the floor)
    moved = (ref.final.position[:, 0, :2] - state.position[:, 0, :2]).norm(dim=-1)
    assert float(moved.min()) > 0.02
    for x, y in zip(ref.states.tensors(), out.states.tensors()):
        assert torch.allclose(x, y, rtol=0, atol=ATOL), float((x - y).abs().max())


@pytest.mark.parametrize("body", ["packed box", "box"])
def test_native_gradients_through_a_moving_static_equal_torch_autograd(body):
    steps = 100
    world, state = _world(body, steps, tilt=0.3 if body == "box" else 0.0)
    ref = _grad(world, state, "torch", steps)
    out = _grad(world, state, "native", steps)
    assert torch.allclose(out, ref, rtol=1e-7, atol=1e-9 * float(ref.abs().max())), \
        float((out - ref).abs().max())


def test_native_forward_mode_equals_reverse_mode_through_a_moving_static():
    steps = 100
    world, state = _world("packed box", steps)
    jac_fwd, jac_rev, _, _ = both_modes(world, state, steps)
    assert torch.allclose(jac_fwd, jac_rev, rtol=1e-10, atol=1e-12 * float(jac_rev.abs().max()))


def test_gradients_through_a_moving_static_equal_finite_differences():
    """The ball's end position after the paddle batted it, by its start's x, y and its velocity:
    the adjoint against central differences of the native rollout."""
    steps = 150
    world, state = _world("ball", steps)
    state = State(*(t[:1] for t in state.tensors()))
    x0 = torch.cat([state.position[0, 0, :2], state.linear_velocity[0, 0, :2]])

    def end(x):
        pos = torch.cat([x[:2], state.position[0, 0, 2:]])[None, None]
        vel = torch.cat([x[2:], state.linear_velocity[0, 0, 2:]])[None, None]
        traj = rollout(world, state.replace(position=pos, linear_velocity=vel), steps=steps, engine="native")
        return traj.final.position[0, 0, :2] @ torch.tensor([1.0, 0.7], dtype=torch.float64)

    x = x0.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(end(x), x)
    eps = 1e-6
    fd = torch.stack([(end(x0 + eps * e) - end(x0 - eps * e)) / (2 * eps) for e in torch.eye(4, dtype=torch.float64)])
    assert float(g.abs().max()) > 0.1  # the batting depends on where the ball stood
    assert torch.allclose(g, fd, rtol=1e-4, atol=1e-6), (g, fd)


def test_the_link_velocity_enters_the_contact():
    """A ball resting on a paddle that slides sideways under it: friction carries the ball along
    (the slip is relative to the paddle); without the paddle's velocity the ball would see no
    slip and stay where it was while the paddle slid away."""
    h, count = 0.001, 1001
    t = torch.arange(count, dtype=torch.float64) * h
    speed = 0.2
    trans = torch.stack([speed * t, torch.zeros_like(t), torch.full_like(t, -0.05)], -1)
    path = ShapePath(rotation=torch.eye(3, dtype=torch.float64).expand(count, 3, 3).clone(), translation=trans,
                     velocity=torch.tensor([speed, 0.0, 0.0], dtype=torch.float64).expand(count, 3).clone(),
                     angular_velocity=torch.zeros(count, 3, dtype=torch.float64))
    plate = replace(StaticShape.make("belt", "box", half=(1.0, 1.0, 0.05), friction=0.8), path=path).at(0)
    world = make_world([box_body(size=(0.1, 0.1, 0.1), per_axis=(3, 3, 3), mass=0.4, friction=0.8)], [plate],
                       dt=0.002, substeps=2, steps=500)
    state = world.state([[0.0, 0.0, 0.05]])
    out = rollout(world, state, steps=500, engine="native")
    # a belt at 0.2 m/s, the box on it from rest: mu g = 7.8 m/s^2 brings it to speed in 26 ms
    # (2.6 mm of slip); after 1 s it has gone 0.2 m less that slip
    x = float(out.final.position[0, 0, 0])
    assert x == pytest.approx(speed * 1.0 - speed ** 2 / (2 * 0.8 * 9.81), abs=0.002)
    assert float(out.final.linear_velocity[0, 0, 0]) == pytest.approx(speed, abs=1e-3)


def test_a_rollout_continued_from_a_step_finds_the_links_there():
    """``native_rollout(first_step=i)`` and ``step(index=i)``: a rollout in two parts is the rollout
    in one (simulate runs in chunks)."""
    from dejaview.sim.native import native_rollout

    steps = 120
    world, state = _world("ball", steps)
    whole = rollout(world, state, steps=steps, engine="native")
    first = native_rollout(world, state, 50)
    rest = native_rollout(world, first.final, steps - 50, first_step=50)
    assert torch.allclose(rest.final.position, whole.final.position, rtol=0, atol=1e-12)
    from dejaview.sim.integrate import step

    s = rollout(world, state, steps=50).final
    for i in range(50, steps):
        s = step(world, s, index=i)
    assert torch.allclose(s.position, whole.final.position, rtol=0, atol=ATOL)
    # and the index matters: the same 70 steps with the links where they stood at the start differ
    again = rollout(world, first.final, steps=steps - 50, engine="native")
    assert not torch.allclose(again.final.position, whole.final.position, atol=1e-3)


def test_a_path_given_as_data_does_not_change_its_substeps():
    """A path built by hand knows no motion to sample again (a robot's does: test_robots_motion)."""
    world, state = _world("ball", 10)
    with pytest.raises(SimulationError, match="path given as data, sampled at the world's substep"):
        world.with_substeps(4)
    assert world.with_substeps(2) is not None  # the same substeps: the same world


def test_joint_paths_interpolate_and_hold():
    from dejaview.scene import JointKeyframe

    keys = (JointKeyframe(0.2, (0.0, 1.0)), JointKeyframe(0.6, (1.0, 1.0)), JointKeyframe(1.0, (1.0, -1.0)))
    q, qdot = joint_path(keys, np.array([0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.5]))
    assert np.allclose(q, [[0, 1], [0, 1], [0.5, 1], [1, 1], [1, 0], [1, -1], [1, -1]])
    assert np.allclose(qdot, [[0, 0], [2.5, 0], [2.5, 0], [0, -5], [0, -5], [0, 0], [0, 0]])


def test_a_penalty_meets_a_moving_link_where_it_is_at_each_record():
    """``contact_penalty`` against a moving static reads its pose at each record (as the rollout
    met it), not where it stood at time 0. A ball rests 0.6 m out on the x axis; the paddle
    (radially 0.15..0.45 m, corners 0.4504 m out) turns past the axis around t = 0.19 s: the least
    gap is that of the box at each record, brute force (about 0.6 - 0.4504 - 0.05), and it moves
    with the ball's start one for one."""
    from dejaview.losses.penalty import contact_penalty

    steps, substeps, dt = 120, 2, 0.002
    statics = [StaticShape.make("floor", "plane"), sweeping_paddle(steps * substeps + 1, dt / substeps)]
    world = make_world([ball_body(radius=0.05, mass=0.3)], statics, dt=dt, substeps=substeps, steps=steps)
    x = torch.tensor([0.6, 0.0, 0.05], dtype=torch.float64, requires_grad=True)
    traj = rollout(world, world.state(x[None]), steps=steps)
    gap = contact_penalty(world, traj, "ball", "arm/paddle")
    paddle, half = world.statics[1], np.array([0.15, 0.02, 0.04])
    path, centres = paddle.path, traj.states.position[:, 0, 0].detach().numpy()
    brute = []
    for t, step_ in enumerate(traj.steps.tolist()):
        j = path.row(step_ * substeps)
        local = path.rotation[j].numpy().T @ (centres[t] - path.translation[j].numpy())
        q = np.abs(local) - half
        brute.append(np.linalg.norm(np.maximum(q, 0)) + min(q.max(), 0) - 0.05)
    assert 0.0995 < min(brute) < 0.1
    assert float(gap.detach()) == pytest.approx(min(brute), abs=1e-9)
    (dx,) = torch.autograd.grad(gap.sum(), x)
    assert float(dx[0]) == pytest.approx(1.0, abs=1e-3)  # along the corner-to-ball direction, near x
    # the paddle as it stood at time 0 is farther: the old reading would have said so
    still = replace(world, statics=tuple(replace(s, path=None) for s in world.statics))
    assert float(contact_penalty(still, traj, "ball", "arm/paddle").detach()) > 0.2
    # the same on the native engine's trajectory (no graph: values)
    native = rollout(world, world.state(x.detach()[None]), steps=steps, engine="native")
    assert float(contact_penalty(world, native, "ball", "arm/paddle")) == pytest.approx(min(brute), abs=1e-9)
