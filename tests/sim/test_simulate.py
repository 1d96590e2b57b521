"""``dejaview.sim.simulate``: the forward run shared by ``dejaview simulate`` and the server."""

from __future__ import annotations

from pathlib import Path

import pytest

from dejaview.errors import SimulationError
from dejaview.io.trajectory import read_trajectory_csv
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
