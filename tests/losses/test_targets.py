"""How the source was seen (``dejaview.losses.targets``): at rest by default, moving, timed, position only.

A flyby, a bounce's apex and a momentary stop do not explain a source seen lying still, under
``evaluate`` ``best`` and ``final`` alike; a target seen moving keeps version 1's best-record meaning.
"""

import math

import pytest
import torch

from dejaview.losses import trajectory_loss
from dejaview.losses.targets import (REST_PARTS, REST_WINDOW, record_interval, resolve, rest_time,
                                     rest_velocities, rollout_steps)
from dejaview.scene.model import InferenceSettings, Target
from dejaview.sim import rollout
from tests.sim.conftest import ball_body, box_body, make_world

DT = 0.002


def flyby(steps=200, speed=1.0):
    """A ball in zero gravity moving along +x at ``speed``: at x = 0.2 m at t = 0.2 s, x = 0.4 m at the end."""
    world = make_world([ball_body()], [], gravity=(0.0, 0.0, 0.0), dt=DT)
    return world, rollout(world, world.state([[0.0, 0.0, 0.0]], linear_velocity=[[speed, 0.0, 0.0]]),
                          steps=steps)


def still(steps=200, at=(0.2, 0.0, 0.0)):
    """A ball lying still (zero gravity, no velocity) at ``at``."""
    world = make_world([ball_body()], [], gravity=(0.0, 0.0, 0.0), dt=DT)
    return world, rollout(world, world.state([list(at)]), steps=steps)


def apex(steps=200):
    """A ball thrown straight up that reaches the top of its flight (zero velocity) at the last step."""
    world = make_world([ball_body()], [], gravity=(0.0, 0.0, -9.81), dt=DT)
    return world, rollout(world, world.state([[0.0, 0.0, 1.0]], linear_velocity=[[0.0, 0.0, 9.81 * steps * DT]]),
                          steps=steps)


def test_a_target_without_time_or_velocities_is_seen_at_rest_and_the_others_are_not():
    assert Target((0, 0, 0)).at_rest
    assert not Target((0, 0, 0), moving=True).at_rest
    assert not Target((0, 0, 0), linear_velocity=(0, 0, 0)).at_rest  # velocities observe themselves
    assert not Target((0, 0, 0), time=0.5).at_rest  # a timed pose, moving or not
    assert Target((0, 0, 0), time=0.5, moving=False).at_rest


@pytest.mark.parametrize("evaluate", ["best", "final"])
def test_a_flyby_does_not_explain_a_source_seen_at_rest(evaluate):
    world, traj = flyby()  # passes x = 0.2 m exactly at step 100
    resting = Target(position=(0.2, 0.0, 0.0))
    loss = trajectory_loss(world, traj, "ball", resting, kind="position", evaluate=evaluate)
    assert loss.item() > 0.2  # compared at the end (0.2 m away), plus its motion
    world, traj = still()
    assert trajectory_loss(world, traj, "ball", resting, kind="position", evaluate=evaluate).item() < 1e-5


def test_a_moving_target_still_accepts_a_flyby_under_best():
    world, traj = flyby()
    moving = Target(position=(0.2, 0.0, 0.0), moving=True)
    assert trajectory_loss(world, traj, "ball", moving, kind="position", evaluate="best").item() < 1e-5
    assert abs(trajectory_loss(world, traj, "ball", moving, kind="position", evaluate="final").item() - 0.2) < 1e-5


def test_a_bounce_apex_at_the_end_is_not_at_rest():
    """Zero velocity at the last record, but it rose 20 cm in the rest window: the mean speed over the
    last part is g T / 2 for a part of length T."""
    world, traj = apex()
    end = traj.states.position[-1, 0, 0].tolist()
    assert traj.states.linear_velocity[-1, 0, 0].norm() < 1e-9
    resting = Target(position=tuple(end))
    loss = trajectory_loss(world, traj, "ball", resting, kind="position", evaluate="final")
    part = REST_WINDOW / REST_PARTS
    sighting, = resolve((resting,), "final", DT, 200)
    lin, _ = rest_velocities(traj, 0, sighting)
    assert lin[0, -1, 2].item() == pytest.approx(9.81 * part / 2, rel=0.05)
    assert loss.item() > 0.1 * 9.81 * part / 2 / REST_PARTS


