"""Bullet as the cross-engine bench's second observing engine (``bench/bullet_engine.py``).

The mapping against closed forms (a bounce, a slide to rest), the bench's Bullet path on one case,
the mismatched worlds. No timing assertions; nothing here is ``slow`` (the solve is one ball).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from click.testing import CliRunner

from dejaview.cli import cli
from dejaview.cli.bench import bench_module

pytest.importorskip("pybullet", reason="Bullet observes here (test extra: pip install -e '.[test]')")
pytest.importorskip("mujoco", reason="the crossengine bench re-simulates in MuJoCo (test extra)")


@pytest.fixture(scope="module")
def ce():
    return bench_module("crossengine")


@pytest.fixture(scope="module")
def bullet():
    return bench_module("bullet_engine")


@pytest.mark.parametrize("e", [0.3, 0.5, 0.8])
def test_a_ball_dropped_in_bullet_bounces_to_e_squared_h(ce, bullet, e):
    """Restitution e maps to sqrt(e) on the ball and on the floor (Bullet multiplies them): a ball
    dropped from h = 0.5 m rebounds to e^2 h (within 3 %: Bullet's weak push-out of the penetration,
    ``CONTACT``, adds 1-2 % to the height; with its defaults the ball did not bounce at this step)."""
    h = 0.5
    scene = ce.make_scene(ce.scene_text(ce.ball("ball", (2.0, 0, h + ce.BALL_R)), 1.0, restitution=e))
    first = math.sqrt(2 * h / 9.81)
    times = [round(first + 0.01 + 0.002 * k, 6) for k in range(int((1.0 - first - 0.01) / 0.002))]
    ends = bullet.bullet_run(scene, times)
    apex = max(ends[t][0][0, 2] for t in times) - ce.BALL_R
    assert apex == pytest.approx(e * e * h, rel=0.03)


@pytest.mark.parametrize("mu", [0.3, 0.5])
def test_a_box_sliding_in_bullet_stops_after_v2_over_2_mu_g(ce, bullet, mu):
    """Friction mu maps to sqrt(mu) on the box and the floor: a box launched at 2 m/s slides
    v^2 / (2 mu g) (within 2 mm), flat and without sinking (Bullet's damping off: with its default
    0.04 the box would stop short)."""
    v = 2.0
    scene = ce.make_scene(ce.scene_text(ce.box("box", (2.0, 0, ce.BOX[2] / 2), (v, 0, 0)), 1.0, friction=mu))
    pos, quat = bullet.bullet_run(scene, (1.0,))[1.0]
    assert pos[0, 0] - 2.0 == pytest.approx(v * v / (2 * mu * 9.81), abs=0.002)
    assert abs(pos[0, 2] - ce.BOX[2] / 2) < 5e-4 and abs(pos[0, 1]) < 1e-3
    assert ce.angle_deg(quat[0], (1, 0, 0, 0)) < 0.5


def test_bullet_materials_multiply_to_dejaviews_pair_values(bullet):
    """A pair's Bullet product is DejaView's combined friction (geometric mean) for any two materials,
    and its restitution where the two agree; no damping, rolling or spinning friction; impossible
    materials are one-line errors."""
    a, b = bullet.material(0.25, 0.3), bullet.material(0.64, 0.3)
    assert a["lateralFriction"] * b["lateralFriction"] == pytest.approx(math.sqrt(0.25 * 0.64))
    assert a["restitution"] * b["restitution"] == pytest.approx(0.3)
    assert all(a[k] == 0 for k in ("linearDamping", "angularDamping", "rollingFriction", "spinningFriction"))
    for bad in ((-0.1, 0.3), (0.5, 1.2), (float("nan"), 0.3)):
        with pytest.raises(ValueError, match="Bullet material"):
            bullet.material(*bad)


def test_mismatched_worlds_are_seeded_per_case_and_within_their_ranges(ce):
    """``mismatch``: friction x0.7-1.4 and restitution 0-0.3, the same draw for a case whichever others
    are chosen (and for its perturbed variants); ``in_world`` applies it to the scene's material."""
    draws = [ce.mismatch(c, 100) for c in ce.CASES]
    assert draws == [ce.mismatch(c, 100) for c in ce.CASES] != [ce.mismatch(c, 101) for c in ce.CASES]
    assert all(0.7 <= f <= 1.4 and 0 <= e <= 0.3 for f, e in draws)
    assert ce.mismatch(ce.perturbed_cases(7, ce.CASES[:1])[0], 100) == draws[0]
    scene = ce.case_scene(ce.CASES[0])
    moved = ce.in_world(scene, (1.2, 0.1))
    assert (moved.simulation.friction, moved.simulation.restitution) == pytest.approx((1.2 * 0.5, 0.1))
    assert ce.in_world(scene, None) is scene
    assert ce.held_out(100) and not ce.held_out(5) and not ce.held_out(None)


def test_the_benchs_bullet_path_solves_a_case_in_a_mismatched_world(ce):
    """One ball on the table, observed and re-simulated by Bullet in a held-out mismatched world, solved
    with model uncertainty and with XML passed through to ``<inference>``: the rows name the engine,
    the world and the kind, and the summary counts them per engine and kind."""
    lines = []
    rows = ce.run(print_fn=lines.append, cases=("ball-on-table",), warp=False, with_fidelity=False, baseline=False,
                  engines=("bullet",), mismatched=100, extra='<model-uncertainty friction="0.3"/>')
    assert [(r["engine"], r["model_uncertainty"]) for r in rows] == [("bullet", "0.2 0.2"), ("bullet", "xml")]
    assert all(r["kind"] == "ball roll" and r["held_out"] and r["world"].startswith("friction x") for r in rows)
    assert all(0 <= r["bullet_end_error_m"] < 1 for r in rows), rows
    assert any("Bullet" in line and "within 3 cm" in line for line in lines), lines
    assert any(line.strip().startswith("ball roll") for line in lines), lines
    assert any("held out" in line for line in lines), lines


def test_bullet_sees_the_fidelity_tables_bounce_as_dejaview_does(ce):
    """The fidelity table's Bullet column: a ball bouncing (e 0.3) ends within 2 cm of DejaView's in
    Bullet as in MuJoCo, and the two engines' gap is in the row."""
    (row,) = ce.fidelity(print_fn=lambda *_: None, names=["bounce (ball dropped 0.5 m, e 0.3)"], times=(1.0,))
    assert row["bullet_gap_1s_m"] <= ce.FIDELITY_TOL and row["gap_1s_m"] <= ce.FIDELITY_TOL, row
    assert np.isfinite(row["mujoco_bullet_gap_1s_m"])


def test_unknown_engines_are_a_one_line_error():
    result = CliRunner().invoke(cli, ["bench", "crossengine", "--engines", "havok", "--no-fidelity"])
    assert result.exit_code != 0 and "--engines" in result.output and "havok" in result.output, result.output


def test_inference_xml_that_is_not_xml_is_a_one_line_error():
    result = CliRunner().invoke(cli, ["bench", "crossengine", "--no-fidelity", "--inference-xml", "<physics-prior"])
    assert result.exit_code != 0 and "--inference-xml" in result.output and "not XML" in result.output, result.output
