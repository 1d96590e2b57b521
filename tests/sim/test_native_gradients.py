"""The native engine's reverse mode by the adjoint against its full-Jacobian path (issue 25).

Reverse mode (``_Traced``: ``lam <- J^T lam`` back through the substeps, by the
hand-written vector-Jacobian products of ``adjoint.h``) and the engine before it
(``DEJAVIEW_NATIVE_GRADIENT=phi``: ``Phi_t`` carried to every record from the
forward-mode dual passes, also what forward mode uses) must give the same
gradients on multi-body scenes with static and body-pair contacts, every record
interval and substep count, batches of different candidates, bodies the loss
never reaches, and random worlds of every static shape kind; and both must agree
with finite differences.
"""

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings

from dejaview.sim import StaticShape, native
from dejaview.sim.integrate import rollout
from dejaview.sim.state import State
from tests.sim.conftest import box_body, make_world
from tests.sim.test_native_schema import worlds

RTOL = 1e-9
ROUNDOFF_FACTOR = 100.0
"""The random worlds' paths may differ by this many times what a 1e-15 m/s change of the start moves
the forward-mode gradient (its round-off, amplified by the contacts)."""
CHAOTIC_RTOL = 1e-5
"""...but never by more than this fraction of the gradient's largest component."""


def _pile(substeps=2, boxes=4, restitution=0.2):
    """A box thrown into a row of resting boxes on a floor, one box far off, resting alone."""
    bodies = [box_body(f"box{i}", size=(0.1, 0.1, 0.05), per_axis=(3, 3, 2), mass=0.5)
              for i in range(boxes)]
    world = make_world(bodies, [StaticShape.make("floor", "plane", restitution=restitution),
                                StaticShape.make("step", "box", position=(0.6, 0.0, 0.02),
                                                 half=(0.1, 0.3, 0.02), restitution=restitution)],
                       substeps=substeps, restitution=restitution)
    pos = [[0.0, 0.0, 0.09]] + [[0.13 + 0.105 * i, 0.02 * i, 0.025] for i in range(boxes - 2)]
    pos.append([-1.0, 0.0, 0.025])  # far away: the loss's adjoint never reaches it
    tilt = [math.cos(0.15), math.sin(0.15) * 0.6, math.sin(0.15) * 0.8, 0.0]
    orient = [tilt] + [[1.0, 0.0, 0.0, 0.0]] * (boxes - 1)
    lin = [[1.6, 0.1, -0.3]] + [[0.0, 0.0, 0.0]] * (boxes - 1)
    ang = [[1.0, -2.0, 3.0]] + [[0.0, 0.0, 0.0]] * (boxes - 1)
    return world, world.state(pos, orientation=orient, linear_velocity=lin, angular_velocity=ang)


def _batch(state, batch):
    shift = torch.linspace(-0.02, 0.02, batch, dtype=torch.float64)
    s = State(*(t.expand(batch, *t.shape[1:]) for t in state.tensors()))
    lin = s.linear_velocity.clone()
    lin[:, 0, 0] += shift * 10
    return s.replace(linear_velocity=lin)


def _loss(traj) -> torch.Tensor:
    """Every record's pose and velocity of every body, each candidate weighted differently."""
    s = traj.states
    w = torch.arange(1, s.position.shape[1] + 1, dtype=torch.float64)[None, :, None, None]
    return ((w * s.position ** 2).sum() + 0.3 * (s.orientation[..., 1:] ** 2).sum()
            + 0.01 * (s.linear_velocity ** 2).sum() + 0.001 * (s.angular_velocity ** 2).sum())


def _reverse(world, state, steps, record_every=1, path="adjoint", monkeypatch=None, loss=_loss):
    monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", path)
    x = torch.cat(state.tensors(), -1).detach().requires_grad_(True)
    traj = rollout(world, State(x[..., :3], x[..., 3:7], x[..., 7:10], x[..., 10:]), steps=steps,
                   record_every=record_every, engine="native")
    (g,) = torch.autograd.grad(loss(traj), x)
    return g


