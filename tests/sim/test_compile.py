"""The opt-in torch.compile path gives the same states and gradients as eager mode.

Marked slow: the first compile of a chunk takes from tens of seconds (this
tiny world) to minutes (a 150-sphere mug), see dejaview.sim.integrate.
"""

import pytest
import torch

from dejaview.sim import StaticShape, rollout
from tests.sim.conftest import box_body, make_world


@pytest.mark.slow
def test_compiled_rollout_and_gradient_match_eager():
    world = make_world([box_body(per_axis=(2, 2, 1))], [StaticShape.make("floor", "plane")])
    state = world.state([[0.0, 0.0, 0.3]], linear_velocity=[[1.0, 0.0, 0.0]],
                        angular_velocity=[[0.0, 2.0, 0.0]])

    def final_and_grad(compile):
        v = state.linear_velocity.clone().requires_grad_(True)
        traj = rollout(world, state.replace(linear_velocity=v), steps=103, compile=compile,
                       compile_chunk=4)
        (g,) = torch.autograd.grad(traj.final.position.sum(), v)
        return traj.states.position.detach(), g

    eager_pos, eager_grad = final_and_grad(False)
    comp_pos, comp_grad = final_and_grad(True)
    assert torch.allclose(comp_pos, eager_pos, rtol=1e-10, atol=1e-12)
    assert torch.allclose(comp_grad, eager_grad, rtol=1e-8, atol=1e-12)


@pytest.mark.slow
def test_more_worlds_than_dynamos_recompile_limit_each_get_their_own_compile(monkeypatch):
    """Each World is traced as its own function: dynamo's limit of 8 recompiles per
    code object (a hard failure under ``fullgraph=True``) is never reached by a process
    that compiles for many Worlds (here 10 balls with different steps: a World's Python
    numbers are guarded constants, so each is a recompile; dynamo's eager backend keeps
    the test to tracing)."""
    import functools

    import torch._dynamo

    from tests.sim.conftest import ball_body

    monkeypatch.setattr(torch, "compile", functools.partial(torch.compile, backend="eager"))
    torch._dynamo.reset()
    assert torch._dynamo.config.recompile_limit < 10
    for i in range(10):
        world = make_world([ball_body()], [StaticShape.make("floor", "plane")], dt=0.001 * (1 + i))
        state = world.state([[0.0, 0.0, 0.049]])  # resting 1 mm deep: contact forces
        comp = rollout(world, state, steps=2, compile=True, compile_chunk=2)
        eager = rollout(world, state, steps=2)
        assert torch.allclose(comp.final.position, eager.final.position, rtol=1e-12, atol=1e-14)


