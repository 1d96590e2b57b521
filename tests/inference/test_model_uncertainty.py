"""Model uncertainty in the likelihood (``dejaview.inference.model_uncertainty``).

Built on ``box_along_shelf`` (a box slid along a shelf board, 0.3-1.0 s): where the box
stops depends on the friction, so variants of the friction spread the ends of one start.
"""

import math
from dataclasses import replace

import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.backends.spheres import SpheresProblem
from dejaview.inference.model_uncertainty import (ModelVariants, design,
                                                  rank_on_heldout, vary_world)
from dejaview.inference.params import ModelParams, SearchParams
from dejaview.inference.posterior import Posterior, PosteriorSettings
from dejaview.scene import ModelUncertainty, Prior
from dejaview.sim.world import _discrete_restitution

from .test_posterior import assert_jacobian_matches_finite_differences, shelf, truth_x


def test_the_default_design_has_each_factors_mean_and_variance_and_balanced_pairs():
    z = design(4)
    assert z.mean(0).abs().max() == 0.0 and (z * z).mean(0).tolist() == [1.0, 1.0, 1.0]
    assert (z.T @ z / 4 - torch.eye(3)).abs().max() == 0.0
    drawn = design(16, seed=3)
    assert drawn.mean(0).abs().max() < 1e-12 and drawn.std(0, unbiased=False).tolist() == pytest.approx([1.0] * 3)


def test_a_variant_world_scales_friction_restitution_and_stiffness():
    scene = shelf()
    world = SpheresProblem.from_scene(scene).world
    v = vary_world(world, 1.2, 2.0, 1.44)
    assert torch.allclose(v.mu_static, 1.2 * world.mu_static)
    assert v.contact.frequency == pytest.approx(1.2 * world.contact.frequency)
    h = world.dt / world.substeps
    e0 = _discrete_restitution(float(world.unload_static.flatten()[0]), world.contact.frequency * h)
    e1 = _discrete_restitution(float(v.unload_static.flatten()[0]), v.contact.frequency * h)
    assert e1 == pytest.approx(2.0 * e0, rel=1e-6)


def _shelf_observing_its_truth():
    """(problem, settings, x): the shelf at 0.3 s observing the truth's own end, and the truth's
    parameters x (1, P)."""
    scene = shelf(duration=0.3, evaluate="final")
    problem = SpheresProblem.from_scene(scene)
    x = truth_x(problem)
    with torch.no_grad():  # observed: the truth's end at 0.3 s
        pos, q = problem.final_pose(problem.simulate(x))
    inf = scene.inference
    seen = replace(inf.target, position=tuple(pos), orientation=tuple(q), moving=True)  # still sliding
    scene = replace(scene, inference=replace(inf, targets=(seen,)))
    return SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene), x


def test_model_uncertainty_makes_a_start_whose_end_hinges_on_friction_cost_more():
    """The truth explains its end exactly under the scene's physics; averaged over friction variants
    (10 %, 20 %) its residuals are the variants' misfits over sqrt(K), and the cost is the mean of their
    costs: larger, and larger still with more uncertainty."""
    # at 0.3 s the box still slides along the shelf (its end moves 1.8 cm per 10 % of friction; by
    # 0.5 s it rests against the corner wall, wherever the friction); "best" would find each
    # variant's moment at the target
    problem, settings, x = _shelf_observing_its_truth()
    exact = Posterior(problem, settings)
    r0, _ = exact.residuals(x)
    costs = []
    for sd in (0.1, 0.2):
        model = ModelVariants.from_world(problem.world, friction=sd, restitution=0.0, stiffness=0.0)
        post = Posterior(problem, settings, model=model)
        r, loss = post.residuals(x)
        n = exact.num_observed
        assert r.shape[1] == r0.shape[1] + (model.count - 1) * n
        # each block is one variant's misfit / sqrt(K)
        for k, w in enumerate(model.worlds):
            own = Posterior(replace(problem, world=w), settings).residuals(x)[0][:, :n]
            assert torch.allclose(r[:, k * n:(k + 1) * n], own / math.sqrt(model.count))
        cost, chi2, _ = post.cost(x)
        assert chi2[0] == pytest.approx(float((r[:, :model.count * n] ** 2).sum()))
        costs.append(float(cost[0]))
    assert float(0.5 * (r0 ** 2).sum()) < 1e-3 < costs[0] < costs[1]


