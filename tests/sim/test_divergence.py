"""The divergence check: a forward simulation whose state turns non-finite or leaves the sane range
ends with one line naming the object, the step and the quantity, in both engines and never with a
NaN in a file; batched evaluation keeps marking a bad candidate non-finite instead."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from dejaview.errors import SimulationError
from dejaview.sim.trajectory_csv import write_trajectory_csv
from dejaview.scene import Scene
from dejaview.scene.model import Velocity
from dejaview.sim import divergence, native
from dejaview.sim.integrate import rollout
from dejaview.sim.simulate import simulate
from tests.sim.conftest import ball_body, box_body, make_world

BALL = Path(__file__).resolve().parents[1] / "fixtures" / "server" / "ball.xml"
ENGINES = ["torch", "native"]


def _ball_scene(**velocity) -> Scene:
    """The fixture ball with a velocity set in Python (the scene reader would refuse these)."""
    scene = Scene.from_xml(BALL)
    ball = scene.object("ball")
    return scene.with_object(replace(ball, velocity=Velocity(**velocity)))


@pytest.mark.parametrize("engine", ENGINES)
def test_a_non_finite_start_stops_at_step_1(engine, tmp_path):
    scene = _ball_scene(linear=(float("nan"), 0.0, 0.0))
    with pytest.raises(SimulationError) as err:
        simulate(scene, engine=engine)
    message = str(err.value)
    assert "\n" not in message
    assert "at step 1 " in message and "object 'ball'" in message and "position is not finite" in message
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("engine", ENGINES)
def test_faster_than_light_is_diverged(engine):
    with pytest.raises(SimulationError, match=r"step 1 .*object 'ball' linear velocity reached 1e\+09 m/s"):
        simulate(_ball_scene(linear=(1e9, 0.0, 0.0)), engine=engine)
    with pytest.raises(SimulationError, match=r"object 'ball' angular velocity reached 1e\+11 rad/s"):
        simulate(_ball_scene(angular=(0.0, 1e11, 0.0)), engine=engine)


def test_both_engines_stop_at_the_same_step(monkeypatch):
    """A ball dropped from 0.4 m, with the speed limit lowered to 2 m/s: it passes 2 m/s after
    0.204 s, i.e. after step 21 of 0.01 s -- in the native engine past its first chunk of steps."""
    monkeypatch.setattr(divergence, "DIVERGED_SPEED", 2.0)
    monkeypatch.setattr("dejaview.sim.simulate.NATIVE_CHUNK", 8)
    scene = _ball_scene()
    scene = scene.replace(simulation=replace(scene.simulation, duration=1.0))
    messages = []
    for engine in ENGINES:
        with pytest.raises(SimulationError) as err:
            simulate(scene, engine=engine, record_every=3)
        messages.append(str(err.value))
    assert messages[0] == messages[1]
    assert "at step 21 (t = 0.21 s): object 'ball' linear velocity reached 2.0" in messages[0]


def test_an_unchecked_batch_keeps_the_good_candidates():
    """Inference evaluates candidates in a batch: a diverged one just turns non-finite there."""
    world = make_world([box_body()], [], gravity=(0.0, 0.0, -9.81), dt=0.01)
    state = world.state([[0.0, 0.0, 1.0]], linear_velocity=[[0.5, 0.0, 0.0]], batch_size=3)
    v = state.linear_velocity.clone()
    v[1, 0, 0] = float("inf")
    for engine in ENGINES:
        out = rollout(world, state.replace(linear_velocity=v), steps=10, engine=engine)
        assert not torch.isfinite(out.final.position[1]).all()
        assert torch.isfinite(out.final.position[[0, 2]]).all()


def test_no_file_gets_a_nan(tmp_path):
    world = make_world([ball_body()], [])
    traj = rollout(world, world.state([[0.0, 0.0, 1.0]]), steps=3)
    bad = replace(traj, states=traj.states.replace(position=traj.states.position.clone()))
    bad.states.position[2, 0, 0, 1] = float("nan")
    with pytest.raises(SimulationError, match="object 'ball' is not finite at step 2"):
        write_trajectory_csv(tmp_path / "t.csv", world, bad)
    assert not (tmp_path / "t.csv").exists()


def test_the_native_check_changes_nothing_on_a_sane_rollout():
    """The same rollout with and without the check in the C++ loop: the same states bit for bit,
    and no step marked diverged. (What the check costs is measured, not asserted: ``dejaview
    bench micro``, section ``divergence``.)"""
    world = make_world([box_body(per_axis=(5, 4, 3))], [native_floor()], dt=0.002)
    state = world.state([[0.0, 0.0, 0.3]], linear_velocity=[[1.0, 0.0, -0.5]],
                        angular_velocity=[[3.0, 2.0, 1.0]])
    init = torch.cat(state.tensors(), -1)
    tensors, floats, ints = native.pack_world(world)
    ext = native.extension()
    plain = ext.rollout(init, 2000, 50, False, tensors, floats, ints, 1)
    checked = ext.rollout(init, 2000, 50, False, tensors, floats + divergence.native_limits(), ints, 1)
    assert (plain[2] == -1).all() and (checked[2] == -1).all()
    assert torch.equal(plain[0], checked[0]) and plain[0].isfinite().all()


def native_floor():
    from dejaview.sim import StaticShape

    return StaticShape.make("floor", "plane")


def test_speed_bounds_are_consistent():
    """Every scene the reader accepts starts far inside the divergence limits."""
    from dejaview.scene import bounds

    assert bounds.MAX_SPEED < divergence.DIVERGED_SPEED / 1e3
    assert bounds.MAX_LENGTH < divergence.DIVERGED_REACH / 1e6
    assert np.isfinite(divergence.DIVERGED_SPEED ** 2)