def test_rest_is_read_from_the_records_of_its_window_only():
    """The loss of a rollout that records the window's steps alone (``record_interval``) is the
    every-step rollout's."""
    target = Target(position=(0.3, 0.0, 0.0))
    sightings = resolve((target,), "best", DT, 200)
    every = record_interval(sightings, 200)
    assert every == math.gcd(200, int(round(REST_WINDOW / REST_PARTS / DT)))
    world, full = flyby()
    _, sparse = flyby() if every == 1 else (world, rollout(world, world.state(
        [[0.0, 0.0, 0.0]], linear_velocity=[[1.0, 0.0, 0.0]]), steps=200, record_every=every))
    a = trajectory_loss(world, full, "ball", target, kind="position")
    b = trajectory_loss(world, sparse, "ball", target, kind="position")
    assert torch.allclose(a, b, atol=1e-12)


def test_timed_targets_read_their_moments_and_add_in_quadrature():
    world, traj = flyby()
    first = Target(position=(0.05, 0.0, 0.0), time=0.05)  # exact
    second = Target(position=(0.13, 0.0, 0.0), time=0.1)  # 3 cm off (x = 0.10 m then)
    assert trajectory_loss(world, traj, "ball", (first,), kind="position").item() < 1e-5
    both = trajectory_loss(world, traj, "ball", (first, second), kind="position").item()
    assert both == pytest.approx(0.03, abs=1e-5)
    third = Target(position=(0.2, 0.04, 0.0), time=0.2)  # 4 cm off
    assert trajectory_loss(world, traj, "ball", (first, second, third), kind="position").item() == \
        pytest.approx(0.05, abs=1e-5)
    sightings = resolve((first, second), "best", DT, 200)
    assert [s.step for s in sightings] == [25, 50] and not any(s.at_rest for s in sightings)
    assert rollout_steps(sightings, 200) == 50  # the rollout need not go past the last observation
    assert record_interval(sightings, 50) == 25


def test_a_position_only_target_ignores_the_orientation():
    world, traj = still(at=(0.1, 0.0, 0.0))
    plain = Target(position=(0.1, 0.0, 0.0))
    turned = Target(position=(0.1, 0.0, 0.0), orientation=(0.0, 1.0, 0.0, 0.0))  # upside down
    assert trajectory_loss(world, traj, "ball", plain, kind="pose").item() < 1e-5
    assert trajectory_loss(world, traj, "ball", turned, kind="pose").item() > 0.1


def test_the_last_target_is_the_untimed_one_else_the_latest():
    a, b, c = Target((0, 0, 0), time=0.2), Target((1, 0, 0), time=0.9), Target((2, 0, 0))
    assert InferenceSettings(source="s", targets=(a, b)).target == b
    assert InferenceSettings(source="s", targets=(c, a, b)).target == c


def test_rest_time_is_when_the_source_stops_moving_for_good():
    world, traj = still()
    assert rest_time(traj, 0, 0.02, 0.2) == 0.0
    world, traj = flyby()
    assert rest_time(traj, 0, 0.02, 0.2) is None
    # a box sliding on a floor with friction 0.5 at 0.3 m/s stops after 0.3 / (0.5 g) = 0.061 s; it moves
    # 2 mm (rest_speed x a part) in the last 0.029 s before that, so it rests from about 0.03-0.07 s on
    from dejaview.sim import StaticShape

    world = make_world([box_body()], [StaticShape.make("floor", "plane")], gravity=(0.0, 0.0, -9.81), dt=DT,
                       friction=0.5)
    traj = rollout(world, world.state([[0.0, 0.0, 0.05]], linear_velocity=[[0.3, 0.0, 0.0]]), steps=300)
    assert 0.02 < rest_time(traj, 0, 0.02, 0.2) < 0.1
    traj = rollout(world, world.state([[0.0, 0.0, 0.05]], linear_velocity=[[3.0, 0.0, 0.0]]), steps=300)
    assert rest_time(traj, 0, 0.02, 0.2) is None  # still sliding at 0.6 s (stops at 0.61 s)