def _same(a, b, rtol=RTOL):
    scale = float(b.abs().max())
    assert scale > 0
    assert float((a - b).abs().max()) <= rtol * scale, float((a - b).abs().max()) / scale


@pytest.mark.parametrize("substeps,record_every", [(2, 1), (2, 7), (1, 1), (3, 4)])
def test_adjoint_equals_the_full_jacobian_path_on_a_pile_of_boxes(monkeypatch, substeps, record_every):
    world, state = _pile(substeps)
    state = _batch(state, 2)
    steps = 150
    adj = _reverse(world, state, steps, record_every, "adjoint", monkeypatch)
    phi = _reverse(world, state, steps, record_every, "phi", monkeypatch)
    _same(adj, phi)
    # the thrown box moved the others: gradients reach them through the pair contacts
    assert float(adj[:, 1].abs().max()) > 1e-3 * float(adj.abs().max())


def test_adjoint_of_a_final_pose_loss_skips_bodies_it_never_reaches(monkeypatch):
    world, state = _pile()

    def final_pose(traj):
        return (traj.states.position[-1, :, 0] ** 2).sum() + (traj.states.orientation[-1, :, 0, 1:] ** 2).sum()

    adj = _reverse(world, state, 150, 1, "adjoint", monkeypatch, final_pose)
    phi = _reverse(world, state, 150, 1, "phi", monkeypatch, final_pose)
    _same(adj, phi)
    assert float(adj[:, 1].abs().max()) > 0  # reached through contacts
    assert torch.equal(adj[:, -1], torch.zeros_like(adj[:, -1]))  # the far box: exactly zero


def test_adjoint_and_forward_mode_agree_with_finite_differences(monkeypatch):
    world, state = _pile(boxes=3)
    steps = 60  # the thrown box has hit the next one (FD needs smaller steps the longer the run)
    x0 = torch.cat(state.tensors(), -1)
    monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", "adjoint")

    def f(x):
        traj = rollout(world, State(x[..., :3], x[..., 3:7], x[..., 7:10], x[..., 10:]), steps=steps,
                       engine="native")
        return (traj.states.position[-1, 0] ** 2).sum()

    x = x0.clone().requires_grad_(True)
    (g_adj,) = torch.autograd.grad(f(x), x)
    jac_fwd = torch.func.jacfwd(f)(x0)
    _same(jac_fwd, g_adj)
    gen = torch.Generator().manual_seed(3)
    for _ in range(3):
        v = torch.zeros_like(x0)  # along the thrown box's linear and angular velocity
        v[0, 0, 7:13] = torch.randn(6, generator=gen, dtype=torch.float64)
        eps = 1e-8  # stiff contacts: central differences converge to the gradient only this close
        with torch.no_grad():
            fd = (f(x0 + eps * v) - f(x0 - eps * v)) / (2 * eps)
        exact = float((g_adj * v).sum())
        assert abs(exact - float(fd)) <= 1e-5 * max(abs(exact), 1e-3), (exact, float(fd))


def test_adjoint_through_an_inference_problem_equals_the_jacobian_path(monkeypatch):
    from dataclasses import replace

    from dejaview.backends.spheres import SpheresProblem
    from dejaview.scene import Scene

    problem = SpheresProblem.from_scene(Scene.from_xml("examples/scenes/box_among_boxes.xml"),
                                          engine="native")
    problem = replace(problem, steps=200)
    x = problem.layout.encode().to(torch.float64)
    x = x + 0.1 * torch.randn(3, x.shape[1], generator=torch.Generator().manual_seed(0), dtype=x.dtype)
    monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", "adjoint")
    loss_a, grad_a = problem.value_and_grad(x, "reverse")
    monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", "phi")
    loss_p, grad_p = problem.value_and_grad(x, "reverse")
    loss_f, grad_f = problem.value_and_grad(x, "forward")
    assert torch.allclose(loss_a, loss_p, rtol=0, atol=1e-12)
    _same(grad_a, grad_p)
    _same(grad_f, grad_a)


