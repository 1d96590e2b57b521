"""Trajectory losses: best / final / pinned time, soft-min, frames, velocities, both AD modes."""

import math

import numpy as np
import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.losses import LOSSES, TrajectoryLoss, softmin, trajectory_loss
from dejaview.scene.model import InferenceSettings, Penalty, Target
from dejaview.sim import BodySpec, State, Trajectory, rollout
from dejaview.sim.rotation import quat_multiply, rotvec_to_quat
from tests.losses.helpers import F64, assert_forward_equals_reverse, axis_angle_quat, random_quat, rng
from tests.sim.conftest import ball_body, box_body, make_world

IDENT = (1.0, 0.0, 0.0, 0.0)


def thrown_ball(steps=200, record_every=1, speed=1.0):
    """A ball in zero gravity moving along +x at ``speed`` from the origin: x(t) = speed t."""
    world = make_world([ball_body()], [], gravity=(0.0, 0.0, 0.0), dt=0.002)
    state = world.state([[0.0, 0.0, 0.0]], linear_velocity=[[speed, 0.0, 0.0]])
    return world, rollout(world, state, steps=steps, record_every=record_every)


def test_losses_table_names_the_scene_losses():
    assert set(LOSSES) == {"pose", "add", "position"}


@pytest.mark.parametrize("kind", ["pose", "add", "position"])
def test_best_is_below_final_for_a_ball_thrown_past_the_target(kind):
    world, traj = thrown_ball()  # ends at x = 0.4 m
    target = Target(position=(0.2, 0.0, 0.0), moving=True)  # seen in motion, at a moment not known
    best = trajectory_loss(world, traj, "ball", target, kind=kind, evaluate="best")
    final = trajectory_loss(world, traj, "ball", target, kind=kind, evaluate="final")
    assert best.shape == final.shape == (1,)
    assert best.item() < 1e-5
    assert abs(final.item() - 0.2) < 1e-5
    assert best.item() < final.item()


def test_soft_min_approaches_the_hard_min_as_temperature_goes_to_zero():
    world, traj = thrown_ball()
    target = Target(position=(0.2013, 0.0, 0.0), moving=True)  # between records: the hard min is > 0
    hard = trajectory_loss(world, traj, "ball", target)
    gaps = [(hard - trajectory_loss(world, traj, "ball", target, softmin_temperature=t)).item()
            for t in (1e-2, 1e-3, 1e-4, 1e-6)]
    assert all(g >= 0 for g in gaps)  # soft-min lies below the min
    assert all(a > b for a, b in zip(gaps, gaps[1:]))
    assert gaps[-1] < 1e-5
    assert gaps[0] <= 1e-2 * math.log(len(traj))  # the documented bound T log(records)
    losses = torch.tensor([[3.0], [1.0], [2.0]], **F64)
    assert torch.allclose(softmin(losses, 1e-8), torch.tensor([1.0], **F64))


def test_time_pins_the_nearest_record():
    world, traj = thrown_ball(record_every=10)  # records every 0.02 s
    target = Target(position=(0.2, 0.0, 0.0), time=0.105)  # nearest record: step 50 (0.10 s)
    for evaluate in ("best", "final"):  # time overrides evaluate
        loss = trajectory_loss(world, traj, "ball", target, kind="position", evaluate=evaluate)
        assert abs(loss.item() - 0.1) < 1e-5
    loss = trajectory_loss(world, traj, "ball", Target(position=(0.2, 0.0, 0.0)), kind="position", time=0.315)
    assert abs(loss.item() - abs(0.32 - 0.2)) < 1e-5  # step 160 = 0.32 s is nearest
    for t in (-0.01, 0.45):
        with pytest.raises(InferenceError, match="outside the trajectory"):
            trajectory_loss(world, traj, "ball", target, time=t)


def test_targets_are_object_origins_converted_through_the_com():
    """A body whose COM is 5 cm off its origin, at the target pose (turned 90 degrees): zero loss."""
    base = box_body()
    off = np.array([0.05, 0.0, 0.0])
    body = BodySpec("box", base.mass, base.inertia, off, base.centers + off, base.radii)
    world = make_world([body], [], gravity=(0.0, 0.0, 0.0))
    q = axis_angle_quat([0, 0, 1], math.pi / 2)
    origin = [0.3, -0.1, 0.2]
    traj = rollout(world, world.state([origin], q[None]), steps=3)
    target = Target(position=tuple(origin), orientation=tuple(q.tolist()))
    for kind in LOSSES:
        assert trajectory_loss(world, traj, "box", target, kind=kind, evaluate="final").item() < 1e-5
    # position compares origins: a wrong orientation does not change it, but does change pose
    wrong = Target(position=tuple(origin), orientation=IDENT)
    assert trajectory_loss(world, traj, "box", wrong, kind="position").item() < 1e-5
    pose = trajectory_loss(world, traj, "box", wrong, kind="pose", eps=0.0).item()
    com_shift = 0.05 * math.sqrt(2)  # R(90 deg) off - off
    assert abs(pose - math.hypot(com_shift, 0.05 * math.pi / 2)) < 1e-9


def test_velocity_terms_are_weighted_and_only_where_the_target_has_them():
    world, traj = thrown_ball()
    at_rest = Target(position=(0.0, 0.0, 0.0), linear_velocity=(0.0, 0.0, 0.0), time=0.0)
    # record 0: at the target position, moving at 1 m/s -> velocity_weight * 1
    assert abs(trajectory_loss(world, traj, "ball", at_rest).item() - 0.1) < 1e-5
    assert abs(trajectory_loss(world, traj, "ball", at_rest, velocity_weight=0.5).item() - 0.5) < 1e-5
    assert trajectory_loss(world, traj, "ball", at_rest, velocity_weight=0).item() < 1e-5
    spinning = Target(position=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 2.0), time=0.0)
    loss = trajectory_loss(world, traj, "ball", spinning, orientation_weight=0.05, velocity_weight=0.1)
    assert abs(loss.item() - 0.1 * 0.05 * 2.0) < 1e-6


