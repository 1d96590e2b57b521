"""The stories bench (bench/stories.py, ``dejaview bench stories``): the generator
(bench/story_scenes.py) and the CLI's options.

No solve in the default run: the one test that solves a story is marked slow.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from lxml import etree

from dejaview.cli import cli
from dejaview.cli.bench import bench_module
from dejaview.inference.posterior import PosteriorSettings
from dejaview.scene import Scene

stories = bench_module("stories")
scenes = bench_module("story_scenes")


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The development set (seed 0, one story of each kind), written to a folder."""
    folder = tmp_path_factory.mktemp("stories")
    made = scenes.make_stories(seed=0, count=len(scenes.KINDS), folder=folder)
    for story in made:
        scenes.write_story(story, folder)
    return folder, made


def test_one_story_of_each_kind_in_turn():
    kinds = list(scenes.KINDS)
    assert len(kinds) >= 6
    assert scenes.story_kinds(len(kinds) + 2) == kinds + kinds[:2]
    assert scenes.story_kinds(3, ["box_thrown"]) == ["box_thrown"] * 3


def test_the_generator_is_deterministic_per_seed(written, tmp_path):
    folder, made = written
    again = scenes.make_stories(seed=0, count=len(made), folder=tmp_path)
    for a, b in zip(made, again):
        assert a.name == b.name and a.truth == b.truth
        scenes.write_story(b, tmp_path)
        assert (folder / f"{a.name}.xml").read_text() == (tmp_path / f"{b.name}.xml").read_text()
    other = scenes.make_stories(seed=1, count=1, folder=tmp_path)[0]
    assert other.truth["initial_state"] != made[0].truth["initial_state"]


def test_a_story_does_not_depend_on_the_others(written, tmp_path):
    _, made = written
    kind = made[3].kind
    alone = scenes.make_story(kind, np.random.default_rng([0, 3]), tmp_path)
    assert alone.truth == made[3].truth


@pytest.mark.parametrize("index", range(len(scenes.KINDS)))
def test_the_scene_file_reads_back_with_no_settings(written, index):
    folder, made = written
    story = made[index]
    path = folder / f"{story.name}.xml"
    scene = Scene.from_xml(path)
    assert scene == story.scene
    inference = etree.parse(str(path)).getroot().find("inference")
    assert set(inference.attrib) == {"source"}
    assert [child.tag for child in inference] == ["target", "start-area"]
    assert set(inference.find("target").attrib) == {"position", "orientation"}
    truth = json.loads((folder / f"{story.name}.truth.json").read_text())
    assert truth["kind"] == story.kind and truth["duration"] == scene.simulation.duration
    assert set(truth["initial_state"]) == {"position", "orientation", "linear_velocity", "angular_velocity"}


@pytest.mark.parametrize("index", range(len(scenes.KINDS)))
def test_the_truth_ends_at_rest_at_the_target(written, index):
    """The written scene, run from the truth's start for its duration, ends at the target, and the
    source has lain still (mean speed and spin over 0.1 s) for the last ``REST_MARGIN`` seconds."""
    folder, made = written
    story = made[index]
    scene = Scene.from_xml(folder / f"{story.name}.xml")
    s = story.truth["initial_state"]
    start = dict(position=s["position"], orientation=s["orientation"], linear=s["linear_velocity"],
                 angular=s["angular_velocity"])
    world, traj, source = scenes.simulate(scene, start)
    assert len(traj.steps) - 1 == round(scene.simulation.duration / scenes.DT)
    target = scene.inference.target
    end = world.object_position(traj.final)[0, source]
    assert float(torch.linalg.vector_norm(end - torch.tensor(target.position, dtype=end.dtype))) < 1e-6
    q = traj.final.orientation[0, source]
    assert abs(abs(float(q @ torch.tensor(target.orientation, dtype=q.dtype))) - 1.0) < 1e-9
    speed, spin = scenes.mean_motion(world, traj, source)
    tail = int(round(scenes.REST_MARGIN / scenes.DT))
    assert float(speed[-tail:].max()) < scenes.REST_SPEED and float(spin[-tail:].max()) < scenes.REST_SPIN
    rest = story.truth["rest_time"]
    assert rest <= scenes.MAX_REST
    assert scene.simulation.duration == scenes.story_duration(rest) >= rest + scenes.REST_MARGIN - 1e-9
    kind = scenes.KINDS[story.kind]
    if kind.leaves_top:
        assert target.position[2] < 0.3  # on the floor, not on its top


@pytest.mark.parametrize("index", range(len(scenes.KINDS)))
def test_the_start_is_feasible_and_inside_its_area(written, index):
    from dejaview.geometry.collision import SceneCollision

    folder, made = written
    story = made[index]
    scene = Scene.from_xml(folder / f"{story.name}.xml")
    area = scene.inference.start_area
    s = story.truth["initial_state"]
    assert all(lo <= p <= hi for lo, p, hi in zip(area.min, s["position"], area.max))
    widths = [hi - lo for lo, hi in zip(area.min, area.max)]
    assert all(scenes.AREA_WIDTH[0] - 1e-9 <= w <= scenes.AREA_WIDTH[1] + 1e-9 for w in widths[:2])
    kind = scenes.KINDS[story.kind]
    if kind.stand is not None:  # on its top, where it stands
        assert area.min[2] == area.max[2] == pytest.approx(kind.stand["top"] + scenes.SOURCES[kind.source]["stand"])
    else:
        assert scenes.AIR_Z[0] <= area.min[2] < area.max[2] <= scenes.AIR_Z[1]
    # not centred on the truth: the truth is drawn inside the area (here: somewhere off its centre)
    assert any(abs(p - (lo + hi) / 2) > 1e-6 for lo, p, hi in zip(area.min[:2], s["position"], area.max[:2]))
    hit, depth, _ = SceneCollision(scene).penetration(scene.inference.source, np.asarray(s["position"]),
                                                      np.asarray(s["orientation"]))
    hit, depth = bool(np.asarray(hit).reshape(-1)[0]), float(np.asarray(depth).reshape(-1)[0])
    assert not hit or depth <= PosteriorSettings.feasibility_margin
    guess = scene.object(scene.inference.source)
    assert all(lo <= p <= hi for lo, p, hi in zip(area.min, guess.pose.position, area.max))


