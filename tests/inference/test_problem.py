"""InferenceProblem: parameters -> the whole initial state, in scenes with several bodies.

Regression: ``InferenceProblem.initial_state`` used to build the source's state
with ``World.state``, which wants every movable body, so any scene with more
than one movable object (``box_among_boxes``, the billiards fixture) failed
with "expected N bodies in the state" before its first rollout.
"""

from pathlib import Path

import torch

from dejaview.inference import InferenceProblem
from dejaview.scene import Scene

ROOT = Path(__file__).resolve().parents[2]
BILLIARDS = ROOT / "tests" / "fixtures" / "inference" / "billiards.xml"
MUG = ROOT / "examples" / "scenes" / "mug_off_counter.xml"


def test_only_the_source_moves_with_the_parameters_in_a_scene_of_two_bodies():
    problem = InferenceProblem.from_scene(Scene.from_xml(BILLIARDS))
    assert problem.world.num_bodies == 2 and problem.world.names[problem.source] == "cue"
    x = torch.tensor([[-1.0], [0.0], [2.0]], dtype=torch.float64)  # three candidates of y
    state = problem.initial_state(x)
    assert state.position.shape == (3, 2, 3)
    other = 1 - problem.source
    for field in ("position", "orientation", "linear_velocity", "angular_velocity"):
        got = getattr(state, field)[:, other]
        assert torch.equal(got, getattr(problem.base, field)[0, other].expand_as(got))
    decoded = problem.layout.decode(x)
    assert torch.allclose(state.position[:, problem.source], decoded["position"])
    with torch.no_grad():
        losses = problem.loss(x)
    assert losses.shape == (3,) and torch.isfinite(losses).all()


def test_the_source_state_is_its_centre_of_mass_as_world_state_gives_it():
    """Scene poses are object-frame origins; the state holds centres of mass. For the mug
    (centre of mass 1.3 cm off its origin) the problem's state must equal ``World.state``
    of the decoded pose, for turned candidates too."""
    problem = InferenceProblem.from_scene(Scene.from_xml(MUG))
    assert problem.world.com[problem.source].norm() > 0.01
    gen = torch.Generator().manual_seed(0)
    x = problem.layout.sample(4, gen)
    s = problem.layout.decode(x)
    expected = problem.world.state(s["position"][:, None], s["orientation"][:, None],
                                   s["linear_velocity"][:, None], s["angular_velocity"][:, None])
    got = problem.initial_state(x)
    for a, b in zip(got.tensors(), expected.tensors()):
        assert torch.allclose(a, b, atol=1e-15)