@pytest.mark.parametrize("substeps", [2, 8])
def test_adjoint_equals_forward_mode_and_torch_where_the_roll_stick_holds_an_edge(monkeypatch, substeps):
    """A box landing on its edge while sliding along it and rolling about it and across it: the
    roll stick of a line contact (``dejaview.sim.line_contact.line_roll_stick``) acts for most of the
    impact, and its hand-written reverse mode (``adjoint.h``'s ``RollStick``) must give the
    gradients of the forward-mode duals and of torch's autograd through the torch engine. At the
    default 2 substeps and at 8 at the same stiffness (``World.with_substeps``), where the roll is
    stopped within four substeps (``line_contact.roll_stop_time``), not one."""
    from dejaview.sim import contacts
    from tests.sim.test_physics import _tilted_box, _weightless

    body, _, _, mu, e, _, _, _, low, q = _tilted_box(35.0)
    world = _weightless([body], [StaticShape.make("floor", "plane", friction=mu, restitution=e)], mu, e)
    world = world.with_substeps(substeps)
    state = world.state([[0.0, 0.0, 0.01 - low.min()]], orientation=q, linear_velocity=[[0.0, 0.2, -1.4]],
                        angular_velocity=[[0.3, 0.0, 0.1]])

    def loss(traj):
        s = traj.states
        return ((s.position[-1] ** 2).sum() + (s.orientation[-1, ..., 1:] ** 2).sum()
                + 0.1 * (s.angular_velocity[-1] ** 2).sum())

    def torch_grad():
        x = torch.cat(state.tensors(), -1).detach().requires_grad_(True)
        traj = rollout(world, State(x[..., :3], x[..., 3:7], x[..., 7:10], x[..., 10:]), steps=30,
                       engine="torch")
        return torch.autograd.grad(loss(traj), x)[0]

    adj = _reverse(world, state, 30, 1, "adjoint", monkeypatch, loss)
    _same(adj, _reverse(world, state, 30, 1, "phi", monkeypatch, loss))
    with_stick = torch_grad()
    _same(adj, with_stick)
    monkeypatch.setattr(contacts, "line_roll_stick", lambda fn, *args: fn)
    without = torch_grad()  # the stick was acting: without it the gradient is another
    assert float((without - with_stick).abs().max()) > 0.1 * float(with_stick.abs().max())


@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                 HealthCheck.function_scoped_fixture])
@given(worlds())
def test_random_worlds_adjoint_equals_the_dual_jacobian_path(monkeypatch, case):
    """Two implementations of one derivative: hand-written reverse mode against forward-mode duals,
    to round-off. Round-off here is the world's own: where contacts amplify it, a start changed by
    1e-15 m/s moves the forward-mode gradient itself. CI drew two bodies thrown onto a static (74
    steps of 3 substeps: the paths 2.6e-10 of the gradient's largest component apart, that change
    1.2e-10) and three balls falling onto a slope (87 steps: 1.6e-9 apart, that change 4.2e-8). So
    the paths must agree to ``RTOL`` or to ``ROUNDOFF_FACTOR`` times what that change moves the
    forward-mode gradient, whichever is larger, and never worse than ``CHAOTIC_RTOL``: a wrong term
    in the adjoint is of the gradient's own size."""
    world, state, steps = case
    steps = min(steps, 100)
    adj = _reverse(world, state, steps, 3, "adjoint", monkeypatch)
    phi = _reverse(world, state, steps, 3, "phi", monkeypatch)
    nudged = [_reverse(world, state.replace(linear_velocity=state.linear_velocity + d), steps, 3, "phi",
                       monkeypatch) for d in (1e-15, -1e-15)]
    roundoff = max(float((g - phi).abs().max()) for g in nudged) / float(phi.abs().max())
    _same(adj, phi, rtol=min(max(RTOL, ROUNDOFF_FACTOR * roundoff), CHAOTIC_RTOL))


