"""The warp backend: gradients against central differences, the same loss as dejaview.losses,
agreement with the sphere simulator, batches, solve and the CLI.

Skipped when warp is not installed (``pip install 'dejaview[warp]'``; CI installs it). The first
test to run compiles Warp's kernels (about a minute on 2 cores, then cached by Warp).
"""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("warp", reason="the warp extra is not installed: pip install 'dejaview[warp]'")

from dejaview.backends import make_problem  # noqa: E402
from dejaview.cli import main  # noqa: E402
from dejaview.errors import InferenceError, SceneError  # noqa: E402
from dejaview.inference import solve  # noqa: E402
from dejaview.inference.solve import SolveParams  # noqa: E402
from dejaview.sim.trajectory_csv import read_trajectory_csv  # noqa: E402
from dejaview.losses import trajectory_loss  # noqa: E402
from dejaview.scene import Scene  # noqa: E402
from dejaview.sim import World, rollout  # noqa: E402
from dejaview.sim.build import initial_state  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "tests" / "fixtures"
FLIGHT = FIXTURES / "backends" / "ball_flight.xml"
DROP = FIXTURES / "backends" / "drop_on_table.xml"
BALL = FIXTURES / "cli" / "ball.xml"
BILLIARDS = FIXTURES / "inference" / "billiards.xml"


@pytest.fixture(scope="module")
def flight():
    return {name: make_problem(FLIGHT, "warp", integrator=name) for name in ("xpbd", "semi-implicit")}


@pytest.mark.parametrize("integrator", ["xpbd", "semi-implicit"])
def test_velocity_gradient_matches_central_differences_in_flight(flight, integrator):
    """Reverse mode through wp.Tape (float32) vs central differences of the loss, on 0.2 s of
    contact-free flight: same sign and within 2 % for every velocity parameter (and the start
    position and rotation vector, through the layout's decode in torch)."""
    problem = flight[integrator]
    x = problem.layout.encode()
    value, grad = problem.value_and_grad(x)
    assert value.shape == (1,) and grad.shape == (1, problem.num_params) == (1, 11)
    names = problem.layout.names()
    h = 1e-2  # scaled units: 1 cm/s, 5 cm/s spin; float32 losses resolve it to ~1e-5 relative
    for i, name in enumerate(names):
        e = torch.zeros_like(x)
        e[0, i] = h
        fd = (problem.loss(x + e) - problem.loss(x - e)).item() / (2 * h)
        g = grad[0, i].item()
        if "velocity" in name:
            assert abs(fd) > 1e-3, name  # the check below must not pass on noise
        if abs(fd) > 1e-3:
            assert np.sign(g) == np.sign(fd), (name, g, fd)
            assert g == pytest.approx(fd, rel=0.02), (name, g, fd)


def test_forward_mode_is_a_clear_error(flight):
    problem = flight["xpbd"]
    with pytest.raises(InferenceError) as info:
        problem.value_and_grad(problem.layout.encode(), "forward")
    assert "reverse" in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(InferenceError, match="reverse"):
        solve(FLIGHT, SolveParams(iterations=1, gradient="forward"), backend="warp")


@pytest.mark.parametrize("kind, evaluate", [("pose", "final"), ("pose", "best"), ("position", "best"),
                                            ("add", "final")])
def test_the_loss_is_the_loss_of_dejaview_losses_on_the_warp_trajectory(kind, evaluate):
    """Warp's loss is ``dejaview.losses.trajectory_loss`` of the same Warp trajectory (the losses are
    written once, in torch), for every loss kind and evaluation."""
    scene = Scene.from_xml(FLIGHT)
    inference = scene.inference.__class__(**{**scene.inference.__dict__, "loss": kind, "evaluate": evaluate})
    scene = scene.__class__(**{**scene.__dict__, "inference": inference})
    problem = make_problem(scene, "warp")
    x = torch.cat([problem.layout.encode(), problem.layout.sample(2, torch.Generator().manual_seed(1))])
    loss = problem.loss(x)
    traj = problem.simulate(x, record_every=1)
    assert len(traj) == problem.steps + 1
    expected = trajectory_loss(problem.sim.frames, traj, problem.source, scene.inference.target, kind=kind,
                               evaluate=evaluate, points=problem.points)
    assert torch.allclose(loss, expected, rtol=1e-6, atol=1e-9), (loss, expected)
    assert (problem.points is not None) == (kind == "add")


def test_restitution_gradients_flow_through_the_tape_without_patching_warp(flight):
    """XPBD's restitution pass clones its input state; the backend's tape keeps that clone's adjoint
    from erasing the gradient (Warp 1.9.1 overwrites it), and ``wp.clone`` stays Warp's own."""
    import warp as wp

    clone = wp.clone
    problem = make_problem(DROP.parent / "ball_flight.xml", "warp", restitution=True)
    x = problem.layout.encode()
    _, grad = problem.value_and_grad(x)
    assert wp.clone is clone
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_both_backends_rest_a_ball_dropped_on_a_table_within_2_cm():
    from dejaview.backends.warp import simulate_scene

    scene = Scene.from_xml(DROP)
    frames, warp_traj = simulate_scene(scene, record_every=100)
    assert frames.names == ("ball",) and warp_traj.steps.tolist()[-1] == 500
    warp_end = frames.object_position(warp_traj.final)[0, 0].numpy()
    world = World.from_scene(scene)
    with torch.no_grad():
        traj = rollout(world, initial_state(world, scene), record_every=world.steps)
    spheres_end = world.object_position(traj.final)[0, 0].numpy()
    assert np.linalg.norm(warp_end - spheres_end) < 0.02, (warp_end, spheres_end)
    # at rest on the table top (z = 0.75 m + radius 5 cm), not on the floor
    assert warp_end[2] == pytest.approx(0.8, abs=0.005) and spheres_end[2] == pytest.approx(0.8, abs=0.005)
    assert warp_traj.final.linear_velocity.norm() < 0.01
    assert traj.final.linear_velocity.norm() < 0.01


