"""The default search (``dejaview.inference.search``) on a cheap scene: budgets, stops, settings.

``box_down_ramp`` frees only the start position's x and y (2 parameters, 320 steps of 5 ms): a
whole search takes well under a second.
"""

from pathlib import Path

import pytest

from dejaview.errors import InferenceError
from dejaview.inference import InferenceProblem, solve
from dejaview.inference.posterior import Posterior, PosteriorSettings
from dejaview.inference.search import JACOBIAN_COST, map_search
from dejaview.scene import Scene

RAMP = Path(__file__).resolve().parents[2] / "examples" / "scenes" / "box_down_ramp.xml"


@pytest.fixture(scope="module")
def scene():
    return Scene.from_xml(RAMP)


def posterior(scene):
    return Posterior(InferenceProblem.from_scene(scene), PosteriorSettings.from_scene(scene))


def test_the_search_explains_the_end_and_reports_its_modes(scene):
    post = posterior(scene)
    seen = []
    result = map_search(post, seed=0, callback=seen.append)
    assert result.chi2 < 1e-3 and result.loss < 1e-3
    assert result.cost == pytest.approx(0.5 * result.chi2)  # flat prior: the cost is the misfit
    assert result.modes and result.modes[0].cost == pytest.approx(result.cost)
    assert [p.iteration for p in seen] == list(range(len(seen))) == [p.iteration for p in result.history]
    assert all(b.best_loss <= a.best_loss for a, b in zip(seen, seen[1:]))
    spent = [p.evaluations for p in seen]
    assert spent == sorted(spent) and spent[-1] <= result.rollouts + JACOBIAN_COST * result.jacobians


def test_same_seed_same_answer_and_should_stop_ends_it(scene):
    a, b = map_search(posterior(scene), seed=3), map_search(posterior(scene), seed=3)
    assert a.x.tolist() == b.x.tolist()
    calls = []
    stopped = map_search(posterior(scene), seed=0, should_stop=lambda: calls.append(1) or len(calls) >= 3)
    assert stopped.stopped and len(stopped.history) == 3


def test_the_budget_bounds_the_rollouts(scene):
    post = posterior(scene)
    result = map_search(post, seed=0, budget=150)
    spent = result.rollouts + JACOBIAN_COST * result.jacobians
    # the budget is checked between batches: at most one generation (or LM trial) beyond it
    assert spent <= 150 + 4 * 16 + 3 * 4
    assert len(result.history) < 20


def test_settings_of_the_local_optimisers_are_errors_with_the_default_search(scene):
    with pytest.raises(InferenceError, match="screen applies to the local optimisers"):
        solve(scene, screen=8)
    with pytest.raises(InferenceError, match="budget applies to the default search"):
        solve(scene, optimizer="adam", budget=100)
    with pytest.raises(InferenceError, match="budget"):
        solve(scene, budget=0)
    result = solve(scene, optimizer="adam", iterations=2)  # the local optimisers stay selectable
    assert result.settings["optimizer"] == "adam" and "search" not in result.to_json()
