"""Recovery suite (``bench/recovery.py``): known pasts of the bundled scenes are recovered.

Each case draws a true initial state of a bundled scene's source (seeded, inside
the start area, keeping the scene's story), simulates it, and solves from the
scene's own guess with only the final pose as the target. Success: the
re-simulated solution within 1 cm and 5 degrees of the target at the
best-matching record (see the bench module's docstring). The whole suite runs
for tens of minutes, hence ``slow``; the cheap tests below check the case
generation only.
"""

import math

import pytest

from dejaview.cli.bench import bench_module


def bench():
    return bench_module("recovery")


def test_the_suite_has_at_least_twenty_cases_over_every_bundled_story_scene():
    recovery = bench()
    cases = recovery.ALL_CASES
    assert len(cases) >= 20
    assert {c.scene for c in cases} == {"ball_off_table", "mug_off_counter", "box_along_shelf",
                                         "box_among_boxes", "ball_down_ramp", "box_down_ramp"}
    assert len({c.name for c in cases}) == len(cases)


def test_a_drawn_truth_is_reproducible_inside_the_start_area_and_keeps_the_story():
    """Seeded draws: the same case gives the same truth and target; the truth starts in
    the scene's start area; the target is the simulated end (the ball on the floor)."""
    recovery = bench()
    case = recovery.Case("box_along_shelf", 0)
    scene, truth, _ = recovery.make_case(case)
    again, truth2, _ = recovery.make_case(case)
    assert truth == truth2 and scene.inference.target == again.inference.target
    area = scene.inference.start_area
    for lo, p, hi in zip(area.min, truth["position"], area.max):
        assert lo <= p <= hi
    assert scene.simulation.duration == recovery.DURATIONS["box_along_shelf"]
    assert scene.inference.target.position == pytest.approx(truth["final_position"])
    assert scene.inference.target.position[0] > 0.36  # it reached the side panel


@pytest.mark.parametrize("name", ["ball_down_ramp", "box_down_ramp"])
def test_a_ramp_case_starts_at_rest_in_the_area_and_ends_on_the_floor(name):
    recovery = bench()
    scene, truth, _ = recovery.make_case(recovery.Case(name, 0))
    assert truth["linear"] == [0.0, 0.0, 0.0] and truth["angular"] == [0.0, 0.0, 0.0]
    area = scene.inference.start_area
    assert all(lo <= p <= hi for lo, p, hi in zip(area.min, truth["position"], area.max))
    assert scene.inference.target.position[2] < 0.2


@pytest.mark.slow
def test_recovery_suite_succeeds_in_at_least_95_percent_of_cases(tmp_path):
    """The suite as ``python bench/recovery.py`` runs it: solve's defaults, nothing else."""
    recovery = bench()
    rows = recovery.run(print_fn=print, csv_path=tmp_path / "recovery.csv")
    assert len(rows) >= 20
    assert all(math.isfinite(r["position_error_m"]) for r in rows)
    rate = sum(r["success"] for r in rows) / len(rows)
    assert rate >= 0.95, [(r["case"], r["position_error_m"], r["angle_error_deg"]) for r in rows]
    assert (tmp_path / "recovery.csv").read_text().count("\n") == len(rows) + 1


def test_sensitivity_of_a_smooth_case_is_small_and_the_truth_has_zero_loss():
    """``bench/sensitivity.py`` on box_along_shelf-1 (a box sliding to the shelf's panel): a start
    moved by 1 um moves the end by well under 0.1 mm, and the loss at the truth is ~0 (the probe
    rebuilds the parameters around the point it is given)."""
    sensitivity = bench_module("sensitivity")
    recovery = bench()
    scene, truth, _ = recovery.make_case(recovery.Case("box_along_shelf", 1))
    (row,) = sensitivity.end_sensitivity(scene, truth, distances=(1e-6,), trials=2)
    assert 0.0 < row["moved_mm_max"] < 0.1
    assert row["turned_deg_max"] < 0.01
    around = sensitivity.loss_around(scene, truth, sigmas=(0.5,), trials=2)
    assert around["loss"] < 1e-9
    assert around["sigmas"][0]["min"] > 1e-3  # half a scaled unit away is visibly off
