"""The default search (``dejaview.inference.search``) on a cheap scene: budgets, stops, settings.

``box_down_ramp`` frees only the start position's x and y (2 parameters, 320 steps of 5 ms): a
whole search takes well under a second.
"""

from pathlib import Path

import pytest
import torch

from dejaview.errors import InferenceError
from dejaview.backends.spheres import SpheresProblem
from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.inference.posterior import Posterior, PosteriorSettings
from dejaview.inference.params import SearchParams
from dejaview.inference.search import MapSearch
from dejaview.scene import Scene

RAMP = Path(__file__).resolve().parents[2] / "examples" / "scenes" / "box_down_ramp.xml"


@pytest.fixture(scope="module")
def scene():
    return Scene.from_xml(RAMP)


def posterior(scene):
    return Posterior(SpheresProblem.from_scene(scene), PosteriorSettings.from_scene(scene))


def test_the_search_explains_the_end_and_reports_its_modes(scene):
    post = posterior(scene)
    seen = []
    result = MapSearch(SearchParams(seed=0)).run(post, callback=seen.append)
    assert result.chi2 < 1e-3 and result.loss < 1e-3
    assert result.cost == pytest.approx(0.5 * result.chi2)  # flat prior: the cost is the misfit
    assert result.modes and result.modes[0].cost == pytest.approx(result.cost)
    assert [p.iteration for p in seen] == list(range(len(seen))) == [p.iteration for p in result.history]
    assert all(b.best_loss <= a.best_loss for a, b in zip(seen, seen[1:]))
    spent = [p.evaluations for p in seen]
    assert spent == sorted(spent) and spent[-1] <= result.rollouts + SearchParams().jacobian_cost * result.jacobians


def test_same_seed_same_answer_and_should_stop_ends_it(scene):
    a, b = MapSearch(SearchParams(seed=3)).run(posterior(scene)), MapSearch(SearchParams(seed=3)).run(posterior(scene))
    assert a.x.tolist() == b.x.tolist()
    calls = []
    stopped = MapSearch().run(posterior(scene), should_stop=lambda: calls.append(1) or len(calls) >= 3)
    assert stopped.stopped and len(stopped.history) == 3


def test_the_budget_bounds_the_rollouts(scene):
    post = posterior(scene)
    result = MapSearch(SearchParams(budget=150)).run(post)
    spent = result.rollouts + SearchParams().jacobian_cost * result.jacobians
    # the budget is checked between batches: at most one generation (or LM trial) beyond it
    assert spent <= 150 + 4 * 16 + 3 * 4
    assert len(result.history) < 20


def test_settings_of_the_local_optimisers_are_errors_with_the_default_search(scene):
    with pytest.raises(InferenceError, match="screen applies to the local optimisers"):
        solve(scene, SolveParams(screen=8))
    with pytest.raises(InferenceError, match="budget applies to the default search"):
        solve(scene, SolveParams(optimizer="adam", budget=100))
    with pytest.raises(InferenceError, match="budget"):
        solve(scene, SolveParams(budget=0))
    result = solve(scene, SolveParams(optimizer="adam", iterations=2))  # the local optimisers stay selectable
    assert result.settings["optimizer"] == "adam" and "search" not in result.to_json()


def test_the_levenberg_marquardt_solve_is_reproducible_and_exact():
    """The damped normal equations are solved by Cholesky, bit for bit the same on every call
    (MKL's lstsq differed by ~1e-16 between calls on the same inputs, and the search turned that
    into different answers); a matrix that is not positive definite falls back to least squares."""
    from dejaview.inference.search import _spd_solve

    gen = torch.Generator().manual_seed(0)
    J = torch.randn(6, 300, 12, generator=gen, dtype=torch.float64)
    A = J.transpose(1, 2) @ J + 1e-2 * torch.eye(12, dtype=torch.float64)
    b = torch.randn(6, 12, generator=gen, dtype=torch.float64)
    first = _spd_solve(A, b)
    for _ in range(20):
        assert torch.equal(_spd_solve(A.clone(), b.clone()), first)
    torch.testing.assert_close((A @ first.unsqueeze(-1)).squeeze(-1), b, rtol=0, atol=1e-10)
    singular = A.clone()
    singular[0] = torch.zeros(12, 12, dtype=torch.float64)
    singular[0, 0, 0] = 1.0
    out = _spd_solve(singular, b)
    assert torch.isfinite(out).all() and float(out[0, 0]) == pytest.approx(float(b[0, 0]))
    torch.testing.assert_close(out[1:], first[1:], rtol=0, atol=0)


def test_a_solve_is_reproducible_bit_for_bit():
    """Two solves of the same scene and seed in one process give the same start, exactly."""
    scene = Scene.from_xml(RAMP.with_name("ball_off_table.xml"))
    a, b = solve(scene, SolveParams(seed=0)), solve(scene, SolveParams(seed=0))
    assert torch.equal(torch.as_tensor(a.optimization.x), torch.as_tensor(b.optimization.x))
    assert a.loss == b.loss
