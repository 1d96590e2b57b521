"""Reading and writing scene XML: strict values, defaults, round trips."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from lxml import etree

from dejaview.errors import SceneError
from dejaview.scene import (
    Exploration,
    HeatmapSettings,
    InferenceSettings,
    ModelUncertainty,
    Observation,
    Optimize,
    Penalty,
    Pose,
    PosteriorRequest,
    Prior,
    Scene,
    SceneObject,
    SimulationSettings,
    StartArea,
    Target,
    Velocity,
)
from dejaview.scene.xml import (
    load_schema,
    normalize_quaternion,
    read_scene_file,
    read_scene_string,
    scene_to_xml,
)

VALID = Path(__file__).resolve().parents[1] / "fixtures" / "scenes" / "valid"

MINIMAL = """<scene version="1">
  <object id="ball" shape="sphere" radius="0.1">
    <pose position="0 0 1"/>
  </object>
</scene>
"""


def ball_scene(pose_attrs: str = 'position="0 0 1"', object_attrs: str = "", extra: str = "") -> str:
    return (f'<scene version="1">\n  <object id="ball" shape="sphere" radius="0.1" {object_attrs}>\n'
            f'    <pose {pose_attrs}/>\n  </object>\n{extra}</scene>\n')


def reason_of(text: str, **kwargs) -> SceneError:
    with pytest.raises(SceneError) as info:
        read_scene_string(text, **kwargs)
    return info.value


# -- round trips ---------------------------------------------------------------
@pytest.mark.parametrize("name", ["example.xml", "primitives.xml", "cube.xml"])
def test_fixture_round_trips(name):
    scene = Scene.from_xml(VALID / name)
    text = scene.to_xml()
    again = Scene.from_string(text, base_dir=VALID)
    assert again == scene
    # and the written text is a fixed point of write(read(.))
    assert again.to_xml() == text


def test_spec_example_reads_as_written():
    scene = Scene.from_xml(VALID / "example.xml")
    assert scene.name == "mug-off-the-counter"
    assert scene.gravity == (0.0, 0.0, -9.81)
    assert scene.simulation == SimulationSettings(dt=0.002, duration=1.5, friction=0.5, restitution=0.2)
    assert [o.id for o in scene.objects] == ["floor", "counter", "mug"]
    floor, counter, mug = scene.objects
    assert floor.shape == "plane" and floor.fixed
    assert counter.mesh == "meshes/counter.obj" and counter.spheres == "packings/counter.spheres"
    assert counter.fixed and counter.pose.position == (0.0, 0.0, 0.45)
    assert mug.mass == 0.35 and not mug.fixed
    assert mug.velocity == Velocity(linear=(0.8, 0.0, 0.0), angular=(0.0, 0.0, 0.0))
    assert scene.resolve(mug.mesh) == VALID / "meshes" / "mug.obj"
    inf = scene.inference
    assert (inf.source, inf.iterations, inf.optimizer, inf.gradient, inf.loss, inf.evaluate, inf.seed) == (
        "mug", 500, "lbfgs", "forward", "pose", "best", 0)
    h = math.sqrt(0.5)
    assert inf.target.position == (0.62, 0.05, 0.05)
    assert inf.target.orientation == pytest.approx((h, h, 0.0, 0.0), abs=1e-15)
    assert inf.optimize == Optimize()
    assert inf.start_area == StartArea(min=(-0.3, -0.3, 0.9), max=(0.3, 0.3, 0.9))
    assert inf.exploration == Exploration(epsilon=0.2, patience=25)
    assert inf.penalties == (Penalty(between=("mug", "counter"), weight=0.1),)
    assert inf.heatmap == HeatmapSettings(cells=(32, 32), samples=8, sigma=0.02)


def test_object_lines_are_recorded_but_not_compared():
    scene = Scene.from_xml(VALID / "example.xml")
    assert [o.line for o in scene.objects] == [4, 7, 10]
    moved = Scene.from_string("\n\n" + scene.to_xml().split("?>", 1)[1], base_dir=VALID)
    assert [o.line for o in moved.objects] != [4, 7, 10]
    assert moved == scene


def programmatic_scene() -> Scene:
    return Scene(
        name="built in python & <escaped> \"quotes\"\nand a newline",
        gravity=(0.1, -0.0, -9.80665),
        simulation=SimulationSettings(dt=1e-4, duration=0.25, friction=0.0, restitution=1.0,
                                      extra={"substeps": "8", "solver": "pgs fast"}),
        objects=(
            SceneObject(id="floor", shape="plane", fixed=True),
            SceneObject(id="box-1", shape="box", size=(0.1, 0.2, 1 / 3), density=500.0,
                        pose=Pose((1 / 7, 2e-300, -1e4), normalize_quaternion((1, 2, 3, 4))),  # at the limit
                        velocity=Velocity((0.0, 0.0, 0.0), (0.0, 0.0, 12.5))),
            SceneObject(id="can", shape="cylinder", radius=0.03, height=0.1, mass=0.3,
                        friction=0.25, restitution=0.0, fixed=True),
            SceneObject(id="cube", mesh="meshes/cube.obj", spheres="packings/cube.spheres",
                        pose=Pose((0.0, 0.0, 0.05))),
        ),
        inference=InferenceSettings(
            source="box-1",
            targets=(Target(position=(1.0, 2.0, 0.05), orientation=normalize_quaternion((0, 0, 0, -1)),
                            linear_velocity=(0.0, 0.0, 0.0), angular_velocity=(1.0, 0.0, 0.0), time=0.25),),
            iterations=3, seed=123456789, optimizer="bfgs", gradient=None, loss="add", evaluate="final",
            optimize=Optimize(position=True, orientation=False, linear_velocity=True, angular_velocity=False),
            start_area=StartArea(min=(-1.0, -1.0, 0.0), max=(1.0, 1.0, 0.5)),
            exploration=Exploration(epsilon=0.0, patience=1),
            penalties=(Penalty(("box-1", "can"), 0.5), Penalty(("cube", "floor"))),
            heatmap=HeatmapSettings(cells=(1, 7), samples=1, sigma=1e-3),
            prior=Prior(speed=1.5, tilt=0.25), observation=Observation(sigma=0.004),
            model_uncertainty=ModelUncertainty(friction=0.1, restitution=0.0),
            posterior=PosteriorRequest(samples=500),
        ),
    )


def test_programmatic_scene_round_trips():
    scene = programmatic_scene()
    again = Scene.from_string(scene.to_xml(), base_dir=VALID)
    assert again == scene
    assert again.name == scene.name  # escaping and the newline survive


def test_write_and_read_a_file(tmp_path):
    scene = Scene.from_xml(VALID / "primitives.xml")
    out = tmp_path / "copy.xml"
    scene.write(out)
    assert Scene.from_xml(out) == scene


def test_minimal_scene_gets_model_defaults():
    scene = read_scene_string(MINIMAL)
    assert scene == Scene(objects=(SceneObject(id="ball", shape="sphere", radius=0.1,
                                               pose=Pose((0.0, 0.0, 1.0))),))
    assert scene.inference is None
    assert scene.simulation == SimulationSettings()


def test_inference_defaults():
    text = ball_scene(extra='  <inference source="ball"><target position="1 0 0"/></inference>\n')
    inf = read_scene_string(text).inference
    assert inf == InferenceSettings(source="ball", targets=(Target(position=(1.0, 0.0, 0.0)),))
    assert inf.gradient is None and inf.optimizer == "auto" and inf.iterations == 200


def test_writer_always_writes_version_and_skips_defaults_that_mean_nothing():
    text = read_scene_string(MINIMAL).to_xml()
    assert text.startswith("<?xml version='1.0' encoding='UTF-8'?>")
    root = etree.fromstring(text.encode())
    assert root.get("version") == "1"
    obj = root.find("object")
    assert obj.get("fixed") is None  # false is the default
    assert obj.find("velocity") is None  # zero velocity is the default
    assert obj.find("pose").get("orientation") == "1.0 0.0 0.0 0.0"  # poses are always complete
    sim = root.find("simulation")
    assert sim is not None and set(sim.attrib) == {"dt", "duration", "friction", "restitution"}


def test_writer_output_is_schema_valid():
    for scene in (programmatic_scene(), Scene.from_xml(VALID / "example.xml")):
        root = etree.fromstring(scene.to_xml().encode())
        assert load_schema().validate(root), load_schema().error_log


def test_floats_are_written_with_repr():
    scene = programmatic_scene()
    text = scene_to_xml(scene)
    assert repr(1 / 3) in text and repr(1 / 7) in text and "-10000.0" in text and "2e-300" in text


def test_writer_refuses_text_xml_cannot_hold():
    scene = read_scene_string(MINIMAL).replace(name="bell\x07")
    with pytest.raises(SceneError, match="cannot write scene as XML"):
        scene.to_xml()


# -- values ----------------------------------------------------------------------
def test_quaternions_are_normalised_on_read():
    scene = read_scene_string(ball_scene('position="0 0 1" orientation="2 0 0 0"'))
    assert scene.objects[0].pose.orientation == (1.0, 0.0, 0.0, 0.0)
    scene = read_scene_string(ball_scene('position="0 0 1" orientation="0 3 0 4"'))
    assert scene.objects[0].pose.orientation == (0.0, 0.6, 0.0, 0.8)


def test_normalize_quaternion_is_idempotent():
    for q in [(0.7071, 0.7071, 0, 0), (1, 2, 3, 4), (1e-3, 0, 0, 1e-3), (0.1, -0.2, 0.3, -0.9)]:
        once = normalize_quaternion(q)
        assert normalize_quaternion(once) == once
        assert math.isclose(sum(c * c for c in once), 1.0, rel_tol=1e-12)
    with pytest.raises(ValueError, match="zero quaternion"):
        normalize_quaternion((0, 0, 0, 0))


def test_quaternion_is_wxyz():
    """The real part comes first: "0 0 0 1" is a half turn about z, not the identity."""
    scene = read_scene_string(ball_scene('position="0 0 1" orientation="0 0 0 1"'))
    w, x, y, z = scene.objects[0].pose.orientation
    assert (w, x, y, z) == (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize("text,value", [
    ("true", True), ("false", False), ("1", True), ("0", False), (" true ", True),
])
def test_booleans(text, value):
    scene = read_scene_string(ball_scene(object_attrs=f'fixed="{text}"'))
    assert scene.objects[0].fixed is value


@pytest.mark.parametrize("text", ["True", "yes", "on", "2", "", "t"])
def test_bad_booleans(text):
    err = reason_of(ball_scene(object_attrs=f'fixed="{text}"'))
    assert "attribute 'fixed'" in err.reason and "not a boolean" in err.reason
    assert err.line == 2 and err.element == "object"


@pytest.mark.parametrize("text,value", [
    ("0.5", 0.5), ("5e-1", 0.5), ("+.5", 0.5), ("  0.5\n", 0.5), ("5.", 5.0), ("1E2", 100.0),
])
def test_numbers(text, value):
    assert read_scene_string(ball_scene(object_attrs=f'mass="{text}"')).objects[0].mass == value


@pytest.mark.parametrize("text,reason", [
    ("nan", "not finite"), ("-inf", "not finite"), ("Infinity", "not finite"), ("1e999", "not finite"),
    ("1_000", "is not a number"), ("0x10", "is not a number"), ("1,5", "is not a number"),
    ("", "needs 1 number, got 0"), ("1 2", "needs 1 number, got 2"), ("½", "is not a number"),
])
def test_bad_numbers_name_the_attribute(text, reason):
    err = reason_of(ball_scene(object_attrs=f'mass="{text}"'))
    assert "'mass'" in err.reason and reason in err.reason


@pytest.mark.parametrize("attr,n", [("position", 3), ("orientation", 4)])
@pytest.mark.parametrize("count", [0, 2, 5])
def test_vector_length_is_exact(attr, n, count):
    values = " ".join(["1"] * count)
    pose = f'position="0 0 1" {attr}="{values}"' if attr == "orientation" else f'position="{values}"'
    if count == n:
        return
    err = reason_of(ball_scene(pose))
    assert err.reason == f"attribute '{attr}' needs {n} numbers, got {count}"
    assert (err.line, err.element) == (3, "pose")


def test_integers_are_strict():
    base = '  <inference source="ball" {}><target position="1 0 0"/></inference>\n'
    assert read_scene_string(ball_scene(extra=base.format('iterations=" 7 "'))).inference.iterations == 7
    for bad in ("7.0", "1e3", "seven", "0x7"):
        err = reason_of(ball_scene(extra=base.format(f'iterations="{bad}"')))
        assert "'iterations'" in err.reason and "not an integer" in err.reason
    err = reason_of(ball_scene(extra=base.format(f'iterations="{"9" * 5000}"')))
    assert "too large" in err.reason


def test_simulation_keeps_backend_attributes():
    scene = Scene.from_xml(VALID / "primitives.xml")
    assert scene.simulation.extra == {"stiffness": "20000", "damping": "50", "substeps": "4"}
    assert scene.simulation.dt == 0.001 and scene.simulation.restitution == 0.0
    root = etree.fromstring(scene.to_xml().encode())
    assert root.find("simulation").get("substeps") == "4"


@pytest.mark.parametrize("where,text", [
    ("scene", '<scene version="1" gravty="0 0 -9.81">'),
    ("pose", '<pose position="0 0 1" orientaton="1 0 0 0"/>'),
])
def test_unknown_attributes_are_errors_outside_simulation(where, text):
    doc = MINIMAL.replace('<scene version="1">', text) if where == "scene" else \
        MINIMAL.replace('<pose position="0 0 1"/>', text)
    err = reason_of(doc)
    assert err.element == where
    assert "unknown attribute" in err.reason and "did you mean" in err.reason


def test_check_files_false_skips_missing_files():
    text = ball_scene().replace('shape="sphere" radius="0.1"', 'mesh="nowhere/thing.stl"')
    assert "not found" in reason_of(text).reason
    scene = read_scene_string(text, check_files=False)
    assert scene.objects[0].mesh == "nowhere/thing.stl"


def test_relative_files_resolve_against_the_scene_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    scene = read_scene_file(VALID / "cube.xml")
    assert scene.resolve(scene.objects[1].mesh) == VALID / "meshes" / "cube.obj"
    # the same text read with another base folder misses the mesh
    err = reason_of((VALID / "cube.xml").read_text(), base_dir=tmp_path, filename="moved.xml")
    assert err.file == "moved.xml" and "mesh file 'meshes/cube.obj' not found" in err.reason


def test_str_and_bytes_read_the_same():
    text = (VALID / "example.xml").read_text()
    assert Scene.from_string(text, base_dir=VALID) == Scene.from_string(text.encode(), base_dir=VALID)


def test_non_ascii_text_is_utf8():
    text = ball_scene().replace("<scene ", '<scene name="Küche – ☕" ')
    assert read_scene_string(text).name == "Küche – ☕"
    assert read_scene_string(text.encode("utf-8")).name == "Küche – ☕"
    err = reason_of(text.encode("latin-1", errors="replace"))
    assert "not well-formed" in err.reason


def test_comments_and_element_order_are_free():
    text = """<?xml version="1.0"?>
