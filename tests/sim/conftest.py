"""Small worlds built in code for simulator tests."""

import numpy as np
import pytest

from dejaview.sim import BodySpec, StaticShape, World


def ball_body(name="ball", radius=0.05, mass=1.0, **kw) -> BodySpec:
    """A solid ball as a single sphere (exact geometry)."""
    inertia = 0.4 * mass * radius ** 2 * np.eye(3)
    return BodySpec(name, mass, inertia, np.zeros(3), np.zeros((1, 3)), np.array([radius]), **kw)


def box_body(name="box", size=(0.2, 0.15, 0.1), mass=1.0, per_axis=(4, 3, 2), **kw) -> BodySpec:
    """A box packed with a regular grid of equal spheres touching its faces."""
    size = np.asarray(size, dtype=float)
    r = float(np.min(size / (2 * np.asarray(per_axis))))
    axes = [np.linspace(-s / 2 + r, s / 2 - r, n) if n > 1 else np.zeros(1)
            for s, n in zip(size, per_axis)]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    a, b, c = size
    inertia = mass / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    return BodySpec(name, mass, inertia, np.zeros(3), centers, np.full(len(centers), r), **kw)


@pytest.fixture
def floor():
    return StaticShape.make("floor", "plane")


def make_world(bodies, statics, **kw) -> World:
    return World.build(bodies, statics, **kw)


def trajectory_loss(traj) -> "torch.Tensor":
    """A smooth scalar of the whole trajectory: every record's pose and velocity."""
    s = traj.states
    return ((s.position ** 2).sum() + 0.3 * (s.orientation[..., 1:] ** 2).sum()
            + 0.01 * (s.linear_velocity ** 2).sum() + 0.001 * (s.angular_velocity ** 2).sum())


def state_gradient(world, state, engine, steps):
    """(13 N B,) reverse gradient of ``trajectory_loss`` after ``steps`` of ``engine`` w.r.t. the state."""
    import torch

    from dejaview.sim.integrate import rollout
    from dejaview.sim.state import State

    tensors = [t.detach().clone().requires_grad_(True) for t in state.tensors()]
    loss = trajectory_loss(rollout(world, State(*tensors), steps=steps, engine=engine))
    return torch.cat([g.flatten() for g in torch.autograd.grad(loss, tensors)])


def both_modes(world, state, steps: int):
    """The native rollout's ``trajectory_loss`` differentiated by the state (B, N, 13) in forward
    mode (``jacfwd``) and in reverse mode: (forward, reverse, the state as one tensor, the loss as a
    function of it)."""
    import torch

    from dejaview.sim.integrate import rollout
    from dejaview.sim.state import State

    x0 = torch.cat(state.tensors(), -1)

    def f(x):
        return trajectory_loss(rollout(world, State(x[..., :3], x[..., 3:7], x[..., 7:10], x[..., 10:]),
                                       steps=steps, engine="native"))

    jac_fwd = torch.func.jacfwd(f)(x0)
    x = x0.clone().requires_grad_(True)
    (jac_rev,) = torch.autograd.grad(f(x), x)
    return jac_fwd, jac_rev, x0, f
