"""Forward and reverse gradients agree with each other and with finite differences."""

import pytest
import torch

from dejaview.sim import StaticShape, World, rollout
from dejaview.sim import contacts, line_contact, sdf
from dejaview.sim.gradients import forward_value_and_grad, reverse_value_and_grad
from dejaview.sim.rotation import geodesic_angle, quat_multiply, rotvec_to_quat
from tests.sim.conftest import box_body, make_world

TARGET_Q = torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64)
TARGET_Q = TARGET_Q / TARGET_Q.norm()


def loss_fn(world: World, x0: torch.Tensor, steps: int, target: torch.Tensor):
    """Final pose error of body 0 from 12 initial-state parameters (position, rotvec, v, w)."""
    q0 = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)

    def fn(x):
        x = x0 + x
        q = quat_multiply(rotvec_to_quat(x[..., 3:6]), q0)
        state = world.state(x[..., None, 0:3], q[..., None, :], x[..., None, 6:9], x[..., None, 9:12])
        final = rollout(world, state, steps=steps).final
        d = final.position[:, 0] - target
        ang = geodesic_angle(final.orientation[:, 0], TARGET_Q.expand_as(final.orientation[:, 0]))
        return (d * d).sum(-1) + 0.1 * ang ** 2

    return fn


def central_difference(fn, x, eps=1e-6):
    grads = []
    for j in range(x.shape[-1]):
        e = torch.zeros_like(x)
        e[..., j] = eps
        grads.append((fn(x + e) - fn(x - e)) / (2 * eps))
    return torch.stack(grads, -1)


def flight_case():
    world = make_world([box_body()], [], dt=0.002, substeps=2)
    x0 = torch.tensor([0.0, 0.0, 1.0, 0.1, -0.2, 0.3, 1.0, 0.5, 2.0, 3.0, -1.0, 2.0], dtype=torch.float64)
    return loss_fn(world, x0, 100, torch.tensor([0.5, 0.0, 1.0], dtype=torch.float64))


