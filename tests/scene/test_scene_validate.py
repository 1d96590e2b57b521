"""Semantic checks on scenes built in Python (no XML, so no lines but object lines)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dejaview.errors import SceneError
from dejaview.scene import (
    Exploration,
    HeatmapSettings,
    InferenceSettings,
    Optimize,
    Penalty,
    Pose,
    Scene,
    SceneObject,
    SimulationSettings,
    StartArea,
    Target,
    Velocity,
)
from dejaview.scene.validate import MESH_SUFFIXES, scene_problems, validate_scene

VALID = Path(__file__).resolve().parents[1] / "fixtures" / "scenes" / "valid"


def good_scene() -> Scene:
    return Scene(
        objects=(
            SceneObject(id="floor", shape="plane", fixed=True),
            SceneObject(id="ball", shape="sphere", radius=0.1, mass=1.0, pose=Pose((0.0, 0.0, 1.0))),
            SceneObject(id="cube", mesh="meshes/cube.obj", spheres="packings/cube.spheres"),
        ),
        inference=InferenceSettings(
            source="ball", targets=(Target(position=(1.0, 0.0, 0.1)),),
            start_area=StartArea((-1.0, -1.0, 1.0), (1.0, 1.0, 1.0)),
            heatmap=HeatmapSettings(), exploration=Exploration(),
            penalties=(Penalty(("ball", "cube")),),
        ),
        base_dir=VALID,
    )


def change_object(scene: Scene, index: int, **changes) -> Scene:
    objs = list(scene.objects)
    objs[index] = dataclasses.replace(objs[index], **changes)
    return scene.replace(objects=tuple(objs))


def change_inference(scene: Scene, **changes) -> Scene:
    return scene.replace(inference=dataclasses.replace(scene.inference, **changes))


def only_problem(scene: Scene, **kwargs) -> SceneError:
    problems = scene_problems(scene, **kwargs)
    assert len(problems) == 1, [str(p) for p in problems]
    return problems[0]


def test_good_scene_passes():
    scene = good_scene()
    assert validate_scene(scene) is scene
    assert scene_problems(scene) == []


@pytest.mark.parametrize("index,changes,reason,element", [
    (1, dict(radius=None), "a sphere needs 'radius'", "object"),
    (1, dict(radius=0.0), "'radius' must be positive", "object"),
    (1, dict(size=(1.0, 1.0, 1.0)), "'size' does not apply to a sphere", "object"),
    (1, dict(shape="box", radius=None, size=(1.0, -1.0, 1.0)), "'size' must be positive", "object"),
    (1, dict(shape="box", radius=None, size=(1.0, 1.0)), "'size' needs 3 numbers, got 2", "object"),
    (1, dict(shape="cylinder"), "a cylinder needs 'height'", "object"),
    (1, dict(shape="cylinder", height=float("nan")), "'height' is not finite", "object"),
    (1, dict(shape=None), "has no geometry", "object"),
    (1, dict(mass=-1.0), "'mass' must be positive", "object"),
    (1, dict(mass="heavy"), "'mass' must be a number, not str", "object"),
    (1, dict(density=0.0), "'density' must be positive", "object"),
    (1, dict(friction=-0.1), "'friction' must be >= 0", "object"),
    (1, dict(restitution=1.01), "'restitution' must be between 0 and 1", "object"),
    (1, dict(id=""), "'id' is empty", "object"),
    (1, dict(id="the ball"), "contains whitespace", "object"),
    (1, dict(pose=Pose((0.0, 0.0, 1.0), (2.0, 0.0, 0.0, 0.0))), "not a unit quaternion", "pose"),
    (1, dict(pose=Pose((0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 0.0))), "zero quaternion", "pose"),
    (1, dict(pose=Pose((0.0, float("inf"), 1.0))), "'position' is not finite", "pose"),
    (1, dict(velocity=Velocity(angular=(0.0, float("nan"), 0.0))), "'angular' is not finite", "velocity"),
    (2, dict(mesh="meshes/cube.fbx"), "unsupported suffix '.fbx'", "object"),
    (2, dict(mesh="meshes/missing.obj"), "mesh file 'meshes/missing.obj' not found", "object"),
    (2, dict(spheres="missing.spheres"), "spheres file 'missing.spheres' not found", "object"),
    (2, dict(radius=0.2), "'radius' does not apply to a mesh", "object"),
    (0, dict(fixed=False), "plane 'floor' must be fixed", "object"),
    (0, dict(shape="torus"), "shape 'torus' is not one of", "object"),
])
def test_object_problems(index, changes, reason, element):
    problems = scene_problems(change_object(good_scene(), index, **changes))
    if "id" not in changes:  # a renamed object also breaks the references to it
        assert len(problems) == 1, [str(p) for p in problems]
    err = problems[0]
    assert reason in err.reason
    assert err.element == element
    assert err.file == "<scene>" and err.line is None


@pytest.mark.parametrize("changes,reason,element", [
    (dict(source="nobody"), "source 'nobody' is not an object", "inference"),
    (dict(source="floor"), "source 'floor' is fixed", "inference"),
    (dict(iterations=0), "'iterations' must be >= 1", "inference"),
    (dict(iterations=2.5), "'iterations' must be an integer", "inference"),
    (dict(seed=-1), "'seed' must be >= 0", "inference"),
    (dict(optimizer="sgd"), "optimizer 'sgd' is not one of", "inference"),
    (dict(gradient="sideways"), "gradient 'sideways' is not one of forward, reverse", "inference"),
    (dict(loss="l2"), "loss 'l2' is not one of pose, add, position", "inference"),
    (dict(evaluate="last"), "evaluate 'last' is not one of best, final", "inference"),
    (dict(targets=(Target((0.0, 0.0, 0.0), time=-0.1),)), "'time' must be >= 0", "target"),
    (dict(targets=(Target((0.0, 0.0, 0.0), time=1.6),)), "after the end of the simulation", "target"),
    (dict(targets=(Target((0.0, 0.0, 0.0), linear_velocity=(0.0, 0.0)),)), "'linear-velocity' needs 3", "target"),
    (dict(targets=(Target((0.0, 0.0, 0.0), linear_velocity=(0.0, 0.0, 0.0), moving=False),)),
     "seen at rest (moving=\"false\") observes no velocities", "target"),
    (dict(targets=(Target((0.0, 0.0, 0.0), time=0.5), Target((0.1, 0.0, 0.0)), Target((0.2, 0.0, 0.0)))),
     "2 targets have no 'time'", "target"),
    (dict(targets=()), "no <target>", "inference"),
    (dict(optimize=Optimize(False, False, False, False)), "nothing to optimize", "optimize"),
    (dict(start_area=StartArea((0.0, 0.0, 0.0), (1.0, 1.0, -1.0))), "greater than 'max' along z", "start-area"),
    (dict(start_area=StartArea((0.0, 0.0, 0.0), (0.0, 1.0, 1.0))), "no x-y extent", "heatmap"),
    (dict(start_area=None), "a heatmap needs a <start-area>", "heatmap"),
    (dict(heatmap=HeatmapSettings(cells=(0, 4))), "'cells' must be >= 1", "heatmap"),
    (dict(heatmap=HeatmapSettings(cells=(4,))), "'cells' needs 2 integers", "heatmap"),
    (dict(heatmap=HeatmapSettings(samples=0)), "'samples' must be >= 1", "heatmap"),
    (dict(heatmap=HeatmapSettings(sigma=0.0)), "'sigma' must be positive", "heatmap"),
    (dict(exploration=Exploration(epsilon=1.5)), "'epsilon' must be between 0 and 1", "exploration"),
    (dict(exploration=Exploration(patience=0)), "'patience' must be >= 1", "exploration"),
    (dict(penalties=(Penalty(("ball", "ghost")),)), "unknown object 'ghost'", "penalty"),
    (dict(penalties=(Penalty(("ball", "ball")),)), "names 'ball' twice", "penalty"),
    (dict(penalties=(Penalty(("ball", "cube"), -1.0),)), "'weight' must be >= 0", "penalty"),
])
def test_inference_problems(changes, reason, element):
    err = only_problem(change_inference(good_scene(), **changes))
    assert reason in err.reason
    assert err.element == element


@pytest.mark.parametrize("changes,reason,element", [
    (dict(simulation=SimulationSettings(dt=0.0)), "'dt' must be positive", "simulation"),
    (dict(simulation=SimulationSettings(duration=-1.0)), "'duration' must be positive", "simulation"),
    (dict(simulation=SimulationSettings(friction=-1.0)), "'friction' must be >= 0", "simulation"),
    (dict(simulation=SimulationSettings(restitution=2.0)), "between 0 and 1", "simulation"),
    (dict(simulation=SimulationSettings(extra={"dt": "1"})), "not a usable attribute name", "simulation"),
    (dict(simulation=SimulationSettings(extra={"two words": "1"})), "not a usable attribute name", "simulation"),
    (dict(gravity=(0.0, 0.0, float("nan"))), "'gravity' is not finite", "scene"),
    (dict(version=2), "unknown scene version 2", "scene"),
])
def test_scene_problems(changes, reason, element):
    err = only_problem(good_scene().replace(**changes))
    assert reason in err.reason
    assert err.element == element


def test_scene_without_objects():
    assert "scene has no objects" in only_problem(Scene(objects=())).reason


def test_duplicate_ids():
    scene = good_scene()
    scene = scene.replace(objects=scene.objects + (dataclasses.replace(scene.objects[1], line=42),))
    err = only_problem(scene)
    assert err.reason == "duplicate id 'ball'"
    assert err.line == 42


def test_problems_come_in_file_order_and_use_object_lines():
    scene = good_scene()
    scene = change_object(scene, 2, mass=-1.0, line=9)
    scene = change_object(scene, 1, radius=-1.0, line=5)
    problems = scene_problems(scene)
    assert [p.line for p in problems] == [5, 9]
    assert str(problems[0]) == "<scene>:5: <object> 'radius' must be positive, got -1.0"
    with pytest.raises(SceneError) as info:
        validate_scene(scene, file="mine.xml")
    assert str(info.value).startswith("mine.xml:5: <object>")


def test_lines_map_names_the_element_line():
    scene = change_inference(good_scene(), iterations=0)
    err = only_problem(scene, lines={("scene",): 1, ("inference",): 20})
    assert err.line == 20
    err = only_problem(change_inference(good_scene(), heatmap=HeatmapSettings(samples=0)),
                       lines={("inference",): 20})
    assert err.line == 20  # falls back to the enclosing element


def test_check_files_false():
    scene = change_object(good_scene(), 2, mesh="meshes/missing.obj")
    assert scene_problems(scene, check_files=False) == []


def test_overlong_file_names_are_scene_errors():
    scene = change_object(good_scene(), 2, mesh="x" * 5000 + ".obj")
    assert "not found" in only_problem(scene).reason


@pytest.mark.parametrize("suffix", MESH_SUFFIXES + tuple(s.upper() for s in MESH_SUFFIXES))
def test_every_mesh_suffix_is_accepted(suffix):
    scene = change_object(good_scene(), 2, mesh="model" + suffix)
    assert scene_problems(scene, check_files=False) == []
