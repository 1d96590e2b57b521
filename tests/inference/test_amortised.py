"""Amortised posteriors (``dejaview.inference.amortised``): the flow's coordinates, Pareto smoothing,
training, the model file and the answers it gives."""

from __future__ import annotations

import math
import pickle
from dataclasses import replace

import pytest
import torch

pytest.importorskip("zuko", reason="the amortised extra (pip install 'dejaview[amortised]')")

from dejaview.errors import InferenceError  # noqa: E402
from dejaview.inference.amortised import AmortisedModel, train  # noqa: E402
from dejaview.inference.amortised.answer import live  # noqa: E402
from dejaview.inference.amortised.coordinates import from_flow, log_jacobian, to_flow  # noqa: E402
from dejaview.inference.amortised.observables import noisy, observed, simulated, width  # noqa: E402
from dejaview.inference.amortised.psis import psis  # noqa: E402
from dejaview.inference.amortised.training import simulate_pairs  # noqa: E402
from dejaview.inference.params import AmortisedParams, TrainParams  # noqa: E402
from dejaview.inference.posterior import Posterior  # noqa: E402
from dejaview.inference.reference import log_density, log_prior_density, prior_draws  # noqa: E402
from dejaview.inference.solve import SolveParams, solve  # noqa: E402
from dejaview.scene import Scene  # noqa: E402

THROW = """<scene version="1" name="{name}">
  <simulation dt="0.01" duration="0.4" friction="0.5" restitution="0.2"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.05" mass="0.2"><pose position="0 0 0.3"/></object>
  <inference source="ball" loss="position" evaluate="final" seed="0">
    <target position="{target}" moving="true"/>
    <observation sigma="{sigma}"/>
    <optimize position="true" orientation="false" linear-velocity="true" angular-velocity="false"/>
    <start-area min="-0.2 -0.2 0.3" max="0.2 0.2 0.3"/>
  </inference>
</scene>
"""

SMALL = TrainParams(simulations=1500, epochs=60, patience=10, transforms=3, hidden=(48, 48), batch=128, lr=3e-3)


def throw(target="0.45 0.1 0.05", sigma=0.05, name="throw") -> Scene:
    return Scene.from_string(THROW.format(target=target, sigma=sigma, name=name))


@pytest.fixture(scope="module")
def model():
    return train(throw(), SMALL)


# ------------------------------------------------------------------ coordinates
def test_flow_coordinates_invert_and_their_jacobian_is_exact():
    scene = Scene.from_xml("examples/scenes/mug_off_counter.xml")
    post = Posterior.from_scene(scene)
    x = prior_draws(post, 64, torch.Generator().manual_seed(1))
    u = to_flow(post, x)
    assert torch.allclose(from_flow(post, u), x, atol=1e-10)
    for i in range(4):  # log |dx/du| against autograd's Jacobian
        jac = torch.autograd.functional.jacobian(lambda v: from_flow(post, v[None])[0], u[i])
        assert float(log_jacobian(post, u[i:i + 1])[0]) == pytest.approx(float(torch.linalg.slogdet(jac)[1]), abs=1e-8)
    far = torch.full((1, x.shape[1]), 40.0, dtype=torch.float64)  # deep in a ball's tail: finite
    assert bool(torch.isfinite(log_jacobian(post, far)).all())


def test_psis_k_hat_tells_a_proposal_that_covers_from_one_that_does_not():
    gen = torch.Generator().manual_seed(0)
    wide = 1.3 * torch.randn(4000, generator=gen, dtype=torch.float64)
    narrow = 0.4 * torch.randn(4000, generator=gen, dtype=torch.float64)
    lw_wide = -0.5 * wide ** 2 + 0.5 * (wide / 1.3) ** 2
    lw_narrow = -0.5 * narrow ** 2 + 0.5 * (narrow / 0.4) ** 2
    smoothed, k_wide = psis(lw_wide)
    _, k_narrow = psis(lw_narrow)
    assert k_wide < 0.5 < 0.7 < k_narrow  # theory: k = 1 - 0.4^2 = 0.84 for the narrow one
    assert float(torch.logsumexp(smoothed, 0)) == pytest.approx(0.0, abs=1e-12)
    # the smoothed weights still estimate E[x^2] = 1 under the target
    w = torch.softmax(smoothed, 0)
    assert float((w * wide ** 2).sum()) == pytest.approx(1.0, abs=0.1)