def test_velocities_within_the_kinds_ranges(written):
    _, made = written
    for story in made:
        kind = scenes.KINDS[story.kind]
        v = story.truth["initial_state"]["linear_velocity"]
        assert kind.speed[0] - 1e-9 <= math.hypot(v[0], v[1]) <= kind.speed[1] + 1e-9
        assert kind.vz[0] - 1e-9 <= v[2] <= kind.vz[1] + 1e-9
        assert math.sqrt(sum(x * x for x in v)) < 5.0  # inside the default flat prior's speed bound


def test_story_duration_rounds_up_to_a_tenth():
    assert scenes.story_duration(1.0) == 1.5
    assert scenes.story_duration(1.1) == 1.6
    assert scenes.story_duration(1.002) == 1.6
    assert scenes.story_duration(3.98) == 4.5


def test_rest_time_of_a_box_dropped_flat():
    """A box let go 1 cm above the floor lies still after a few tenths of a second; one sliding at
    1 m/s to the end of a short horizon is not at rest."""
    kind = scenes.KINDS["box_thrown"]
    folder = scenes.PACKINGS  # only for resolving relative names: the scene is not written
    scene = scenes.base_scene(kind, ([0.0, 0.0, 0.5], [0.3, 0.3, 0.8]), folder, duration=1.0)
    start = dict(position=[0.0, 0.0, 0.06], orientation=[1.0, 0.0, 0.0, 0.0], linear=[0.0, 0.0, 0.0],
                 angular=[0.0, 0.0, 0.0])
    world, traj, source = scenes.simulate(scene, start)
    rest = scenes.rest_time(world, traj, source)
    assert rest is not None and 0.1 <= rest < 0.6
    sliding = dict(start, linear=[1.0, 0.0, 0.0])
    world, traj, source = scenes.simulate(scene, sliding, steps=50)
    assert scenes.rest_time(world, traj, source) is None


def test_the_knobbly_ball_reaches_the_mesh(tmp_path):
    rows = scenes.knobbly_ball()
    reach = np.linalg.norm(rows[:, :3], axis=1) + rows[:, 3]
    assert rows.shape == (13, 4) and float(reach.max()) == pytest.approx(0.05)
    path = scenes.write_knobbly(tmp_path)
    from dejaview.geometry.packing import SpherePacking

    packing = SpherePacking.read(path)
    assert len(packing) == 13 and np.allclose(packing.radii, rows[:, 3])


def test_no_solve_writes_the_stories_and_a_csv(tmp_path):
    path = tmp_path / "stories.csv"
    result = CliRunner().invoke(cli, ["bench", "stories", "--no-solve", "--count", "2", "--kinds", "box_thrown",
                                      "--out", str(tmp_path / "out"), "--csv", str(path)])
    assert result.exit_code == 0, result.output
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["story"] for r in rows] == ["s0-00-box_thrown", "s0-01-box_thrown"]
    for r in rows:
        assert (tmp_path / "out" / "seed0" / f"{r['story']}.xml").is_file()
        assert (tmp_path / "out" / "seed0" / f"{r['story']}.truth.json").is_file()


@pytest.mark.parametrize("args, hint", [
    (["--count", "0"], "--count"),
    (["--seed", "-1"], "--seed"),
    (["--seed", "x"], "--seed"),
    (["--kinds", "nope"], "--kinds"),
    (["--kinds", ","], "--kinds"),
])
def test_cli_option_errors(args, hint, tmp_path):
    result = CliRunner().invoke(cli, ["bench", "stories", "--no-solve", "--out", str(tmp_path), *args])
    assert result.exit_code == 2, result.output
    assert hint in result.output


def test_cli_help_lists_the_options():
    result = CliRunner().invoke(cli, ["bench", "stories", "--help"])
    assert result.exit_code == 0, result.output
    for option in ("--seed", "--count", "--kinds", "--out", "--no-solve", "--csv", "--check"):
        assert option in result.output
    result = CliRunner().invoke(cli, ["bench", "--help"])
    assert "stories" in result.output


def test_script_option_errors(tmp_path):
    for args in (["--count", "0"], ["--seed", "-1"], ["--kinds", "nope"]):
        with pytest.raises(SystemExit) as info:
            stories.main([*args, "--no-solve", "--out", str(tmp_path)])
        assert info.value.code == 2


@pytest.mark.slow
def test_solve_story_reports_the_end_and_the_matched_record(written):
    """One story solved with the defaults: the row's columns (not whether it is solved)."""
    folder, made = written
    story = next(s for s in made if s.kind == "box_thrown")
    row = stories.solve_story(folder / f"{story.name}.xml")
    for key in ("end_mm", "end_deg", "matched_mm", "matched_deg", "seconds", "end_speed", "resim_mm"):
        assert math.isfinite(row[key]), key
    assert row["kind"] == "box_thrown" and row["rollouts"] > 0
    assert row["solved"] == (row["end_mm"] <= 10.0 and row["end_deg"] <= 5.0)
    assert row["resim_mm"] < 1e-3  # the solve's own re-simulation and an independent rollout agree
