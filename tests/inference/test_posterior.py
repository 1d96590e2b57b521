"""The posterior of ``dejaview.inference.posterior``: residuals, priors, Jacobians, feasibility.

Built on ``box_along_shelf`` (a box slid along a shelf board: smooth, 0.5 s) and on
``mug_off_counter`` (the start area lies on the counter top, so moving the mug down puts it
into the counter).
"""

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.backends.spheres import SpheresProblem
from dejaview.inference.posterior import (Posterior, PosteriorSettings,
                                          feasibility_check)
from dejaview.scene import Observation, Prior, Scene

SCENES = Path(__file__).resolve().parents[2] / "examples" / "scenes"


def shelf(duration=0.5, **inference):
    scene = Scene.from_xml(SCENES / "box_along_shelf.xml")
    scene = replace(scene, simulation=replace(scene.simulation, duration=duration))
    return replace(scene, inference=replace(scene.inference, **inference))


def truth_x(problem, name="box_along_shelf"):
    """Parameters (1, P) of the bundled scene ``name``'s true start."""
    import json

    truth = json.loads((SCENES / f"{name}.truth.json").read_text())["initial_state"]
    return problem.layout.encode(position=truth["position"], linear_velocity=truth["linear_velocity"],
                                 angular_velocity=truth["angular_velocity"]).double()


def test_defaults_fill_in_and_heatmap_sigma_stands_for_the_observation():
    s = PosteriorSettings.from_scene(shelf())
    assert (s.sigma, s.angle_sigma) == (PosteriorSettings.sigma, PosteriorSettings.angle_sigma)
    assert s.speed is s.spin is s.tilt is None
    mug = Scene.from_xml(SCENES / "mug_off_counter.xml")
    assert PosteriorSettings.from_scene(mug).sigma == mug.inference.heatmap.sigma
    given = replace(mug, inference=replace(mug.inference, observation=Observation(sigma=0.003)))
    assert PosteriorSettings.from_scene(given).sigma == 0.003
    js = PosteriorSettings.from_scene(shelf(prior=Prior(speed=1.0))).to_json()
    assert js["prior"]["speed"] == 1.0 and js["prior"]["speed_bound"] is None
    assert js["prior"]["spin_bound"] > 0 and js["observation"]["sigma"] == PosteriorSettings.sigma


@pytest.mark.parametrize("settings, name", [(dict(sigma=-1.0), "sigma"), (dict(speed=0.0), "speed"),
                                            (dict(tilt=math.nan), "tilt")])
def test_bad_values_are_one_line_errors(settings, name):
    with pytest.raises(InferenceError, match=name):
        PosteriorSettings(**settings).check()


def test_the_true_start_explains_its_own_end_and_an_other_does_not():
    scene = shelf(duration=1.0)
    problem = SpheresProblem.from_scene(scene)
    post = Posterior(problem, PosteriorSettings.from_scene(scene))
    x = torch.cat([truth_x(problem), problem.layout.encode().double()])
    cost, chi2, loss = post.cost(x)
    assert loss[0] < 1e-4  # the bundled target is the truth's end (rounded), where it lies still:
    assert chi2[0] < 0.1  # its rest is observed too, and it has settled to within a tenth of that noise
    assert chi2[1] > 10.0
    assert post.rollouts == 2
    # cost = 0.5 * chi2 plus the flat prior's bound terms (zero inside the bounds)
    assert cost[1] == pytest.approx(0.5 * chi2[1])


@pytest.mark.parametrize("evaluate", ["best", "final"])
def test_the_reported_loss_is_the_scenes_loss_at_one_of_the_candidates_records(evaluate):
    """``observation_residuals``' loss is the scene's per-record loss at the record it compares
    (computed there only): one of that candidate's per-record losses, the last one for final."""
    from dejaview.losses import LOSSES

    scene = shelf(duration=0.5, evaluate=evaluate)
    moving = replace(scene.inference.target, moving=True)  # seen in motion: evaluate decides
    scene = replace(scene, inference=replace(scene.inference, targets=(moving,)))
    problem = SpheresProblem.from_scene(scene)
    post = Posterior(problem, PosteriorSettings.from_scene(scene))
    x = torch.cat([truth_x(problem), problem.layout.encode().double(),
                   problem.layout.sample(3, torch.Generator().manual_seed(1)).double()])
    traj = problem.simulate(x, record_every=5)
    _, loss = post.observation_residuals(traj)
    every = LOSSES[problem.loss_kind](problem.world, problem.source, traj.states, post._target_origin,
                                      post._target_q, orientation_weight=problem.orientation_weight,
                                      points=problem.points)  # (T, B)
    gap = (every - loss).abs().min(0).values if evaluate == "best" else (every[-1] - loss).abs()
    assert loss.shape == (5,) and float(gap.max()) < 1e-12