# ------------------------------------------------------------------ observations
def test_observation_vector_of_the_truth_is_the_target_and_noise_has_the_stated_spread():
    scene = Scene.from_xml("examples/scenes/mug_off_counter.xml")
    post = Posterior.from_scene(scene).without_model()
    y_obs = observed(post)
    assert y_obs.shape == (width(post),)
    truth = _truth_x(post, "examples/scenes/mug_off_counter.truth.json")
    with torch.no_grad():
        y = simulated(post, post.trajectories(truth)[0])
    assert float((y[0, :3] - y_obs[:3]).norm()) < 0.01  # the truth ends where the mug is seen
    assert float((y[0, 3:9] - y_obs[3:9]).abs().max()) < 0.1
    many = noisy(post, y.expand(4000, -1).clone(), torch.Generator().manual_seed(2))
    assert float((many[:, :3] - y[:, :3]).std()) == pytest.approx(post.settings.sigma, rel=0.05)


def _truth_x(post, path):
    import json

    t = json.loads(open(path).read())["initial_state"]
    lay = post.layout
    return lay.encode(**{k: torch.tensor(t[k], dtype=torch.float64) for k in
                         ("position", "orientation", "linear_velocity", "angular_velocity")}).to(torch.float64)


# ------------------------------------------------------------------ training and the file
def test_training_set_is_the_same_in_processes_as_here():
    scene = throw()
    p = replace(SMALL, simulations=300, chunk=64)
    x1, y1, _ = simulate_pairs(scene, p)
    x2, y2, _ = simulate_pairs(scene, replace(p, workers=2))
    assert torch.equal(x1, x2) and torch.equal(y1, y2)


def test_training_set_is_the_same_simulated_a_few_rollouts_at_a_time():
    """The rollout batch a memory limit shrinks (``sizing.check_train_memory``) leaves the pairs as
    they are: each rollout is independent of the others in its batch."""
    scene = throw()
    p = replace(SMALL, simulations=200, chunk=64)
    x1, y1, _ = simulate_pairs(scene, p)
    x2, y2, _ = simulate_pairs(scene, p, rollout_batch=7)
    assert torch.equal(x1, x2) and torch.equal(y1, y2)


def test_training_over_its_memory_limit_is_refused_before_any_simulation(monkeypatch):
    from dejaview import memory
    from dejaview.errors import ResourceError
    from dejaview.inference.amortised import training

    def no_simulation(*args, **kwargs):
        raise AssertionError("simulated although the training does not fit")

    monkeypatch.setattr(training, "simulate_pairs", no_simulation)
    with pytest.raises(ResourceError) as err:
        train(throw(), replace(SMALL, memory_limit=memory.resident() + 2 ** 20))
    message = str(err.value)
    assert message.startswith("1500 training simulations would need about ") and "\n" not in message
    assert message.endswith("over the limit of " + memory.format_size(err.value.limit)
                            + " (this server's limit for one job)")


def test_a_training_that_fits_only_in_smaller_rollout_batches_gets_them():
    from dejaview import memory
    from dejaview.inference.amortised.sizing import check_train_memory, train_bytes
    from dejaview.inference.sizing import candidate_bytes

    post = Posterior.from_scene(throw()).without_model()
    p = replace(SMALL, chunk=512)
    candidate = candidate_bytes(post.problem)
    fixed = train_bytes(post, p, candidate, 0)
    assert train_bytes(post, p, candidate, 10) == fixed + 10 * candidate
    assert check_train_memory(post, replace(p, memory_limit=memory.resident() + fixed + 1000 * candidate)) == 512
    batch = check_train_memory(post, replace(p, memory_limit=memory.resident() + fixed + 200 * candidate))
    assert 16 <= batch < 512