def test_a_block_prefers_a_path_and_the_environment_still_wins(monkeypatch):
    monkeypatch.delenv("DEJAVIEW_NATIVE_GRADIENT", raising=False)
    assert native.gradient_path() == "adjoint"
    with native.preferring("phi"):
        assert native.gradient_path() == "phi"
        monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", "adjoint")
        assert native.gradient_path() == "adjoint"
        monkeypatch.delenv("DEJAVIEW_NATIVE_GRADIENT")
    assert native.gradient_path() == "adjoint"
    with pytest.raises(ValueError, match="gradient path must be one of"):
        with native.preferring("bogus"):
            pass


def test_unknown_gradient_path_is_a_one_line_error(monkeypatch):
    from dejaview.errors import SimulationError

    monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", "bogus")
    with pytest.raises(SimulationError, match="DEJAVIEW_NATIVE_GRADIENT must be one of"):
        native.gradient_path()


def _box_off_a_ledge(box: bool = True):
    """A box body (``box_half``: its faces exact against a static box's edges) sliding and turning
    off a ledge's edge, half over it, onto a floor."""
    body = box_body("box", size=(0.2, 0.15, 0.1), per_axis=(4, 3, 2),
                    box_half=(0.1, 0.075, 0.05) if box else None)
    world = make_world([body], [StaticShape.make("floor", "plane"),
                                StaticShape.make("ledge", "box", position=(0.0, 0.05, 0.15), half=(0.3, 0.3, 0.15),
                                                 orientation=(math.cos(0.1), 0.0, 0.0, math.sin(0.1)))])
    tilt = [math.cos(0.02), 0.0, math.sin(0.02), 0.0]
    state = world.state([[0.26, 0.1, 0.3495]], orientation=[tilt], linear_velocity=[[1.0, 0.3, 0.0]],
                        angular_velocity=[[0.2, -0.5, 0.3]])
    return world, state


def test_adjoint_equals_forward_mode_torch_and_differences_where_a_static_box_edge_meets_a_box_face(monkeypatch):
    """A box tipping over a ledge's edge (rotated 11 deg about z), its face on the edge: the
    ledge's edge points against the box's exact faces (``box_edges.static_edge_points``) carry it,
    and their hand-written reverse mode (``adjoint.h``, ``edge_contact``) must give the gradients of
    the forward-mode duals, of torch's autograd through the torch engine and of differences."""
    world, state = _box_off_a_ledge()
    steps = 60

    def loss(traj):
        s = traj.states
        return ((s.position[-1] ** 2).sum() + (s.orientation[-1, ..., 1:] ** 2).sum()
                + 0.1 * (s.angular_velocity[-1] ** 2).sum())

    adj = _reverse(world, state, steps, 1, "adjoint", monkeypatch, loss)
    _same(adj, _reverse(world, state, steps, 1, "phi", monkeypatch, loss))
    x0 = torch.cat(state.tensors(), -1).detach()
    x = x0.clone().requires_grad_(True)
    traj = rollout(world, State(x[..., :3], x[..., 3:7], x[..., 7:10], x[..., 10:]), steps=steps, engine="torch")
    _same(adj, torch.autograd.grad(loss(traj), x)[0], rtol=1e-7)
    monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", "adjoint")

    def f(x):
        return loss(rollout(world, State(x[..., :3], x[..., 3:7], x[..., 7:10], x[..., 10:]), steps=steps,
                            engine="native"))

    gen = torch.Generator().manual_seed(5)
    for _ in range(3):
        v = torch.zeros_like(x0)
        v[0, 0, 7:13] = torch.randn(6, generator=gen, dtype=torch.float64)
        eps = 1e-8
        with torch.no_grad():
            fd = (f(x0 + eps * v) - f(x0 - eps * v)) / (2 * eps)
        exact = float((adj * v).sum())
        assert abs(exact - float(fd)) <= 1e-5 * max(abs(exact), 1e-3), (exact, float(fd))
    # the edge points acted: the same packing without its exact box tips otherwise
    plain, _ = _box_off_a_ledge(box=False)
    with torch.no_grad():
        a = rollout(world, state, steps=steps, engine="native").states
        b = rollout(plain, state, steps=steps, engine="native").states
    assert float((a.orientation[-1] - b.orientation[-1]).abs().max()) > 1e-3
