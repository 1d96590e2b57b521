"""Property tests: mutated scene XML gives a Scene or a SceneError, nothing else;
generated valid scenes round-trip through ``to_xml``."""

from __future__ import annotations

import copy
import math
from pathlib import Path

from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from lxml import etree

from dejaview.errors import SceneError
from dejaview.scene import (
    EVALUATES,
    GRADIENTS,
    LOSSES,
    OPTIMIZERS,
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
from dejaview.scene.bounds import SIM_EXTRAS
from dejaview.scene.validate import scene_problems
from dejaview.scene.xml import normalize_quaternion, read_scene_string

VALID = Path(__file__).resolve().parents[1] / "fixtures" / "scenes" / "valid"
SEEDS = [(VALID / name).read_bytes() for name in ("example.xml", "primitives.xml", "cube.xml")]
FUZZ = settings(max_examples=250, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def outcome(data: bytes | str):
    """Read ``data``; assert it gives a Scene or a well-formed SceneError and return it."""
    try:
        scene = read_scene_string(data, base_dir=VALID, filename="fuzz.xml")
    except SceneError as exc:
        message = str(exc)
        assert message.startswith("fuzz.xml"), message
        assert "\n" not in message, message
        assert exc.reason
        return exc
    assert isinstance(scene, Scene)
    # whatever is accepted can be written and read back to the same scene
    assert read_scene_string(scene.to_xml(), base_dir=VALID) == scene
    return scene


# -- mutations -------------------------------------------------------------------
xml_text = st.text(st.characters(exclude_categories=("Cs", "Cc")), max_size=30)
attr_values = st.one_of(
    xml_text,
    st.sampled_from(["", "0", "1", "-1", "nan", "inf", "-0", "1e999", "true", "false", "0 0 0",
                     "0 0 0 0", "1 0 0 0", "1 2", "1 2 3 4 5", "floor", "mug", "ball mug",
                     "sphere", "box", "plane", "cylinder", "lbfgs", "adam", "reverse",
                     "meshes/cube.obj", "../../../../etc/passwd", "x.fbx", "  7  "]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.lists(st.floats(-10, 10), min_size=0, max_size=5).map(lambda v: " ".join(map(repr, v))),
)
attr_names = st.sampled_from([
    "id", "shape", "size", "radius", "height", "mesh", "spheres", "fixed", "mass", "density",
    "friction", "restitution", "position", "orientation", "linear", "angular", "source",
    "iterations", "seed", "optimizer", "gradient", "loss", "evaluate", "min", "max", "epsilon",
    "patience", "between", "weight", "cells", "samples", "sigma", "time", "linear-velocity",
    "angular-velocity", "version", "name", "gravity", "dt", "duration", "bogus", "mas",
])
tag_names = st.sampled_from(["scene", "simulation", "object", "pose", "velocity", "inference",
                             "target", "optimize", "start-area", "exploration", "penalty",
                             "heatmap", "colour", "include"])


@st.composite
def tree_mutation(draw) -> bytes:
    root = etree.fromstring(draw(st.sampled_from(SEEDS)))
    for _ in range(draw(st.integers(1, 4))):
        elements = list(root.iter(etree.Element))
        el = draw(st.sampled_from(elements))
        op = draw(st.sampled_from(["del-attr", "set-attr", "dup", "del", "rename", "move", "text"]))
        if op == "del-attr" and el.attrib:
            del el.attrib[draw(st.sampled_from(sorted(el.attrib)))]
        elif op == "set-attr":
            name = draw(st.one_of(attr_names, st.sampled_from(sorted(el.attrib) or ["id"])))
            value = draw(attr_values)
            try:
                el.set(name, value)
            except ValueError:  # text XML cannot hold: not a document anyone can write
                pass
        elif op == "dup" and el is not root:
            el.addnext(copy.deepcopy(el))
        elif op == "del" and el is not root:
            el.getparent().remove(el)
        elif op == "rename":
            el.tag = draw(tag_names)
        elif op == "move" and el is not root:
            target = draw(st.sampled_from(elements))
            if el not in target.iterancestors() and target is not el and el not in list(target.iter()):
                target.append(el)
        elif op == "text":
            try:
                el.text = draw(xml_text)
            except ValueError:
                pass
    return etree.tostring(root)


@st.composite
def byte_mutation(draw) -> bytes:
    data = bytearray(draw(st.sampled_from(SEEDS)))
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["truncate", "replace", "insert", "delete"]))
        i = draw(st.integers(0, len(data)))
        if op == "truncate":
            del data[i:]
        elif op == "replace" and i < len(data):
            data[i] = draw(st.integers(0, 255))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[i:i + draw(st.integers(1, 40))]
    return bytes(data)


@FUZZ
@given(tree_mutation())
def test_tree_mutations_give_scene_or_scene_error(data):
    outcome(data)


@FUZZ
@given(byte_mutation())
def test_byte_mutations_give_scene_or_scene_error(data):
    outcome(data)


@settings(max_examples=100, deadline=None)
@given(st.one_of(st.binary(max_size=200), st.text(max_size=200)))
def test_random_input_gives_scene_error(data):
    assert isinstance(outcome(data), SceneError)


def test_mutations_reach_both_outcomes():
    """Sanity check of the fuzzers: some mutants stay valid and others do not."""
    seed = SEEDS[1]
    assert isinstance(outcome(seed), Scene)
    assert isinstance(outcome(seed.replace(b'mass="0.2"', b'mass="0.3"')), Scene)
    assert isinstance(outcome(seed[: len(seed) // 2]), SceneError)


# -- generated valid scenes ------------------------------------------------------
def finite(lo=-1e3, hi=1e3):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


positive = st.floats(1e-6, 1e3)
# within dejaview.scene.bounds: sizes 1 cm..10 m and densities 1..1e4 kg/m^3 keep every
# primitive's mass from its density within MIN_MASS..MAX_MASS
size = st.floats(1e-2, 10)
density = st.floats(1, 1e4)
vec3 = st.tuples(finite(), finite(), finite())
ids = st.from_regex(r"[A-Za-z_][A-Za-z0-9_.\-]{0,11}", fullmatch=True)


@st.composite
def unit_quaternions(draw):
    q = draw(st.tuples(*[finite(-1, 1)] * 4))
    assume(math.sqrt(sum(c * c for c in q)) > 1e-3)
    return normalize_quaternion(q)


@st.composite
def scene_objects(draw, object_id: str, movable: bool):
    kind = draw(st.sampled_from(["box", "sphere", "cylinder", "mesh"] + ([] if movable else ["plane"])))
    geometry = {
        "box": lambda: dict(shape="box", size=draw(st.tuples(size, size, size))),
        "sphere": lambda: dict(shape="sphere", radius=draw(size)),
        "cylinder": lambda: dict(shape="cylinder", radius=draw(size), height=draw(size)),
        "plane": lambda: dict(shape="plane"),
        "mesh": lambda: dict(mesh="meshes/cube.obj",
                             spheres=draw(st.sampled_from([None, "packings/cube.spheres"]))),
    }[kind]()
    optional = lambda s: draw(st.one_of(st.none(), s))  # noqa: E731
    return SceneObject(
        id=object_id,
        pose=Pose(draw(vec3), draw(unit_quaternions())),
        velocity=draw(st.one_of(st.just(Velocity()), st.builds(Velocity, vec3, vec3))),
        fixed=not movable,
        mass=optional(positive), density=optional(density),
        friction=optional(finite(0, 10)), restitution=optional(finite(0, 1)),
        **geometry,
    )


@st.composite
def scenes(draw):
    names = draw(st.lists(ids, min_size=1, max_size=5, unique=True))
    movable = [True] + [draw(st.booleans()) for _ in names[1:]]
    objects = tuple(draw(scene_objects(n, m)) for n, m in zip(names, movable))
    duration = draw(st.floats(1e-3, 10))
    simulation = SimulationSettings(
        # 10 s at 3e-5 s: 333,334 steps, within the step budget at a box body's 4 substeps
        dt=draw(st.floats(3e-5, 1e-1)), duration=duration,
        friction=draw(finite(0, 5)), restitution=draw(finite(0, 1)),
        extra=draw(st.dictionaries(st.from_regex(r"[a-z][a-z0-9\-]{0,8}", fullmatch=True)
                                   .filter(lambda k: k not in ("dt", "duration", "friction", "restitution")
                                           and k not in SIM_EXTRAS),
                                   xml_text.filter(lambda t: "\r" not in t), max_size=3)),
    )
    inference = None
    if draw(st.booleans()):
        low = draw(vec3)
        area = draw(st.one_of(st.none(), st.builds(
            lambda lo, d: StartArea(lo, tuple(a + b for a, b in zip(lo, d))),
            st.just(low), st.tuples(st.floats(0.01, 10), st.floats(0.01, 10), st.floats(0, 10)))))
        pairs = [(a, b) for a in names for b in names if a != b]
        inference = InferenceSettings(
            source=draw(st.sampled_from([n for n, m in zip(names, movable) if m])),
            targets=(Target(
                position=draw(vec3), orientation=draw(st.one_of(st.none(), unit_quaternions())),
                linear_velocity=draw(st.one_of(st.none(), vec3)),
                angular_velocity=draw(st.one_of(st.none(), vec3)),
                time=draw(st.one_of(st.none(), st.floats(0, duration))),
                moving=draw(st.sampled_from((None, True))),
            ),),
            iterations=draw(st.integers(1, 10_000)), seed=draw(st.integers(0, 2**63 - 1)),
            optimizer=draw(st.sampled_from(OPTIMIZERS)),
            gradient=draw(st.sampled_from((None,) + GRADIENTS)),
            loss=draw(st.sampled_from(LOSSES)), evaluate=draw(st.sampled_from(EVALUATES)),
            optimize=draw(st.builds(Optimize, st.booleans(), st.booleans(), st.booleans(),
                                    st.booleans()).filter(Optimize.any)),
            start_area=area,
            exploration=draw(st.one_of(st.none(), st.builds(Exploration, finite(0, 1), st.integers(1, 100)))),
            penalties=tuple(draw(st.lists(st.builds(Penalty, st.sampled_from(pairs), finite(0, 10)),
                                          max_size=3))) if pairs else (),
            heatmap=draw(st.one_of(st.none(), st.builds(
                HeatmapSettings, st.tuples(st.integers(1, 64), st.integers(1, 64)),
                st.integers(1, 16), st.floats(1e-4, 1)))) if area is not None else None,
        )
    return Scene(
        objects=objects,
        name=draw(st.one_of(st.none(), xml_text.filter(lambda t: "\r" not in t))),
        gravity=draw(st.tuples(*[finite(-500, 500)] * 3)), simulation=simulation, inference=inference, base_dir=VALID,
    )


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenes())
def test_generated_scenes_are_valid_and_round_trip(scene):
    assert scene_problems(scene) == []
    again = read_scene_string(scene.to_xml(), base_dir=VALID)
    assert again == scene
