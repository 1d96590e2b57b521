"""Screening (``solve(screen=N)``): random guesses ranked by their loss before optimising."""

from pathlib import Path

import pytest
import torch

from dejaview.backends import as_problem, make_problem
from dejaview.errors import InferenceError
from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.inference.local import screen_guesses
from dejaview.scene import Scene

ROOT = Path(__file__).resolve().parents[2]
BALL = ROOT / "tests" / "fixtures" / "inference" / "ball_throw.xml"


def test_screened_guesses_are_ranked_by_their_own_loss_and_keep_the_first():
    """Every returned guess carries the loss ``problem.loss`` gives it, best first; the
    scene's guess is among them; batches do not change the numbers."""
    problem = as_problem(make_problem(Scene.from_xml(BALL)))
    first = problem.layout.encode().to(problem.dtype)
    ranked, losses = screen_guesses(problem, first, 9, torch.Generator().manual_seed(1), batch=4)
    assert ranked.shape == (10, problem.num_params) and losses.shape == (10,)
    assert torch.all(losses[1:] >= losses[:-1])
    with torch.no_grad():
        again = problem.loss(ranked)
    torch.testing.assert_close(again, losses, rtol=1e-10, atol=1e-12)
    assert any(torch.equal(row, first[0]) for row in ranked)


def test_a_stop_request_ends_screening_with_what_was_ranked():
    problem = as_problem(make_problem(Scene.from_xml(BALL)))
    first = problem.layout.encode().to(problem.dtype)
    ranked, losses = screen_guesses(problem, first, 9, torch.Generator().manual_seed(1), batch=4,
                                    should_stop=lambda: True)
    assert ranked.shape[0] == losses.shape[0] == 4  # the first batch only


def test_solve_starts_from_the_best_screened_guess():
    """The first evaluation of a screened solve is the best screened loss, which beats the
    scene's own guess here; result settings say how many guesses were screened."""
    scene = Scene.from_xml(BALL)
    plain = solve(scene, SolveParams(iterations=1, optimizer="adam"))
    screened = solve(scene, SolveParams(iterations=1, optimizer="adam", screen=15))
    problem = as_problem(make_problem(scene))
    _, losses = screen_guesses(problem, problem.layout.encode().to(problem.dtype), 15,
                               torch.Generator().manual_seed(scene.inference.seed))
    assert screened.settings["screened"] == 16 and plain.settings["screened"] == 0
    assert screened.iterations[0].loss == pytest.approx(float(losses[0]), rel=1e-9)
    assert screened.iterations[0].loss < plain.iterations[0].loss


def test_half_the_first_round_is_drawn_around_the_scenes_guess():
    """With ``near`` 0.5 half the draws lie around the scene's guess (normal, ``sigma``
    in scaled parameters), the others come from the prior (velocities: a ball of radius
    3 m/s, mean speed 2.25 m/s). With ``near`` 0 (the default) all come from the prior;
    ``solve(screen_near=...)`` passes the fraction on."""
    problem = as_problem(make_problem(Scene.from_xml(BALL)))
    first = problem.layout.encode().to(problem.dtype)
    vel = [i for i, n in enumerate(problem.layout.names()) if n.startswith("linear_velocity")]
    ranked, _ = screen_guesses(problem, first, 200, torch.Generator().manual_seed(0), near=0.5,
                               sigma=0.1)
    near = (ranked - first).norm(dim=-1) < 0.8  # 8 sigma; 5 parameters: ~2.2 sigma typical
    assert 101 <= int(near.sum()) <= 103  # the guess itself, the near half, maybe a prior draw
    assert float(ranked[~near][:, vel].norm(dim=-1).mean()) > 1.8
    prior, _ = screen_guesses(problem, first, 200, torch.Generator().manual_seed(0), sigma=0.1)
    assert int(((prior - first).norm(dim=-1) < 0.8).sum()) <= 3


@pytest.mark.parametrize("bad", [-1, True, 2.5])
def test_bad_screen_counts_are_one_line_errors(bad):
    with pytest.raises(InferenceError, match="screen must be a non-negative integer"):
        solve(Scene.from_xml(BALL), SolveParams(iterations=1, screen=bad))