@pytest.mark.slow
def test_compiled_gradient_rollout_matches_eager_through_body_pair_contacts():
    """A box thrown into two resting ones: the training graph (grad enabled) of a compiled
    chunk gives eager's states. With ``index_add`` scattering the pair forces, inductor
    (torch 2.13) miscompiled it: states off by 1e-3 from the first pair contact on, so
    compiled solves optimised another loss than the one re-simulated."""
    bodies = [box_body(f"box{i}", size=(0.1, 0.1, 0.1), per_axis=(2, 2, 2), mass=0.8) for i in range(3)]
    world = make_world(bodies, [StaticShape.make("floor", "plane")])
    state = world.state([[0.0, 0.0, 0.06], [0.15, 0.0, 0.05], [0.15, 0.11, 0.05]],
                        linear_velocity=[[1.5, 0.1, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
                        angular_velocity=[[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])

    def states_and_grad(compile):
        # the thrown box's velocity only (a resting box's own velocity has an ill-conditioned
        # gradient: its friction removes any slip within a substep)
        v0 = state.linear_velocity[:, :1].clone().requires_grad_(True)
        v = torch.cat([v0, state.linear_velocity[:, 1:]], 1)
        traj = rollout(world, state.replace(linear_velocity=v), steps=60, compile=compile,
                       compile_chunk=2)
        (g,) = torch.autograd.grad(traj.final.position[..., 0].sum(), v0)
        return traj.states.position.detach(), traj.final.position.detach(), g

    eager_pos, eager_end, eager_grad = states_and_grad(False)
    moved = torch.linalg.vector_norm(eager_end[0, 1:] - state.position[0, 1:], dim=-1)
    assert moved.max() > 0.01  # the thrown box did knock the others
    comp_pos, _, comp_grad = states_and_grad(True)
    assert torch.allclose(comp_pos, eager_pos, rtol=1e-10, atol=1e-12)
    assert torch.allclose(comp_grad, eager_grad, rtol=1e-8, atol=1e-12)


@pytest.mark.slow
def test_compiled_rollout_matches_eager_where_a_static_box_edge_meets_a_box_face():
    """A box body sliding off a ledge (``dejaview.sim.box_edges``): the ledge's edge points are made
    with the shape, outside the compiled code (made inside it, their count's ``round`` of a traced
    half extent stopped dynamo), and the compiled states are eager's."""
    from tests.sim.test_native_gradients import _box_off_a_ledge

    world, state = _box_off_a_ledge()
    with torch.no_grad():
        eager = rollout(world, state, steps=20).states
        comp = rollout(world, state, steps=20, compile=True, compile_chunk=5).states
    assert float((eager.orientation[-1] - state.orientation).abs().max()) > 1e-3  # it tipped
    assert torch.allclose(comp.position, eager.position, rtol=1e-10, atol=1e-12)
    assert torch.allclose(comp.orientation, eager.orientation, rtol=1e-10, atol=1e-12)


def test_small_matmul_under_compile_is_the_matrix_product():
    """``small_matmul`` switches to a broadcast sum under torch.compile: same products, batched
    and with a 2-D right operand, and the same gradients (a tiny graph: seconds to compile)."""
    from dejaview.sim.rotation import small_matmul

    a = torch.randn(2, 3, 5, 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, 3, 3, 4, dtype=torch.float64)
    c = torch.randn(3, 3, dtype=torch.float64)
    traced = []

    def products(a, b, c):
        traced.append(torch.compiler.is_compiling())  # runs while dynamo traces
        return small_matmul(a, b), small_matmul(a, c)

    ab, ac = torch.compile(products, fullgraph=True)(a, b, c)
    assert traced and all(traced)  # the compiled branch was the one traced
    assert torch.allclose(ab, a @ b, rtol=1e-14, atol=1e-14)
    assert torch.allclose(ac, a @ c, rtol=1e-14, atol=1e-14)
    (g,) = torch.autograd.grad((ab.sum() + ac.square().sum()), a)
    (g_ref,) = torch.autograd.grad(((a @ b).sum() + (a @ c).square().sum()), a)
    assert torch.allclose(g, g_ref, rtol=1e-12, atol=1e-12)


def test_a_moving_static_compiles_once_for_every_chunk_and_matches_eager(monkeypatch):
    """A moving robot's links (``dejaview.sim.motion``): each chunk takes its substeps' posed Worlds as
    inputs (``compiled_chunk``'s ``posed``), so the chunks of the rollout share their traces, and the
    links stand where eager mode has them at each substep: the same states and gradients. Dynamo's
    eager backend keeps the test to tracing (inductor's own code generation is the slow tests')."""
    import functools

    import torch._dynamo

    from tests.sim.test_moving_statics import _world

    monkeypatch.setattr(torch, "compile", functools.partial(torch.compile, backend="eager"))
    torch._dynamo.reset()
    steps = 45  # the paddle, 0.3 rad short of the ball, meets it from step ~20 on
    world, state = _world("ball", steps, theta0=-0.3)

    def run(compile):
        v = state.linear_velocity.clone().requires_grad_(True)
        traj = rollout(world, state.replace(linear_velocity=v), steps=steps, compile=compile, compile_chunk=1)
        (g,) = torch.autograd.grad(traj.final.position.sum(), v)
        return traj.states.position.detach(), g

    eager_pos, eager_grad = run(False)
    assert float((eager_pos[-1] - eager_pos[0]).abs().max()) > 1e-3  # pushed
    torch._dynamo.utils.counters.clear()
    comp_pos, comp_grad = run(True)
    # 45 chunks, two traces: the first chunk's positions need no gradient, the others' do (as in
    # any compiled rollout); the chunks' posed statics are inputs, not guards
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 2
    assert torch.allclose(comp_pos, eager_pos, rtol=1e-12, atol=1e-14)
    assert torch.allclose(comp_grad, eager_grad, rtol=1e-10, atol=1e-14)


def test_gradients_of_a_compiled_box_body_against_a_moving_box_link_are_refused():
    """Inductor's gradients of a primitive box pushed by a moving box paddle came out 5e-3 off (of
    7e-3; its states and dynamo's tracing alone were exact, and a box body against a static box's
    edges is exact): refused in one line, only where gradients are recorded."""
    from dejaview.errors import SimulationError
    from tests.sim.test_moving_statics import _world

    world, state = _world("box", 4)
    with pytest.raises(SimulationError, match="box body meets a moving box link") as info:
        rollout(world, state, steps=4, compile=True)
    assert "\n" not in str(info.value)
