"""Inference as composable objects (docs/inference.md, "Composing the inference"): the
composition a researcher writes gives ``solve``'s answer, and the parameter objects refuse
what they cannot run."""

import dataclasses
import inspect
from pathlib import Path

import pytest
import torch

import dejaview
from dejaview.errors import InferenceError
from dejaview.inference import (LocalParams, MapSearch, Posterior, Sampler, SamplerParams, SearchParams,
                                SolveParams, fit_locally)
from dejaview.scene import Scene

RAMP = Path(__file__).resolve().parents[2] / "examples" / "scenes" / "ball_down_ramp.xml"


def test_the_search_composed_by_hand_is_solves_search():
    scene = Scene.from_xml(RAMP)
    result = dejaview.solve(scene, SolveParams(seed=2, iterations=30))
    posterior = Posterior.from_scene(scene)
    found = MapSearch(SearchParams(seed=2, iterations=30)).run(posterior)
    assert torch.equal(found.x, result.optimization.x)
    assert found.rollouts == result.settings["search"]["rollouts"]


def test_the_sampler_composed_by_hand_is_solves_sampler():
    scene = Scene.from_xml(RAMP)
    result = dejaview.solve(scene, SolveParams(seed=3, iterations=20, samples=30))
    posterior = Posterior.from_scene(scene)
    found = MapSearch(SearchParams(seed=3, iterations=20)).run(posterior)
    samples = Sampler(SamplerParams(seed=3)).sample(posterior, found.modes, 30)
    assert torch.equal(samples.x, result.posterior.x)


def test_the_local_pipeline_runs_on_the_problem_alone():
    scene = Scene.from_xml(RAMP)
    result = dejaview.solve(scene, SolveParams(optimizer="adam", iterations=5, seed=1))
    opt, info = fit_locally(result.problem, LocalParams(optimizer="adam", iterations=5, seed=1))
    assert torch.equal(opt.x, result.optimization.x) and info["gradient"] == "reverse"


@pytest.mark.parametrize("make, fragment", [
    (lambda: SearchParams(budget=0), "SearchParams.budget must be a positive integer"),
    (lambda: SearchParams(noise_quantile=1.5), "SearchParams.noise_quantile must be a fraction"),
    (lambda: SamplerParams(ess_fraction=1.0), "SamplerParams.ess_fraction must lie strictly between"),
    (lambda: SamplerParams(particles=2.5), "SamplerParams.particles must be a positive integer"),
    (lambda: LocalParams(optimizer="newton"), "LocalParams.optimizer must be one of"),
])
def test_a_parameter_out_of_range_is_a_one_line_error_naming_it(make, fragment):
    with pytest.raises(InferenceError) as info:
        make()
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_the_parameters_are_frozen_and_solve_takes_few_arguments():
    with pytest.raises(dataclasses.FrozenInstanceError):
        SearchParams().budget = 1
    assert len(inspect.signature(dejaview.solve).parameters) <= 8
