"""A source that must hit another object to end where it does needs the contact penalty.

``tests/fixtures/inference/billiards.xml``: on a frictionless table a light cue
ball was launched along +x at a known 2 m/s from the rail x = 0; only its y
along the rail is unknown (one parameter, in the start area [-0.3, 0.05]). A
heavy ball rests at (0.3, 0). The cue ball was observed (final pose, 0.2 s)
glancing off the heavy ball at (0.174, -0.153): truly launched at y = -0.04.
Without the collision the cue ball ends on the line x = 0.4, so the target is
out of its reach, and the target loss alone pulls it to the nearest miss
(y = -0.153, 0.226 m away) and holds it there: between that miss and the
heavy ball the loss rises, and nothing in it says that hitting the heavy ball
would help. ``<penalty between="cue heavy">`` adds the smallest gap between the
two over the trajectory, pulling the cue ball's path onto the heavy ball;
once they touch, the penalty is zero and the target loss takes the cue ball
to the true start. Both runs are L-BFGS from the scene's guess y = -0.25,
which misses by 15 cm.

Measured (2 shared cores): with the penalty, loss 5e-5 m after 3 iterations
(12 evaluations, ~20 s); without, loss 0.226 m, stuck from iteration ~8 on.
"""

from pathlib import Path

import pytest
import torch

from dejaview.inference import solve
from dejaview.inference.solve import SolveParams
from dejaview.losses import contact_penalty
from dejaview.scene import Scene

BILLIARDS = Path(__file__).resolve().parents[1] / "fixtures" / "inference" / "billiards.xml"
TRUE_Y = -0.04
PENALTY = '    <penalty between="cue heavy" weight="1"/>\n  </inference>'


def scene(penalty: bool) -> Scene:
    text = BILLIARDS.read_text(encoding="utf-8")
    if penalty:
        text = text.replace("  </inference>", PENALTY, 1)
    return Scene.from_string(text, base_dir=BILLIARDS.parent, filename=BILLIARDS.name)


def end_error(result) -> float:
    """Distance of the re-simulated final position from the target (evaluate="final")."""
    end, _ = result.final_pose()
    target = result.scene.inference.target.position
    return float(torch.linalg.vector_norm(torch.tensor(end) - torch.tensor(target)))


def touched(result) -> bool:
    """Did the cue ball touch the heavy ball in the re-simulated solution?"""
    gap = contact_penalty(result.problem.world, result.trajectory, "cue", "heavy")
    return gap.item() == 0.0


@pytest.fixture(scope="module")
def runs():
    with_penalty = solve(scene(penalty=True), SolveParams(iterations=15, tolerance=0.005))
    without = solve(scene(penalty=False), SolveParams(iterations=15, tolerance=0.005))
    return with_penalty, without


def test_the_initial_guess_misses_and_the_scenes_differ_only_by_the_penalty():
    a, b = scene(True), scene(False)
    assert [p.between for p in a.inference.penalties] == [("cue", "heavy")]
    assert b.inference.penalties == ()
    assert a.objects == b.objects and a.inference.target == b.inference.target
    guess_y = a.object("cue").pose.position[1]
    assert abs(guess_y) - 0.1 >= 0.15 - 1e-9  # radii 0.05 + 0.05: a 15 cm miss


def test_with_the_penalty_the_solve_finds_the_collision_and_the_true_start(runs):
    """Converged: the re-simulated end within 1 cm of the target, through a collision,
    and from the true launch point (the problem has one solution here)."""
    result, _ = runs
    assert result.loss < 0.01
    assert end_error(result) < 0.01
    assert touched(result)
    assert result.initial_state["position"][1] == pytest.approx(TRUE_Y, abs=0.005)


def test_without_the_penalty_the_solve_stays_at_the_nearest_miss(runs):
    """Not converged: the cue ball never reaches the heavy ball, and ends more than
    20 cm from the target (the nearest miss is 22.6 cm away)."""
    _, result = runs
    assert not touched(result)
    assert result.loss > 0.2
    assert end_error(result) > 0.2
    assert result.initial_state["position"][1] < -0.1  # still on the missing side