@pytest.mark.parametrize("name, velocity", [("box_along_shelf", True), ("mug_off_counter", False)])
def test_evaluate_best_compares_the_record_with_the_least_chi_square(name, velocity):
    """With ``evaluate="best"`` the residuals are those of the record that fits best: their
    chi-square is the least of the records' own (each record's computed alone). The mug tumbles
    about changing axes, the box slides (with a target velocity)."""
    from dejaview.sim.state import State, Trajectory

    scene = Scene.from_xml(SCENES / f"{name}.xml")
    scene = replace(scene, simulation=replace(scene.simulation, duration=0.6),
                    inference=replace(scene.inference, evaluate="best"))
    target = replace(scene.inference.target, moving=True)  # seen in motion at a moment not known
    if velocity:
        target = replace(target, linear_velocity=(0.1, 0.0, 0.0))
    scene = replace(scene, inference=replace(scene.inference, targets=(target,)))
    problem = SpheresProblem.from_scene(scene)
    post = Posterior(problem, PosteriorSettings.from_scene(scene))
    x = torch.cat([truth_x(problem, name), problem.layout.sample(5, torch.Generator().manual_seed(2)).double()])
    traj = problem.simulate(x, record_every=5)
    r, _ = post.observation_residuals(traj)
    each = []
    for t in range(len(traj)):
        one = Trajectory(State(*(v[t:t + 1] for v in traj.states.tensors())), traj.steps[t:t + 1], traj.dt)
        each.append((post.observation_residuals(one)[0] ** 2).sum(-1))
    least = torch.stack(each).min(0).values
    assert torch.allclose((r ** 2).sum(-1), least, rtol=1e-9, atol=1e-12)


def test_prior_residuals_are_velocities_over_their_deviations_and_flat_inside_the_bounds():
    scene = Scene.from_xml(SCENES / "mug_off_counter.xml")
    problem = SpheresProblem.from_scene(scene)
    lay = problem.layout
    x = lay.encode(linear_velocity=[2.0, 0.0, 0.0], angular_velocity=[0.0, 0.0, 6.0]).double()
    x[0, lay.block_slice("orientation")] = torch.tensor([0.0, 0.0, 0.4]) / lay.scale["orientation"]
    prior = Posterior(problem, PosteriorSettings(speed=1.0, spin=3.0, tilt=0.2)).prior_residuals(x)[0]
    assert prior.tolist() == pytest.approx([0.0, 0.0, 2.0, 2.0, 0.0, 0.0, 0.0, 0.0, 2.0])
    flat = Posterior(problem, PosteriorSettings(speed_bound=5.0, spin_bound=50.0)).prior_residuals(x)
    assert flat.abs().max() == 0.0
    fast = lay.encode(linear_velocity=[6.0, 0.0, 0.0]).double()
    beyond = Posterior(problem, PosteriorSettings(speed_bound=5.0)).prior_residuals(fast)[0]
    assert beyond[0].item() == pytest.approx(1.0 / (0.05 * 5.0))


def test_prior_draws_follow_the_prior():
    scene = Scene.from_xml(SCENES / "mug_off_counter.xml")
    problem = SpheresProblem.from_scene(scene)
    post = Posterior(problem, PosteriorSettings(speed=0.5, spin=2.0))
    x = post.sample(4000, torch.Generator().manual_seed(0))
    d = problem.layout.decode(x)
    assert d["linear_velocity"].std(0).tolist() == pytest.approx([0.5] * 3, rel=0.06)
    assert d["angular_velocity"].std(0).tolist() == pytest.approx([2.0] * 3, rel=0.06)
    area = scene.inference.start_area
    assert (d["position"][:, 0] >= area.min[0]).all() and (d["position"][:, 0] <= area.max[0]).all()


def test_the_residual_jacobian_matches_finite_differences():
    scene = shelf(duration=0.3, prior=Prior(speed=2.0))
    problem = SpheresProblem.from_scene(scene)
    post = Posterior(problem, PosteriorSettings.from_scene(scene))
    assert_jacobian_matches_finite_differences(post, truth_x(problem) + 0.05)


def assert_jacobian_matches_finite_differences(post, x, h=1e-6):
    """``post.jacobian`` at x (1, P) against central differences of ``post.residuals``, column by
    column (rtol 1e-5); returns the residuals and the Jacobian."""
    r, J = post.jacobian(x)
    assert J.shape == (1, r.shape[1], x.shape[1])
    for j in range(x.shape[1]):
        e = torch.zeros_like(x)
        e[0, j] = h
        with torch.no_grad():
            fd = (post.residuals(x + e)[0] - post.residuals(x - e)[0]) / (2 * h)
        assert torch.allclose(J[0, :, j], fd[0], rtol=1e-5, atol=1e-5 * max(1.0, float(fd.abs().max())))
    return r, J


def test_a_start_inside_the_counter_is_rejected_by_fcl_without_simulating_it():
    scene = Scene.from_xml(SCENES / "mug_off_counter.xml")
    problem = SpheresProblem.from_scene(scene)
    check = feasibility_check(scene, problem)
    post = Posterior(problem, PosteriorSettings.from_scene(scene), feasible=check)
    on_top = problem.layout.encode(position=[0.0, 0.0, 0.95]).double()
    # the start area is flat at the counter top's height: build the buried pose directly
    pos = torch.tensor([[0.0, 0.0, 0.95], [0.0, 0.0, 0.90], [0.0, 0.0, 0.50]], dtype=torch.float64)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3, dtype=torch.float64)
    assert check(pos, q).tolist() == [True, False, False]
    # a candidate tilted 45 degrees about y on the counter top (the start area's height) cuts
    # 2.4 cm into it with a lower edge: it is not simulated
    tipped = on_top.clone()
    tipped[0, problem.layout.block_slice("orientation")] = torch.tensor([0.0, math.pi / 4, 0.0]) / 0.5
    cost, chi2, _ = post.cost(torch.cat([on_top, tipped]))
    assert math.isfinite(cost[0]) and cost[1] == math.inf and chi2[1] == math.inf
    assert post.rollouts == 1