def sliding_case():
    floor = StaticShape.make("floor", "plane", friction=0.4)
    world = make_world([box_body(friction=0.4)], [floor], dt=0.002, substeps=2, friction=0.4)
    # start at the resting sink (mg / k = g / omega^2) so every bottom sphere is in contact
    z = 0.05 - 9.81 / world.contact.frequency ** 2
    x0 = torch.tensor([0.0, 0.0, z, 0.0, 0.0, 0.0, 2.0, 0.3, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    return loss_fn(world, x0, 80, torch.tensor([0.5, 0.1, 0.05], dtype=torch.float64))


@pytest.mark.parametrize("case", [flight_case, sliding_case], ids=["flight", "sliding"])
def test_forward_equals_reverse_equals_finite_differences(case):
    fn = case()
    x = torch.zeros(1, 12, dtype=torch.float64)
    v_rev, g_rev = reverse_value_and_grad(fn, x)
    v_fwd, g_fwd = forward_value_and_grad(fn, x)
    assert torch.allclose(v_rev, v_fwd, rtol=1e-12)
    scale = g_rev.abs().max()
    assert ((g_fwd - g_rev).abs().max() / scale) < 1e-6
    g_fd = central_difference(fn, x)
    assert ((g_fd - g_rev).abs().max() / scale) < 1e-4


def test_batched_gradients_are_per_candidate():
    """A batch of B candidates gives the same gradients as B single runs."""
    fn = flight_case()
    x = torch.randn(3, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.1
    _, g_batch = forward_value_and_grad(fn, x)
    for b in range(3):
        _, g_one = reverse_value_and_grad(fn, x[b:b + 1])
        assert torch.allclose(g_batch[b:b + 1], g_one, rtol=1e-8, atol=1e-10)


def test_checkpointed_reverse_gradient_matches_plain():
    floor = StaticShape.make("floor", "plane")
    world = make_world([box_body()], [floor])
    state0 = world.state([[0.0, 0.0, 0.3]], linear_velocity=[[1.0, 0.0, 0.0]])

    def grad(ckpt):
        v = state0.linear_velocity.clone().requires_grad_(True)
        traj = rollout(world, state0.replace(linear_velocity=v), steps=120, checkpoint_every=ckpt)
        traj.final.position.sum().backward()
        return v.grad

    assert torch.allclose(grad(None), grad(20), rtol=1e-10, atol=1e-12)


def test_gradients_finite_at_zero_rotation_and_zero_velocity():
    """Zero rotation vector, zero angular velocity, zero sliding speed: no NaN."""
    floor = StaticShape.make("floor", "plane")
    world = make_world([box_body()], [floor])
    x0 = torch.tensor([0.0, 0.0, 0.05] + [0.0] * 9, dtype=torch.float64)
    fn = loss_fn(world, x0, 30, torch.tensor([0.1, 0.0, 0.05], dtype=torch.float64))
    x = torch.zeros(1, 12, dtype=torch.float64)
    for mode in (forward_value_and_grad, reverse_value_and_grad):
        _, g = mode(fn, x)
        assert torch.isfinite(g).all()


def _rand(*shape, seed=0):
    return torch.rand(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def test_gradcheck_normal_force():
    depth = (_rand(2, 5) * 0.01 + 1e-3).requires_grad_(True)
    vn = (_rand(2, 5, seed=1) - 0.5).requires_grad_(True)
    stiff = torch.tensor(1e4, dtype=torch.float64)
    unload = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda d, v, u: contacts.normal_force(d, contacts.depth_weights(d), v, stiff, u, 0.01, 250.0),
        (depth, vn, unload))


def test_gradcheck_friction_force():
    vt = (_rand(4, 3) - 0.5).requires_grad_(True)
    coulomb = (_rand(4, seed=2) + 0.1).requires_grad_(True)
    stick = (_rand(4, seed=8) * 3 + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(contacts.friction_force, (vt, coulomb, stick))
    # and at zero slip (sticking): finite, zero force
    zero = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(contacts.friction_force, (zero, coulomb, stick))


def test_friction_is_coulomb_while_sliding_and_stops_slip_when_slow():
    mu_fn = torch.tensor([2.0], dtype=torch.float64)
    stick = torch.tensor([1e4], dtype=torch.float64)  # strong stick limit
    fast = contacts.friction_force(torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64), mu_fn, stick)
    assert torch.allclose(fast, torch.tensor([[-2.0, 0.0, 0.0]], dtype=torch.float64), rtol=1e-6)
    slow = contacts.friction_force(torch.tensor([[1e-6, 0.0, 0.0]], dtype=torch.float64), mu_fn, stick)
    assert torch.allclose(slow, torch.tensor([[-1e-2, 0.0, 0.0]], dtype=torch.float64), rtol=1e-6)


def test_gradcheck_sdf_grid_lookup():
    values = _rand(5, 6, 7, seed=3) - 0.5
    origin = torch.tensor([-0.1, -0.2, 0.0], dtype=torch.float64)
    # points strictly inside cells (trilinear interpolation is smooth there)
    p = (origin + 0.1 * (torch.tensor([1.3, 2.6, 3.2]) + 0.4 * _rand(6, 3, seed=4))).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: sdf.sdf_grid(q, values, origin, 0.1), (p,))


def test_sdf_grid_gradient_is_derivative_of_distance():
    values = _rand(5, 6, 7, seed=5)
    origin = torch.zeros(3, dtype=torch.float64)
    p = (0.1 * (torch.tensor([1.3, 2.6, 3.2]) + 0.4 * _rand(6, 3, seed=6))).requires_grad_(True)
    d, g = sdf.sdf_grid(p, values, origin, 0.1)
    (auto,) = torch.autograd.grad(d.sum(), p)
    assert torch.allclose(auto, g, atol=1e-10)


@pytest.mark.parametrize("shape", ["box", "sphere", "cylinder"])
def test_analytic_sdf_gradient_matches_autograd(shape):
    p = ((_rand(50, 3, seed=7) - 0.5) * 0.8).requires_grad_(True)
    if shape == "box":
        d, n = sdf.sdf_box(p, torch.tensor([0.2, 0.1, 0.15], dtype=torch.float64))
    elif shape == "sphere":
        d, n = sdf.sdf_sphere(p, 0.2)
    else:
        d, n = sdf.sdf_cylinder(p, 0.15, 0.2)
    (auto,) = torch.autograd.grad(d.sum(), p)
    assert torch.allclose(auto, n, atol=1e-8)
    assert torch.allclose(n.norm(dim=-1), torch.ones(50, dtype=torch.float64), atol=1e-8)


def _line_set(roll_spin: float, along_spin: float, clean: bool = False):
    """Three contacts of a box's edge on the floor (along y, 0.2 m long, 0.1 m below and 0.08 m
    beside the centre) and a fourth barely touching off the line, their depth weights, unit
    normals, normal forces, and a spin of ``roll_spin`` about x (lifting one end of the edge) plus
    ``along_spin`` about y (rolling over the edge): (fn, weight, arm, normal, spin, mass, inv_w).
    ``clean``: the fourth contact not touching and the normals all +z (the line exactly along y)."""
    arm = torch.tensor([[[[0.08, -0.1, -0.1], [0.08, 0.0, -0.1], [0.08, 0.1, -0.1], [0.0, 0.02, -0.1]]]],
                       dtype=torch.float64)
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(1, 1, 4, 3).clone()
    weight = torch.tensor([[[0.3, 0.35, 0.35, 0.0]]], dtype=torch.float64)
    if not clean:
        normal[0, 0, 1] = torch.tensor([0.05, 0.0, 1.0], dtype=torch.float64) / (1.0025 ** 0.5)
        weight = torch.tensor([[[0.3, 0.35, 0.34, 0.01]]], dtype=torch.float64)
    fn = torch.tensor([[[9.0, 10.0, 11.0, 0.2]]], dtype=torch.float64)
    spin = torch.tensor([[[roll_spin, along_spin, 0.0]]], dtype=torch.float64)
    inv_w = torch.diag(torch.tensor([300.0, 200.0, 150.0], dtype=torch.float64)).expand(1, 1, 3, 3)
    return fn, weight, arm, normal, spin.squeeze(-2), torch.tensor([1.0], dtype=torch.float64), inv_w


def test_line_roll_stick_holds_the_roll_of_an_edge_and_nothing_else():
    """``line_contact.line_roll_stick``: on an edge spinning about x (the roll that lifts one end) the
    sinking end is pressed and the lifting end unloaded, by the forces that stop that roll in one
    substep; a spin about the edge (rolling over it) changes nothing, nor does any spin on a set
    that is not a line (four contacts at a square's corners); gradients exact (gradcheck)."""
    h = 1e-3
    fn, weight, arm, normal, spin, mass, inv_w = _line_set(2.0, 0.0)
    out = line_contact.line_roll_stick(fn, weight, arm, normal, spin, mass, inv_w, h)
    # spin +x: the end at y = +0.1 moves up (+z), the end at y = -0.1 down
    assert out[0, 0, 0] > fn[0, 0, 0] + 1.0 and out[0, 0, 2] < fn[0, 0, 2] - 1.0
    assert torch.equal(out[0, 0, 2], torch.zeros((), dtype=torch.float64))  # unloaded, not pulled
    rolled = line_contact.line_roll_stick(*_line_set(0.0, 5.0, clean=True)[:5], mass, inv_w, h)
    assert torch.allclose(rolled, fn, rtol=0, atol=1e-9)
    square = torch.tensor([[[[0.1, 0.1, -0.1], [-0.1, 0.1, -0.1], [-0.1, -0.1, -0.1], [0.1, -0.1, -0.1]]]],
                          dtype=torch.float64)
    flat = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(1, 1, 4, 3)
    assert torch.equal(line_contact.line_roll_stick(fn, weight, square, flat, spin, mass, inv_w, h), fn)
    # one sphere touching a floor and a wall (a ball in a corner): two contacts, so a "line", but
    # a sphere's spin moves no contact point along its normal: nothing changes
    corner = torch.tensor([[[[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]]],
                          dtype=torch.float64)
    ball = -0.05 * corner
    two = torch.tensor([[[0.6, 0.4, 0.0, 0.0]]], dtype=torch.float64)
    wild = torch.tensor([[3.0, -2.0, 5.0]], dtype=torch.float64)
    assert torch.allclose(line_contact.line_roll_stick(fn, two, ball, corner, wild, mass, inv_w, h), fn,
                          rtol=0, atol=1e-9)
    # one touching contact: a point (gate 0), the forces and their derivatives those of fn alone
    one = torch.tensor([[[1.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)
    fn1 = fn.clone().requires_grad_(True)
    arm1 = arm.clone().requires_grad_(True)
    out1 = line_contact.line_roll_stick(fn1, one, arm1, normal, wild, mass, inv_w, h)
    assert torch.equal(out1, fn)
    g_fn, g_arm = torch.autograd.grad(out1.sum(), (fn1, arm1), allow_unused=True)
    assert torch.equal(g_fn, torch.ones_like(fn)) and (g_arm is None or not g_arm.any())
    fn, weight, arm, normal, spin, mass, inv_w = _line_set(0.3, 1.0)
    args = tuple(t.clone().requires_grad_(True) for t in (fn, weight, arm, normal, spin))
    assert torch.autograd.gradcheck(
        lambda *a: line_contact.line_roll_stick(*a, mass, inv_w, h), args)


def test_gradcheck_static_contact_wrench():
    floor = StaticShape.make("floor", "plane")
    world = make_world([box_body()], [floor])
    base = world.state([[0.0, 0.0, 0.048]], orientation=[[0.999, 0.02, 0.03, 0.0]],
                       linear_velocity=[[0.5, 0.1, -0.2]], angular_velocity=[[0.3, -0.2, 0.1]])

    def f(x, v, w):
        s = base.replace(position=x, linear_velocity=v, angular_velocity=w)
        spheres = world.sphere_positions(s)
        from dejaview.sim.rotation import quat_to_matrix

        rot = quat_to_matrix(s.orientation)
        inv_w = rot @ world.inv_inertia @ rot.transpose(-1, -2)
        return contacts.static_contact_wrench(world, s, spheres, 0.001, inv_w)

    args = tuple(t.clone().requires_grad_(True) for t in (base.position, base.linear_velocity,
                                                          base.angular_velocity))
    assert torch.autograd.gradcheck(f, args)


@pytest.mark.parametrize("per_axis", [(2, 2, 2), (4, 3, 2)])
def test_gradient_through_a_resting_box_matches_finite_differences(per_axis):
    """A box at rest on the floor (zero slip, so the slip direction is undefined):
    d(final x) / d(initial vx) is a few mm per m/s (friction stops a nudge within a substep).
    With the effective mass taken along the slip direction the reverse-mode gradient grew
    1.6x per substep (-8e20 after 60 steps for the 2 x 2 x 2 packing)."""
    world = make_world([box_body(size=(0.1, 0.1, 0.1), per_axis=per_axis, mass=0.8)],
                       [StaticShape.make("floor", "plane")])
    with torch.no_grad():  # settled: pressed into the floor, slip exactly zero by symmetry
        state = rollout(world, world.state([[0.0, 0.0, 0.05]]), steps=20).final

    def final_x(vx):
        v = torch.cat([vx.reshape(1, 1, 1), torch.zeros(1, 1, 2, dtype=vx.dtype)], -1)
        return rollout(world, state.replace(linear_velocity=v), steps=60).final.position[0, 0, 0]

    vx = torch.zeros((), dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(final_x(vx), vx)
    eps = 1e-6
    with torch.no_grad():
        fd = (final_x(vx + eps) - final_x(vx - eps)) / (2 * eps)
    assert 0.0 < float(fd) < 0.02
    assert torch.allclose(grad, fd, rtol=1e-3, atol=1e-6)
