"""SpheresProblem: parameters -> the whole initial state, in scenes with several bodies.

Regression: ``SpheresProblem.initial_state`` used to build the source's state
with ``World.state``, which wants every movable body, so any scene with more
than one movable object (``box_among_boxes``, the billiards fixture) failed
with "expected N bodies in the state" before its first rollout.
"""

import math
from pathlib import Path

import pytest
import torch

from dejaview.backends.spheres import SpheresProblem
from dejaview.losses.targets import REST_PARTS, REST_WINDOW
from dejaview.scene import Scene

ROOT = Path(__file__).resolve().parents[2]
BILLIARDS = ROOT / "tests" / "fixtures" / "inference" / "billiards.xml"
MUG = ROOT / "examples" / "scenes" / "mug_off_counter.xml"


def test_only_the_source_moves_with_the_parameters_in_a_scene_of_two_bodies():
    problem = SpheresProblem.from_scene(Scene.from_xml(BILLIARDS))
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
    problem = SpheresProblem.from_scene(Scene.from_xml(MUG))
    assert problem.world.com[problem.source].norm() > 0.01
    gen = torch.Generator().manual_seed(0)
    x = problem.layout.sample(4, gen)
    s = problem.layout.decode(x)
    expected = problem.world.state(s["position"][:, None], s["orientation"][:, None],
                                   s["linear_velocity"][:, None], s["angular_velocity"][:, None])
    got = problem.initial_state(x)
    for a, b in zip(got.tensors(), expected.tensors()):
        assert torch.allclose(a, b, atol=1e-15)


BOX_RAMP = ROOT / "examples" / "scenes" / "box_down_ramp.xml"  # evaluate="final", no penalty
BOXES = ROOT / "examples" / "scenes" / "box_among_boxes.xml"  # every position axis free


def _with_inference(path, **attrs):
    """The scene at path with its <inference> attributes replaced."""
    from dataclasses import replace

    scene = Scene.from_xml(path)
    return replace(scene, inference=replace(scene.inference, **attrs))


@pytest.mark.parametrize("moving", [True, False])
def test_a_final_pose_loss_records_only_what_it_reads_and_equals_the_every_step_loss_and_gradient(moving):
    """A loss that reads only the end state (a target seen moving, evaluate final, no penalty)
    simulates recording the end alone; one seen at rest, the end and its rest window's steps; value
    and gradient are those of the rollout that records every step."""
    from dataclasses import replace

    scene = Scene.from_xml(BOX_RAMP)
    target = replace(scene.inference.target, moving=True if moving else None)
    problem = SpheresProblem.from_scene(replace(scene, inference=replace(scene.inference, targets=(target,))))
    assert problem.evaluate == "final" and not problem.penalties
    window = int(round(REST_WINDOW / REST_PARTS / problem.world.dt))
    assert problem.record_every == (problem.steps if moving else math.gcd(problem.steps, window))
    every = replace(problem, record_every=1)
    gen = torch.Generator().manual_seed(1)
    x = problem.layout.sample(3, gen)
    with torch.no_grad():
        records = problem.simulate(x).states.position.shape[0]
        assert records == (2 if moving else problem.steps // problem.record_every + 1)
    for mode in ("reverse", "forward"):
        value, grad = problem.value_and_grad(x, mode)
        value_1, grad_1 = every.value_and_grad(x, mode)
        assert torch.allclose(value, value_1, rtol=0, atol=1e-12)
        assert torch.allclose(grad, grad_1, rtol=1e-9, atol=1e-12)


def test_losses_that_read_more_than_the_end_record_every_step():
    scene = Scene.from_xml(BOX_RAMP)
    moving = replace_target(scene, moving=True)
    best = SpheresProblem.from_scene(_with_inference(BOX_RAMP, evaluate="best", targets=moving))
    assert best.record_every == 1
    from dejaview.scene.model import Penalty

    penalised = SpheresProblem.from_scene(_with_inference(
        BOX_RAMP, penalties=(Penalty(between=("box", "ramp"), weight=1.0),)))
    assert penalised.record_every == 1


def replace_target(scene, **changes) -> tuple:
    """The scene's one target with ``changes``, as ``targets``."""
    from dataclasses import replace

    return (replace(scene.inference.target, **changes),)


def test_decoding_every_position_axis_equals_decoding_them_one_by_one():
    """The all-axes shortcut of ParameterLayout.decode against the per-axis path (a layout that
    frees the same three axes one column at a time gives the same numbers)."""
    from dataclasses import replace

    problem = SpheresProblem.from_scene(Scene.from_xml(BOXES))
    layout = problem.layout
    assert layout.position_axes == (0, 1, 2) and layout.lo is not None
    x = layout.sample(5, torch.Generator().manual_seed(2))
    got = layout.decode(x)["position"]
    lo, hi = layout.lo, layout.hi
    expected = lo + (hi - lo) * torch.sigmoid(x[:, :3])
    assert torch.equal(got, expected)
    # per-candidate boxes (the heatmap's cells): (B, 3) bounds
    cells = replace(layout, lo=lo.expand(5, 3) - 0.1 * torch.arange(5.0, dtype=lo.dtype)[:, None],
                    hi=hi.expand(5, 3).clone())
    pos = cells.decode(x)["position"]
    assert torch.equal(pos, cells.lo + (cells.hi - cells.lo) * torch.sigmoid(x[:, :3]))
