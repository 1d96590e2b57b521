"""How the source was seen, through the posterior and the solve: at rest by default, moving, tracked.

A box slides on a floor (friction 0.5): from 1.5 m/s it stops after 0.31 s, 0.23 m on. Seen lying
there, only a start that stops there explains it; a faster one that slides through the same pose
(a flyby) explains a target seen moving at a moment not known, not one seen at rest.
"""

from dataclasses import replace

import pytest
import torch

from dejaview.backends.spheres import SpheresProblem
from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.inference.posterior import Posterior, PosteriorSettings
from dejaview.inference.search import stages
from dejaview.scene import Scene

SLIDE = """<scene version="1" name="slide">
  <simulation dt="0.002" duration="{duration}" friction="0.5" restitution="0.1"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="box" shape="box" size="0.1 0.1 0.1" mass="0.5"><pose position="0 0 0.05"/></object>
  <inference source="box" evaluate="{evaluate}">
    {targets}
    <optimize position="true" orientation="false" linear-velocity="true" angular-velocity="false"/>
    <start-area min="-0.1 -0.1 0.05" max="0.1 0.1 0.05"/>
  </inference>
</scene>"""


def slide_scene(targets: str, duration: float = 0.8, evaluate: str = "best") -> Scene:
    return Scene.from_string(SLIDE.format(targets=targets, duration=duration, evaluate=evaluate))


def start(problem, vx: float, x: float = 0.0):
    return problem.layout.encode(position=(x, 0.0, 0.05), linear_velocity=(vx, 0.0, 0.0)).double()


def end_of(problem, x) -> float:
    with torch.no_grad():
        pos, _ = problem.final_pose(problem.simulate(x, steps=problem.duration_steps, record_every=1))
    return pos[0]


@pytest.mark.parametrize("evaluate", ["best", "final"])
def test_a_flyby_is_not_an_answer_to_a_source_seen_at_rest_but_is_to_one_seen_moving(evaluate):
    problem = SpheresProblem.from_scene(slide_scene('<target position="0.2 0 0.05"/>', evaluate=evaluate))
    rest_x = end_of(problem, start(problem, 1.5))  # where the slow start stops
    fast = start(problem, 2.5)  # slides through rest_x at 0.1 s and on to 0.64 m
    target = f'<target position="{rest_x} 0 0.05" orientation="1 0 0 0"'
    for moving, explained in (("", False), (' moving="true"', evaluate == "best")):
        scene = slide_scene(target + moving + "/>", evaluate=evaluate)
        problem = SpheresProblem.from_scene(scene)
        post = Posterior(problem, PosteriorSettings.from_scene(scene))
        x = torch.cat([start(problem, 1.5), fast])
        _, chi2, _ = post.cost(x)
        assert chi2[0] < 1.0  # the start that stops there explains both readings
        assert (float(chi2[1]) < 1.0) == explained, (moving, float(chi2[1]))


def test_the_solve_of_a_source_seen_at_rest_ends_there_at_rest():
    problem = SpheresProblem.from_scene(slide_scene('<target position="0.2 0 0.05"/>'))
    rest_x = end_of(problem, start(problem, 1.5))
    scene = slide_scene(f'<target position="{rest_x} 0.02 0.05" orientation="1 0 0 0"/>')
    result = solve(scene, SolveParams(seed=0))
    data = result.to_json()
    assert data["end_error"]["position_error"] < 0.005 and data["end_error"]["time"] == pytest.approx(0.8)
    assert data["rest"]["came_to_rest_s"] is not None and data["rest"]["came_to_rest_s"] < 0.6
    assert data["warnings"] == []
    assert data["targets"][0]["at_rest"] and data["observations"][0]["at_rest"]


def test_a_duration_too_short_to_come_to_rest_is_warned_with_the_duration_it_needs():
    """1 m from the area needs 3.1 m/s, which slides for 0.63 s: nothing rests there by 0.5 s."""
    scene = slide_scene('<target position="1.0 0 0.05" orientation="1 0 0 0"/>', duration=0.5)
    result = solve(scene, SolveParams(seed=0, iterations=40))
    rest = result.settings["rest"]
    assert rest["came_to_rest_s"] is None
    assert 0.6 < rest["needs_duration_s"] <= 1.2
    warning, = result.settings["warnings"]
    assert "still moving at the end of the simulation (0.5 s)" in warning
    assert f'<simulation duration="{rest["needs_duration_s"]:g}">' in warning