def test_the_modes_are_ranked_on_held_out_variants_not_on_the_ones_they_were_fitted_to():
    """``rank_on_heldout``: each mode's negative log posterior under ``ModelParams.heldout_variants`` variants drawn
    apart from the design (the same standard deviations, another stream), lowest first, whatever the order and
    costs the refinement gave them: a start fitted to the design's four physics by chance (here a
    worse start handed the lower cost) does not win on that."""
    from dejaview.inference.search import Mode

    problem, settings, x = _shelf_observing_its_truth()
    model = ModelVariants.from_world(problem.world, friction=0.2, restitution=0.2)
    post = Posterior(problem, settings, model=model)
    worse = x[0] + 0.1 * torch.ones_like(x[0])
    modes = [Mode(worse, 1.0, 2.0, 0.01), Mode(x[0], 5.0, 10.0, 0.0)]
    ranked, rollouts = rank_on_heldout(post, modes, seed=3)
    assert torch.equal(ranked[0].x, x[0]) and torch.equal(ranked[1].x, worse)
    assert [m.cost for m in ranked] == [5.0, 1.0]  # the fitted costs kept, the order the held-out one's
    held = ModelVariants.from_world(problem.world, 0.2, 0.2, count=ModelParams.heldout_variants, seed=ModelParams.heldout_seed + 3)
    assert not any(torch.allclose(h, d) for h in held.levels for d in model.levels)
    expected = Posterior(problem, settings, model=held).cost(torch.stack([x[0], worse]))[0]
    assert [m.heldout for m in ranked] == pytest.approx(expected.tolist(), rel=1e-12)
    held_post = Posterior(problem, settings, model=held)  # the mean end's misfit: the variants' mean residual
    mean = torch.stack([held_post.observation_residuals(t)[0]
                        for t in held_post.trajectories(torch.stack([x[0], worse]))]).mean(0)
    assert [m.heldout_mean_chi2 for m in ranked] == pytest.approx((mean * mean).sum(-1).tolist(), rel=1e-12)
    assert ranked[0].heldout_mean_chi2 < 2 * ranked[0].heldout  # the spread about the mean left out
    assert rollouts == 2  # candidates, as Posterior.rollouts counts them (each under every held-out physics)
    assert ranked[0].heldout < ranked[1].heldout
    one, spent = rank_on_heldout(post, modes[:1], seed=3)
    assert one == modes[:1] and one[0].heldout is None and spent == 0


def test_where_no_refined_mode_explains_the_end_the_searchs_other_modes_are_refined_too():
    """``refine_under_variants``: the search's answer and its next three modes are refined first; where
    the best of them does not explain the end under the held-out variants (``explains_end``: the
    chi-square of their mean end over the 0.999 quantile), the search's other modes cheapest under the variants
    are refined and ranked beside them, and the truth among them is the answer. Where the first ones
    explain it, the others are never refined."""
    from dejaview.inference.model_uncertainty import explains_end
    from dejaview.inference.search import refine_under_variants
    from dejaview.inference.search import Mode, SearchResult

    problem, settings, x = _shelf_observing_its_truth()
    # 2 %: the truth's end moves by about the observation's noise (sigma 5 mm), so it explains the end
    post = Posterior(problem, settings, model=ModelVariants.from_world(problem.world, 0.02, 0.02))
    gen = torch.Generator().manual_seed(5)
    far = [x[0] + 0.6 * torch.randn(x.shape[1], generator=gen, dtype=x.dtype) for _ in range(4)]
    truth = Mode(x[0], 0.0, 0.0, 0.0)

    def found(xs):
        return SearchResult(x=xs[0], loss=0.0, history=[], best_index=0,
                            modes=[Mode(v, float(i), float(i), 0.0) for i, v in enumerate(xs)])

    def refine(xs):  # no Levenberg-Marquardt step (one Jacobian each): every mode stays where it was found
        before = post.jacobians
        res = refine_under_variants(post, found(xs), params=SearchParams(lm_final_iterations=0))
        return res, post.jacobians - before

    alone, _ = refine(far)
    assert not explains_end(post, alone.modes[0]) and len(alone.modes) == 4
    res, jacobians = refine(far + [truth.x])
    assert torch.allclose(res.x, x[0], atol=1e-3) and explains_end(post, res.modes[0])
    assert res.modes[0].heldout_mean_chi2 < 1.0 and len(res.modes) == 5 and jacobians == 5
    assert [m.heldout for m in res.modes] == sorted(m.heldout for m in res.modes)
    first, jacobians = refine([truth.x] + far)  # the answer explains the end: the fifth is not refined
    assert explains_end(post, first.modes[0]) and len(first.modes) == 4 and jacobians == 4
    with_chi2 = replace(truth, heldout=1.0, heldout_mean_chi2=22.4)
    assert explains_end(post, with_chi2) and not explains_end(post, replace(with_chi2, heldout_mean_chi2=22.5))
    assert explains_end(post, truth)  # never ranked: nothing to hold it against