<!-- a comment -->
<scene version="1">
  <inference source="ball"><!-- c --><heatmap/><start-area min="0 0 0" max="1 1 0"/>
    <target position="1 0 0"/></inference>
  <object id="ball" shape="sphere" radius="0.1"><velocity linear="1 0 0"/><pose position="0 0 1"/></object>
  <simulation duration="2"/>
</scene>"""
    scene = read_scene_string(text)
    assert scene.simulation.duration == 2.0
    assert scene.inference.heatmap == HeatmapSettings()
    assert scene.objects[0].velocity.linear == (1.0, 0.0, 0.0)


def test_file_errors():
    with pytest.raises(SceneError, match="cannot read scene file"):
        read_scene_file("/definitely/not/here.xml")
    with pytest.raises(SceneError, match="cannot read scene file"):
        read_scene_file(VALID)


@pytest.mark.parametrize("doc,shown", [
    ('<s:scene xmlns:s="urn:x" version="1"/>', "s:scene"),
    ('<scene xmlns="urn:x" version="1"/>', "{urn:x}scene"),
    ('<world version="1"/>', "world"),
])
def test_wrong_root_is_named_as_written(doc, shown):
    err = reason_of(doc)
    assert err.reason == f"root element is <{shown}>, expected <scene>"
    assert (err.line, err.element) == (1, shown)


def test_scene_error_format():
    err = reason_of(ball_scene(object_attrs='mass="-1"'), filename="a/b.xml")
    assert str(err) == "a/b.xml:2: <object> 'mass' must be positive, got -1.0"


@pytest.mark.parametrize("element, fragment", [
    ('<posterior samples="-1"/>', "<posterior> 'samples' must be >= 0"),
    ('<posterior samples="2.5"/>', "samples"),
    ('<model-uncertainty friction="-0.1"/>', "<model-uncertainty> 'friction' must be >= 0"),
    ('<model-uncertainty restitution="nan"/>', "restitution"),
    ('<model-uncertainty friction="3"/>', "beyond the limit"),
    ('<posterior samples="1"/><posterior samples="2"/>', "posterior"),
])
def test_posterior_and_model_uncertainty_are_checked(element, fragment):
    text = ball_scene(extra=f'  <inference source="ball"><target position="1 0 0"/>{element}</inference>\n')
    with pytest.raises(SceneError) as info:
        Scene.from_string(text).validate()
    assert fragment in str(info.value)
    assert len(str(info.value).splitlines()) == 1


# -- how the source was seen ---------------------------------------------------------
TRACKED = """<scene version="1">
  <simulation duration="1.0"/>
  <object id="floor" shape="plane" fixed="true"><pose position="0 0 0"/></object>
  <object id="ball" shape="sphere" radius="0.1"><pose position="0 0 1"/></object>
  <inference source="ball">
    <target position="0.1 0 0.9" time="0.2"/>
    <target position="0.3 0 0.5" orientation="1 0 0 0" time="0.5" moving="true"/>
    <target position="0.5 0 0.1" orientation="0 0 0 1" time="1.0" moving="false"/>
    <observation sigma="0.01" rest-speed="0.05" rest-spin="0.5"/>
  </inference>
