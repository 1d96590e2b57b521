"""The native engine's schema (``dejaview.sim.native.schema``) and the two engines held together on
randomly generated worlds.

``schema.h`` must be what ``schema.header()`` generates; the C++ checks the arrays it is given
against the schema and names the field that is wrong. Hypothesis draws worlds (1-3 bodies of 1-5
spheres, every static shape kind, poses, velocities, materials, substeps, batches) on which the
native engine's states and both of its gradient modes equal the torch engine's.

Skipped (every test here) only where the native extension cannot be built (no C++ compiler):
there is then no native engine to compare; ``.ci/run`` builds it, so CI runs them.
"""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dejaview.sim import BodySpec, StaticShape, World, native
from dejaview.sim.integrate import rollout
from dejaview.sim.native import schema
from dejaview.sim.sdf import sdf_box
from dejaview.sim.state import State
from dejaview.sim.world import STATIC_KINDS

HEADER = Path(native.__file__).with_name("schema.h")

pytestmark = pytest.mark.skipif(not native.available(), reason="the native extension does not build here")


def test_the_committed_header_is_generated_from_the_schema():
    assert HEADER.read_text() == schema.header(), (
        "schema.h is out of date: regenerate it (dejaview/sim/native/schema.py's docstring)")


def test_the_schema_covers_every_static_kind_and_the_model_constants():
    from dejaview.sim import contacts

    assert list(schema.KINDS) == list(STATIC_KINDS)
    assert schema.CONSTANTS["SLIP_EPS"][0] == contacts.SLIP_EPS
    assert schema.CONSTANTS["SMOOTH_MIN_POWER"][0] == contacts.SMOOTH_MIN_POWER
    offsets = schema.shape_offsets()
    assert max(first + width for first, width in offsets.values()) == schema.SHAPE_WIDTH
    text = HEADER.read_text()
    for f in schema.WORLD_FIELDS:
        assert f"{f.name.upper()} = " in text


def test_a_bodys_state_row_is_the_states_fields_in_order_and_the_header_names_it():
    from dataclasses import fields

    from dejaview.sim import epsilons
    from dejaview.sim.state import STATE_LAYOUT, STATE_WIDTH, state_offsets

    assert [name for name, _, _ in STATE_LAYOUT] == [f.name for f in fields(State)]
    x = torch.arange(2 * 3 * STATE_WIDTH, dtype=torch.float64).reshape(2, 3, STATE_WIDTH)
    state = State.from_flat(x)
    assert [t.shape[-1] for t in state.tensors()] == [width for _, width, _ in STATE_LAYOUT]
    assert torch.equal(state.flat(), x)
    text = HEADER.read_text()
    for name, (first, _) in state_offsets().items():
        assert f"constexpr int STATE_{name.upper()} = {first};" in text
    assert f"constexpr int STATE_WIDTH = {STATE_WIDTH};" in text
    for name, (value, _) in schema.EPSILONS.items():
        assert f"constexpr double {name} = {value!r};" in text
        assert getattr(epsilons, name, value) == value  # the torch engine's value, where it has one


def _ball_world():
    ball = BodySpec("ball", 1.0, 0.004 * np.eye(3), np.zeros(3), np.zeros((1, 3)), np.array([0.05]))
    return World.build([ball], [StaticShape.make("floor", "plane")], steps=10)


@pytest.mark.parametrize("field, bad, message", [
    ("mass", lambda t: t.float(), "'mass': expected float64"),
    ("counts", lambda t: t.double(), "'counts': expected int64"),
    ("inertia", lambda t: t.reshape(-1, 9), "'inertia': expected 3 dimensions"),
    ("centers", lambda t: torch.cat([t, t]), "'centers': dimension 0 is 2, expected 1"),
    ("shapes", lambda t: t[:, :-1], "'shapes': dimension 1 is"),
])
def test_the_engine_names_the_field_it_was_given_wrong(field, bad, message):
    world = _ball_world()
    tensors, floats, ints = schema.pack(world)
    index = [f.name for f in schema.WORLD_FIELDS].index(field)
    tensors = list(tensors)
    tensors[index] = bad(tensors[index])
    init = torch.cat(world.state([[0.0, 0.0, 0.2]]).tensors(), -1)
    with pytest.raises(RuntimeError, match=message):
        native.extension().rollout(init, 5, 1, 0, tensors, floats, ints, 1)
    with pytest.raises(RuntimeError, match="floats"):
        native.extension().rollout(init, 5, 1, 0, list(schema.pack(world)[0]), floats[:-1], ints, 1)


# ----------------------------------------------------------------------------- random worlds
def _grid_static(position) -> StaticShape:
    half = torch.tensor([0.2, 0.15, 0.08], dtype=torch.float64)
    spacing, margin = 0.02, 0.08
    lo = -half - margin
    n = [int(round(float(2 * (h + margin)) / spacing)) + 1 for h in half]
    axes = [lo[i] + spacing * torch.arange(n[i], dtype=torch.float64) for i in range(3)]
    values, _ = sdf_box(torch.stack(torch.meshgrid(*axes, indexing="ij"), -1), half)
    return StaticShape.make("block", "grid", position=position, grid=values.numpy(), grid_origin=lo.numpy(),
                            grid_spacing=spacing)


