"""Every broken fixture is refused with its file, line and reason, via the API and the CLI."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.errors import SceneError
from dejaview.scene import Scene

SCENES = Path(__file__).resolve().parents[1] / "fixtures" / "scenes"
VALID = SCENES / "valid"
BROKEN = SCENES / "broken"

# fixture file -> (expected substring of the reason, expected line, expected element or None)
BROKEN_SCENES = {
    "bad-boolean.xml": ("'fixed': 'yes' is not a boolean", 5, "object"),
    "billion-laughs.xml": ("DOCTYPE declarations are not allowed", 2, "!DOCTYPE"),
    "box-without-size.xml": ("a box needs 'size'", 8, "object"),
    "duplicate-id.xml": ("duplicate id 'floor' (first used on line 5)", 8, "object"),
    "empty.xml": ("empty file", 1, None),
    "external-dtd.xml": ("DOCTYPE declarations are not allowed", 3, "!DOCTYPE"),
    "external-entity-file.xml": ("DOCTYPE declarations are not allowed", 3, "!DOCTYPE"),
    "external-entity-http.xml": ("DOCTYPE declarations are not allowed", 2, "!DOCTYPE"),
    "garbage.xml": ("not well-formed XML", 1, None),
    "heatmap-without-start-area.xml": ("a heatmap needs a <start-area>", 13, "heatmap"),
    "infinite-mass.xml": ("attribute 'mass' is not finite", 8, "object"),
    "missing-id.xml": ("missing required attribute 'id'", 8, "object"),
    "missing-mesh-file.xml": ("mesh file 'meshes/nowhere.obj' not found", 8, "object"),
    "missing-pose.xml": ("missing required child element <pose>", 8, "object"),
    "missing-spheres-file.xml": ("spheres file 'nowhere.spheres' not found", 8, "object"),
    "missing-target.xml": ("missing required child element <target>", 11, "inference"),
    "missing-version.xml": ("missing required attribute 'version'", 3, "scene"),
    "misspelt-attribute.xml": ("unknown attribute 'mas' (did you mean 'mass'?)", 8, "object"),
    "nan-position.xml": ("attribute 'position' is not finite ('NaN')", 9, "pose"),
    "negative-mass.xml": ("'mass' must be positive, got -0.2", 8, "object"),
    "negative-radius.xml": ("'radius' must be positive, got -0.05", 8, "object"),
    "penalty-same-object.xml": ("names 'ball' twice", 12, "penalty"),
    "penalty-unknown-object.xml": ("'between' names unknown object 'table'", 12, "penalty"),
    "plane-not-fixed.xml": ("plane 'floor' must be fixed", 5, "object"),
    "restitution-above-one.xml": ("'restitution' must be between 0 and 1, got 1.5", 4, "simulation"),
    "shape-and-mesh.xml": ("has both shape and mesh", 8, "object"),
    "source-fixed.xml": ("source 'floor' is fixed", 11, "inference"),
    "source-missing.xml": ("source 'mug' is not an object of the scene", 11, "inference"),
    "start-area-inverted.xml": ("'min' is greater than 'max' along y", 13, "start-area"),
    "target-time-after-end.xml": ("'time' 2.5 is after the end of the simulation", 12, "target"),
    "text-in-element.xml": ("text is not allowed inside <object>", 8, "object"),
    "truncated.xml": ("not well-formed XML", 12, None),
    "two-simulations.xml": ("<simulation> may appear only once inside <scene>", 5, "simulation"),
    "unknown-element.xml": ("unknown element <colour> inside <object>", 9, "colour"),
    "unknown-optimizer.xml": ("optimizer 'sgd' is not one of auto, gd, adam, lbfgs, bfgs", 11, "inference"),
    "unknown-shape.xml": ("shape 'cone' is not one of", 8, "object"),
    "unknown-version.xml": ("unknown scene version '2'", 3, "scene"),
    "unsupported-mesh-suffix.xml": ("unsupported suffix '.fbx'", 8, "object"),
    "wrong-root.xml": ("root element is <world>, expected <scene>", 3, "world"),
    "wrong-vector-length.xml": ("attribute 'position' needs 3 numbers, got 2", 9, "pose"),
    "xinclude.xml": ("unknown element <xi:include> inside <scene>", 11, "xi:include"),
    "zero-iterations.xml": ("'iterations' must be >= 1, got 0", 11, "inference"),
    "zero-quaternion.xml": ("attribute 'orientation' is a zero quaternion", 9, "pose"),
}

VALID_SCENES = {
    "example.xml": (3, "mug"),
    "primitives.xml": (4, None),
    "cube.xml": (2, "cube"),
}


def test_table_covers_every_broken_fixture():
    on_disk = {p.name for p in BROKEN.glob("*.xml")}
    assert on_disk == set(BROKEN_SCENES)
    assert len(on_disk) >= 20


@pytest.mark.parametrize("name", sorted(BROKEN_SCENES))
def test_broken_fixture_rejected_by_api(name):
    reason, line, element = BROKEN_SCENES[name]
    path = BROKEN / name
    with pytest.raises(SceneError) as info:
        Scene.from_xml(path)
    err = info.value
    assert reason in err.reason
    assert err.file == str(path)
    assert err.line == line
    assert err.element == element
    message = str(err)
    assert message.startswith(f"{path}:{line}:")
    if element is not None:
        assert f"<{element}>" in message
    assert "\n" not in message


@pytest.mark.parametrize("name", sorted(BROKEN_SCENES))
def test_broken_fixture_rejected_by_cli(name):
    reason, line, _ = BROKEN_SCENES[name]
    path = str(BROKEN / name)
    result = CliRunner().invoke(cli, ["validate", path])
    assert result.exit_code == 2, result.output
    assert result.stdout == ""
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1
    assert f"{path}:{line}:" in err
    assert reason in err


@pytest.mark.parametrize("name", sorted(VALID_SCENES))
def test_valid_fixture_accepted(name):
    n, source = VALID_SCENES[name]
    scene = Scene.from_xml(VALID / name)
    assert len(scene.objects) == n
    assert (scene.inference.source if scene.inference else None) == source
    assert scene.path == VALID / name
    assert scene.base_dir == VALID


def test_cli_reports_every_valid_scene():
    paths = [str(VALID / n) for n in sorted(VALID_SCENES)]
    result = CliRunner().invoke(cli, ["validate", *paths])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines == [
        f"OK {VALID / 'cube.xml'}: 2 objects, source=cube",
        f"OK {VALID / 'example.xml'}: 3 objects, source=mug",
        f"OK {VALID / 'primitives.xml'}: 4 objects, source=none",
    ]
    assert result.stderr == ""


def test_cli_mixed_valid_and_broken_checks_all_and_fails():
    good, bad = VALID / "cube.xml", BROKEN / "negative-mass.xml"
    result = CliRunner().invoke(cli, ["validate", str(bad), str(good), "/no/such/scene.xml"])
    assert result.exit_code == 2
    assert f"OK {good}" in result.stdout
    errors = result.stderr.strip().splitlines()
    assert len(errors) == 2
    assert f"{bad}:8:" in errors[0]
    assert "/no/such/scene.xml" in errors[1] and "cannot read" in errors[1]


def test_cli_can_skip_the_file_check():
    path = str(BROKEN / "missing-mesh-file.xml")
    assert CliRunner().invoke(cli, ["validate", path]).exit_code == 2
    result = CliRunner().invoke(cli, ["validate", "--no-file-check", path])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"OK {path}: 2 objects, source=ball")


def test_cli_subprocess_exit_status():
    """The real entry point (``python -m dejaview``) exits 2 on a bad scene and 0 on good ones."""
    env = dict(os.environ)
    root = Path(__file__).resolve().parents[2]
    env["PYTHONPATH"] = str(root) + os.pathsep + env.get("PYTHONPATH", "")
    bad = subprocess.run([sys.executable, "-m", "dejaview", "validate", str(BROKEN / "source-fixed.xml")],
                         capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 2
    assert f"{BROKEN / 'source-fixed.xml'}:11: <inference> source 'floor' is fixed" in bad.stderr
    good = subprocess.run([sys.executable, "-m", "dejaview", "validate", str(VALID / "example.xml")],
                          capture_output=True, text=True, env=env, timeout=120)
    assert good.returncode == 0, good.stderr
    assert good.stdout.strip() == f"OK {VALID / 'example.xml'}: 3 objects, source=mug"