TRACKED = """<scene version="1" name="toss">
  <simulation dt="0.002" duration="0.3" friction="0.5" restitution="0.3"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.3"><pose position="0 0 0.5"/></object>
  <inference source="ball">
    {targets}
    <optimize position="true" orientation="false" linear-velocity="true" angular-velocity="false"/>
    <start-area min="-0.2 -0.2 0.3" max="0.2 0.2 0.7"/>
    <observation sigma="0.005"/>
  </inference>
</scene>"""


def tracked_truth():
    """A ball tossed from (0.05, -0.03, 0.5) at (1.2, 0.4, 1.0) m/s, seen by position at 0.1 s,
    0.2 s and 0.3 s (in flight): its scene and true parameters."""
    scene = Scene.from_string(TRACKED.format(targets='<target position="0 0 0" time="0.3"/>'))
    problem = SpheresProblem.from_scene(scene)
    truth = problem.layout.encode(position=(0.05, -0.03, 0.5), linear_velocity=(1.2, 0.4, 1.0)).double()
    with torch.no_grad():
        traj = problem.simulate(truth, steps=150, record_every=50)
    seen = problem.world.object_position(traj.states)[1:, 0, problem.source]  # at 0.1, 0.2, 0.3 s
    targets = "\n    ".join(f'<target position="{" ".join(f"{v:.6f}" for v in p.tolist())}" time="{t}"/>'
                           for p, t in zip(seen, (0.1, 0.2, 0.3)))
    return Scene.from_string(TRACKED.format(targets=targets)), truth


def test_timed_position_only_targets_each_read_their_moment():
    scene, truth = tracked_truth()
    problem = SpheresProblem.from_scene(scene)
    post = Posterior(problem, PosteriorSettings.from_scene(scene))
    assert post.num_observed == 9 and problem.steps == 150 and problem.record_every == 50
    r, loss = post.observation_residuals(problem.simulate(truth))
    assert r.abs().max() < 1e-3 and loss[0] < 1e-5  # the truth explains each moment (rounded to a micron)
    moved = replace(scene.inference.targets[1], position=(0.0, 0.0, 0.0))
    other = replace(scene, inference=replace(scene.inference, targets=(scene.inference.targets[0], moved,
                                                                      scene.inference.targets[2])))
    r2, _ = Posterior(SpheresProblem.from_scene(other), post.settings).observation_residuals(problem.simulate(truth))
    assert r2[0, :3].abs().max() < 1e-3 and r2[0, 3:6].abs().max() > 10  # the second moment's misfit alone
    assert r2[0, 6:].abs().max() < 1e-3


def test_a_tracked_source_is_searched_stage_by_stage_and_found():
    scene, truth = tracked_truth()
    problem = SpheresProblem.from_scene(scene)
    post = Posterior(problem, PosteriorSettings.from_scene(scene))
    assert [len(prefix) for prefix in stages(post)] == [1, 2]
    result = solve(scene, SolveParams(seed=0))
    assert result.settings["search"]["observation_chi2"] < 1.0
    for row in result.observations():
        assert row["position_error"] < 0.005 and row["angle_error_deg"] is None
    assert result.initial_state["linear_velocity"] == pytest.approx([1.2, 0.4, 1.0], abs=0.05)


def test_laplace_draws_spread_as_the_earlier_stages_posterior():
    """``laplace_draws``: half about the best mode, the rest about the next; at scale 1 their spread
    is the stage's Laplace covariance (J^T J)^-1, at scale 2 twice it."""
    from dejaview.inference.search import Mode, laplace_draws

    scene, truth = tracked_truth()
    post = Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))
    part = post.restricted(stages(post)[1])
    x = truth[0]
    other = x + 0.3
    draws = laplace_draws(part, [Mode(x, 1.0, 1.0, 0.0), Mode(other, 2.0, 2.0, 0.0)], 4000, seed=3)
    assert draws.shape == (4000, x.numel())
    _, J = part.jacobian(x[None])
    sd = torch.sqrt(torch.diagonal(torch.linalg.inv(J[0].T @ J[0])))
    first = draws[:2000]
    at1, at2 = first[0::2] - x, first[1::2] - x  # scales 1 and 2 alternate
    assert torch.allclose(at1.std(0), sd, rtol=0.1) and torch.allclose(at2.std(0), 2 * sd, rtol=0.1)
    assert torch.allclose(draws[2000:].mean(0), other, atol=float(4 * sd.max() / 20))