@pytest.mark.slow
def test_training_set_is_the_same_on_ray_as_here():
    pytest.importorskip("ray")
    scene = throw()
    p = replace(SMALL, simulations=200, chunk=64)
    x1, y1, _ = simulate_pairs(scene, p)
    x2, y2, _ = simulate_pairs(scene, replace(p, workers=2, ray="local"))
    assert torch.equal(x1, x2) and torch.equal(y1, y2)


def test_model_file_round_trip_and_refusals(model, tmp_path):
    post = Posterior.from_scene(throw())
    path = model.save(tmp_path / "throw.dvflow")
    again = AmortisedModel.load(path)
    x = prior_draws(post, 16, torch.Generator().manual_seed(3))
    y = observed(post)
    assert torch.allclose(again.log_prob(post, y, x), model.log_prob(post, y, x), atol=1e-12)
    again.check_fits(post)  # another target, same scene: fits
    replace_target = Posterior.from_scene(throw(target="0.3 -0.1 0.05"))
    again.check_fits(replace_target)
    other = Posterior.from_scene(throw().__class__.from_string(
        THROW.format(target="0.45 0.1 0.05", sigma=0.05, name="t").replace('radius="0.05"', 'radius="0.06"')))
    with pytest.raises(InferenceError, match="trained for throw"):
        again.check_fits(other)
    truncated = tmp_path / "truncated.dvflow"
    truncated.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])
    with pytest.raises(InferenceError, match="not an amortised model file") as info:
        AmortisedModel.load(truncated)
    assert "\n" not in str(info.value)

    class Boom:
        def __reduce__(self):
            return (exec, ("open('" + str(tmp_path / "executed") + "', 'w').write('x')",))

    hostile = tmp_path / "hostile.dvflow"
    hostile.write_bytes(pickle.dumps({"weights": Boom()}))
    with pytest.raises(InferenceError, match="not an amortised model file"):
        AmortisedModel.load(hostile)
    torch.save({"weights": torch.zeros(3)}, tmp_path / "torch.dvflow")
    with pytest.raises(InferenceError, match="not an amortised model file"):
        AmortisedModel.load(tmp_path / "torch.dvflow")
    assert not (tmp_path / "executed").exists()


# ------------------------------------------------------------------ answers
def test_amortised_posterior_equals_the_prior_importance_reference(model):
    """Weighed by the exact likelihood, the flow's draws give the posterior's mean and spread that
    brute-force importance sampling from the prior gives (a broad posterior: sigma 5 cm)."""
    scene = throw()
    result = solve(scene, SolveParams(samples=400, amortised=model))
    am = result.settings["amortised"]
    assert am["fitted"] and am["k_hat"] <= 0.7, am
    post = Posterior.from_scene(scene)
    xs = prior_draws(post, 150000, torch.Generator().manual_seed(5))
    w = torch.softmax(log_density(post, xs) - log_prior_density(post, xs), 0)  # the likelihood
    assert float(1 / (w * w).sum()) > 200  # the reference's own effective sample size

    def physical(x):  # start x, y (m) and velocity (m/s)
        d = post.layout.decode(x)
        return torch.cat([d["position"][:, :2], d["linear_velocity"]], 1)

    ref = physical(xs)
    ref_mean = (w[:, None] * ref).sum(0)
    ref_sd = ((w[:, None] * (ref - ref_mean) ** 2).sum(0)).sqrt()
    got = physical(result.posterior.x)
    assert result.posterior.stats["method"] == "amortised"
    assert torch.all((got.mean(0) - ref_mean).abs() < 0.3 * ref_sd), (got.mean(0), ref_mean, ref_sd)
    assert torch.all((got.std(0) / ref_sd - 1).abs() < 0.25), (got.std(0), ref_sd)
    assert result.loss < 0.05  # the refined best draw explains the end within the noise


def test_a_flow_that_does_not_fit_falls_back_to_the_sampler_and_says_so(model):
    scene = throw(sigma=0.002)  # ten times sharper than the flow learnt: its draws miss
    sharp = train(scene, replace(SMALL, simulations=300, epochs=3))
    result = solve(scene, SolveParams(samples=40, amortised=sharp, budget=3000))
    am = result.settings["amortised"]
    assert not am["fitted"] and am["k_hat"] > 0.7 and am["fallback"] == "sampler"
    assert result.posterior.stats["method"] == "smc"
    assert any("does not fit" in w for w in result.settings["warnings"])