def test_unknown_names_are_errors():
    world, traj = thrown_ball(steps=2)
    with pytest.raises(InferenceError):
        trajectory_loss(world, traj, "ball", Target(position=(0, 0, 0)), kind="chamfer")
    with pytest.raises(InferenceError):
        trajectory_loss(world, traj, "ball", Target(position=(0, 0, 0)), evaluate="worst")
    with pytest.raises(InferenceError):
        TrajectoryLoss("ball", Target(position=(0, 0, 0)), kind="chamfer")


def test_trajectory_loss_object_adds_weighted_penalties():
    world = make_world([ball_body("a"), ball_body("b")], [], gravity=(0.0, 0.0, 0.0))
    traj = rollout(world, world.state([[0.0, 0, 0], [0.3, 0, 0]]), steps=2)
    inference = InferenceSettings(source="a", targets=(Target(position=(0.1, 0.0, 0.0)),), loss="position",
                                  penalties=(Penalty(("a", "b"), weight=0.5),))
    objective = TrajectoryLoss.from_inference(inference)
    expected = 0.1 + 0.5 * (0.3 - 0.1)
    assert abs(objective(world, traj).item() - expected) < 1e-5


def batch_trajectory(seed=0, t=6, b=3):
    """A random (T, B, 1, ...) trajectory of a box, as a function of a flat parameter vector."""
    g = rng(seed)
    pos = torch.randn(t, b, 1, 3, generator=g, **F64) * 0.1
    rot = torch.randn(t, b, 1, 3, generator=g, **F64)
    vel = torch.randn(t, b, 1, 3, generator=g, **F64)
    return pos, rot, vel


@pytest.mark.parametrize("kind", ["pose", "add", "position"])
@pytest.mark.parametrize("evaluate,temperature", [("best", None), ("best", 0.01), ("final", None)])
def test_gradcheck_and_forward_equals_reverse_on_random_trajectories(kind, evaluate, temperature):
    base = box_body()
    off = np.array([0.02, -0.01, 0.03])
    world = make_world([BodySpec("box", 1.0, base.inertia, off, base.centers + off, base.radii)], [])
    pos, rot, vel = batch_trajectory()
    target = Target(position=(0.05, 0.0, -0.02), orientation=tuple(random_quat(seed=1).tolist()),
                    linear_velocity=(0.1, 0.2, 0.3), angular_velocity=(1.0, 0.0, -1.0))

    def fn(x):  # x: (B, 3) shifts every record of candidate b, plus a rotation of it
        p = pos + x[None, :, None, :3]
        q = rotvec_to_quat(rot + x[None, :, None, 3:])
        traj = Trajectory(State(p, q, vel, vel), torch.arange(pos.shape[0]), 0.01)
        return trajectory_loss(world, traj, "box", target, kind=kind, evaluate=evaluate,
                               softmin_temperature=temperature)

    x = torch.randn(3, 6, generator=rng(2), **F64) * 0.05
    assert_forward_equals_reverse(fn, x)
    assert torch.autograd.gradcheck(fn, (x.clone().requires_grad_(True),))


def test_gradients_through_a_rollout_agree_and_are_finite_at_zero_error():
    """A spinning box in flight; the target is its own state at a record, so the best loss is 0."""
    world = make_world([box_body(per_axis=(2, 2, 1))], [], dt=0.002)
    q0 = torch.tensor(IDENT, **F64)

    def simulate(x):
        q = quat_multiply(rotvec_to_quat(x[..., 3:6]), q0)
        state = world.state(x[..., None, 0:3], q[..., None, :], x[..., None, 6:9], x[..., None, 9:12])
        return rollout(world, state, steps=20, record_every=4)

    x0 = torch.tensor([[0.0, 0.0, 1.0, 0.1, -0.2, 0.3, 1.0, 0.5, 2.0, 3.0, -1.0, 2.0]], **F64)
    ref = simulate(x0)
    k = 3  # record at step 12; COM == origin for this box
    target = Target(position=tuple(ref.states.position[k, 0, 0].tolist()),
                    orientation=tuple(ref.states.orientation[k, 0, 0].tolist()), moving=True)
    best = lambda x: trajectory_loss(world, simulate(x), "box", target, kind="pose")  # noqa: E731
    assert best(x0).item() < 1e-8
    g = assert_forward_equals_reverse(best, x0)
    assert g.abs().max() < 1e-4
    pinned = lambda x: trajectory_loss(world, simulate(x), "box", target, time=0.024)  # noqa: E731
    assert pinned(x0).item() < 1e-8
    assert_forward_equals_reverse(pinned, x0)
    final = lambda x: trajectory_loss(world, simulate(x), "box", target, kind="add",  # noqa: E731
                                      evaluate="final")
    assert_forward_equals_reverse(final, x0 + torch.randn(2, 12, generator=rng(3), **F64) * 0.05)
    # seen at rest: the end and the mean velocities over the rest window (its records 0 and 10 of 20)
    resting = Target(position=target.position, orientation=target.orientation)
    rest = lambda x: trajectory_loss(world, rollout(world, world.state(  # noqa: E731
        x[..., None, 0:3], quat_multiply(rotvec_to_quat(x[..., 3:6]), q0)[..., None, :], x[..., None, 6:9],
        x[..., None, 9:12]), steps=200, record_every=50), "box", resting)
    assert_forward_equals_reverse(rest, x0 + torch.randn(2, 12, generator=rng(4), **F64) * 0.05)