def test_laplace_draws_skip_a_mode_without_a_finite_curvature(monkeypatch):
    from dejaview.inference.search import Mode, laplace_draws

    scene, truth = tracked_truth()
    post = Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))
    part = post.restricted(stages(post)[1])
    real = part.jacobian

    def broken(x):
        r, J = real(x)
        J = J.clone()
        J[0] = float("nan")
        return r, J

    monkeypatch.setattr(part, "jacobian", broken)
    modes = [Mode(truth[0], 1.0, 1.0, 0.0), Mode(truth[0] + 0.3, 2.0, 2.0, 0.0)]
    draws = laplace_draws(part, modes, 100, seed=0)
    assert draws.shape == (50, truth.shape[1]) and bool(torch.isfinite(draws).all())


def test_the_last_stage_of_a_tracked_search_keeps_half_of_it(monkeypatch):
    """Earlier stages spend ``stage_share`` each, counted by their rollouts' length; the search over
    every sighting keeps at least ``last_share`` of the iterations and budget however many there
    were (a box tracked at six moments had left its last stage one iteration)."""
    from dejaview.inference import search as search_module
    from dejaview.inference.params import SearchParams

    scene, _ = tracked_truth()
    post = Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))
    given = []
    real = search_module.MapSearch._stage

    def spy(part, params, callback, should_stop, seeds, near=None):
        given.append((part.problem.steps, params.iterations, params.budget, near))
        return real(part, params, callback, should_stop, seeds, near)

    monkeypatch.setattr(search_module.MapSearch, "_stage", staticmethod(spy))
    p = SearchParams(seed=0, iterations=24, budget=3000, stage_share=0.45)
    search_module.MapSearch(p).run(post)
    assert [g[0] for g in given] == [50, 100, 150]
    assert [g[1] for g in given[:2]] == [10, 10] and given[0][2] == int(0.45 * 3000 / (50 / 150))
    assert given[2][1] >= 12 and given[2][2] >= 1500  # 0.45 + 0.45 of the iterations would leave 2
    assert given[0][3] is None and given[1][3].shape[0] > 0 and given[2][3].shape[0] > 0


def test_the_truths_credible_level_is_the_posterior_mass_more_probable_than_it():
    """``solve(truth=)``: the most probable start itself lies at the 0 % credible level (nothing is more
    probable), a start that misses every observation at 100 %; each carries its -log posterior."""
    from dejaview.inference.posterior_report import truth_report

    scene, truth = tracked_truth()
    result = solve(scene, SolveParams(seed=0, samples=40), truth=dict(position=[0.05, -0.03, 0.5],
                   orientation=[1, 0, 0, 0],
                                                        linear_velocity=[1.2, 0.4, 1.0],
                                                        angular_velocity=[0, 0, 0]))
    t = result.settings["truth"]
    assert 0.0 <= t["credible_level"] <= 1.0 and set(t["in_90"]) == set(result.settings["posterior"]["intervals"])
    assert t["observation_chi2"] < 1e-4  # the observations were made of this start (to a micron)
    problem = result.problem
    post = Posterior(problem, PosteriorSettings.from_scene(scene))
    best = {k: result.initial_state[k] for k in ("position", "orientation", "linear_velocity", "angular_velocity")}
    assert truth_report(post, result.posterior, problem.layout, best)["credible_level"] <= 0.05
    far = dict(best, linear_velocity=[0.0, 0.0, 0.0])
    report = truth_report(post, result.posterior, problem.layout, far)
    assert report["credible_level"] == 1.0 and report["observation_chi2"] > 100


@pytest.mark.slow
def test_a_box_tracked_over_its_tumble_is_found_through_the_stages():
    """``bench/identify_calibration.py``'s box truth 1, its first throw, with the physics known: a
    box tossed onto the floor, its pose seen at six moments (0.1-0.9 s), tumbling between the fifth
    and the last. Measured (2026-12-07): with the earlier stages' modes alone as seeds the last
    stage ended at -log posterior 220 (the truth's 24.8; with the last stage given half the search,
    45); with draws about them (``laplace_draws``) refined first, 20.4 (40 s)."""
    from dejaview.cli.bench_table import bench_module
    from dejaview.inference.identify import physics_fixed
    from dejaview.inference.search import MapSearch
    from dejaview.inference.params import SearchParams

    ic = bench_module("identify_calibration")
    gen = torch.Generator().manual_seed(ic.SEED + 1)
    scene = ic.base_scene("box")
    post = Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))
    z = torch.randn(1, len(post.layout.physics_names), generator=gen, dtype=torch.float64)
    start = post.sample(1, gen)
    start[:, -z.shape[1]:] = z
    seen = ic.tracked(scene, post, start, ic.TIMES["box"], gen)
    known = Posterior.from_scene(physics_fixed(seen, post.layout.physics, z))
    with torch.no_grad():
        truth_cost = float(known.cost(start[:, :-z.shape[1]])[0][0])
    result = MapSearch(SearchParams(seed=1)).run(known)
    assert truth_cost == pytest.approx(24.8, abs=0.1)
    assert result.cost < truth_cost


