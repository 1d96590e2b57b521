"""``dejaview.sim.simulate``: the forward run shared by ``dejaview simulate`` and the server."""

from __future__ import annotations

from pathlib import Path

import pytest

from dejaview.errors import SimulationError
from dejaview.sim.trajectory_csv import read_trajectory_csv
from dejaview.scene import Scene
from dejaview.sim.simulate import SimulationStopped, simulate

BALL = Path(__file__).resolve().parents[1] / "fixtures" / "server" / "ball.xml"


def test_free_flight_csv_and_progress(tmp_path):
    calls = []
    # the torch engine calls back after every step (the native engine between chunks of steps:
    # tests/sim/test_native.py)
    run = simulate(Scene.from_xml(BALL), callback=lambda step, total: calls.append((step, total)),
                   engine="torch")
    assert run.steps == 20 and calls == [(i, 20) for i in range(1, 21)]
    traj = read_trajectory_csv(run.write(tmp_path)["trajectory"])
    assert traj["ball"]["position"][-1][0] == pytest.approx(0.1, abs=1e-12)  # 0.5 m/s for 0.2 s
    assert run.csv() == (tmp_path / "trajectory.csv").read_text()


def test_should_stop_ends_the_run_at_the_next_step():
    seen = []
    with pytest.raises(SimulationStopped, match="after 3 of 20 steps"):
        simulate(Scene.from_xml(BALL), callback=lambda s, n: seen.append(s), should_stop=lambda: len(seen) >= 3,
                 engine="torch")
    assert seen == [1, 2, 3]


def test_steps_and_record_every():
    run = simulate(Scene.from_xml(BALL), steps=5, record_every=2)
    assert run.trajectory.steps.tolist() == [0, 2, 4, 5]
    for bad in ({"steps": 0}, {"record_every": 0}):
        with pytest.raises(SimulationError):
            simulate(Scene.from_xml(BALL), **bad)


def test_a_step_budget_on_every_entry_point(monkeypatch):
    """``simulate`` and ``rollout`` refuse absurd step counts with one line instead of running for
    ever (or failing to allocate); the budget (steps x substeps) is a named constant, overridable."""
    from dejaview.scene import bounds
    from dejaview.sim import World
    from dejaview.sim.build import initial_state
    from dejaview.sim.integrate import rollout

    scene = Scene.from_xml(BALL)  # 2 substeps
    for engine in ("native", "torch"):
        with pytest.raises(SimulationError, match=r"the simulation is 1e\+12 steps x 2 substeps = "
                                                  r"2e\+12 integration steps, over the budget of 2000000"):
            simulate(scene, steps=10 ** 12, engine=engine)
    with pytest.raises(SimulationError, match="over the budget of 40 "):
        simulate(scene, steps=21, max_steps=40)
    assert simulate(scene, steps=20, max_steps=40).steps == 20
    world = World.from_scene(scene)
    with pytest.raises(SimulationError, match="the rollout is 1000001 steps x 2 substeps"):
        rollout(world, initial_state(world, scene), steps=bounds.MAX_STEPS // 2 + 1, engine="native")
    monkeypatch.setenv("DEJAVIEW_MAX_STEPS", "30")
    with pytest.raises(SimulationError, match="over the budget of 30 "):
        simulate(scene, steps=16)
    with pytest.raises(SimulationError, match="the default rollout is 20 steps x 2 substeps"):
        World.from_scene(scene)
    # recording every 10**30th step is recording the first and the last (and fits in C++)
    monkeypatch.delenv("DEJAVIEW_MAX_STEPS")
    assert simulate(scene, steps=5, record_every=10 ** 30).trajectory.steps.tolist() == [0, 5]