def test_the_jacobian_with_model_uncertainty_matches_finite_differences():
    scene = shelf(duration=0.3, prior=Prior(speed=2.0))
    problem = SpheresProblem.from_scene(scene)
    model = ModelVariants.from_world(problem.world, friction=0.2, restitution=0.2)
    post = Posterior(problem, PosteriorSettings.from_scene(scene), model=model)
    r, _ = assert_jacobian_matches_finite_differences(post, truth_x(problem) + 0.05)
    assert r.shape[1] > 4 * post.num_observed


def test_the_jacobian_with_model_uncertainty_uses_the_carried_jacobians_and_equals_the_adjoints(monkeypatch):
    """Under model uncertainty a box's Jacobian has 4 x 6 rows through the rollouts against 13
    columns of its state Jacobians: ``Posterior.jacobian`` asks the native engine for the carried
    Jacobians (``preferring("phi")``, 1.4-1.6x faster solves on the crossengine boxes), and its
    rows equal the adjoint's to round-off. Skipped where the native extension does not build (no
    compiler): the path it checks is the native engine's."""
    from dejaview.sim import native

    if not native.available():
        pytest.skip("the native extension does not build here")
    scene = shelf(duration=0.3, prior=Prior(speed=2.0))
    problem = SpheresProblem.from_scene(scene)
    model = ModelVariants.from_world(problem.world, friction=0.2, restitution=0.2)
    post = Posterior(problem, PosteriorSettings.from_scene(scene), model=model)
    x = truth_x(problem) + 0.05
    paths, preferring = [], native.preferring

    def spy(path):
        paths.append(path)
        return preferring(path)

    monkeypatch.setattr(native, "preferring", spy)
    r, jac = post.jacobian(x)
    monkeypatch.setenv("DEJAVIEW_NATIVE_GRADIENT", "adjoint")
    r_adj, jac_adj = post.jacobian(x)
    assert paths == ["phi", "phi"]  # asked for; the environment's path wins the second time
    assert torch.allclose(r, r_adj, rtol=0, atol=1e-12)  # the same rollouts (the carried path's by dual passes)
    assert torch.allclose(jac, jac_adj, rtol=1e-8, atol=1e-10 * float(jac.abs().max()))
    single = Posterior(problem, PosteriorSettings.from_scene(scene))
    single.jacobian(x)
    assert single.num_observed == 18 and paths[-1] == "phi"  # the pose and its rest: 18 rows >= 13
    moving = replace(scene.inference.target, moving=True)
    scene = replace(scene, inference=replace(scene.inference, evaluate="final", targets=(moving,)))
    single = Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))
    single.jacobian(x)
    assert single.num_observed == 6 and paths[-1] == "adjoint"  # 6 rows: one adjoint pass each