def test_a_tracked_source_is_sampled_sighting_after_sighting_and_exactly():
    """The bridge tempers in the first moment's observation, then the first two, then all three
    (``sampling.sighting_chain``); the samples still follow the posterior, here a Gaussian known in
    closed form: a toss in flight is linear in the start's position and velocity, each axis seen
    at 0.1, 0.2 and 0.3 s with 5 mm of noise."""
    from dejaview.inference.params import SamplerParams
    from dejaview.inference.posterior_report import physical
    from dejaview.inference.sampling import Sampler, sighting_chain
    from dejaview.inference.search import MapSearch

    scene, truth = tracked_truth()
    post = Posterior.from_scene(scene)
    chain = sighting_chain(post)
    assert [c.problem.steps for c in chain] == [50, 100] and [len(c.sightings) for c in chain] == [1, 2]
    single = Scene.from_string(TRACKED.format(targets='<target position="0.4 0.1 0.6" time="0.3"/>'))
    assert sighting_chain(Posterior.from_scene(single)) == []
    modes = MapSearch().run(post).modes
    samples = Sampler(SamplerParams(seed=1)).sample(post, modes, 300)
    assert samples.stats["rollouts"] > samples.stats["rollouts_by_length"]  # short rollouts counted by length
    values = physical(post.layout, samples.x)  # (N, 6): position x y z, velocity x y z
    t = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    design = torch.stack([torch.ones_like(t), t], -1)
    cov = 0.005 ** 2 * torch.linalg.inv(design.T @ design)  # per axis: (position, velocity)
    sd = torch.sqrt(torch.diagonal(cov))
    best = physical(post.layout, modes[0].x[None])[0]
    for axis in range(3):
        for k, col in enumerate((axis, 3 + axis)):
            assert float(values[:, col].std()) == pytest.approx(float(sd[k]), rel=0.25)
            assert abs(float(values[:, col].mean() - best[col])) < 0.5 * float(sd[k])


def test_a_sample_more_probable_than_the_search_s_answer_becomes_the_answer():
    """``solve.refine_from_samples``: the runs' best samples are refined, and one that ends more
    probable than the search's answer replaces it, first among the modes."""
    from dejaview.inference.params import SearchParams
    from dejaview.inference.sampling import PosteriorSamples
    from dejaview.inference.search import Mode, SearchResult
    from dejaview.inference.solve import refine_from_samples

    scene, truth = tracked_truth()
    post = Posterior.from_scene(scene)
    poor = truth[0] + 0.3  # a start far off, as a search stuck in another basin would answer
    cost, chi2, loss = (float(v[0]) for v in post.cost(poor[None]))
    opt = SearchResult(x=poor, loss=loss, cost=cost, chi2=chi2, modes=[Mode(poor, cost, chi2, loss)])
    gen = torch.Generator().manual_seed(0)
    x = truth + 0.01 * torch.randn(8, truth.shape[1], generator=gen, dtype=torch.float64)
    samples = PosteriorSamples(x=x, weights=torch.full((8,), 1 / 8, dtype=torch.float64),
                               log_density=-post.cost(x)[0], component=torch.zeros(8, dtype=torch.long),
                               mode_index=[0], run=torch.arange(8) % 2)
    better = refine_from_samples(post, opt, samples, SearchParams())
    assert better.cost < 1.0 < cost and better.modes[0].cost == better.cost and better.modes[1] is opt.modes[0]
    assert samples.mode_index == [1] and better.rollouts > 0 and better.jacobians > 0
    assert torch.allclose(better.x, truth[0], atol=0.05)
    again = refine_from_samples(post, better, samples, SearchParams())  # nothing better: the same answer
    assert torch.equal(again.x, better.x) and len(again.modes) == len(better.modes)
    near = replace(opt, cost=better.cost + 0.5)  # better by less than sample_gain (1 nat): kept
    assert torch.equal(refine_from_samples(post, near, samples, SearchParams()).x, poor)
