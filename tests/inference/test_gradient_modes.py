"""Forward and reverse mode drive the optimiser along the same path.

The two gradient modes compute the same derivative by different routes
(``torch.func.jvp`` vmapped over the parameter basis vs. autograd with
checkpointing). With a fixed seed, ``solve`` must then make the same
decisions in either mode: the same loss at every iteration, to rounding. The
problem is real but cheap: ``tests/fixtures/inference/ball_throw.xml``, a
ball (one exact sphere) tossed onto a floor and bouncing once in 0.1 s, with
5 free parameters (start x, y and the linear velocity). Forward mode costs
~15-35x a rollout in eager torch, so the runs are a few iterations each.
"""

from pathlib import Path

import pytest

from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.scene import Scene

BALL = Path(__file__).resolve().parents[1] / "fixtures" / "inference" / "ball_throw.xml"


@pytest.fixture(scope="module")
def ball():
    return Scene.from_xml(BALL)


@pytest.mark.parametrize("optimizer, iterations", [("gd", 3), ("adam", 3), ("lbfgs", 2)])
def test_forward_and_reverse_mode_follow_the_same_path(ball, optimizer, iterations):
    """Same seed, same optimiser: every iteration's loss and best loss agree to 1e-6
    relative between the modes, as do the final state and the number of evaluations
    (L-BFGS's line search takes the same trial steps). The path must go somewhere:
    the loss drops, so the comparison is not of a run standing still."""
    runs = {mode: solve(ball, SolveParams(optimizer=optimizer, gradient=mode, iterations=iterations, seed=7))
            for mode in ("forward", "reverse")}
    fwd, rev = runs["forward"], runs["reverse"]
    assert fwd.settings["gradient"] == "forward" and rev.settings["gradient"] == "reverse"
    assert len(fwd.iterations) == len(rev.iterations) == iterations
    for pf, pr in zip(fwd.iterations, rev.iterations):
        assert pf.loss == pytest.approx(pr.loss, rel=1e-6)
        assert pf.best_loss == pytest.approx(pr.best_loss, rel=1e-6)
        assert pf.evaluations == pr.evaluations
    assert fwd.loss == pytest.approx(rev.loss, rel=1e-6)
    for key in ("position", "linear_velocity"):
        assert fwd.initial_state[key] == pytest.approx(rev.initial_state[key], rel=1e-6, abs=1e-9)
    assert rev.iterations[-1].best_loss < rev.iterations[0].loss