@pytest.mark.parametrize("bad", [-0.1, 1.5])
def test_screen_near_outside_zero_to_one_is_a_one_line_error(bad):
    with pytest.raises(InferenceError, match=r"screen_near must be a fraction in \[0, 1\]"):
        solve(Scene.from_xml(BALL), SolveParams(iterations=1, screen=4, screen_near=bad))


def test_restarts_take_the_next_best_screened_guesses_in_order():
    """GD with a zero step never moves, so every iteration stalls; with epsilon 1 and
    patience 1 each restart must bring in the next screened guess: the losses seen are
    the screened ranking, best first."""
    scene = Scene.from_xml(BALL)
    iterations = []
    result = solve(scene, SolveParams(iterations=200, optimizer="gd", lr=0.0, screen=15, epsilon=1.0,
                   patience=1), callback=iterations.append, should_stop=lambda: len(iterations) >= 12)
    problem = as_problem(make_problem(scene))
    _, losses = screen_guesses(problem, problem.layout.encode().to(problem.dtype), 15,
                               torch.Generator().manual_seed(scene.inference.seed))
    seen = []
    for p in iterations:
        if not seen or abs(p.loss - seen[-1]) > 1e-12:
            seen.append(p.loss)
    assert len(seen) >= 4
    assert seen == pytest.approx(losses[:len(seen)].tolist(), rel=1e-9)
    assert result.loss == pytest.approx(float(losses[0]), rel=1e-9)


def test_refinement_rounds_draw_around_the_best_guesses():
    """Round 2 (cross-entropy method) samples a normal fitted to round 1's elite: its guesses
    are better than round 1's random ones on the whole, and the first round is unchanged."""
    problem = as_problem(make_problem(Scene.from_xml(BALL)))
    first = problem.layout.encode().to(problem.dtype)
    one, loss_one = screen_guesses(problem, first, 24, torch.Generator().manual_seed(2))
    two, loss_two = screen_guesses(problem, first, 24, torch.Generator().manual_seed(2), rounds=2,
                                   elite=6)
    assert two.shape == (49, problem.num_params)
    assert torch.all(loss_two[1:] >= loss_two[:-1])
    new = torch.stack([loss for row, loss in zip(two, loss_two)
                       if not any(torch.equal(row, r) for r in one)])
    assert new.shape == (24,)
    assert new.median() < loss_one.median()
    assert new.median() < loss_one.sort().values[6]  # as good as round 1's elite, typically
    assert loss_two[0] <= loss_one[0]


def test_bad_screen_rounds_are_one_line_errors():
    with pytest.raises(InferenceError, match="screen rounds must be a positive integer"):
        solve(Scene.from_xml(BALL), SolveParams(iterations=1, screen=3, screen_rounds=0))


def test_restarts_take_the_first_rounds_guesses_before_the_refinements():
    """The pool keeps the loss order within each part: first round (spread over the prior)
    first, then the refinement rounds, which crowd around the start."""
    from dejaview.inference.local import restart_pool, screen_rounds_ranked

    problem = as_problem(make_problem(Scene.from_xml(BALL)))
    first = problem.layout.encode().to(problem.dtype)
    ranked, losses, drawn = screen_rounds_ranked(problem, first, 12, torch.Generator().manual_seed(3),
                                                 rounds=3, elite=4)
    assert ranked.shape[0] == drawn.shape[0] == 37
    assert int((drawn == 0).sum()) == 13 and int((drawn == 2).sum()) == 12
    assert torch.all(losses[1:] >= losses[:-1])
    two, loss_two = screen_guesses(problem, first, 12, torch.Generator().manual_seed(3), rounds=3, elite=4)
    assert torch.equal(two, ranked) and torch.equal(loss_two, losses)
    pool = torch.stack(restart_pool(ranked[1:], drawn[1:]))
    n0 = int((drawn[1:] == 0).sum())
    assert torch.equal(pool[:n0], ranked[1:][drawn[1:] == 0])
    assert torch.equal(pool[n0:], ranked[1:][drawn[1:] > 0])
    assert not torch.equal(pool, ranked[1:])  # the refinements rank high: the order changed
