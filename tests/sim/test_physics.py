"""The simulator against closed-form physics."""

import numpy as np
import pytest
import torch

from dejaview.sim import StaticShape, rollout
from tests.sim.conftest import ball_body, box_body, make_world

G = 9.81


def test_free_fall_matches_analytic_within_integrator_error():
    """Semi-implicit Euler: x_n = x0 + v0 t + g t^2 / 2 + g t h / 2 exactly (h the substep)."""
    world = make_world([ball_body()], [], dt=0.002, substeps=2)
    v0 = torch.tensor([0.5, -0.2, 2.0], dtype=torch.float64)
    state = world.state([[0.0, 0.0, 1.0]], linear_velocity=[v0.tolist()])
    steps = 250
    traj = rollout(world, state, steps=steps)
    t = steps * world.dt
    h = world.dt / world.substeps
    g = world.gravity
    analytic = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) + v0 * t + 0.5 * g * t * t
    known_error = 0.5 * g * t * h
    got = traj.final.position[0, 0]
    assert torch.allclose(got, analytic + known_error, atol=1e-9)
    assert (got - analytic).abs().max() <= 0.5 * G * t * h + 1e-9
    assert torch.allclose(traj.final.linear_velocity[0, 0], v0 + g * t, atol=1e-9)


def test_box_sliding_stops_at_v2_over_2_mu_g():
    mu, v0 = 0.4, 2.0
    box = box_body(friction=mu)
    floor = StaticShape.make("floor", "plane", friction=mu)
    world = make_world([box], [floor], dt=0.002, substeps=2, friction=mu)
    state = world.state([[0.0, 0.0, 0.05]], linear_velocity=[[v0, 0.0, 0.0]])
    traj = rollout(world, state, steps=400)
    x = traj.states.position[:, 0, 0, 0]
    speed = traj.states.linear_velocity[:, 0, 0, 0]
    assert speed[-1].abs() < 1e-3
    expected = v0 ** 2 / (2 * mu * G)
    assert abs(x[-1].item() - expected) / expected < 0.03


@pytest.mark.parametrize("e", [0.5, 0.8])
def test_ball_rebounds_to_e_squared_h(e):
    r, h0 = 0.05, 0.5
    world = make_world([ball_body(radius=r, restitution=e)],
                       [StaticShape.make("floor", "plane", restitution=e)], dt=0.002, substeps=2)
    traj = rollout(world, world.state([[0.0, 0.0, h0 + r]]), steps=600)
    z = traj.states.position[:, 0, 0, 2].numpy() - r
    first_contact = int(np.argmax(z < 0))
    bottom = first_contact + int(np.argmin(z[first_contact:first_contact + 50]))
    rebound = z[bottom:].max()
    assert abs(rebound - e * e * h0) / (e * e * h0) < 0.10


def test_box_resting_on_table_stays_and_gains_no_energy():
    top = StaticShape.make("table", "box", position=(0.0, 0.0, 0.70), half=(0.6, 0.4, 0.05))
    box = box_body(mass=2.0)
    world = make_world([box], [top], dt=0.002, substeps=2)
    start = [[0.1, -0.05, 0.75 + 0.05]]
    state = world.state(start)
    traj = rollout(world, state, steps=1500)  # 3 s
    pos = traj.states.position[:, 0, 0]
    drift = (pos - pos[0]).norm(dim=-1).max().item()
    assert drift < 1e-3
    m = world.mass[0]
    v = traj.states.linear_velocity[:, 0, 0]
    w = traj.states.angular_velocity[:, 0, 0]
    inertia = world.inertia[0]
    energy = 0.5 * m * (v * v).sum(-1) + 0.5 * (w * (w @ inertia)).sum(-1) + m * G * pos[:, 2]
    assert (energy - energy[0]).max().item() < 1e-6
    # and it is at rest at the end
    assert v[-1].norm() < 1e-3 and w[-1].norm() < 1e-2


def test_frictionless_elastic_collision_conserves_momentum():
    a = ball_body("a", mass=1.0, friction=0.0, restitution=1.0)
    b = ball_body("b", mass=1.0, friction=0.0, restitution=1.0)
    world = make_world([a, b], [], gravity=(0.0, 0.0, 0.0), dt=0.002, substeps=2,
                       friction=0.0, restitution=1.0)
    state = world.state([[0.0, 0.0, 0.0], [0.3, 0.01, 0.0]],
                        linear_velocity=[[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    traj = rollout(world, state, steps=300)
    m = world.mass[:, None]
    p0 = (m * state.linear_velocity[0]).sum(0)
    p1 = (m * traj.final.linear_velocity[0]).sum(0)
    assert (p1 - p0).norm() / p0.norm() < 0.01
    e0 = 0.5 * (m * state.linear_velocity[0] ** 2).sum()
    e1 = 0.5 * (m * traj.final.linear_velocity[0] ** 2).sum()
    assert abs(e1 - e0) / e0 < 0.05  # (nearly) elastic
    # an off-centre hit sends b off along the line of centres
    assert traj.final.linear_velocity[0, 1, 0] > 0.9


def test_float32_runs_and_matches_float64():
    world = make_world([ball_body()], [StaticShape.make("floor", "plane")])
    s64 = world.state([[0.0, 0.0, 0.3]], linear_velocity=[[1.0, 0.0, 0.0]])
    t64 = rollout(world, s64, steps=200)
    w32 = world.to(dtype=torch.float32)
    t32 = rollout(w32, s64.to(dtype=torch.float32), steps=200)
    assert t32.final.position.dtype == torch.float32
    assert torch.allclose(t32.final.position.double(), t64.final.position, atol=2e-3)