def test_the_scene_element_builds_the_variants_and_bad_values_are_one_line_errors():
    scene = shelf(model_uncertainty=ModelUncertainty(friction=0.1, restitution=0.3))
    world = SpheresProblem.from_scene(scene).world
    model = ModelVariants.from_scene(scene, world)
    assert model.count == 4 and (model.friction, model.restitution) == (0.1, 0.3)
    js = model.to_json()
    assert js["friction"] == 0.1 and js["variants"] == 4 and len(js["levels"]) == 4
    assert ModelVariants.from_scene(shelf(), world) is None
    assert ModelVariants.from_scene(shelf(model_uncertainty=ModelUncertainty(friction=0.0)), world) is None
    with pytest.raises(InferenceError, match="friction must be a number >= 0"):
        ModelVariants.from_world(world, friction=-0.1)
    with pytest.raises(InferenceError, match="at least 2 variants"):
        ModelVariants.from_world(world, friction=0.1, count=1)


SLIDE = """<scene version="1" name="slide"><simulation dt="0.002" duration="0.4" friction="0.5" restitution="0.3"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0" orientation="1 0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.4">
    <pose position="0 0 0.05" orientation="1 0 0 0"/><velocity linear="1 0 0" angular="0 0 0"/></object>
  <inference source="ball" loss="position" evaluate="final">
    <target position="0.35 0.02 0.05" orientation="1 0 0 0" moving="true"/>
    <optimize position="false" orientation="false" linear-velocity="true" angular-velocity="false"/>
    {element}
  </inference></scene>"""


def test_the_cli_reads_the_element_and_the_flag_and_records_it(tmp_path):
    import json

    from click.testing import CliRunner

    from dejaview.cli import cli

    path = tmp_path / "slide.xml"
    path.write_text(SLIDE.format(element='<model-uncertainty friction="0.2" restitution="0.1"/>'))
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["solve", str(path), "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    data = json.loads((out / "result.json").read_text())
    mu = data["model_uncertainty"]
    assert (mu["friction"], mu["restitution"], mu["variants"]) == (0.2, 0.1, 4)
    modes = data["search"]["modes"]  # ranked on the held-out variants (3 modes here): the answer is the first
    held = [m["heldout_neg_log_posterior"] for m in modes]
    assert len(modes) >= 2 and held == sorted(held)
    assert all(0 <= m["heldout_mean_end_chi2"] <= 2 * m["heldout_neg_log_posterior"] for m in modes)
    assert modes[0]["initial_state"]["position"] == pytest.approx(data["initial_state"]["position"])
    result = CliRunner().invoke(cli, ["solve", str(path), "-o", str(out), "--quiet",
                                      "--model-uncertainty", "0.05", "0"])
    assert result.exit_code == 0, result.output
    assert json.loads((out / "result.json").read_text())["model_uncertainty"]["friction"] == 0.05
    result = CliRunner().invoke(cli, ["solve", str(path), "-o", str(out), "--quiet",
                                      "--model-uncertainty", "0", "0"])
    assert "model_uncertainty" not in json.loads((out / "result.json").read_text())
    result = CliRunner().invoke(cli, ["solve", str(path), "-o", str(out), "--optimizer", "lbfgs"])
    assert result.exit_code != 0 and "<model-uncertainty> needs the default search" in str(result.exception)
    bad = tmp_path / "bad.xml"
    bad.write_text(SLIDE.format(element='<model-uncertainty friction="-0.1"/>'))
    result = CliRunner().invoke(cli, ["solve", str(bad), "-o", str(out)])
    assert result.exit_code != 0 and "'friction' must be >= 0" in str(result.exception)


def test_a_service_solve_job_reads_the_element_from_its_scene(tmp_path):
    from fastapi.testclient import TestClient

    from dejaview.server.app import create_app
    from tests.server.test_rest import wait_state

    root = tmp_path / "root"
    root.mkdir()
    with TestClient(create_app(scene_root=root, results_dir=tmp_path / "results", workers=1,
                               executor="thread")) as client:
        xml = SLIDE.format(element='<model-uncertainty friction="0.2" restitution="0.1"/>')
        response = client.post("/jobs", json={"kind": "solve", "scene_xml": xml})
        assert response.status_code == 202, response.text
        status = wait_state(client, response.json()["job_id"])
        assert status["state"] == "done", status
        result = client.get(f"/jobs/{status['job_id']}/result.json").json()
        assert result["model_uncertainty"]["friction"] == 0.2