def _static(kind: str, position, angle: float) -> StaticShape:
    q = (math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0)  # tilted about y
    if kind == "plane":
        return StaticShape.make("slope", "plane", position=position, orientation=q)
    if kind == "box":
        return StaticShape.make("block", "box", position=position, orientation=q, half=(0.2, 0.15, 0.08))
    if kind == "sphere":
        return StaticShape.make("dome", "sphere", position=(position[0], position[1], position[2] - 0.2),
                                radius=0.3)
    if kind == "cylinder":
        return StaticShape.make("drum", "cylinder", position=position, orientation=q, radius=0.2,
                                half_height=0.1)
    return _grid_static(position)


floats = st.floats  # a short name for the many draws below


@st.composite
def worlds(draw):
    """(world, state, steps): bodies dropped and thrown onto a random static over a floor."""
    n = draw(st.integers(1, 3))
    bodies = []
    for i in range(n):
        count = draw(st.integers(1, 5))
        centers = np.array(draw(st.lists(st.tuples(*[floats(-0.04, 0.04)] * 3), min_size=count,
                                         max_size=count)))
        radii = np.array(draw(st.lists(floats(0.015, 0.04), min_size=count, max_size=count)))
        mass = draw(floats(0.3, 2.0))
        moments = np.array(draw(st.tuples(*[floats(0.5, 2.0)] * 3))) * mass * 1e-3
        bodies.append(BodySpec(f"b{i}", mass, np.diag(moments), np.zeros(3), centers, radii,
                               friction=draw(floats(0.1, 0.9)), restitution=draw(floats(0.0, 0.7))))
    kind = draw(st.sampled_from(STATIC_KINDS))
    statics = [_static(kind, (draw(floats(-0.05, 0.05)), 0.0, 0.05), draw(floats(-0.3, 0.3))),
               StaticShape.make("floor", "plane", position=(0.0, 0.0, -0.3))]
    world = World.build(bodies, statics, substeps=draw(st.integers(1, 3)), steps=10,
                        friction=draw(floats(0.2, 0.8)))
    batch = draw(st.integers(1, 2))
    pos = [[draw(floats(-0.1, 0.1)), draw(floats(-0.1, 0.1)), 0.3 + 0.12 * i] for i in range(n)]
    lin = [[draw(floats(-1.0, 1.0)) for _ in range(3)] for _ in range(n)]
    ang = [[draw(floats(-5.0, 5.0)) for _ in range(3)] for _ in range(n)]
    axis = np.array(draw(st.tuples(*[floats(-1.0, 1.0)] * 3))) + 1e-3
    angle = draw(floats(0.0, 3.0))
    q = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis / np.linalg.norm(axis)])
    state = world.state(pos, orientation=[q.tolist()] * n, linear_velocity=lin, angular_velocity=ang,
                        batch_size=batch)
    if batch > 1:
        state = state.replace(position=state.position + torch.tensor([[[0.0, 0.0, 0.0]], [[0.03, -0.02, 0.01]]],
                                                                     dtype=torch.float64))
    return world, state, draw(st.integers(40, 160))


SETTINGS = settings(max_examples=10, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _loss(traj) -> torch.Tensor:
    s = traj.states
    return ((s.position ** 2).sum() + 0.3 * (s.orientation[..., 1:] ** 2).sum()
            + 0.01 * (s.linear_velocity ** 2).sum() + 0.001 * (s.angular_velocity ** 2).sum())


@SETTINGS
@given(worlds())
def test_random_worlds_native_states_equal_the_torch_engine(case):
    world, state, steps = case
    with torch.no_grad():
        ref = rollout(world, state, steps=steps, record_every=7, engine="torch")
        out = rollout(world, state, steps=steps, record_every=7, engine="native")
    for a, b in zip(out.states.tensors(), ref.states.tensors()):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-9)


@SETTINGS
@given(worlds())
def test_random_worlds_native_gradients_equal_torch_autograd_in_both_modes(case):
    world, state, steps = case
    steps = min(steps, 80)
    x0 = torch.cat(state.tensors(), -1)  # (B, N, 13)

    def f(x, engine):
        return _loss(rollout(world, State(x[..., :3], x[..., 3:7], x[..., 7:10], x[..., 10:]), steps=steps,
                             record_every=5, engine=engine))

    x = x0.clone().requires_grad_(True)
    (ref,) = torch.autograd.grad(f(x, "torch"), x)
    x = x0.clone().requires_grad_(True)
    (rev,) = torch.autograd.grad(f(x, "native"), x)
    v = torch.randn(x0.shape, generator=torch.Generator().manual_seed(0), dtype=x0.dtype)
    _, fwd = torch.func.jvp(lambda y: f(y, "native"), (x0,), (v,))
    scale = float(ref.abs().max()) + 1e-12
    torch.testing.assert_close(rev, ref, rtol=1e-7, atol=1e-9 * scale)
    torch.testing.assert_close(fwd, (ref * v).sum(), rtol=1e-7, atol=1e-9 * scale * float(v.abs().sum()))