def test_a_batch_is_independent_environments():
    """K candidates in one Warp model (and in chunks) give each candidate's own loss and gradient."""
    problem = make_problem(FLIGHT, "warp")
    x = torch.cat([problem.layout.encode(), problem.layout.sample(2, torch.Generator().manual_seed(0))])
    values, grads = problem.value_and_grad(x)
    problem.max_envs = 2  # chunks of 2 + 1
    values2, grads2 = problem.value_and_grad(x)
    for i in range(3):
        alone, g_alone = problem.value_and_grad(x[i:i + 1])
        assert values[i].item() == pytest.approx(alone.item(), rel=1e-5)
        assert torch.allclose(grads[i], g_alone[0], rtol=1e-4, atol=1e-6)
    assert torch.allclose(values, values2) and torch.allclose(grads, grads2)


def test_every_movable_object_is_simulated_and_written(tmp_path):
    problem = make_problem(BILLIARDS, "warp")
    traj = problem.simulate(problem.layout.encode(), steps=20, record_every=5)
    assert traj.states.position.shape == (5, 1, 2, 3)
    rows = read_trajectory_csv(problem.write_trajectory(tmp_path / "t.csv", traj))
    assert set(rows) == set(problem.body_names) and len(rows) == 2


def test_bad_warp_settings_are_errors(tmp_path):
    text = FLIGHT.read_text().replace('restitution="0.3"/>', 'restitution="0.3" warp-integrator="rk4"/>')
    bad = tmp_path / "bad.xml"
    bad.write_text(text)
    with pytest.raises(SceneError, match="warp-integrator"):
        make_problem(bad, "warp")
    with pytest.raises(InferenceError, match="integrator"):
        make_problem(FLIGHT, "warp", integrator="rk4")
    bad.write_text(text.replace('warp-integrator="rk4"', 'warp-restitution="maybe"'))
    with pytest.raises(SceneError, match="warp-restitution"):
        make_problem(bad, "warp")
    good = tmp_path / "good.xml"
    good.write_text(text.replace("rk4", "semi-implicit").replace('restitution="0.3" warp', 'restitution="0.3" '
                                                                 'warp-substeps="3" warp'))
    settings = make_problem(good, "warp").simulation_settings()
    assert settings["integrator"] == "semi-implicit" and settings["substeps"] == 3
    assert settings["restitution"] is False and make_problem(good, "warp", restitution=True).sim.settings["restitution"]


def test_cli_solve_with_warp_ends_near_the_target(tmp_path):
    """``dejaview solve --backend warp``: result.json says warp, and the best start re-simulated in
    Warp ends within 1 mm of the target."""
    with pytest.raises(SystemExit) as info:
        main(["solve", str(BALL), "-o", str(tmp_path), "--backend", "warp", "--iterations", "5", "--quiet"])
    assert info.value.code == 0
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "warp" and data["gradient"] == "reverse"
    assert data["simulation"]["integrator"] == "xpbd"
    problem = make_problem(BALL, "warp")
    x = problem.layout.encode(linear_velocity=data["initial_state"]["linear_velocity"])
    end, _ = problem.final_pose(problem.simulate(x))
    target = Scene.from_xml(BALL).inference.target.position
    assert np.linalg.norm(np.subtract(end, target)) < 1e-3
    rows = read_trajectory_csv(tmp_path / "trajectory.csv")
    assert np.allclose(rows["ball"]["position"][-1], end, atol=1e-6)


@pytest.mark.slow
def test_solve_an_example_scene_with_warp():
    """examples/scenes/ball_rolled.xml (a mesh ball bowled across the floor, 40 steps of 10 ms),
    L-BFGS in Warp from the scene's guess: the re-simulated end lies within 1 cm of the target."""
    scene = ROOT / "examples" / "scenes" / "ball_rolled.xml"
    result = solve(scene, SolveParams(iterations=40, tolerance=1e-3), backend="warp")
    end, _ = result.final_pose()
    target = Scene.from_xml(scene).inference.target.position
    assert np.linalg.norm(np.subtract(end, target)) < 0.01


def test_cli_simulate_with_warp_rests_the_dropped_ball_where_spheres_does(tmp_path):
    for backend in ("warp", "spheres"):
        with pytest.raises(SystemExit) as done:
            main(["simulate", str(DROP), "-o", str(tmp_path / backend), "--backend", backend, "--quiet"])
        assert done.value.code in (0, None)
    warp = read_trajectory_csv(tmp_path / "warp" / "trajectory.csv")
    spheres = read_trajectory_csv(tmp_path / "spheres" / "trajectory.csv")
    assert warp["ball"]["step"][-1] == spheres["ball"]["step"][-1]
    gap = np.asarray(warp["ball"]["position"][-1]) - np.asarray(spheres["ball"]["position"][-1])
    assert np.linalg.norm(gap) < 0.02