def test_live_answer_draws_from_the_flow_and_knows_an_observation_it_never_saw(model):
    post = Posterior.from_scene(throw())
    out = live(post, model, cells=(8, 8))
    assert out["samples"].shape == (AmortisedParams().live_draws, 3) and out["fitted"]
    assert sum(map(sum, out["heatmap"]["probability"])) == pytest.approx(1.0)
    far = live(Posterior.from_scene(throw(target="5 5 3")), model)
    assert not far["fitted"]


def test_amortised_needs_the_default_search_and_a_start_area(model):
    with pytest.raises(InferenceError, match="optimizer auto"):
        solve(throw(), SolveParams(optimizer="lbfgs", amortised=model))
    no_area = Scene.from_string(THROW.format(target="0.45 0.1 0.05", sigma=0.05, name="t").replace(
        '<start-area min="-0.2 -0.2 0.3" max="0.2 0.2 0.3"/>', ""))
    with pytest.raises(InferenceError, match="start-area"):
        train(no_area, SMALL)


def test_cli_train_then_solve_and_heatmap_from_the_model(tmp_path):
    from click.testing import CliRunner

    from dejaview.cli import cli

    scene = tmp_path / "throw.xml"
    scene.write_text(THROW.format(target="0.45 0.1 0.05", sigma=0.05, name="throw"))
    model = tmp_path / "throw.dvflow"
    runner = CliRunner()
    out = runner.invoke(cli, ["train", str(scene), "-o", str(model), "--simulations", "400", "-q"])
    assert out.exit_code == 0, out.output
    assert "trained on 400 simulations" in out.output and model.is_file()
    out = runner.invoke(cli, ["solve", str(scene), "-o", str(tmp_path / "solved"), "--amortised", str(model),
                              "--samples", "50", "--budget", "2000", "-q"])
    assert out.exit_code == 0, out.output
    import json

    written = json.loads((tmp_path / "solved" / "result.json").read_text())
    assert written["amortised"]["draws"] >= 1000 and "k_hat" in written["amortised"]
    assert (tmp_path / "solved" / "posterior.csv").is_file()
    out = runner.invoke(cli, ["heatmap", str(scene), "-o", str(tmp_path / "map"), "--amortised", str(model),
                              "--cells", "4x4", "--samples", "2", "-q", "--no-plot"])
    assert out.exit_code == 0, out.output
    heat = json.loads((tmp_path / "map" / "heatmap.json").read_text())
    assert sum(map(sum, heat["probability"])) == pytest.approx(1.0)
    # a model of another scene: one line, exit 2 (the CLI's error), nothing written
    other = tmp_path / "other.xml"
    other.write_text(THROW.format(target="0.45 0.1 0.05", sigma=0.05, name="other").replace('mass="0.2"', 'mass="0.3"'))
    out = runner.invoke(cli, ["solve", str(other), "-o", str(tmp_path / "o"), "--amortised", str(model)])
    assert isinstance(out.exception, InferenceError), out.output
    message = str(out.exception)
    assert message.startswith(f"{model}: the amortised model was trained for throw") and "\n" not in message
    assert not (tmp_path / "o").exists()


def test_an_orientation_the_loss_does_not_read_is_not_observed():
    """A position loss ignores the target's orientation, so the flow must not condition on it (it
    would be sharper than the posterior)."""
    text = THROW.format(target="0.45 0.1 0.05", sigma=0.05, name="t").replace(
        '<target position="0.45 0.1 0.05"', '<target position="0.45 0.1 0.05" orientation="1 0 0 0"')
    post = Posterior.from_scene(Scene.from_string(text))
    assert width(post) == 3 and observed(post).shape == (3,)
    pose = Posterior.from_scene(Scene.from_string(text.replace('loss="position"', 'loss="pose"')))
    assert width(pose) == 9