</scene>
"""


def test_several_timed_targets_position_only_and_moving_read_and_round_trip():
    scene = read_scene_string(TRACKED)
    a, b, c = scene.inference.targets
    assert (a.time, a.orientation, a.moving, a.at_rest) == (0.2, None, None, False)
    assert (b.time, b.orientation, b.moving, b.at_rest) == (0.5, (1.0, 0.0, 0.0, 0.0), True, False)
    assert (c.time, c.moving, c.at_rest) == (1.0, False, True)
    assert scene.inference.target == c  # the last observation
    ob = scene.inference.observation
    assert (ob.sigma, ob.rest_speed, ob.rest_spin) == (0.01, 0.05, 0.5)
    text = scene.to_xml()
    assert 'moving="false"' in text and text.count("<target ") == 3
    assert read_scene_string(text) == scene
    etree.fromstring(text.encode()).getroottree()  # well formed
    assert load_schema().validate(etree.fromstring(text.encode()))


def test_a_lone_target_without_orientation_reads_as_position_only_and_is_seen_at_rest():
    t = read_scene_string(TRACKED.replace(TRACKED[TRACKED.index("    <target"):TRACKED.index("    <observation")],
                                          '    <target position="0.5 0 0.1"/>\n')).inference.target
    assert t.orientation is None and t.time is None and t.at_rest


def test_two_targets_without_time_name_the_second_one_and_its_line():
    text = TRACKED.replace(' time="0.2"', "").replace(' time="0.5"', "")
    err = reason_of(text)
    assert "targets have no 'time'" in err.reason and err.line == 7 and err.element == "target"
    assert "'moving'" in reason_of(TRACKED.replace('moving="true"', 'moving="maybe"')).reason

